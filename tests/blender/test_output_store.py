"""The output stores (output_store.py): a deformer's output on the mesh's attributes or in a position
carrier gives the same shape bit for bit, for every kind and both output forms, in frames in any
order and across switches; the cost model picks the carrier beside many objects and the attributes
for a large mesh in a small scene; Apply, Remove, copies, bakes and files behave alike."""

from __future__ import annotations

import importlib
import math

import bpy
import numpy as np
import pytest

from tests.blender.test_cage_deformer import add_cage_deformer, box_cage

FRAMES = (7, 1, 12, 7)


@pytest.fixture
def store(installed, monkeypatch):
    module = importlib.import_module(f"{installed.package}.blender.update.output_store")
    if not module.POSITIONS_TAG_THEMSELVES:
        pytest.skip(f"Blender {bpy.app.version_string} does not see a position write without a full tag: "
                    "the attributes are its only store (output_store.POSITIONS_TAG_THEMSELVES)")
    monkeypatch.setattr(module, "forced", None)
    return module


def _key(obj, frames_values: dict) -> None:
    for frame, (location, rotation) in frames_values.items():
        obj.location, obj.rotation_euler = location, rotation
        obj.keyframe_insert("location", frame=frame)
        obj.keyframe_insert("rotation_euler", frame=frame)


def _probe_rig(bl, name: str, x: float, armature_first: bool):
    body = bl.grid_cube(cuts=4, name=name)
    body.location.x = x
    probes = [bl.empty(f"{name}A", (x + 1.5, 0, 0)), bl.empty(f"{name}B", (x - 1.5, 0, 0))]
    bpy.context.view_layer.update()
    deformer = bl.add_probe_deformer(body, probes)
    _key(probes[0], {1: ((x + 1.5, 0, 0), (0, 0, 0)), 12: ((x + 1.8, 0.3, 0.6), (0.3, 0.0, 1.2))})
    if armature_first:  # a modifier that only moves vertices before ours: the motion path
        arm = bpy.data.objects.new(f"{name}Arm", bpy.data.armatures.new(f"{name}Arm"))
        bpy.context.scene.collection.objects.link(arm)
        mod = body.modifiers.new("Armature", "ARMATURE")
        mod.object = arm
        body.modifiers.move(len(body.modifiers) - 1, 0)
    return body, deformer


def _rigs(bl):
    """A probe rig on the offset path, one on the motion path, a cage rig and a bone rig."""
    rigs = [_probe_rig(bl, "Offsets", 0.0, False), _probe_rig(bl, "Motions", 5.0, True)]
    target = bl.grid_cube(cuts=4, name="Caged")
    target.location.y = 5.0
    cage = box_cage()
    cage.location.y = 5.0
    bpy.context.view_layer.update()
    rigs.append((target, add_cage_deformer(target, cage)))
    _key(cage, {1: ((0, 5.0, 0), (0, 0, 0)), 12: ((0.4, 5.2, 0.1), (0.2, 0.1, 0.5))})
    return rigs


def _play(bl, rigs) -> dict:
    got = {}
    for frame in FRAMES:
        bpy.context.scene.frame_set(frame)
        for body, deformer in rigs:
            assert deformer.status == "", deformer.status
            got[body.name, frame] = bl.evaluated_positions(body).copy()
    return got


def _carrier(store, body, deformer):
    mod = next(m for m in body.modifiers if m.type == "NODES" and m.name.startswith("Affine"))
    return store.carrier_of(body, mod)


