"""Bones as controls (kinds/bone.py): an affine skin measured against Blender's Armature modifier with
Preserve Volume (dual quaternions) on a bar with identical vertex groups.

The bar runs along +X from 0 to 4 (cross-section 0.4 × 0.4); its bones lie on the X axis. Weights are
smooth ramps in x, quantised to 1/256 so that they can be painted per value (no loop over vertices).
"""

from __future__ import annotations

import importlib
import itertools
import math

import bpy
import numpy as np
import pytest

LENGTH = 4.0
HALF = 0.2


def _bar(bl, cuts: int = 23, name: str = "Bar"):
    obj = bl.grid_cube(cuts=cuts, size=2.0, name=name)
    co = bl.rest_positions(obj).astype(np.float64)
    co[:, 0] = (co[:, 0] + 1.0) * 0.5 * LENGTH
    co[:, 1:] *= HALF
    obj.data.vertices.foreach_set("co", co.astype(np.float32).ravel())
    obj.data.update()
    return obj


def _armature(heads: list[float], name: str = "Rig"):
    """A chain of connected bones along +X from heads[i] to heads[i+1] (names B0, B1, …)."""
    data = bpy.data.armatures.new(name)
    arm = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    previous = None
    for i, (a, b) in enumerate(itertools.pairwise(heads)):
        bone = data.edit_bones.new(f"B{i}")
        bone.head, bone.tail = (a, 0.0, 0.0), (b, 0.0, 0.0)
        bone.roll = 0.0
        if previous is not None:
            bone.parent, bone.use_connect = previous, True
        previous = bone
    bpy.ops.object.mode_set(mode="OBJECT")
    return arm


def _paint(obj, weights: np.ndarray, names: list[str]) -> None:
    """Vertex groups `names` holding weights (N, m), quantised to 1/256: one add() per value."""
    q = np.round(weights * 256.0) / 256.0
    for j, name in enumerate(names):
        group = obj.vertex_groups.new(name=name)
        for value in np.unique(q[:, j]):
            if value > 0.0:
                group.add(np.flatnonzero(q[:, j] == value).tolist(), float(value), "REPLACE")


def _ramp_weights(x: np.ndarray, centers: list[float], width: float) -> np.ndarray:
    """Partition of unity of hat functions of the given width around the bones' centres."""
    hats = np.maximum(0.0, 1.0 - np.abs(x[:, None] - np.array(centers)[None, :]) / width)
    hats[:, 0] = np.where(x <= centers[0], 1.0, hats[:, 0])
    hats[:, -1] = np.where(x >= centers[-1], 1.0, hats[:, -1])
    return hats / hats.sum(axis=1, keepdims=True)


def _rig(bl, heads=(0.0, 2.0, 4.0), width=None):
    bar = _bar(bl)
    arm = _armature(list(heads))
    names = [f"B{i}" for i in range(len(heads) - 1)]
    centers = [0.5 * (a + b) for a, b in itertools.pairwise(heads)]
    x = bl.rest_positions(bar)[:, 0].astype(np.float64)
    _paint(bar, _ramp_weights(x, centers, width or (centers[1] - centers[0])), names)
    native = bar.modifiers.new("Armature", "ARMATURE")
    native.object = arm
    native.use_deform_preserve_volume = True
    native.show_viewport = native.show_render = False
    bpy.context.view_layer.objects.active = bar
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar, arm]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    assert deformer.status == "" and deformer.weight_mode == "VERTEX_GROUPS"
    return bar, arm, native, deformer


def _ours_and_native(bl, bar, native, deformer):
    deformer.show_viewport = True
    native.show_viewport = False
    bpy.context.view_layer.update()
    ours = bl.evaluated_positions(bar).astype(np.float64)
    deformer.show_viewport = False
    native.show_viewport = True
    bpy.context.view_layer.update()
    theirs = bl.evaluated_positions(bar).astype(np.float64)
    deformer.show_viewport = True
    native.show_viewport = False
    bpy.context.view_layer.update()
    return ours, theirs


def _twist_at(rest: np.ndarray, posed: np.ndarray, x0: float) -> float:
    """The mean rotation (degrees, about +X) of the cross-section nearest x = x0."""
    gap = np.abs(rest[:, 0] - x0)
    ring = gap <= gap.min() + 1e-4
    ring &= np.hypot(rest[:, 1], rest[:, 2]) > 1e-6
    a0 = np.arctan2(rest[ring, 2], rest[ring, 1])
    a1 = np.arctan2(posed[ring, 2], posed[ring, 1])
    delta = np.angle(np.mean(np.exp(1j * (a1 - a0))))
    return math.degrees(delta)


def test_rest_pose_gives_the_mesh_back(bl):
    bar, _arm, _native, _deformer = _rig(bl)
    assert np.array_equal(bl.evaluated_positions(bar), bl.rest_positions(bar))


def test_rigid_motions_under_180_agree_with_preserve_volume(bl):
    bar, arm, native, deformer = _rig(bl, heads=(0.0, 1.0, 2.0, 3.0, 4.0))
    bones = arm.pose.bones
    for pb in bones:
        pb.rotation_mode = "XYZ"
    bones["B1"].rotation_euler = (0.0, math.radians(60.0), math.radians(30.0))
    bones["B2"].rotation_euler = (math.radians(20.0), 0.0, math.radians(45.0))
    bones["B3"].rotation_euler = (0.0, math.radians(90.0), 0.0)
    ours, theirs = _ours_and_native(bl, bar, native, deformer)
    difference = np.abs(ours - theirs).max()
    print(f"bar test, rigid bones < 180°: max |ours − Preserve Volume| = {difference:.4f} (bar length 4)")
    assert difference < 0.0025 * LENGTH
    assert deformer.status == ""


