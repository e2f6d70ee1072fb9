"""The deformer as a real modifier: it deforms what reaches it in the stack (shape keys, an Armature,
Subdivision, another of our deformers), like a Hook at the same place, and linked duplicates never
corrupt each other. Inputs are read with our modifier disabled; expectations are computed without
the add-on (numpy, or the core's contract function on the input positions)."""

from __future__ import annotations

import importlib
import math
from pathlib import Path

import bpy
import numpy as np
import pytest
from mathutils import Matrix

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"

#: Two poses of a two-level rig (outer: location, rotation, non-uniform scale; inner: rotation), so the
#: world map G = outer · inner has rotation, scale, shear and translation (det > 0): an object's own
#: channels cannot hold a shear, a parent chain can.
POSE_1 = ((0.4, -0.3, 0.6), (0.2, -0.5, 0.9), (1.3, 0.8, 1.1), (0.7, 0.3, -0.4))
POSE_2 = ((-0.2, 0.5, 0.1), (-0.3, 0.1, -0.9), (0.9, 1.2, 1.0), (0.2, -0.6, 0.3))


def _probes(bl, prefix: str = "P"):
    probes = [bl.empty(f"{prefix}0", (1.2, 0.0, 0.0)), bl.empty(f"{prefix}1", (-1.2, 0.3, 0.0)),
              bl.empty(f"{prefix}2", (0.0, 0.0, 1.5))]
    probes[0].rotation_euler = (0.3, 0.2, 0.1)
    probes[1].scale = (1.5, 1.0, 0.7)
    bpy.context.view_layer.update()
    return probes


def _move_all(objects, pose) -> Matrix:
    """Parent `objects` under a new two-level rig at identity, pose it; returns the world map G every
    object was moved by."""
    outer, inner = (bpy.data.objects.new(name, None) for name in ("RigOuter", "RigInner"))
    for rig in (outer, inner):
        bpy.context.scene.collection.objects.link(rig)
    inner.parent = outer
    for obj in objects:
        obj.parent = inner
    location, rotation, scale, inner_rotation = pose
    outer.location, outer.rotation_euler, outer.scale = location, rotation, scale
    inner.rotation_euler = inner_rotation
    bpy.context.view_layer.update()
    return inner.matrix_world.copy()


def _local(target, G) -> np.ndarray:
    """G (world) as it acts in the target's local space."""
    T = np.array(target.matrix_world, dtype=np.float64)
    return np.linalg.inv(T) @ np.array(G, dtype=np.float64) @ T


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]


def _our_modifier(target, deformer):
    package = bpy.context.preferences.addons[next(a.module for a in bpy.context.preferences.addons
                                                  if a.module.endswith("affine_deformers"))].module
    nodes = importlib.import_module(f"{package}.affine_deformers.blender.files.nodes")
    storage = importlib.import_module(f"{package}.affine_deformers.blender.files.storage")
    return nodes.find_modifier(target, storage.offset_name(deformer.uid))


def _input_of(bl, target, deformer) -> np.ndarray:
    """What reaches the deformer's modifier (with everything after it disabled too, and itself off)."""
    mod = _our_modifier(target, deformer)
    after = list(target.modifiers)[list(target.modifiers).index(mod):]
    flags = [m.show_viewport for m in after]
    for m in after:
        m.show_viewport = False
    try:
        return bl.evaluated_positions(target).copy()
    finally:
        for m, flag in zip(after, flags, strict=True):
            m.show_viewport = flag


def _shape_keyed(bl):
    target = bl.grid_cube(cuts=8)
    target.shape_key_add(name="Basis", from_mix=False)
    key = target.shape_key_add(name="Bulge", from_mix=False)
    co = bl.rest_positions(target).astype(np.float64)
    bulged = co + np.stack([0.3 * co[:, 1] * co[:, 2], 0.25 * np.sin(2.0 * co[:, 0]), 0.4 * co[:, 0] ** 2], 1)
    key.data.foreach_set("co", bulged.astype(np.float32).ravel())
    return target, key