def test_both_stores_give_the_same_shape_bit_for_bit(bl, installed, store):
    rigs = _rigs(bl)
    results = {}
    for forced in ("ATTRIBUTES", "POSITIONS", "ATTRIBUTES", "POSITIONS"):
        store.forced = forced
        installed.evaluate.forget()
        results.setdefault(forced, []).append(_play(bl, rigs))
        for body, deformer in rigs:
            found = _carrier(store, body, deformer)
            has_points = found is not None and len(found.data.vertices) > 0
            assert has_points == (forced == "POSITIONS"), (body.name, forced)
            own = {a.name for a in body.data.attributes if a.name.startswith(("affdef", ".affdef")) and
                   not a.name.split("_")[-1].startswith(("idx", "w"))}
            assert bool(own) == (forced == "ATTRIBUTES"), (body.name, forced, own)
    reference = results["ATTRIBUTES"][0]
    assert np.abs(reference["Offsets", 12] - reference["Offsets", 1]).max() > 0.1
    for runs in results.values():
        for run in runs:
            for key, value in run.items():
                assert np.array_equal(value, reference[key]), key
    counts = {body.name: len(_carrier(store, body, d).data.vertices) - 1 for body, d in rigs}
    n = {body.name: len(body.data.vertices) for body, _d in rigs}
    assert counts["Offsets"] == n["Offsets"] and counts["Motions"] == 4 * n["Motions"], (counts, n)


def test_the_cost_model_chooses_by_the_scene_and_the_mesh(bl, store):
    body, deformer = _probe_rig(bl, "Small", 0.0, False)
    big = bl.uv_sphere(segments=256, rings=128, location=(9, 0, 0))
    probes = [bl.empty("BigA", (10.5, 0, 0)), bl.empty("BigB", (7.5, 0, 0))]
    bpy.context.view_layer.update()
    big_deformer = bl.add_probe_deformer(big, probes)
    _key(probes[0], {1: ((10.5, 0, 0), (0, 0, 0)), 12: ((10.8, 0.3, 0.6), (0.3, 0.0, 1.2))})
    bpy.context.scene.frame_set(5)
    assert store._chosen[big.session_uid, big_deformer.uid] == "ATTRIBUTES", "a large mesh in a small scene"
    crowd = bpy.data.collections.new("Crowd")
    bpy.context.scene.collection.children.link(crowd)
    for i in range(3000):
        crowd.objects.link(bpy.data.objects.new(f"E{i}", None))
    for frame in (6, 7):  # the first update after the objects came counts them (after the frame)
        bpy.context.scene.frame_set(frame)
    assert store._chosen[body.session_uid, deformer.uid] == "POSITIONS", "a small mesh beside many objects"
    # 32,514 points × 75 ns = 2.4 ms < 0.7 × 3,000 objects × 4.5 µs: the carrier beside them too
    assert store._chosen[big.session_uid, big_deformer.uid] == "POSITIONS"
    assert deformer.status == "" and big_deformer.status == ""


def test_a_modifier_that_adds_points_before_ours_keeps_the_attributes(bl, store):
    store.forced = "POSITIONS"
    body, deformer = _probe_rig(bl, "Mirrored", 0.0, False)
    mirror = body.modifiers.new("Mirror", "MIRROR")
    body.modifiers.move(len(body.modifiers) - 1, 0)
    bpy.context.scene.frame_set(12)
    found = _carrier(store, body, deformer)
    assert found is None or len(found.data.vertices) == 0
    assert deformer.status == "" and len(bl.evaluated_positions(body)) > len(body.data.vertices)
    assert mirror.show_viewport