@pytest.mark.parametrize(("turn", "ours_mid"), [(270.0, 135.0), (360.0, 180.0)])
def test_twists_past_180_go_on_where_preserve_volume_flips(bl, turn, ours_mid):
    bar, arm, native, deformer = _rig(bl)
    rest = bl.rest_positions(bar).astype(np.float64)
    end = arm.pose.bones["B1"]
    end.rotation_mode = "XYZ"
    end.rotation_euler.y = math.radians(turn)  # a bone's own axis is its local Y
    ours, theirs = _ours_and_native(bl, bar, native, deformer)
    mid = _twist_at(rest, ours, 2.0)
    native_mid = _twist_at(rest, theirs, 2.0)
    print(f"{turn:.0f}° end twist, middle: ours {mid:.1f}°, Preserve Volume {native_mid:.1f}°")
    assert abs(((mid - ours_mid + 180.0) % 360.0) - 180.0) < 1.0
    assert abs(((native_mid - ours_mid + 180.0) % 360.0) - 180.0) > 45.0  # the native one flips
    # Smooth: the twist grows monotonically along the bar (no flip between rings).
    xs = np.unique(np.round(rest[:, 0], 5))
    twists = np.unwrap(np.radians([_twist_at(rest, ours, x) for x in xs]))
    assert np.all(np.diff(twists) * np.sign(turn) >= -1e-3)


def test_a_scaled_and_sheared_bone_is_followed_exactly(bl):
    bar, arm, native, deformer = _rig(bl, heads=(0.0, 2.0, 4.0))
    bones = arm.pose.bones
    bones["B0"].scale = (1.0, 1.0, 2.0)  # non-uniform: its rotated child is sheared
    bones["B1"].rotation_mode = "XYZ"
    bones["B1"].rotation_euler = (0.0, 0.0, math.radians(35.0))
    bones["B1"].scale = (1.3, 0.7, 1.0)
    bpy.context.view_layer.update()
    rest = bl.rest_positions(bar).astype(np.float64)
    ours, theirs = _ours_and_native(bl, bar, native, deformer)
    full = rest[:, 0] > 3.0  # weight 1 on B1
    pose, bone = arm.pose.bones["B1"], arm.data.bones["B1"]
    frame = np.linalg.solve(np.array(bar.matrix_world), np.array(arm.matrix_world))
    motion = frame @ np.array(pose.matrix) @ np.linalg.inv(np.array(bone.matrix_local)) @ np.linalg.inv(frame)
    expected = rest[full] @ motion[:3, :3].T + motion[:3, 3]
    det = np.linalg.det(motion[:3, :3].astype(np.float64))
    assert abs(det - 1.0) > 0.5 and np.isclose(det, 2.0 * 0.91, rtol=1e-4)  # it does scale, by 2 × 0.91
    error = np.abs(ours[full] - expected).max()
    native_error = np.abs(theirs[full] - expected).max() / np.abs(expected - rest[full]).max()
    print(f"scaled + sheared bone: ours {error:.2e}, Preserve Volume {100 * native_error:.0f}% of the motion")
    assert error < 1e-5


def _volume(bl, obj) -> float:
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = obj.evaluated_get(depsgraph).data
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    co = bl.evaluated_positions(obj).astype(np.float64)[tris.reshape(-1, 3)]
    return float(np.einsum("ti,ti->t", co[:, 0], np.cross(co[:, 1], co[:, 2])).sum() / 6.0)


def test_volume_is_kept_in_a_90_degree_bend(bl):
    bar, arm, _native, deformer = _rig(bl, width=1.5)
    rest_volume = _volume(bl, bar)
    end = arm.pose.bones["B1"]
    end.rotation_mode = "XYZ"
    end.rotation_euler.z = math.radians(90.0)
    bpy.context.view_layer.update()
    ratio = _volume(bl, bar) / rest_volume
    print(f"90° bend: volume ratio {ratio:.4f}")
    assert deformer.status == ""
    assert ratio >= 0.99


def test_moving_the_armature_object_alone_does_not_move_the_mesh(bl):
    bar, arm, _native, deformer = _rig(bl)
    rest = bl.rest_positions(bar)
    arm.location = (1.0, 2.0, 0.5)
    arm.rotation_euler.z = 0.7
    bpy.context.view_layer.update()
    assert np.abs(bl.evaluated_positions(bar) - rest).max() < 1e-5
    assert deformer.status == ""


def test_a_bone_name_with_braces_is_named_in_the_status(bl):
    bar, arm, _native, deformer = _rig(bl)
    arm.data.bones["B1"].name = "Tail{0}"
    deformer.bones[1].name = "Tail{0}"
    arm.pose.bones["Tail{0}"].scale = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    assert "Bone 'Tail{0}' is scaled to zero" in deformer.status
    # It collapses what it holds (test_artist_moves.py); B0's own vertices (x ≤ 1) stay at rest.
    rest, got = bl.rest_positions(bar), bl.evaluated_positions(bar)
    assert np.array_equal(got[rest[:, 0] <= 1.0], rest[rest[:, 0] <= 1.0])
    assert np.abs(got - rest).max() > 0.5