def _bending_armature(target, angle: float = 1.0):
    """Two bones along x through the target, smooth vertex groups, an Armature modifier (added first)
    and the second bone turned by `angle` about z."""
    data = bpy.data.armatures.new("Rig")
    rig = bpy.data.objects.new("Rig", data)
    bpy.context.scene.collection.objects.link(rig)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    b1 = data.edit_bones.new("B1")
    b1.head, b1.tail = (-1.2, 0.0, 0.0), (0.0, 0.0, 0.0)
    b2 = data.edit_bones.new("B2")
    b2.head, b2.tail = (0.0, 0.0, 0.0), (1.2, 0.0, 0.0)
    b2.parent, b2.use_connect = b1, True
    bpy.ops.object.mode_set(mode="OBJECT")
    co = np.empty(len(target.data.vertices) * 3, dtype=np.float32)
    target.data.vertices.foreach_get("co", co)
    x = co.reshape(-1, 3)[:, 0]
    w2 = np.clip((x + 0.4) / 0.8, 0.0, 1.0)
    g1, g2 = target.vertex_groups.new(name="B1"), target.vertex_groups.new(name="B2")
    for i, w in enumerate(w2):
        g1.add([i], float(1.0 - w), "REPLACE")
        g2.add([i], float(w), "REPLACE")
    mod = target.modifiers.new("Armature", "ARMATURE")
    mod.object = rig
    pose = rig.pose.bones["B2"]
    pose.rotation_mode = "XYZ"
    pose.rotation_euler = (0.0, 0.0, angle)
    bpy.context.view_layer.update()
    return rig, mod


def _expected_contract(installed, target, deformer, probes, points: np.ndarray, bl) -> np.ndarray:
    """The core's contract function on the given input positions: φ(Σ w ψ(A_i)) p."""
    transforms = np.stack([bl.local_motion(target, p, item.rest_matrix)
                           for p, item in zip(probes, deformer.probes, strict=True)])
    weights = bl.dense_weights(target, deformer)
    return installed.deform.deform_points(points.astype(np.float64), transforms, weights)


# ------------------------------------------------------------------------------------ shape keys


@pytest.mark.parametrize("value", [1.0, 0.5])
def test_common_motion_on_a_shape_keyed_mesh_is_exact(bl, value):
    target, key = _shape_keyed(bl)
    key.value = value
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, normalize="SUM")
    before = bl.evaluated_positions(target).copy()
    keyed = _input_of(bl, target, deformer)
    assert np.array_equal(before, keyed), "at rest the modifier passes the keyed shape through"
    assert np.abs(keyed - bl.rest_positions(target)).max() > 0.1 * value, "the key does move the mesh"
    G = _move_all(probes, POSE_1)
    got = bl.evaluated_positions(target)
    assert np.abs(got - _apply(_local(target, G), keyed)).max() < 1e-5
    assert deformer.status == ""


def test_a_non_common_motion_deforms_the_keyed_shape(installed, bl):
    target, key = _shape_keyed(bl)
    key.value = 0.7
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, weight_mode="FALLOFF", radius=2.5)
    probes[0].rotation_euler.z += 1.1
    probes[2].location.x -= 0.4
    probes[1].scale.y = 1.6
    bpy.context.view_layer.update()
    keyed = _input_of(bl, target, deformer)
    got = bl.evaluated_positions(target)
    expected = _expected_contract(installed, target, deformer, probes, keyed, bl)
    assert np.abs(got - expected).max() < 1e-5
    assert np.abs(got - keyed).max() > 0.1


@pytest.mark.attributes  # inspects the attribute store (conftest: skipped on POSITIONS)
def test_a_basis_only_key_keeps_the_fast_path_until_its_shape_differs(installed, bl):
    """A lone reference key holding the mesh's positions changes nothing (offsets stay exact); once its
    data differ, that is what reaches the modifier, and the deformer switches to motions."""
    target = bl.grid_cube(cuts=6)
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, weight_mode="FALLOFF", radius=2.5)
    probes[0].rotation_euler.z += 0.9
    bpy.context.view_layer.update()
    before = bl.evaluated_positions(target).copy()
    basis = target.shape_key_add(name="Basis", from_mix=False)
    assert np.array_equal(bl.evaluated_positions(target), before), "same path, same bits"
    assert installed.storage.read_offsets(target.data, deformer.uid) is not None
    co = bl.rest_positions(target)
    co[:, 2] += 0.25 * co[:, 0]
    basis.data.foreach_set("co", co.ravel())
    target.data.update()
    got = bl.evaluated_positions(target)
    assert installed.storage.read_offsets(target.data, deformer.uid) is None, "one output form at a time"
    assert np.abs(got - _expected_contract(installed, target, deformer, probes, co, bl)).max() < 1e-5


# ------------------------------------------------------------------------------------ armature


def test_common_motion_after_an_armature_is_exact(bl):
    target = bl.grid_cube(cuts=8)
    _bending_armature(target)
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, normalize="SUM")
    bent = _input_of(bl, target, deformer)
    assert np.abs(bent - bl.rest_positions(target)).max() > 0.3, "the armature bends the mesh"
    G = _move_all(probes, POSE_1)
    got = bl.evaluated_positions(target)
    assert np.abs(got - _apply(_local(target, G), bent)).max() < 1e-5
    assert deformer.status == ""