def test_apply_remove_and_copies_with_a_position_carrier(bl, installed, store):
    store.forced = "POSITIONS"
    body, deformer = _probe_rig(bl, "Body", 0.0, False)
    bpy.context.scene.frame_set(12)
    shown = bl.evaluated_positions(body).copy()
    found = _carrier(store, body, deformer)
    assert found is not None and len(found.data.vertices) == len(body.data.vertices) + 1
    copy = body.copy()  # Shift+D of a script: its modifier names the original's carrier at first
    copy.data = body.data.copy()
    copy.location.x = 8.0
    bpy.context.scene.collection.objects.link(copy)
    bpy.context.scene.frame_set(11)
    bpy.context.scene.frame_set(12)
    copy_carrier = _carrier(store, copy, copy.affine_deformers[0])
    assert copy_carrier is not None and copy_carrier != found, "a copy gets a carrier of its own"
    assert np.array_equal(bl.evaluated_positions(body), shown)
    copy_shown = bl.evaluated_positions(copy).copy()
    store.forced = "ATTRIBUTES"  # the copy's own result, through the other store
    installed.evaluate.forget()
    bpy.context.scene.frame_set(11)
    bpy.context.scene.frame_set(12)
    assert np.array_equal(bl.evaluated_positions(copy), copy_shown)
    store.forced = "POSITIONS"
    installed.evaluate.forget()
    bpy.context.scene.frame_set(11)
    bpy.context.scene.frame_set(12)
    name = found.name
    bl.run_op(bpy.ops.object.affine_deformer_apply, body, index=0)
    assert len(body.affine_deformers) == 0 and name not in bpy.data.objects, "the carrier goes with it"
    assert np.array_equal(bl.rest_positions(body), shown), "applied: the shown shape is the mesh's"
    copy_name = copy_carrier.name
    bl.run_op(bpy.ops.object.affine_deformer_remove, copy, index=0)
    assert copy_name not in bpy.data.objects


_OPEN = """
import json
import numpy as np
{enable}
bpy.ops.wm.open_mainfile(filepath={path!r}, load_ui=False)
body = bpy.data.objects["Body"]
def positions():
    mesh = body.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).tolist()
out = {{"opened": positions()}}
bpy.context.scene.frame_set(12)
out["12"] = positions()
json.dump(out, open({out!r}, "w"))
"""


def test_a_position_carrier_is_saved_and_reopens_with_or_without_the_addon(bl, store, tmp_path):
    import json

    store.forced = "POSITIONS"
    body, _deformer = _probe_rig(bl, "Body", 0.0, False)
    bpy.context.scene.frame_set(12)
    at_12 = bl.evaluated_positions(body).copy()
    bpy.context.scene.frame_set(7)
    at_7 = bl.evaluated_positions(body).copy()
    path = tmp_path / "positions.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    empty_user = tmp_path / "no_addon"
    empty_user.mkdir()
    for enable, env in (("enable_addon()", None), ("", {"BLENDER_USER_RESOURCES": str(empty_user)})):
        out = tmp_path / f"{bool(enable)}.json"
        bl.run_blender(_OPEN.format(enable=enable, path=str(path), out=str(out)), env_extra=env)
        got = {key: np.array(value, np.float32) for key, value in json.loads(out.read_text()).items()}
        assert np.array_equal(got["opened"], at_7), "the saved frame shows the saved shape"
        if enable:
            assert np.array_equal(got["12"], at_12)
        else:  # without the add-on: the input at another frame (frame_check.py), not a stale shape
            assert np.array_equal(got["12"], bl.rest_positions(body)), "the input"
    assert math.isfinite(float(at_12.sum()))


def test_a_bake_captures_the_output_of_a_position_carrier(bl, installed, store, tmp_path):
    from tests.blender.test_bake import _bake, _live, _scene

    store.forced = "POSITIONS"
    target, deformer = _scene(bl, tmp_path)
    frames = range(1, 21)
    live = _live(bl, target, frames)
    found = _carrier(store, target, deformer)
    assert found is not None and len(found.data.vertices) > 0, "the live output is in a carrier"
    bpy.context.scene.frame_set(7)
    assert _bake(bl, target, index=0, mode="PC2") == {"FINISHED"}
    pc2 = importlib.import_module(f"{installed.package}.blender.tools.pc2")
    samples, _start, _rate = pc2.read_pc2(tmp_path / "Cube_Probe_Deformer.pc2")
    for frame in frames:
        assert np.abs(samples[frame - 1] - live[frame]).max() <= 1e-5, frame
    assert np.array_equal(_live(bl, target, (10,))[10], live[10]), "the cache plays the frames back"