def test_bad_inputs_get_a_message_and_the_input_passes_through(bl):
    bar, arm, _native, deformer = _rig(bl)
    rest = bl.rest_positions(bar)
    pose = arm.pose.bones["B1"]
    pose.rotation_mode = "XYZ"
    pose.rotation_euler.y = 1.0
    bpy.context.view_layer.update()
    assert np.abs(bl.evaluated_positions(bar) - rest).max() > 0.01
    pose.scale = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    assert "Bone 'B1' is scaled to zero" in deformer.status
    got = bl.evaluated_positions(bar)  # what it holds collapses (test_artist_moves.py), B0's stays
    assert np.array_equal(got[rest[:, 0] <= 1.0], rest[rest[:, 0] <= 1.0]) and not np.array_equal(got, rest)
    pose.scale = (-1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert "Bone 'B1' is mirrored" in deformer.status
    pose.scale = (1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert deformer.status == ""
    posed = bl.evaluated_positions(bar).copy()
    arm.data.bones["B1"].name = "Renamed"  # followed (issue 57): the item takes the new name
    bpy.context.view_layer.update()
    assert deformer.status == "" and deformer.bones[1].name == "Renamed"
    assert np.array_equal(bl.evaluated_positions(bar), posed)
    arm.data.bones["Renamed"].name = "B1"
    bpy.context.view_layer.update()
    assert deformer.status == "" and deformer.bones[1].name == "B1"
    arm.data.bones.active = arm.data.bones["B1"]
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    arm.data.edit_bones.remove(arm.data.edit_bones["B1"])  # deleted: nothing to follow
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.update()
    assert "has no bone named 'B1'" in deformer.status and "rebind" not in deformer.status
    assert np.array_equal(bl.evaluated_positions(bar), rest)
    bpy.data.objects.remove(arm, do_unlink=True)
    bpy.context.view_layer.update()
    assert "armature" in deformer.status.lower()
    assert np.array_equal(bl.evaluated_positions(bar), rest)


def test_an_armature_disabled_in_viewports_is_followed_while_the_deformer_is_on(bl, installed):
    """The monitor icon on the armature or on its collection (as riggers do): the modifier names the
    armature in its collection, whose relation evaluates the pose (an Object input evaluates only the
    transform: relations.object_input_evaluates), so the mesh follows the pose as when the armature is
    enabled. With the deformer off in viewports the update skips it (nothing is read or written, as
    for a disabled modifier) and, enabled again, it follows the pose; enabled again, or hidden with
    the eye icon, nothing is named."""
    nodes = importlib.import_module(f"{installed.package}.blender.files.nodes")
    bar, arm, _native, deformer = _rig(bl)
    mod = nodes.find_modifier(bar, f"affdef_{deformer.uid}_offset")
    rest = bl.rest_positions(bar)
    bone = arm.pose.bones["B1"]
    bone.rotation_mode = "XYZ"
    shown = {}
    for angle in (0.6, -0.4, 0.9):  # each pose with the armature enabled: the reference
        bone.rotation_euler.z = angle
        bpy.context.view_layer.update()
        shown[angle] = bl.evaluated_positions(bar).copy()
    assert nodes.controls(mod) == (None, None), "enabled everywhere: evaluated without a relation"

    def follows(angle: float) -> None:
        bone.rotation_euler.z = angle
        bpy.context.view_layer.update()
        assert np.array_equal(bl.evaluated_positions(bar), shown[angle]), angle
        assert deformer.status == ""

    arm.hide_viewport = True
    follows(0.6)
    cage, collection = nodes.controls(mod)
    assert cage is None and set(collection.objects) == {arm}, "in the collection, not on the Object input"
    follows(-0.4)
    deformer.show_viewport = False  # nothing asks for the pose then: skipped, as a disabled modifier is
    kept = bl.stored_offsets(bar, deformer)
    bone.rotation_euler.z = 0.9
    bpy.context.view_layer.update()
    assert deformer.status == "" and np.array_equal(bl.stored_offsets(bar, deformer), kept), "nothing read"
    deformer.show_viewport = True
    follows(0.9)
    arm.hide_viewport = False
    arm.hide_set(True)  # the eye icon: evaluated anyway
    follows(0.6)
    assert nodes.controls(mod) == (None, None)
    arm.hide_set(False)
    rigs = bpy.data.collections.new("Rigs")
    bpy.context.scene.collection.children.link(rigs)
    rigs.objects.link(arm)
    bpy.context.scene.collection.objects.unlink(arm)
    rigs.hide_viewport = True  # its collection disabled in viewports
    follows(-0.4)
    assert set(nodes.controls(mod)[1].objects) == {arm}
    rigs.hide_viewport = False
    follows(0.9)
    assert nodes.controls(mod) == (None, None), "enabled again: the relation is dropped"
    bone.rotation_euler.z = 0.0
    bpy.context.view_layer.update()
    assert np.array_equal(bl.evaluated_positions(bar), rest)


def test_an_armature_disabled_and_keyed_between_frame_changes_is_read_at_its_pose(bl, installed):
    """frame_set runs no depsgraph_update_post, so no update saw the armature disabled: the handler
    finds it unevaluated, names it and evaluates again, instead of reading the stale pose."""
    bar, arm, _native, deformer = _rig(bl)
    _key_twist(arm, "B1", {1: 0.0, 20: 90.0})
    expected = {}
    for frame in (10, 20):
        bpy.context.scene.frame_set(frame)
        expected[frame] = bl.evaluated_positions(bar).copy()
    bpy.context.scene.frame_set(1)
    arm.hide_viewport = True
    for frame in (10, 20):
        bpy.context.scene.frame_set(frame)
        assert np.array_equal(bl.evaluated_positions(bar), expected[frame]), frame
        assert deformer.status == ""


def test_a_file_naming_a_disabled_armature_on_the_object_input_is_resynced_at_load(bl, installed, tmp_path):
    """Files saved before armatures went in the collection name a disabled armature on the Object input
    (its pose stale): at load the armature moves to the collection, and the mesh follows its pose."""
    nodes = importlib.import_module(f"{installed.package}.blender.files.nodes")
    bar, arm, _native, deformer = _rig(bl)
    bone = arm.pose.bones["B1"]
    bone.rotation_mode = "XYZ"
    bone.rotation_euler.z = 0.7
    bpy.context.view_layer.update()
    shown = bl.evaluated_positions(bar).copy()
    bone.rotation_euler.z = 0.0
    arm.hide_viewport = True
    bpy.context.view_layer.update()
    mod = nodes.find_modifier(bar, f"affdef_{deformer.uid}_offset")
    nodes.set_controls(mod, arm, None)
    assert nodes.controls(mod) == (arm, None)
    path = tmp_path / "named_on_the_object_input.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    bar, arm = bpy.data.objects["Bar"], bpy.data.objects["Rig"]
    deformer = bar.affine_deformers[0]
    cage, collection = nodes.controls(nodes.find_modifier(bar, f"affdef_{deformer.uid}_offset"))
    assert cage is None and set(collection.objects) == {arm}
    arm.pose.bones["B1"].rotation_euler.z = 0.7
    bpy.context.view_layer.update()
    assert np.array_equal(bl.evaluated_positions(bar), shown)
    assert deformer.status == ""


def _key_twist(arm, bone: str, frames_degrees: dict[int, float]) -> None:
    pose = arm.pose.bones[bone]
    pose.rotation_mode = "XYZ"
    for frame, degrees in frames_degrees.items():
        pose.rotation_euler.y = math.radians(degrees)
        pose.keyframe_insert("rotation_euler", index=1, frame=frame)


def test_keyed_twists_depend_only_on_the_frame_and_survive_reopening(bl, tmp_path):
    bar, arm, _native, deformer = _rig(bl)
    _key_twist(arm, "B1", {1: 0.0, 20: 400.0})
    rest = bl.rest_positions(bar).astype(np.float64)
    seen = {}
    for frame in (20, 1, 10, 20, 15, 10):
        bpy.context.scene.frame_set(frame)
        got = bl.evaluated_positions(bar)
        if frame in seen:
            assert np.array_equal(seen[frame], got), f"frame {frame} depends on the frames before"
        seen[frame] = got.copy()
        assert deformer.status == ""
    assert np.array_equal(seen[1], rest.astype(np.float32))
    assert abs(_twist_at(rest, seen[20].astype(np.float64), 2.0) - 200.0 + 360.0) < 1.0  # 400° / 2
    bl.check_frames_survive_reopen(bar, (1, 10, 20), tmp_path)


def test_a_common_bone_motion_moves_what_reaches_the_modifier(bl):
    """Shape keys before the deformer: a motion G shared by every bone gives exactly G · (the mix)."""
    bar, arm, _native, deformer = _rig(bl)
    bar.shape_key_add(name="Basis", from_mix=False)
    key = bar.shape_key_add(name="Bulge", from_mix=False)
    co = bl.rest_positions(bar).astype(np.float64)
    co[:, 1] *= 1.0 + 0.5 * np.exp(-((co[:, 0] - 2.0) ** 2))
    key.data.foreach_set("co", co.astype(np.float32).ravel())
    key.value = 1.0
    root = arm.pose.bones["B0"]
    root.rotation_mode = "XYZ"
    root.rotation_euler = (0.3, 0.0, 0.8)  # B1 is connected: the whole chain moves rigidly
    bpy.context.view_layer.update()
    frame = np.linalg.solve(np.array(bar.matrix_world), np.array(arm.matrix_world))
    pose, bone = arm.pose.bones["B0"], arm.data.bones["B0"]
    motion = frame @ np.array(pose.matrix) @ np.linalg.inv(np.array(bone.matrix_local)) @ np.linalg.inv(frame)
    expected = co @ motion[:3, :3].T + motion[:3, 3]
    assert deformer.status == ""
    assert np.abs(bl.evaluated_positions(bar) - expected).max() < 1e-5


def test_convert_an_armature_modifier_and_back(bl):
    bar = _bar(bl)
    arm = _armature([0.0, 2.0, 4.0])
    x = bl.rest_positions(bar)[:, 0].astype(np.float64)
    _paint(bar, _ramp_weights(x, [1.0, 3.0], 2.0), ["B0", "B1"])
    bar.modifiers.new("Wave", "WAVE").show_viewport = False  # a modifier above: the place must be kept
    native = bar.modifiers.new("Armature", "ARMATURE")
    native.object = arm
    bar.modifiers.new("Smooth", "SMOOTH").show_viewport = False
    pose = arm.pose.bones["B1"]
    pose.rotation_mode = "XYZ"
    pose.rotation_euler.z = math.radians(40.0)
    bpy.context.view_layer.update()
    theirs = bl.evaluated_positions(bar).astype(np.float64)
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_armature_convert(modifier="Armature") == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    names = [m.name for m in bar.modifiers]
    assert names[:2] == ["Wave", "Armature"] and names[3] == "Smooth", names
    assert bar.modifiers[2].type == "NODES" and not native.show_viewport and not native.show_render
    assert deformer.kind == "BONE" and deformer.armature == arm
    assert [b.name for b in deformer.bones] == ["B0", "B1"]
    assert deformer.weight_mode == "VERTEX_GROUPS" and deformer.status == ""
    ours = bl.evaluated_positions(bar).astype(np.float64)
    full = (x < 1.0) | (x > 3.0)  # one bone each: both are exact there
    assert np.abs(ours[full] - theirs[full]).max() < 1e-5
    assert np.abs(ours - theirs).max() < 0.05  # the blend region: linear blend vs ours
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_armature_restore(index=0) == {"FINISHED"}
    assert len(bar.affine_deformers) == 0 and native.show_viewport and native.show_render
    assert [m.name for m in bar.modifiers] == ["Wave", "Armature", "Smooth"]
    assert np.array_equal(bl.evaluated_positions(bar), theirs.astype(np.float32))


def test_convert_refuses_clearly(bl):
    bar = _bar(bl)
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert not bpy.ops.object.affine_armature_convert.poll()
    native = bar.modifiers.new("Armature", "ARMATURE")
    native.object = _armature([0.0, 2.0, 4.0])
    native.use_vertex_groups = False
    with (bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]),
          pytest.raises(RuntimeError, match="envelopes only")):
        bpy.ops.object.affine_armature_convert()
    assert len(bar.affine_deformers) == 0 and native.show_viewport