def test_a_non_common_motion_after_an_armature_deforms_the_bent_shape(installed, bl):
    target = bl.grid_cube(cuts=8)
    _bending_armature(target, angle=-0.8)
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, weight_mode="FALLOFF", radius=2.5)
    probes[1].rotation_euler.x += 0.9
    probes[0].location.z += 0.5
    bpy.context.view_layer.update()
    bent = _input_of(bl, target, deformer)
    got = bl.evaluated_positions(target)
    assert np.abs(got - _expected_contract(installed, target, deformer, probes, bent, bl)).max() < 1e-5


@pytest.mark.parametrize("blend_mode", ["LINEAR", "AFFINE_LOG"])
def test_blend_mode_and_strength_after_an_armature(installed, bl, blend_mode):
    """The linear comparison blend and a strength below 1 on the motion path: v' = (Σ w_i A_i +
    (1 − Σ w_i) I) v, and φ(s Σ w_i ψ(A_i)) v, on the bent input."""
    target = bl.grid_cube(cuts=6)
    _bending_armature(target, angle=0.7)
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, weight_mode="FALLOFF", radius=2.5, blend_mode=blend_mode,
                                     strength=0.6)
    probes[0].rotation_euler.y += 0.8
    probes[2].scale.x = 1.4
    bpy.context.view_layer.update()
    bent = _input_of(bl, target, deformer).astype(np.float64)
    got = bl.evaluated_positions(target)
    W = 0.6 * bl.dense_weights(target, deformer)
    transforms = np.stack([bl.local_motion(target, p, item.rest_matrix)
                           for p, item in zip(probes, deformer.probes, strict=True)])
    if blend_mode == "LINEAR":
        expected = bent + np.einsum("vm,mij,vj->vi", W, transforms[:, :3, :3] - np.eye(3), bent)
        expected += W @ transforms[:, :3, 3]
    else:
        expected = installed.deform.deform_points(bent, transforms, W)
    assert np.abs(got - expected).max() < 1e-5
    assert np.abs(got - bent).max() > 0.05


def test_stack_position_changes_the_result_as_a_hooks_does(bl):
    """Ours (every probe moved by G) and a Hook (its empty moved by G, all vertices, no falloff) on two
    identical bent meshes: the same result above the Armature and below it, and the two differ."""
    results = {}
    for name in ("ours", "hook"):
        target = bl.grid_cube(cuts=6, name=f"Bar_{name}")
        _bending_armature(target, angle=1.2)
        if name == "ours":
            controls = _probes(bl, prefix=f"{name}_")
            deformer = bl.add_probe_deformer(target, controls, normalize="SUM")
            mod = _our_modifier(target, deformer)
        else:
            hook_empty = bl.empty("Hook", (0.3, 0.2, 0.1))
            controls = [hook_empty]
            bpy.context.view_layer.update()
            mod = target.modifiers.new("Hook", "HOOK")
            mod.object = hook_empty
            mod.falloff_type = "NONE"
            mod.vertex_indices_set(range(len(target.data.vertices)))
            mod.matrix_inverse = hook_empty.matrix_world.inverted() @ target.matrix_world
        _move_all(controls, POSE_1)
        below = bl.evaluated_positions(target).copy()
        target.modifiers.move(list(target.modifiers).index(mod), 0)
        above = bl.evaluated_positions(target).copy()
        results[name] = (below, above)
        if name == "ours":
            assert deformer.status == ""
    (ours_below, ours_above), (hook_below, hook_above) = results["ours"], results["hook"]
    assert np.abs(ours_below - ours_above).max() > 0.2, "the order matters for this rig"
    assert np.abs(ours_below - hook_below).max() < 1e-5
    assert np.abs(ours_above - hook_above).max() < 1e-5


# ------------------------------------------------------------------------------------ two deformers


def test_two_deformers_compose_in_stack_order(bl):
    target = bl.grid_cube(cuts=8)
    first, second = _probes(bl, "A"), _probes(bl, "B")
    d1 = bl.add_probe_deformer(target, first, normalize="SUM")
    d2 = bl.add_probe_deformer(target, second, normalize="SUM")
    rest = bl.rest_positions(target).copy()
    G1 = _move_all(first, POSE_1)
    G2 = _move_all(second, POSE_2)
    got = bl.evaluated_positions(target)
    expected = _apply(_local(target, G2) @ _local(target, G1), rest)
    assert np.abs(got - expected).max() < 1e-5
    assert d1.status == d2.status == ""
    # Swapped in the stack, they compose the other way round.
    target.modifiers.move(1, 0)
    got = bl.evaluated_positions(target)
    expected = _apply(_local(target, G1) @ _local(target, G2), rest)
    assert np.abs(got - expected).max() < 1e-5


