"""Read-ahead (read_ahead.py): frames computed before Blender evaluates them give exactly the shapes of
the update after the frame — keyed, parented, constrained and driven probes, bones posed through IK,
cages driven by an Armature modifier and by shape keys, frames in any order and motion-blur subframes
— and need no write after the frame (one evaluation); what cannot be read ahead (a target that moves)
is still right, written after the frame."""

from __future__ import annotations

import importlib

import bpy
import numpy as np
import pytest

from tests.blender.test_cage_deformer import add_cage_deformer, box_cage

VISITS = ((5, 0.0), (1, 0.0), (12, 0.0), (7, 0.25), (12, 0.0), (3, 0.5))


def _keyed(obj, path: str, values: dict) -> None:
    for frame, value in values.items():
        setattr(obj, path, value)
        obj.keyframe_insert(path, frame=frame)


def _probes(bl):
    body = bl.grid_cube(cuts=4, name="Probed")
    parent = bl.empty("Parent", (0, 0, 0))
    places = (("Keyed", (1.5, 0, 0)), ("Parented", (-1.5, 0, 0)), ("Tracked", (0, 1.5, 0)),
              ("Driven", (0, -1.5, 0)))
    keyed, parented, tracked, driven = (bl.empty(name, location) for name, location in places)
    bpy.context.view_layer.update()
    bl.add_probe_deformer(body, [keyed, parented, tracked, driven])
    _keyed(keyed, "location", {1: (1.5, 0, 0), 12: (1.9, 0.4, 0.7)})
    _keyed(parent, "rotation_euler", {1: (0, 0, 0), 12: (0.2, 0.1, 0.9)})
    parented.parent = parent
    aim = bl.empty("Aim", (3, 3, 1))
    _keyed(aim, "location", {1: (3, 3, 1), 12: (-2, 3, 2)})
    constraint = tracked.constraints.new("TRACK_TO")
    constraint.target = aim
    driver = driven.driver_add("scale", 2).driver
    driver.type = "SCRIPTED"
    variable = driver.variables.new()
    variable.targets[0].id = parent
    variable.targets[0].data_path = "rotation_euler.z"
    driver.expression = "1 + var"
    return body