def test_distance_weights_without_groups(bl):
    bar = _bar(bl)
    arm = _armature([0.0, 2.0, 4.0])
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar, arm]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    assert deformer.weight_mode == "INVERSE_DISTANCE" and deformer.status == ""
    pose = arm.pose.bones["B1"]
    pose.rotation_mode = "XYZ"
    pose.rotation_euler.z = math.radians(30.0)
    bpy.context.view_layer.update()
    rest = bl.rest_positions(bar)
    moved = np.abs(bl.evaluated_positions(bar) - rest).max(axis=1)
    x = rest[:, 0]
    assert moved[x > 3.5].min() > moved[x < 0.5].max()  # the end follows B1, the root stays


def test_a_chosen_set_of_bones(bl):
    bar, arm, _native, deformer = _rig(bl, heads=(0.0, 1.0, 2.0, 3.0, 4.0))
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_deformer_bone_remove(index=0, bone_index=3) == {"FINISHED"}
        assert [b.name for b in deformer.bones] == ["B0", "B1", "B2"]
        pose = arm.pose.bones["B3"]
        pose.rotation_mode = "XYZ"
        pose.rotation_euler.z = 0.8  # not a control any more: its vertices follow B2 (normalised)
        bpy.context.view_layer.update()
        rest = bl.rest_positions(bar)
        assert np.array_equal(bl.evaluated_positions(bar), rest)
        assert bpy.ops.object.affine_deformer_bone_add(index=0, bone="B3") == {"FINISHED"}
        assert np.abs(bl.evaluated_positions(bar) - rest).max() > 0.1
        with pytest.raises(RuntimeError, match="no bone named 'Nope'"):
            bpy.ops.object.affine_deformer_bone_add(index=0, bone="Nope")
        with pytest.raises(RuntimeError, match="already a control"):
            bpy.ops.object.affine_deformer_bone_add(index=0, bone="B3")
    assert deformer.status == ""