# ------------------------------------------------------------------------------------ topology changes


@pytest.mark.parametrize("kind", ["SUBSURF", "MIRROR", "ARRAY", "SOLIDIFY"])
def test_modifiers_that_add_vertices_before_the_deformer_carry_the_motions(bl, kind):
    target = bl.grid_cube(cuts=4)
    added = target.modifiers.new(kind.title(), kind)
    if kind == "SUBSURF":
        added.levels = 1
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, normalize="SUM")
    subdivided = _input_of(bl, target, deformer)
    assert len(subdivided) > len(target.data.vertices)
    G = _move_all(probes, POSE_1)
    got = bl.evaluated_positions(target)
    assert got.shape == subdivided.shape
    assert np.abs(got - _apply(_local(target, G), subdivided)).max() < 1e-5
    assert deformer.status == ""


def test_a_modifier_that_rebuilds_the_mesh_before_it_is_named_and_the_input_passes(bl):
    target = bl.grid_cube(cuts=4)
    remesh = target.modifiers.new("Remesh", "REMESH")
    remesh.voxel_size = 0.2
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes)
    G = _move_all(probes, POSE_1)
    got = bl.evaluated_positions(target)
    assert np.array_equal(got, _input_of(bl, target, deformer)), "the input passes through unchanged"
    assert "'Remesh'" in deformer.status and "below" in deformer.status
    remesh.show_viewport = remesh.show_render = False
    bpy.context.view_layer.update()
    bl.evaluated_positions(target)
    assert deformer.status == ""
    assert np.abs(bl.evaluated_positions(target) - _apply(_local(target, G), bl.rest_positions(target))
                  ).max() < 1e-5


# ------------------------------------------------------------------------------------ cage


def test_cage_after_an_armature_reproduces_a_common_motion(bl):
    target = bl.grid_cube(cuts=6, size=1.6)
    _bending_armature(target, angle=0.8)
    cage = bl.grid_cube(cuts=1, size=2.6, name="Cage")
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, cage]):
        assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
    deformer = target.affine_deformers[0]
    bent = _input_of(bl, target, deformer)
    # The cage's vertices moved by G (a shape change: per-face motions; the cage sits at the origin
    # unrotated, so its object space is world space), then the cage object itself by G2 (outer motion).
    probe = bpy.data.objects.new("Measure", None)
    bpy.context.scene.collection.objects.link(probe)
    G = np.array(_move_all([probe], POSE_1), dtype=np.float64)
    co = np.empty(len(cage.data.vertices) * 3, dtype=np.float32)
    cage.data.vertices.foreach_get("co", co)
    cage.data.vertices.foreach_set("co", _apply(G, co.reshape(-1, 3)).astype(np.float32).ravel())
    cage.data.update()
    bpy.context.view_layer.update()
    got = bl.evaluated_positions(target)
    assert np.abs(got - _apply(_local(target, G), bent)).max() < 1e-5
    G2 = np.array(_move_all([cage], POSE_2), dtype=np.float64)
    got = bl.evaluated_positions(target)
    assert np.abs(got - _apply(_local(target, G2 @ G), bent)).max() < 1e-5
    assert deformer.status == ""


# ------------------------------------------------------------------------------------ linked duplicates


def test_a_linked_duplicate_never_changes_the_original(installed, bl):
    target = bl.grid_cube(cuts=6)
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, weight_mode="FALLOFF", radius=2.5)
    probes[0].rotation_euler.z += 0.8
    bpy.context.view_layer.update()
    original = bl.evaluated_positions(target).copy()
    copy = target.copy()  # what Alt+D makes: the same mesh, copied modifiers and deformers
    bpy.context.scene.collection.objects.link(copy)
    copy.location.x += 3.0
    bpy.context.view_layer.update()
    bl.evaluated_positions(copy)
    assert np.array_equal(bl.evaluated_positions(target), original), "the original is bit-for-bit unchanged"
    assert copy.data == target.data and copy.affine_deformers[0].uid != deformer.uid
    # The copy deforms by its own probes' motions relative to it (probes did not move with it).
    copy_deformer = copy.affine_deformers[0]
    got = bl.evaluated_positions(copy)
    expected = _expected_contract(installed, copy, copy_deformer, probes, bl.rest_positions(copy), bl)
    assert np.abs(got - expected).max() < 1e-5
    assert deformer.status == copy_deformer.status == ""
    # Moving a probe now changes both, each by its own result; removing the copy's deformer leaves the
    # original's data alone.
    probes[1].location.y += 0.3
    bpy.context.view_layer.update()
    moved = bl.evaluated_positions(target).copy()
    assert np.abs(moved - original).max() > 1e-3
    with bpy.context.temp_override(active_object=copy, object=copy, selected_objects=[copy]):
        assert bpy.ops.object.affine_deformer_remove(index=0) == {"FINISHED"}
    assert np.array_equal(bl.evaluated_positions(target), moved)
    assert np.array_equal(bl.evaluated_positions(copy), bl.rest_positions(copy))


