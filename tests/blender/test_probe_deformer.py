"""The probe deformer driven like an artist / script does: exactness at rest, exact common motions,
rigidity, locality, and the life-cycle operators (rebind, remove, apply, probe add/remove)."""

from __future__ import annotations

import importlib
import math

import bpy
import numpy as np
import pytest
from mathutils import Matrix


def _three_probes(bl):
    probes = [bl.empty("P0", (1.2, 0.0, 0.0)), bl.empty("P1", (-1.2, 0.3, 0.0)),
              bl.empty("P2", (0.0, 0.0, 1.5))]
    probes[0].rotation_euler = (0.3, 0.2, 0.1)  # non-trivial rest poses
    probes[1].scale = (1.5, 1.0, 0.7)
    return probes


def _world(positions: np.ndarray, matrix) -> np.ndarray:
    M = np.array(matrix, dtype=np.float64)
    return positions.astype(np.float64) @ M[:3, :3].T + M[:3, 3]


def test_probes_at_rest_leave_the_mesh_bit_for_bit(bl):
    target = bl.grid_cube(cuts=12)
    before = bl.rest_positions(target).copy()
    probes = _three_probes(bl)
    deformer = bl.add_probe_deformer(target, probes)
    assert deformer.is_bound and deformer.status == ""
    assert deformer.bound_vertex_count == len(before) > 1000
    assert np.array_equal(bl.rest_positions(target), before), "binding must not touch the mesh data"
    assert np.array_equal(bl.evaluated_positions(target), before)

    saved = probes[0].location.copy(), probes[0].rotation_euler.copy()
    probes[0].location.x += 0.7
    probes[0].rotation_euler.z += 0.4
    assert np.abs(bl.evaluated_positions(target) - before).max() > 0.1
    probes[0].location, probes[0].rotation_euler = saved  # the same channels give the same matrix, bitwise
    bpy.context.scene.frame_set(5)
    assert np.array_equal(bl.evaluated_positions(target), before), "back at rest: bit-for-bit again"


def test_common_affine_motion_is_reproduced_exactly(bl):
    """All probes hang below a two-level rig; posing the rig moves every probe by the same G, which has
    rotation, non-uniform scale, shear (scale between two rotations) and translation."""
    target = bl.grid_cube(cuts=10)
    target.matrix_world = Matrix.Translation((0.5, 1.0, -0.3)) @ Matrix.Rotation(0.4, 4, "Z")
    outer, inner = bl.empty("Outer"), bl.empty("Inner")
    inner.parent = outer
    probes = _three_probes(bl)
    for probe in probes:
        probe.parent = inner
    bl.add_probe_deformer(target, probes, normalize="SUM", weight_mode="INVERSE_DISTANCE")
    rest_world = _world(bl.rest_positions(target), target.matrix_world)

    outer.location, outer.rotation_euler, outer.scale = (0.3, -0.2, 0.5), (0.2, -0.5, 0.9), (1.3, 0.8, 1.1)
    inner.rotation_euler = (0.7, 0.3, -0.4)
    deformed_world = _world(bl.evaluated_positions(target), target.matrix_world)
    G = np.array(inner.evaluated_get(bpy.context.evaluated_depsgraph_get()).matrix_world, dtype=np.float64)
    S = G[:3, :3].T @ G[:3, :3]
    assert np.abs(S - np.diag(np.diag(S))).max() > 0.05, "G must shear the probes' frame"
    expected = _world(rest_world, G)
    assert np.abs(deformed_world - expected).max() < 1e-5
    assert np.abs(expected - rest_world).max() > 0.5, "the motion must be substantial"


def _paint_constant(obj, name: str, weight: float) -> None:
    group = obj.vertex_groups.new(name=name)
    group.add(list(range(len(obj.data.vertices))), weight, "REPLACE")