def test_bake_follows_the_bones(bl, tmp_path):
    bar, arm, _native, deformer = _rig(bl)
    _key_twist(arm, "B1", {1: 0.0, 5: 300.0})
    live = {}
    for frame in (1, 3, 5):
        bpy.context.scene.frame_set(frame)
        live[frame] = bl.evaluated_positions(bar).copy()
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_deformer_bake(index=0, mode="SHAPE_KEYS", frame_start=1,
                                                   frame_end=5) == {"FINISHED"}
    assert not deformer.show_viewport
    for frame in (1, 3, 5):
        bpy.context.scene.frame_set(frame)
        assert np.abs(bl.evaluated_positions(bar) - live[frame]).max() < 1e-5, frame


def test_distance_weights_to_vertex_groups_keep_the_deformation(bl):
    """Bones' automatic (distance) weights → groups named after the bones (the Armature modifier's
    convention) → painted weights: the same deformation to 1e-6."""
    bar = _bar(bl)
    arm = _armature([0.0, 2.0, 4.0])
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar, arm]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    pose = arm.pose.bones["B1"]
    pose.rotation_mode = "XYZ"
    pose.rotation_euler = (0.0, math.radians(200.0), math.radians(30.0))
    bpy.context.view_layer.update()
    before = bl.evaluated_positions(bar).astype(np.float64)
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_deformer_weights_to_groups(index=0) == {"FINISHED"}
    assert deformer.weight_mode == "VERTEX_GROUPS" and {g.name for g in bar.vertex_groups} == {"B0", "B1"}
    bpy.context.view_layer.update()
    assert np.abs(bl.evaluated_positions(bar) - before).max() <= 1e-6
    assert deformer.status == ""