# ------------------------------------------------------------------------------------ apply


def test_apply_after_an_armature_writes_the_deformers_own_effect(bl):
    """Our Apply, like Blender's Apply of a modifier that is not first: the deformer's motion applied
    to the mesh's own shape; the Armature stays and now bends the applied shape."""
    target = bl.grid_cube(cuts=6)
    _bending_armature(target, angle=0.6)
    probes = _probes(bl)
    bl.add_probe_deformer(target, probes, normalize="SUM")
    rest = bl.rest_positions(target).copy()
    G = _move_all(probes, POSE_1)
    bl.evaluated_positions(target)
    assert bl.run_op(bpy.ops.object.affine_deformer_apply, target, index=0) == {"FINISHED"}
    assert len(target.affine_deformers) == 0
    assert np.abs(bl.rest_positions(target) - _apply(_local(target, G), rest)).max() < 1e-5
    assert [m.type for m in target.modifiers] == ["ARMATURE"]


def test_blenders_own_apply_of_the_modifier(bl):
    target = bl.grid_cube(cuts=6)
    _bending_armature(target, angle=0.0)  # a modifier before ours (the motion path) that does not move
    probes = _probes(bl)
    deformer = bl.add_probe_deformer(target, probes, normalize="SUM")
    rest = bl.rest_positions(target).copy()
    G = _move_all(probes, POSE_1)
    expected = bl.evaluated_positions(target).copy()
    mod = _our_modifier(target, deformer)
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.modifier_apply(modifier=mod.name) == {"FINISHED"}
    assert np.abs(bl.rest_positions(target) - expected).max() < 1e-6
    assert np.abs(expected - _apply(_local(target, G), rest)).max() < 1e-5
    bl.evaluated_positions(target)
    assert "removed or applied" in deformer.status


# ------------------------------------------------------------------------------------ files of 0.1.0


def test_a_file_saved_by_0_1_0_opens_and_deforms_as_before(bl, tmp_path):
    expected = dict(np.load(FIXTURES / "saved_by_0_1_0_expected.npz"))
    out = tmp_path / "got.npz"
    bl.run_blender(f"""
        import numpy as np
        enable_addon()
        bpy.ops.wm.open_mainfile(filepath={str(FIXTURES / "saved_by_0_1_0.blend")!r}, load_ui=False)
        result = {{}}
        for frame in (1, 5, 10, 7):
            bpy.context.scene.frame_set(frame)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            for name in ("Bar", "Caged"):
                mesh = bpy.data.objects[name].evaluated_get(depsgraph).data
                co = np.empty(len(mesh.vertices) * 3, np.float32)
                mesh.vertices.foreach_get("co", co)
                result[f"{{name}}_{{frame}}"] = co.reshape(-1, 3)
        result["status"] = np.array(";".join(d.status for name in ("Bar", "Caged")
                                             for d in bpy.data.objects[name].affine_deformers))
        group = bpy.data.node_groups["AffineDeformer"]
        result["version"] = np.array(group["affine_deformers_group"])
        np.savez({str(out)!r}, **result)
    """)
    got = dict(np.load(out))
    assert str(got["status"]) == ";"
    assert int(got["version"]) == 6, "the node group is upgraded on load"
    for name, positions in expected.items():
        assert np.abs(got[name] - positions).max() < 1e-6, name
    assert np.abs(expected["Bar_10"] - expected["Bar_1"]).max() > 1.0, "the fixture deforms"


def test_motion_path_survives_save_and_reopen(bl, tmp_path):
    target, key = _shape_keyed(bl)
    key.value = 1.0
    probes = _probes(bl)
    bl.add_probe_deformer(target, probes, weight_mode="FALLOFF", radius=2.5)
    probes[0].keyframe_insert("rotation_euler", frame=1)
    probes[0].rotation_euler.z += math.radians(150)
    probes[0].keyframe_insert("rotation_euler", frame=20)
    bl.check_frames_survive_reopen(target, (1, 10, 20), tmp_path)
