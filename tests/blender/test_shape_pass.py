"""Preserve Shape (the shape-preserving pass, MATH.md §15) in Blender: exact where it must be, a factor
built once per bind and reused, frames in any order, bad meshes refused with a message naming the fix,
the motion path under shape keys, saved with the file — and a bend that keeps its shape better than
the per-vertex field.

The rig: a subdivided bar along z with two probes at its ends (inverse distance); the top probe moves.
"""

from __future__ import annotations

import importlib

import bmesh
import bpy
import numpy as np
import pytest
from mathutils import Euler, Matrix

from tests.blender.conftest import PACKAGE

BAR = (0.3, 0.3, 2.0)  # half extents


def bar(name: str = "Bar", cuts: int = 8):
    """A box bar |x|, |y| ≤ 0.3, |z| ≤ 2 with `cuts` cuts per edge, its long edges cut 4× as often."""
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=2.0)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=cuts, use_grid_fill=True)
    for v in bm.verts:
        v.co = (v.co.x * BAR[0], v.co.y * BAR[1], v.co.z * BAR[2])
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def rig(bl, **options):
    target = bar()
    low, high = bl.empty("Low", (0.0, 0.0, -2.0)), bl.empty("High", (0.0, 0.0, 2.0))
    deformer = bl.add_probe_deformer(target, [low, high], weight_mode="INVERSE_DISTANCE", **options)
    return target, low, high, deformer


def shape_pass():
    return importlib.import_module(f"{PACKAGE}.blender.update.shape_pass")