def test_a_twist_past_180_under_a_turned_parent_stays_on_the_bone_axis(bl):
    # Blending each bone's whole motion (parent turn and twist together: one screw) moved the middle
    # ring 0.32 off the joint here; blending down the hierarchy keeps it on the joint (MATH.md §14).
    bar, arm, native, deformer = _rig(bl)
    rest = bl.rest_positions(bar).astype(np.float64)
    root, end = arm.pose.bones["B0"], arm.pose.bones["B1"]
    root.rotation_mode = end.rotation_mode = "XYZ"
    root.rotation_euler.z = math.radians(10.0)  # the whole bar bends 10° about the root's head
    end.rotation_euler.y = math.radians(270.0)
    ours, theirs = _ours_and_native(bl, bar, native, deformer)
    joint = np.array(arm.pose.bones["B1"].head)  # B1's head now (armature = bar space here)
    ring = np.abs(rest[:, 0] - 2.0) < 1e-4  # the middle ring: weight ½ on each bone
    off_ours = np.linalg.norm(ours[ring].mean(axis=0) - joint)
    off_native = np.linalg.norm(theirs[ring].mean(axis=0) - joint)
    # In the root bone's frame (its 10° turn undone) the middle ring has turned half of 270° about
    # the bar's axis, and the far end all of it.
    turn = np.array(root.matrix) @ np.linalg.inv(np.array(arm.data.bones["B0"].matrix_local))
    back = (ours - turn[:3, 3]) @ turn[:3, :3]
    mid, tip = _twist_at(rest, back, 2.0), _twist_at(rest, back, LENGTH)
    print(f"10° root bend + 270° end twist: middle ring off the joint by {off_ours:.4f} (ours), "
          f"{off_native:.4f} (Preserve Volume); bar half-width {HALF}; middle turned {mid:.2f}° (ours), "
          f"{_twist_at(rest, (theirs - turn[:3, 3]) @ turn[:3, :3], 2.0):.2f}° (Preserve Volume)")
    assert deformer.status == ""
    assert off_ours < 0.01 * HALF
    assert abs(mid - 135.0) < 0.5
    assert abs(((tip - 270.0 + 180.0) % 360.0) - 180.0) < 0.5
    radius = np.hypot(back[ring, 1], back[ring, 2]) / np.hypot(rest[ring, 1], rest[ring, 2])
    assert np.abs(radius - 1.0).max() < 1e-3


@pytest.mark.attributes  # inspects the attribute store (conftest: skipped on POSITIONS)
@pytest.mark.parametrize("path", ["OFFSET", "MOTION"])
def test_random_pose_changes_match_a_full_recompute_bit_for_bit(bl, installed, path):
    # The blend down the hierarchy recomputes only the vertices that read a changed bone (as prefix
    # or as a factor): every incremental result must equal an evaluation from nothing, bit for bit.
    bar, arm, _native, deformer = _rig(bl, heads=(0.0, 1.0, 2.0, 3.0, 4.0), width=1.5)
    if path == "MOTION":  # a shape key before the deformer: it then writes per-vertex motions
        bar.shape_key_add(name="Basis")
        key = bar.shape_key_add(name="Bulge")
        co = bl.rest_positions(bar).astype(np.float64)
        co[:, 1:] *= 1.3
        key.data.foreach_set("co", co.astype(np.float32).ravel())
        key.value = 0.5
    storage = installed.storage
    read = ((lambda: storage.read_offsets(bar.data, deformer.uid).copy()) if path == "OFFSET"
            else (lambda: storage.read_motions(bar.data, deformer.uid).copy()))
    bones = arm.pose.bones
    for pose_bone in bones:
        pose_bone.rotation_mode = "XYZ"
    rng = np.random.default_rng(11)
    bpy.context.view_layer.update()
    moved, previous = 0, read()
    for step in range(16):
        for pose_bone in rng.choice(list(bones), size=rng.integers(1, 3), replace=False):
            action = rng.integers(0, 3)
            if action == 0:  # back to rest
                pose_bone.rotation_euler, pose_bone.scale = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
            elif action == 1:
                pose_bone.rotation_euler = tuple(rng.uniform(-4.0, 4.0, 3))  # past 180° too
            else:
                pose_bone.scale = tuple(rng.uniform(0.6, 1.5, 3))
        bpy.context.view_layer.update()
        assert deformer.status == ""
        incremental = read()
        installed.evaluate.forget()
        installed.evaluate.evaluate_object(bar, bpy.context.evaluated_depsgraph_get())
        assert np.array_equal(incremental, read()), step
        moved += int(not np.array_equal(incremental, previous))
        previous = incremental
        bpy.context.view_layer.update()  # warm the caches again for the next step
    assert moved > 10