@pytest.mark.parametrize("blend_mode", ["AFFINE_LOG", "LINEAR"])
def test_rigid_probe_motions_give_rigid_results(bl, blend_mode):
    """Constant painted weights 0.25 / 0.75 and two different rigid motions: with the log blend every
    vertex moves by the same rigid transform (fitted Jacobian orthonormal, det 1); the linear blend of
    the same matrices shrinks the mesh — which shows this test can fail."""
    target = bl.uv_sphere(segments=24, rings=12)
    probes = [bl.empty("A", (0.0, 0.0, 1.0)), bl.empty("B", (0.0, 0.0, -1.0))]
    _paint_constant(target, "A", 0.25)
    _paint_constant(target, "B", 0.75)
    deformer = bl.add_probe_deformer(target, probes, weight_mode="VERTEX_GROUPS", normalize="SUM",
                                     blend_mode=blend_mode)
    assert deformer.status == ""
    probes[0].rotation_euler = (0.0, 0.0, 2.0)
    probes[0].location = (0.5, 0.0, 1.0)
    probes[1].rotation_euler = (1.2, 0.0, -0.4)
    rest = bl.rest_positions(target).astype(np.float64)
    moved = bl.evaluated_positions(target).astype(np.float64)
    homogeneous = np.hstack([rest, np.ones((len(rest), 1))])
    fit, *_ = np.linalg.lstsq(homogeneous, moved, rcond=None)
    J = fit[:3].T
    assert np.abs(homogeneous @ fit - moved).max() < 1e-5, "one transform for all vertices"
    orthonormality = np.abs(J.T @ J - np.eye(3)).max()
    if blend_mode == "AFFINE_LOG":
        assert orthonormality < 1e-5
        assert abs(np.linalg.det(J) - 1.0) < 1e-5
    else:
        assert orthonormality > 1e-2


def test_falloff_deforms_only_inside_the_radius(bl):
    target = bl.grid_cube(cuts=16)
    turned, still = bl.empty("Turned", (1.0, 0.0, 0.0)), bl.empty("Still", (-1.0, 0.0, 0.0))
    radius = 0.8
    bl.add_probe_deformer(target, [turned, still], weight_mode="FALLOFF", radius=radius, normalize="NONE")
    rest = bl.rest_positions(target)
    turned.rotation_euler.x = math.pi / 2
    moved = bl.evaluated_positions(target)
    distance = np.linalg.norm(rest - np.array([1.0, 0.0, 0.0], np.float32), axis=1)
    displacement = np.linalg.norm(moved - rest, axis=1)
    outside = distance > radius * (1 + 1e-6)
    assert outside.sum() > 100 and (~outside).sum() > 20
    assert displacement[outside].max() < 1e-7, "vertices outside the radius must stay put"
    assert displacement[~outside].max() > 0.2


def test_strength_scales_towards_rest(bl):
    target = bl.uv_sphere()
    probe = bl.empty("P", (0.0, 0.0, 0.0))
    deformer = bl.add_probe_deformer(target, [probe])
    rest = bl.rest_positions(target)
    probe.location = (0.0, 0.0, 2.0)
    full = bl.evaluated_positions(target)
    deformer.strength = 0.5
    half = bl.evaluated_positions(target)
    deformer.strength = 0.0
    assert np.array_equal(bl.evaluated_positions(target), rest)
    assert np.abs(full - rest - [0, 0, 2]).max() < 1e-5
    assert np.abs(half - rest - [0, 0, 1]).max() < 1e-5


@pytest.mark.attributes  # inspects the attribute store (conftest: skipped on POSITIONS)
def test_it_is_a_real_modifier(bl):
    target = bl.uv_sphere()
    probe = bl.empty("P")
    deformer = bl.add_probe_deformer(target, [probe])
    (mod,) = target.modifiers
    assert mod.type == "NODES" and mod.node_group.name == "AffineDeformer"
    node_types = {n.bl_idname for n in mod.node_group.nodes}
    assert {"GeometryNodeSetPosition", "GeometryNodeInputNamedAttribute"} <= node_types
    assert f"affdef_{deformer.uid}_offset" in target.data.attributes

    probe.location = (0.0, 1.0, 0.0)
    moved = bl.evaluated_positions(target)
    deformer.show_viewport = False
    assert mod.show_viewport is False
    assert np.array_equal(bl.evaluated_positions(target), bl.rest_positions(target))
    mod.show_viewport = True  # the modifier's own toggle shows through the deformer's property
    assert deformer.show_viewport is True
    deformer.show_render = False
    assert mod.show_render is False
    # Blender's own Apply of our modifier gives the deformed shape
    with bpy.context.temp_override(active_object=target, object=target):
        bpy.ops.object.modifier_apply(modifier=mod.name)
    assert np.abs(bl.rest_positions(target) - moved).max() == 0.0