def _bones(bl):
    body = bl.grid_cube(cuts=6, name="Boned")
    body.location.x = 6.0
    arm = bpy.data.objects.new("Arm", bpy.data.armatures.new("Arm"))
    arm.location.x = 6.0
    bpy.context.scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    parent = None
    for i, (a, b) in enumerate(((-1.0, 0.0), (0.0, 1.0))):
        bone = arm.data.edit_bones.new(f"B{i}")
        bone.head, bone.tail = (a, 0, 0), (b, 0, 0)
        if parent is not None:
            bone.parent, bone.use_connect = parent, True
        parent = bone
    bpy.ops.object.mode_set(mode="OBJECT")
    goal = bl.empty("Goal", (7.0, 0.0, 0.5))
    _keyed(goal, "location", {1: (7.0, 0.0, 0.5), 12: (6.3, 0.6, 1.0)})
    ik = arm.pose.bones["B1"].constraints.new("IK")
    ik.target, ik.chain_count = goal, 2
    with bpy.context.temp_override(active_object=body, object=body, selected_objects=[body, arm]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    return body


def _cages(bl):
    body = bl.grid_cube(cuts=4, name="Caged")
    body.location.y = 6.0
    cage = box_cage()
    cage.location.y = 6.0
    bpy.context.view_layer.update()
    add_cage_deformer(body, cage)
    cage.shape_key_add(name="Basis")
    bulge = cage.shape_key_add(name="Bulge")
    co = np.empty(len(bulge.data) * 3, np.float32)
    bulge.data.foreach_get("co", co)
    bulge.data.foreach_set("co", (co * 1.3).ravel())
    _keyed(bulge, "value", {1: 0.0, 12: 1.0})
    rig = bpy.data.objects.new("CageArm", bpy.data.armatures.new("CageArm"))
    bpy.context.scene.collection.objects.link(rig)
    _keyed(rig, "location", {1: (0, 6.0, 0), 12: (0.3, 6.2, 0.1)})
    rig.location = (0, 6.0, 0)
    mod = cage.modifiers.new("Armature", "ARMATURE")  # no bones: the armature object's motion alone
    mod.object = rig
    return body


def _play(bl, bodies) -> dict:
    got = {}
    for frame, subframe in VISITS:
        bpy.context.scene.frame_set(frame, subframe=subframe)
        for body in bodies:
            statuses = [d.status for d in body.affine_deformers]
            assert statuses == [""] * len(statuses), statuses
            got[body.name, frame, subframe] = bl.evaluated_positions(body).copy()
    return got


@pytest.fixture
def modules(installed, monkeypatch):
    ahead = importlib.import_module(f"{installed.package}.blender.update.read_ahead")
    evaluate = importlib.import_module(f"{installed.package}.blender.update.evaluate")
    monkeypatch.setattr(ahead, "enabled", True)
    monkeypatch.setattr(ahead, "always", True)  # these scenes are small: read ahead all the same
    return ahead, evaluate


def _count_writes(evaluate, monkeypatch) -> list:
    """Each write of an output, tagged 'ahead' (before the frame's evaluation) or 'after'."""
    writes, phase = [], ["after"]
    real_run, real_write = evaluate.run, evaluate._write

    def run(scene, depsgraph, read=None):
        phase[0] = "ahead" if read is not None else "after"
        return real_run(scene, depsgraph, read=read)

    monkeypatch.setattr(evaluate, "run", run)
    monkeypatch.setattr(evaluate, "_write", lambda *a, **k: writes.append(phase[0]) or real_write(*a, **k))
    return writes


@pytest.mark.parametrize("store", ["ATTRIBUTES", "POSITIONS"])
def test_frames_read_ahead_are_the_frames_written_after_bit_for_bit(bl, installed, modules, monkeypatch,
                                                                   store):
    ahead, evaluate = modules
    output_store = importlib.import_module(f"{installed.package}.blender.update.output_store")
    if store == "POSITIONS" and not output_store.POSITIONS_TAG_THEMSELVES:
        pytest.skip(f"no position store on Blender {bpy.app.version_string}")
    monkeypatch.setattr(output_store, "forced", store)
    bodies = [_probes(bl), _bones(bl), _cages(bl)]
    ahead.enabled = False
    evaluate.forget()
    after = _play(bl, bodies)
    assert np.abs(after["Probed", 12, 0.0] - after["Probed", 1, 0.0]).max() > 0.1
    assert np.abs(after["Boned", 12, 0.0] - after["Boned", 1, 0.0]).max() > 0.1
    assert np.abs(after["Caged", 12, 0.0] - after["Caged", 1, 0.0]).max() > 0.1
    ahead.enabled = True
    evaluate.forget()
    writes = _count_writes(evaluate, monkeypatch)
    read = _play(bl, bodies)
    for key, value in after.items():
        assert np.array_equal(read[key], value), key
    assert writes.count("ahead") >= len(bodies) * (len(VISITS) - 1), writes
    assert "after" not in writes, "every frame was right before its evaluation: no second one"
    helper = bpy.data.scenes.get(ahead.HELPER)
    assert helper is not None and {o.name for o in helper.collection.objects} >= {"Keyed", "Arm", "Cage"}


def test_a_moving_target_is_written_after_the_frame(bl, modules, monkeypatch):
    _ahead, evaluate = modules
    body = _probes(bl)
    _keyed(body, "location", {1: (0, 0, 0), 12: (0.5, 0.2, 0.0)})
    writes = _count_writes(evaluate, monkeypatch)
    got = _play(bl, [body])
    assert "after" in writes, "its transform is the frame's, which the helper does not evaluate"
    evaluate.forget()
    _ahead.enabled = False
    again = _play(bl, [body])
    for key, value in again.items():
        assert np.array_equal(got[key], value), key


def test_the_helper_scene_is_never_saved_and_hides_nothing(bl, modules, tmp_path):
    ahead, _evaluate = modules
    body = _probes(bl)
    bpy.context.scene.frame_set(4)
    assert bpy.data.scenes.get(ahead.HELPER) is not None
    keyed = bpy.data.objects["Keyed"]
    bpy.context.scene.collection.objects.unlink(keyed)  # taken out of the artist's scene
    bpy.context.scene.frame_set(5)
    assert "not in any scene" in body.affine_deformers[0].status, body.affine_deformers[0].status
    bpy.context.scene.collection.objects.link(keyed)
    path = tmp_path / "saved.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)  # the open file stays another one
    with bpy.data.libraries.load(str(path)) as (data_from, _data_to):
        assert ahead.HELPER not in data_from.scenes, "the helper scene is not saved"
    bpy.context.scene.frame_set(6)
    assert body.affine_deformers[0].status == ""


def test_a_small_scene_is_not_read_ahead_a_large_one_is(bl, modules, monkeypatch):
    """Reading ahead reads the controls twice; it pays only where the evaluation it saves walks many
    objects (read_ahead.WALK_SECONDS, READ_SECONDS)."""
    ahead, evaluate = modules
    monkeypatch.setattr(ahead, "always", False)
    body = _probes(bl)
    writes = _count_writes(evaluate, monkeypatch)
    _play(bl, [body])
    assert "ahead" not in writes, "a handful of objects: written after the frame"
    crowd = bpy.data.collections.new("Crowd")
    bpy.context.scene.collection.children.link(crowd)
    for i in range(1000):
        crowd.objects.link(bpy.data.objects.new(f"E{i}", None))
    bpy.context.scene.frame_set(2)  # the first update after they came counts them
    writes.clear()
    _play(bl, [body])
    assert "ahead" in writes and "after" not in writes, writes