def test_bone_rows_in_a_batch_equal_each_alone_bit_for_bit(installed):
    """kinds.bone._bone_rows computes the bones that moved in one batch: every row must get the bits it
    gets alone (the memo stores rows whatever batch made them) and agree with the one-bone function;
    a bone with a problem gets its message, channels that cannot be unwrapped a NaN turn."""
    import importlib

    import mathutils

    bone = importlib.import_module(f"{installed.package}.blender.kinds.bone")
    rng = np.random.default_rng(3)

    def affine(scale: float = 1.0) -> np.ndarray:
        q = mathutils.Quaternion(rng.normal(size=4)).normalized()
        m = np.eye(4)
        m[:3, :3] = np.array(q.to_matrix()) * scale
        m[:3, 3] = rng.normal(size=3)
        return np.float32(m).astype(np.float64)

    frame = affine(1.3)
    frame_inverse = bone._inverse_affine(frame)
    n = 8
    rests = np.stack([affine() for _ in range(n)])
    poses = np.stack([affine() for _ in range(n)])
    modes = ["XYZ", "QUATERNION", "AXIS_ANGLE", "ZYX", "XYZ", "QUATERNION", "XYZ", "XYZ"]
    channels = [(*rng.normal(size=3) * 5.0, 0.0) if m not in ("QUATERNION", "AXIS_ANGLE")
                else tuple(rng.normal(size=4)) for m in modes]
    poses[4] = rests[4]  # bone 4 at rest (unturned channels)
    channels[4] = (0.0, 0.0, 0.0, 0.0)
    poses[6, 1, 3] = np.inf  # bone 6: not finite
    channels[7] = (1e9, 0.0, 0.0, 0.0)  # bone 7: too many turns to unwrap
    batch = bone._bone_rows(frame, frame_inverse, poses, rests, modes, channels)
    for i in range(n):
        alone = bone._bone_rows(frame, frame_inverse, poses[i : i + 1], rests[i : i + 1], modes[i : i + 1],
                                channels[i : i + 1])[0]
        row = batch[i]
        assert (row.error, row.at_rest, row.unturned) == (alone.error, alone.at_rest, alone.unturned), i
        for a, b in ((row.matrix, alone.matrix), (row.turn, alone.turn), (row.head, alone.head)):
            assert a.tobytes() == b.tobytes(), i
        single = bone._bone_row(frame, frame_inverse, poses[i], rests[i], modes[i], channels[i])
        assert (single.error, single.at_rest, single.unturned) == (row.error, row.at_rest, row.unturned), i
        assert np.allclose(single.matrix, row.matrix, rtol=0, atol=1e-12), i
        assert np.allclose(single.turn, row.turn, rtol=0, atol=1e-9, equal_nan=True), i
        assert np.array_equal(single.head, row.head), i
    assert batch[4].at_rest and np.array_equal(batch[4].matrix, np.eye(4))
    assert "non-finite" in batch[6].error
    assert np.isnan(batch[7].turn).all() and not batch[7].error
    assert not any(batch[i].error for i in (0, 1, 2, 3, 5))