def test_add_without_selected_empties_creates_two_probes_at_the_ends_of_the_longest_axis(bl):
    """With no Empty selected, the deformer gets two new probes at the centres of the bounding box's
    two faces across the mesh's longest axis (world space; issue #50), so it deforms at once."""
    target = bl.uv_sphere(location=(1.0, 2.0, 3.0))
    target.scale = (1.0, 2.5, 1.0)
    bpy.context.view_layer.update()
    deformer = bl.add_probe_deformer(target, [])
    ends = [item.object for item in deformer.probes]
    assert len(ends) == 2 and all(o is not None and o.type == "EMPTY" for o in ends)
    assert np.allclose(ends[0].matrix_world.translation, (1.0, 2.0 - 2.5, 3.0), atol=1e-5)
    assert np.allclose(ends[1].matrix_world.translation, (1.0, 2.0 + 2.5, 3.0), atol=1e-5)
    assert deformer.status == ""
    ends[1].location.z += 1.0
    moved = bl.evaluated_positions(target) - bl.rest_positions(target)
    far = bl.rest_positions(target)[:, 1] > 0.9  # local y: the end at the moved probe
    assert moved[far, 2].min() > 0.5 and np.abs(moved[~far]).max() < 1.0


def test_rebind_makes_the_current_pose_the_rest(bl):
    target = bl.uv_sphere()
    probes = [bl.empty("A", (0, 0, 1)), bl.empty("B", (0, 0, -1))]
    deformer = bl.add_probe_deformer(target, probes)
    probes[0].rotation_euler.z = 1.0
    rest = bl.rest_positions(target)
    assert not np.array_equal(bl.evaluated_positions(target), rest)
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    assert np.array_equal(bl.evaluated_positions(target), rest)
    assert deformer.probes[0].rest_matrix[:] != pytest.approx(list(np.eye(4).ravel()))


def test_weight_options_update_live_and_keep_the_rest_pose(bl):
    target = bl.grid_cube(cuts=12)
    probes = [bl.empty("A", (1, 0, 0)), bl.empty("B", (-1, 0, 0))]
    deformer = bl.add_probe_deformer(target, probes, weight_mode="FALLOFF", radius=1.0)
    rest_before = [tuple(p.rest_matrix) for p in deformer.probes]
    probes[0].location.y = 0.5
    small = bl.evaluated_positions(target)
    deformer.radius = 2.5  # no rebind needed
    large = bl.evaluated_positions(target)
    assert np.abs(large - small).max() > 0.05
    assert [tuple(p.rest_matrix) for p in deformer.probes] == rest_before
    deformer.max_influences = 1
    columns = [a for a in target.data.attributes if a.name.startswith(f".affdef_{deformer.uid}_idx")]
    # 1 probe per vertex, and the pooled control where the two probes about tie (docs/MATH.md §12)
    assert len(columns) == 2 and {a.data[0].value for a in columns[1:]} == {2}


def test_remove_gives_back_the_exact_rest_shape(bl):
    target = bl.uv_sphere()
    probe = bl.empty("P")
    deformer = bl.add_probe_deformer(target, [probe])
    uid = deformer.uid
    probe.rotation_euler.y = 0.8
    rest = bl.rest_positions(target).copy()
    assert not np.array_equal(bl.evaluated_positions(target), rest)
    assert bl.run_op(bpy.ops.object.affine_deformer_remove, target, index=0) == {"FINISHED"}
    assert len(target.affine_deformers) == 0 and len(target.modifiers) == 0
    assert not [a.name for a in target.data.attributes if uid in a.name]
    assert np.array_equal(bl.evaluated_positions(target), rest)
    assert np.array_equal(bl.rest_positions(target), rest)