def signed_volume(obj, points: np.ndarray) -> float:
    mesh = obj.data
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", tris)
    a, b, c = (points[tris.reshape(-1, 3)[:, k]].astype(np.float64) for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_a_motion_shared_by_every_probe_is_exact_and_a_rigid_one_stays_rigid(bl):
    target, low, high, deformer = rig(bl, preserve_shape=True)
    rest = bl.rest_positions(target).astype(np.float64)
    G = Matrix.Translation((0.7, -0.2, 0.4)) @ Euler((0.4, -0.3, 1.1)).to_matrix().to_4x4()
    for probe in (low, high):  # one rigid motion G of both probes' frames: the whole bar moves with them
        probe.matrix_world = G @ probe.matrix_world
    bpy.context.view_layer.update()
    moved = bl.evaluated_positions(target).astype(np.float64)
    # the probes' common motion, independently of the add-on: A = C · C_rest⁻¹ for the top probe
    A = bl.local_motion(target, high, deformer.probes[1].rest_matrix)
    expected = rest @ A[:3, :3].T + A[:3, 3]
    assert deformer.status == ""
    assert np.abs(moved - expected).max() < 2e-5, np.abs(moved - expected).max()


def test_the_factor_is_built_once_and_frames_do_not_depend_on_their_order(bl):
    target, _low, high, deformer = rig(bl, preserve_shape=True)
    scene = bpy.context.scene
    for frame, angle in ((1, 0.0), (10, 1.2), (20, 2.4)):
        high.rotation_euler = (angle, 0.0, 0.0)
        high.location = (0.0, 0.6 * angle, 2.0)
        high.keyframe_insert("rotation_euler", frame=frame)
        high.keyframe_insert("location", frame=frame)
    built = []
    module = shape_pass()
    original = module._build
    module._build = lambda *args: built.append(1) or original(*args)
    try:
        results = {}
        for frame in (20, 1, 10, 20, 10):
            scene.frame_set(frame)
            got = bl.evaluated_positions(target)
            if frame in results:
                assert np.array_equal(got, results[frame]), f"frame {frame} differs on a second visit"
            results[frame] = got
    finally:
        module._build = original
    assert deformer.status == ""
    assert not built, f"factored {len(built)} more times"  # once, at the first update after the option
    assert "Factored" in module.summary(target, deformer)
    assert np.abs(results[1] - bl.rest_positions(target)).max() < 1e-6  # the bind pose is the rest shape


def edge_distortion(obj, rest: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """|l/l0 − 1| over the mesh's edges."""
    edges = np.empty(len(obj.data.edges) * 2, dtype=np.int64)
    obj.data.edges.foreach_get("vertices", edges)
    a, b = edges.reshape(-1, 2).T
    length = np.linalg.norm(moved[a] - moved[b], axis=1) / np.linalg.norm(rest[a] - rest[b], axis=1)
    return np.abs(length - 1.0)


def test_a_bend_keeps_edge_lengths_better_than_the_per_vertex_field(bl):
    target, _low, high, deformer = rig(bl)
    rest = bl.rest_positions(target).astype(np.float64)
    high.rotation_euler = (np.pi / 2, 0.0, 0.0)  # the top end turned 90°
    high.location = (0.0, 1.2, 1.2)
    bpy.context.view_layer.update()
    field = bl.evaluated_positions(target)
    deformer.preserve_shape = True
    bpy.context.view_layer.update()
    shaped = bl.evaluated_positions(target)
    before, after = (edge_distortion(target, rest, p.astype(np.float64)) for p in (field, shaped))
    v0 = signed_volume(target, rest)
    print(f"edge |l/l0 - 1| max / p99: per-vertex {before.max():.3f} / {np.percentile(before, 99):.3f}, "
          f"preserve shape {after.max():.3f} / {np.percentile(after, 99):.3f}; volume "
          f"{signed_volume(target, field) / v0:.3f} / {signed_volume(target, shaped) / v0:.3f}")
    assert deformer.status == ""
    assert after.max() < 0.8 * before.max()
    assert np.percentile(after, 99) < 0.8 * np.percentile(before, 99)
    deformer.preserve_shape = False  # off again: the per-vertex field exactly as before
    bpy.context.view_layer.update()
    assert np.array_equal(bl.evaluated_positions(target), field)


def test_degenerate_triangles_are_refused_with_the_fix_and_the_mesh_passes_through(bl):
    target, _low, high, deformer = rig(bl)
    mesh = target.data
    co = bl.rest_positions(target)
    first = mesh.polygons[0].vertices
    co[first[1]] = co[first[0]]  # two corners of one face on top of each other
    mesh.vertices.foreach_set("co", co.ravel())
    mesh.update()
    bpy.ops.object.select_all(action="DESELECT")
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    deformer.preserve_shape = True
    high.location.x += 0.5
    bpy.context.view_layer.update()
    assert "Merge by Distance" in deformer.status, deformer.status
    assert np.isfinite(bl.evaluated_positions(target)).all()
    assert np.array_equal(bl.evaluated_positions(target), bl.rest_positions(target))


@pytest.mark.parametrize("kind", ["shape keys"])
def test_on_the_motion_path_the_correction_follows_what_reaches_the_modifier(bl, kind):
    target, _low, high, deformer = rig(bl, preserve_shape=True)
    high.rotation_euler = (0.8, 0.0, 0.0)
    bpy.context.view_layer.update()
    offset_result = bl.evaluated_positions(target)
    basis = target.shape_key_add(name="Basis", from_mix=False)
    assert basis is not None
    bpy.context.view_layer.update()  # the Basis holds the rest shape: still the offset path
    assert np.abs(bl.evaluated_positions(target) - offset_result).max() < 1e-5
    key = target.shape_key_add(name="Fat", from_mix=False)
    co = bl.rest_positions(target) * np.array([1.2, 1.2, 1.0], dtype=np.float32)
    key.data.foreach_set("co", co.ravel())
    key.value = 0.0  # keyed positions present but off: what reaches the modifier is the rest shape
    bpy.context.view_layer.update()
    assert deformer.status == ""
    assert np.abs(bl.evaluated_positions(target) - offset_result).max() < 1e-4
    key.value = 1.0
    bpy.context.view_layer.update()
    fat = bl.evaluated_positions(target)
    assert deformer.status == "" and np.isfinite(fat).all()
    assert np.abs(fat - offset_result).max() > 0.01  # the fat shape reached the modifier and moved


def test_saved_and_reopened_the_pass_is_on_and_gives_the_same_shape(bl, tmp_path):
    target, _low, high, deformer = rig(bl, preserve_shape=True, shape_iterations=2)
    high.rotation_euler = (1.0, 0.0, 0.3)
    bpy.context.view_layer.update()
    before = bl.evaluated_positions(target)
    path = str(tmp_path / "shape.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    target = bpy.data.objects["Bar"]
    deformer = target.affine_deformers[0]
    assert deformer.preserve_shape and deformer.shape_iterations == 2
    bpy.context.view_layer.update()
    assert np.abs(bl.evaluated_positions(target) - before).max() < 1e-6


def test_an_edit_of_the_faces_alone_is_followed(bl):
    """Splitting a bar's quads along the other diagonals keeps every vertex and the bind (issue 57); the
    pass must use the new faces at once: the twin bound with those faces from the start."""
    def make(name: str, split: bool):
        target = bar(name)
        if split:
            _split(target)
        low, high = bl.empty(f"{name} Low", (0.0, 0.0, -2.0)), bl.empty(f"{name} High", (0.0, 0.0, 2.0))
        deformer = bl.add_probe_deformer(target, [low, high], weight_mode="INVERSE_DISTANCE",
                                         preserve_shape=True)
        high.rotation_euler = Euler((0.0, 1.2, 0.4))
        high.location.x += 0.8
        bpy.context.view_layer.update()
        return target, deformer

    target, deformer = make("Edited", False)
    before = bl.evaluated_positions(target).copy()
    _split(target)
    followed = bl.evaluated_positions(target).copy()
    assert deformer.status == "", deformer.status
    twin, _twin_deformer = make("Twin", True)
    fresh = bl.evaluated_positions(twin).copy()
    assert np.abs(fresh - before).max() > 1e-5, "the faces matter to the pass"
    assert np.abs(followed - fresh).max() < 1e-5, np.abs(followed - fresh).max()


def _split(obj) -> None:
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    bmesh.ops.triangulate(bm, faces=bm.faces[:], quad_method="ALTERNATE")  # not the diagonals Blender takes
    bm.to_mesh(obj.data)
    bm.free()
    obj.data.update()