def _ring_rig(bl):
    """A cylinder (radius 0.5, z from −1 to 1) and an armature of a root bone below it (z −1.7 → −1.6)
    with 8 child bones parallel to z on a ring of radius 1: the ring ties on the axis, so distance
    weights at 4 influences pool weight (MATH.md §12), on the bones' tree."""
    bpy.ops.mesh.primitive_cylinder_add(vertices=64, radius=0.5, depth=2.0)
    tube = bpy.context.active_object
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    bpy.ops.mesh.subdivide(number_cuts=12)
    bpy.ops.object.mode_set(mode="OBJECT")
    data = bpy.data.armatures.new("Ring")
    arm = bpy.data.objects.new("Ring", data)
    bpy.context.scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    root = data.edit_bones.new("Root")
    root.head, root.tail = (0.0, 0.0, -1.7), (0.0, 0.0, -1.6)
    for i in range(8):
        a = 2.0 * math.pi * i / 8
        bone = data.edit_bones.new(f"R{i}")
        bone.head, bone.tail = (math.cos(a), math.sin(a), -1.0), (math.cos(a), math.sin(a), 1.0)
        bone.parent = root
    bpy.ops.object.mode_set(mode="OBJECT")
    with bpy.context.temp_override(active_object=tube, object=tube, selected_objects=[tube, arm]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = tube.affine_deformers[0]
    deformer.max_influences = 4
    assert deformer.weight_mode == "INVERSE_DISTANCE" and deformer.status == ""
    return tube, arm, deformer


@pytest.mark.attributes  # inspects the attribute store (conftest: skipped on POSITIONS)
def test_pooled_bone_weight_follows_the_bones_tree(bl, installed):
    """Distance weights of a ring of 8 bones at 4 influences pool weight (on the axis all of it) on
    the pooled nodes m … 2m (the mean of a bone's children, of the roots): the mesh gets what the core
    computes with core.hierarchy's tables, a motion of the root moves it rigidly, the compiled and
    incremental results equal a recompute, and Weights → Vertex Groups keeps the deformation."""
    tube, arm, deformer = _ring_rig(bl)
    storage = installed.storage
    m = len(deformer.bones)
    indices, values = storage.read_weights(tube.data, deformer.uid, 2 * m + 1)
    pooled = np.where(indices >= m, values, 0.0).sum(axis=1)
    assert pooled.max() > 0.3 and (pooled > 0.0).mean() > 0.2 and indices.max() <= 2 * m
    rest = bl.rest_positions(tube).astype(np.float64)

    root = arm.pose.bones["Root"]
    root.rotation_mode = "XYZ"
    root.rotation_euler = (0.4, -0.3, 0.9)
    root.location = (0.2, -0.1, 0.3)
    bpy.context.view_layer.update()
    M = np.array(root.matrix) @ np.linalg.inv(np.array(arm.data.bones["Root"].matrix_local))
    got = bl.evaluated_positions(tube).astype(np.float64)
    assert np.abs(got - (rest @ M[:3, :3].T + M[:3, 3])).max() < 1e-5, "the skeleton's motion, exactly"

    root.rotation_euler, root.location = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    bend = arm.pose.bones["R0"]
    bend.rotation_mode = "XYZ"
    bend.rotation_euler = (0.0, 0.0, 0.0)
    bend.rotation_euler.x = math.radians(60.0)
    bend.location = (0.0, 0.36, 0.0)
    bpy.context.view_layer.update()
    got = bl.evaluated_positions(tube).astype(np.float64)
    assert deformer.status == ""
    hierarchy = importlib.import_module(f"{installed.package}.core.hierarchy")
    aff3 = importlib.import_module(f"{installed.package}.core.aff3")
    A = np.stack([np.eye(4)] + [np.array(arm.pose.bones[f"R{i}"].matrix)
                                @ np.linalg.inv(np.array(arm.data.bones[f"R{i}"].matrix_local))
                                for i in range(8)])
    parents = np.array([-1] + [0] * 8)
    params, matrices = hierarchy.pool_tables(aff3.params_from_matrices(hierarchy.local_motions(A, parents)),
                                             A, hierarchy.pool_mix(parents, np.ones(m)))
    layout = hierarchy.chain_layout(indices, values, hierarchy.pool_parents(parents))
    expected = hierarchy.chain_points(rest, params, hierarchy.prefix_table(matrices), layout)
    assert np.abs(got - expected).max() < 1e-4
    axis = np.hypot(rest[:, 0], rest[:, 1]) < 1e-6
    assert np.abs(got - rest)[~axis].max() > 0.05

    incremental = storage.read_offsets(tube.data, deformer.uid).copy()
    installed.evaluate.forget()
    installed.evaluate.evaluate_object(tube, bpy.context.evaluated_depsgraph_get())
    assert np.array_equal(incremental, storage.read_offsets(tube.data, deformer.uid))

    with bpy.context.temp_override(active_object=tube, object=tube, selected_objects=[tube]):
        assert bpy.ops.object.affine_deformer_weights_to_groups(index=0) == {"FINISHED"}
    assert deformer.weight_mode == "VERTEX_GROUPS"
    bpy.context.view_layer.update()
    assert np.abs(bl.evaluated_positions(tube) - got).max() <= 1e-5
    assert deformer.status == ""

    deformer.weight_mode = "INVERSE_DISTANCE"
    deformer.max_influences = 4
    deformer.blend_mode = "LINEAR"
    bpy.context.view_layer.update()
    assert deformer.status == "" and np.abs(bl.evaluated_positions(tube) - rest).max() > 0.05


def test_an_update_of_many_bone_deformed_objects_matches_each_alone_bit_for_bit(bl, installed, monkeypatch):
    """One update of several bone-deformed objects computes all their moved bones in one batch and their
    parameters in one batch per branch treatment (evaluate._prefetch, kinds.bone's prefetch) and their
    vertices in one kernel batch (accel.KernelBatch); each object gets bit for bit the offsets it gets
    evaluated alone, and a deformer naming a bone its armature lost reports it without touching the
    others."""
    import importlib

    bone = importlib.import_module(f"{installed.package}.blender.kinds.bone")
    rng = np.random.default_rng(7)
    rigs = []
    for n, rule in enumerate(("CHANNELS", "SHORTEST", "CHANNELS", "CHANNELS")):
        bar, arm, _native, deformer = _rig(bl, heads=(0.0, 1.0, 2.0, 3.0, 4.0), width=1.5)
        for obj in (bar, arm):
            obj.location = (0.0, 3.0 * n, 0.5 * n)
            obj.rotation_euler = (0.0, 0.0, 0.4 * n)
        deformer.branch_rule = rule
        for pose_bone in arm.pose.bones:
            pose_bone.rotation_mode = ("XYZ", "QUATERNION", "AXIS_ANGLE", "ZXY")[n]
        rigs.append((bar, arm, deformer))
    bpy.context.view_layer.update()
    for _bar_obj, arm, _deformer in rigs:  # an update after the bind's: the next one is incremental
        arm.pose.bones[0].location.x += 0.01
    bpy.context.view_layer.update()
    batches, kernel_batches = [], []
    real = bone._bone_rows
    monkeypatch.setattr(bone, "_bone_rows", lambda *a: batches.append(len(a[2])) or real(*a))
    kernel = importlib.import_module(f"{installed.package}.accel.batch").KernelBatch
    real_run = kernel.run
    monkeypatch.setattr(kernel, "run", lambda self: kernel_batches.append(len(self)) or real_run(self))
    for _bar_obj, arm, _deformer in rigs:
        for pose_bone in arm.pose.bones:
            if pose_bone.rotation_mode == "QUATERNION":
                pose_bone.rotation_quaternion = tuple(rng.normal(size=4))
            elif pose_bone.rotation_mode == "AXIS_ANGLE":
                pose_bone.rotation_axis_angle = (float(rng.uniform(-9.0, 9.0)), *rng.normal(size=3))
            else:
                pose_bone.rotation_euler = tuple(rng.uniform(-4.0, 4.0, 3))  # past 180° too
            pose_bone.scale = tuple(rng.uniform(0.7, 1.4, 3))
    lost = rigs[3][1]
    lost.data.bones["B3"].use_deform = False  # no longer a deform bone: a rename cannot be followed to it
    lost.data.bones["B3"].name = "Gone"  # its deformer still names B3
    bpy.context.view_layer.update()
    assert batches == [15], "in one batch: every bone read, the lost rig's up to the missing one"
    if importlib.import_module(f"{installed.package}.accel").active():
        assert kernel_batches[0] == 3, "the blends of the three sound rigs in one kernel batch"
    assert "no bone named 'B3'" in rigs[3][2].status
    for bar, _arm, deformer in rigs[:3]:
        assert deformer.status == ""
        shown = bl.stored_offsets(bar, deformer)
        assert np.abs(shown).max() > 0.05
        alone = bl.recomputed_offsets(bar, deformer)
        assert shown.tobytes() == alone.tobytes(), bar.name