def test_apply_writes_the_deformed_shape_and_removes_the_deformer(bl):
    target = bl.uv_sphere()
    probes = [bl.empty("A", (0, 0, 1)), bl.empty("B", (0, 0, -1))]
    deformer = bl.add_probe_deformer(target, probes)
    uid = deformer.uid
    probes[0].rotation_euler.z = 1.3
    probes[1].scale = (1.4, 1.0, 1.0)
    deformed = bl.evaluated_positions(target).copy()
    assert bl.run_op(bpy.ops.object.affine_deformer_apply, target, index=0) == {"FINISHED"}
    assert len(target.affine_deformers) == 0 and len(target.modifiers) == 0
    assert not [a.name for a in target.data.attributes if uid in a.name]
    assert np.array_equal(bl.rest_positions(target), deformed)
    assert np.array_equal(bl.evaluated_positions(target), deformed)


def test_probe_add_and_remove_keep_the_other_rest_poses(bl):
    target = bl.grid_cube(cuts=8)
    a, b = bl.empty("A", (1, 0, 0)), bl.empty("B", (-1, 0, 0))
    deformer = bl.add_probe_deformer(target, [a, b])
    rest_a = tuple(deformer.probes[0].rest_matrix)
    a.location.x = 1.5  # A moves; adding C must not rebind A
    c = bl.empty("C", (0, 0, 1.5))
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, c]):
        assert bpy.ops.object.affine_deformer_probe_add(index=0) == {"FINISHED"}
    assert [p.object for p in deformer.probes] == [a, b, c]
    assert tuple(deformer.probes[0].rest_matrix) == rest_a
    assert tuple(deformer.probes[2].rest_matrix)[3::4] == (0.0, 0.0, 1.5, 1.0)
    assert deformer.bound_vertex_count == len(target.data.vertices) and deformer.status == ""
    moved = bl.evaluated_positions(target)
    assert np.abs(moved - bl.rest_positions(target)).max() > 0.1

    remove_first = bpy.ops.object.affine_deformer_probe_remove
    assert bl.run_op(remove_first, target, index=0, probe_index=0) == {"FINISHED"}
    assert [p.object for p in deformer.probes] == [b, c]
    assert np.array_equal(bl.evaluated_positions(target), bl.rest_positions(target)), "b, c are at rest"
    assert bl.run_op(remove_first, target, index=0, probe_index=0) == {"FINISHED"}
    with pytest.raises(RuntimeError, match="last probe"):
        bl.run_op(remove_first, target, index=0, probe_index=0)
    assert [p.object for p in deformer.probes] == [c]


def test_undo_and_redo_restore_consistent_shapes(bl):
    target = bl.uv_sphere()
    probe = bl.empty("P")
    bl.add_probe_deformer(target, [probe])
    rest = bl.rest_positions(target).copy()
    bpy.ops.ed.undo_push(message="bound")
    probe.location = (0.0, 0.0, 0.75)
    moved = bl.evaluated_positions(target).copy()
    assert np.abs(moved - rest - [0, 0, 0.75]).max() < 1e-5
    bpy.ops.ed.undo_push(message="moved")
    bpy.ops.ed.undo()
    target = bpy.data.objects["Sphere"]  # undo reloads the data: old references are invalid
    assert bpy.data.objects["P"].location.z == 0.0
    assert np.array_equal(bl.evaluated_positions(target), rest)
    bpy.ops.ed.redo()
    target = bpy.data.objects["Sphere"]
    assert bpy.data.objects["P"].location.z == 0.75
    assert np.array_equal(bl.evaluated_positions(target), moved)


def _stored_sparse(target, deformer) -> tuple[np.ndarray, np.ndarray]:
    """(indices (N, K), values (N, K) float64) as stored in the `.affdef_<uid>_idx<k>` / `_w<k>`
    attributes."""
    n, columns = len(target.data.vertices), []
    while (a_i := target.data.attributes.get(f".affdef_{deformer.uid}_idx{len(columns)}")) is not None:
        idx, w = np.empty(n, dtype=np.int32), np.empty(n, dtype=np.float32)
        a_i.data.foreach_get("value", idx)
        target.data.attributes[f".affdef_{deformer.uid}_w{len(columns)}"].data.foreach_get("value", w)
        columns.append((idx, w.astype(np.float64)))
    return np.stack([c[0] for c in columns], axis=1), np.stack([c[1] for c in columns], axis=1)


def test_pooled_weight_of_a_ring_of_probes(bl, installed):
    """12 probes on a ring around a sphere, 4 influences: near the ring's axis, where the
    probes tie, part of each vertex's weight is pooled (a 5th column, index 12; docs/MATH.md §12).
    Moving the whole ring moves the sphere exactly with it; moving one probe gives the core's field
    with the pooled control's row (the weight-scaled mean of the probes' parameters); an incremental
    update equals a full recompute bit for bit; the preview's weights include the pooled share; and
    Weights → Vertex Groups keeps the deformation, raising Max Influences to keep every probe."""
    target = bl.uv_sphere(segments=48, rings=24, radius=0.9)
    rig = bl.empty("Rig")
    probes = []
    for i in range(12):
        angle = 2.0 * math.pi * i / 12
        probe = bl.empty(f"P{i:02d}", (math.cos(angle), math.sin(angle), 0.0))
        probe.parent = rig
        probes.append(probe)
    deformer = bl.add_probe_deformer(target, probes, max_influences=4)
    deformer.probes[3].weight_scale = 1.5
    assert deformer.status == ""
    idx, val = _stored_sparse(target, deformer)
    assert idx.shape[1] == 5 and np.all(idx[:, 4] == 12), "the pooled control's column"
    assert (val[:, 4] > 0.0).mean() > 0.2 and val[:, 4].max() > 0.9, "the poles pool (nearly) everything"
    rest = bl.rest_positions(target).astype(np.float64)

    rig.location, rig.rotation_euler, rig.scale = (0.2, -0.3, 0.4), (0.3, -0.2, 0.8), (1.2, 0.9, 1.1)
    G = np.array(rig.evaluated_get(bpy.context.evaluated_depsgraph_get()).matrix_world, dtype=np.float64)
    common = bl.evaluated_positions(target)
    assert np.abs(common - _world(rest, G)).max() < 1e-5, "a common motion is exact"

    rig.location, rig.rotation_euler, rig.scale = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    probes[0].location.z += 0.36
    probes[0].rotation_euler.y = math.radians(60.0)
    got = bl.evaluated_positions(target)
    A = np.stack([bl.local_motion(target, p, item.rest_matrix) for p, item in zip(probes, deformer.probes,
                                                                                 strict=True)])
    A[np.abs(A - np.eye(4)).max(axis=(1, 2)) < 1e-6] = np.eye(4)
    weights = importlib.import_module(f"{installed.package}.core.weights")
    scales = np.array([item.weight_scale for item in deformer.probes])
    params = weights.with_pool(installed.aff3.params_from_matrices(A), weights.pool_weights(scales))
    expected = installed.deform.deform_points_params(rest, params, idx, val)
    assert np.abs(got - expected).max() < 1e-5
    assert np.abs(got - rest).max() > 0.2

    probes[5].location.x -= 0.2  # an incremental update (the pooled row changes too)
    bpy.context.view_layer.update()
    assert np.array_equal(bl.stored_offsets(target, deformer), bl.recomputed_offsets(target, deformer))

    preview = importlib.import_module(f"{installed.package}.blender.tools.weight_preview")
    shares = np.stack([preview.control_weights(target, deformer, i) for i in range(12)], axis=1)
    np.testing.assert_allclose(shares, bl.dense_weights(target, deformer), atol=1e-12)
    assert np.abs(shares.sum(axis=1) - 1.0).max() < 1e-5
    deformer.weight_preview = "ALL"
    assert preview.preview_colors(target, deformer).shape == (len(rest), 3)

    moved = bl.evaluated_positions(target).copy()
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.affine_deformer_weights_to_groups(index=0) == {"FINISHED"}
    assert deformer.weight_mode == "VERTEX_GROUPS" and deformer.max_influences == 12
    assert np.abs(bl.evaluated_positions(target) - moved).max() < 1e-5
