"""The fast paths of the frame handler give exactly what a full recompute gives.

bound.py caches bind data per bind generation and recomputes only the vertices influenced by
controls whose blend parameters changed; these tests drive random sequences of control changes and
compare every result bit for bit with a recompute from nothing (caches dropped), so the result still
depends only on the current inputs."""

from __future__ import annotations

import importlib
from types import SimpleNamespace

import bmesh
import bpy
import numpy as np
import pytest


@pytest.fixture
def ns(bl, installed) -> SimpleNamespace:
    """The test helpers plus the installed layer's evaluate, storage, bind-data and blend modules."""
    return SimpleNamespace(**vars(bl), evaluate=installed.evaluate, storage=installed.storage,
                           bound=importlib.import_module(f"{installed.package}.blender.update.bound"),
                           blend=importlib.import_module(f"{installed.package}.blender.update.blend"),
                           package=installed.package)


def _rig(ns, n_probes: int = 6):
    target = ns.grid_cube(cuts=14)
    rng = np.random.default_rng(7)
    probes = [ns.empty(f"P{i}", tuple(rng.uniform(-1.2, 1.2, 3))) for i in range(n_probes)]
    deformer = ns.add_probe_deformer(target, probes, radius=1.2, weight_mode="FALLOFF")
    bpy.context.view_layer.update()
    return target, probes, deformer, rng


def test_random_control_changes_match_a_full_recompute_bit_for_bit(ns):
    target, probes, deformer, rng = _rig(ns)
    rest = {p.name: (p.location.copy(), p.rotation_euler.copy(), p.scale.copy()) for p in probes}
    touched = 0
    for step in range(25):
        for probe in rng.choice(probes, size=rng.integers(1, 4), replace=False):
            action = rng.integers(0, 4)
            if action == 0:  # back exactly to rest: its parameters become exactly zero
                probe.location, probe.rotation_euler, probe.scale = rest[probe.name]
            elif action == 1:
                probe.location += type(probe.location)(rng.normal(scale=0.2, size=3))
            elif action == 2:
                probe.rotation_euler = tuple(rng.uniform(-3.0, 3.0, 3))
            else:
                probe.scale = tuple(rng.uniform(0.5, 1.6, 3))
        if step == 12:
            deformer.strength = 0.7  # settings changes recompute everything
        bpy.context.view_layer.update()
        incremental = ns.stored_offsets(target, deformer)
        touched += int(np.any(incremental != 0.0))
        assert deformer.status == ""
        assert np.array_equal(incremental, ns.recomputed_offsets(target, deformer)), step
        bpy.context.view_layer.update()  # warm the caches again for the next step
    assert touched > 15  # the sequence really deformed the mesh


def test_incremental_update_touches_only_influenced_vertices(ns):
    target, probes, deformer, _ = _rig(ns)
    probes[0].location.x += 0.3
    bpy.context.view_layer.update()
    bound = ns.bound._bound[(target.session_uid, deformer.uid)]
    first = bound.result.offsets
    calls = []
    deform = ns.blend.accel  # the kernel dispatch the layer calls (compiled or numpy)
    originals = deform.deform_points_params, deform.deform_points_params_rows

    def full(points, *args, **kwargs):
        calls.append(("full", len(points)))
        return originals[0](points, *args, **kwargs)

    def some(points, params, indices, values, rows, *args, **kwargs):
        calls.append(("rows", len(rows)))
        return originals[1](points, params, indices, values, rows, *args, **kwargs)

    deform.deform_points_params, deform.deform_points_params_rows = full, some
    try:
        probes[1].location.z += 0.2
        bpy.context.view_layer.update()
        bpy.context.view_layer.update()  # the second pass (our own write) does no kernel work
    finally:
        deform.deform_points_params, deform.deform_points_params_rows = originals
    influenced = np.flatnonzero(np.any((bound.indices == 1) & (bound.values != 0.0), axis=1))
    assert calls == [("rows", len(influenced))], "one kernel call, on exactly the vertices probe 1 influences"
    assert 0 < len(influenced) < len(bound.points)
    assert bound.result.offsets is first  # updated in place
    assert np.array_equal(ns.stored_offsets(target, deformer), ns.recomputed_offsets(target, deformer))


def test_edited_rest_shape_is_picked_up_without_rebinding(ns):
    """The cached rest positions are checked against the mesh on every evaluation: a script (or Edit /
    Sculpt Mode) moving vertices is seen at the next update, exactly as before the cache existed."""
    target, probes, deformer, _ = _rig(ns)
    probes[2].rotation_euler.z += 0.5
    bpy.context.view_layer.update()
    co = ns.storage.read_positions(target.data).copy()
    co[:40] *= 1.1
    ns.storage.write_positions(target.data, co)
    bpy.context.view_layer.update()
    bpy.context.view_layer.update()
    after_edit = ns.stored_offsets(target, deformer)
    assert np.array_equal(after_edit, ns.recomputed_offsets(target, deformer))
    evaluated = ns.evaluated_positions(target)
    assert np.allclose(evaluated, co + after_edit, atol=1e-6)


def test_rebind_and_reweight_invalidate_the_cached_weights(ns):
    target, probes, deformer, _ = _rig(ns)
    probes[0].location.y -= 0.4
    bpy.context.view_layer.update()
    before = ns.stored_offsets(target, deformer)
    deformer.radius = 0.6  # re-weights live (new bind generation)
    bpy.context.view_layer.update()
    reweighted = ns.stored_offsets(target, deformer)
    assert not np.array_equal(reweighted, before)
    assert np.array_equal(reweighted, ns.recomputed_offsets(target, deformer))


def test_affected_rows_of_few_and_of_many_controls(ns):
    """`BindRecord.affected_rows` (the rows an incremental update recomputes): the sorted vertices with
    a non-zero weight on any of the given controls, whether it gathers per-control row lists (few
    controls) or tags every row-list entry with its control's flag (many: a cage's faces or nodes)."""
    rng = np.random.default_rng(11)
    n, m, k = 5000, 300, 6
    indices = np.argsort(rng.random((n, m)), axis=1)[:, :k].astype(np.int32)  # distinct per row, as bound
    values = np.where(rng.random((n, k)) < 0.3, 0.0, rng.random((n, k)))
    points = rng.normal(size=(n, 3))
    bound = ns.bound.BindRecord(("test",), 1, points.astype(np.float32), points, indices, values, columns=m)
    accel = importlib.import_module(f"{ns.package}.accel")
    try:
        for compiled in (True, False):  # many controls: the compiled pass, or numpy's
            accel.set_enabled(compiled)
            for size in (1, 2, 5, 32, 33, 80, 299, 300):
                controls = np.sort(rng.choice(m, size=size, replace=False))
                want = np.flatnonzero((np.isin(indices, controls) & (values != 0.0)).any(axis=1))
                got = bound.affected_rows(controls)
                assert np.array_equal(got, want), (compiled, size)
    finally:
        accel.set_enabled(True)


def test_mesh_arrays_read_through_attributes_equal_the_rna_reads(ns):
    """storage.corner_vertices / edge_vertices / face_corners (plain attribute copies, totals from
    the starts) give exactly what MeshLoop.vertex_index, MeshEdge.vertices and MeshPolygon's
    loop_start / loop_total give, on triangles, quads and an n-gon, an edited mesh and an empty one."""
    mesh = bpy.data.meshes.new("mixed")
    verts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (3, 1, 0), (2.5, 2, 0), (1.5, 2, 0),
             (2, 3, 1)]
    mesh.from_pydata(verts, [(7, 8)], [(0, 1, 2, 3), (1, 4, 2), (4, 5, 6, 7, 2)])
    empty = bpy.data.meshes.new("nothing")
    for me in (mesh, empty):
        for _ in range(2):
            loops = np.empty(len(me.loops), dtype=np.int32)
            edges = np.empty(2 * len(me.edges), dtype=np.int32)
            start = np.empty(len(me.polygons), dtype=np.int32)
            total = np.empty(len(me.polygons), dtype=np.int32)
            me.loops.foreach_get("vertex_index", loops)
            me.edges.foreach_get("vertices", edges)
            me.polygons.foreach_get("loop_start", start)
            me.polygons.foreach_get("loop_total", total)
            got_start, got_total = ns.storage.face_corners(me)
            assert np.array_equal(ns.storage.corner_vertices(me), loops)
            assert np.array_equal(ns.storage.edge_vertices(me), edges)
            assert np.array_equal(got_start, start) and np.array_equal(got_total, total)
            assert got_start.dtype == got_total.dtype == np.int32
            if me.polygons:  # a second round on an edited mesh: one face deleted, the offsets shift
                assert total.tolist() == [4, 3, 5]
                bm = bmesh.new()
                bm.from_mesh(me)
                bm.faces.ensure_lookup_table()
                bm.verts.ensure_lookup_table()
                bmesh.ops.delete(bm, geom=[bm.faces[1]], context="FACES_ONLY")
                bm.faces.new([bm.verts[i] for i in (0, 3, 8)])
                bm.to_mesh(me)
                bm.free()


def test_group_input_identifiers_follow_edits_of_the_interface(ns):
    """nodes._input_identifiers keeps its map per group and item names: a socket added, removed,
    renamed or moved is seen at the next call, and one replaced by a socket of the same name and
    place after the next depsgraph update."""
    nodes = importlib.import_module(f"{ns.package}.blender.files.nodes")
    ng = bpy.data.node_groups.new("interface", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    ns.grid_cube(cuts=1).modifiers.new("uses the group", "NODES").node_group = ng  # in the depsgraph
    # Only identifier strings are kept: an interface item's Python object dangles once it is removed.
    first = ng.interface.new_socket("A", in_out="INPUT", socket_type="NodeSocketString").identifier
    assert nodes._input_identifier(ng, "A", "NodeSocketString") == first
    second = ng.interface.new_socket("B", in_out="INPUT", socket_type="NodeSocketObject")
    assert nodes._input_identifier(ng, "B", "NodeSocketObject") == second.identifier
    second.name = "C"
    assert nodes._input_identifier(ng, "B", "NodeSocketObject") is None
    assert nodes._input_identifier(ng, "C", "NodeSocketObject") == second.identifier
    ng.interface.remove(ng.interface.items_tree["A"])
    again = ng.interface.new_socket("A", in_out="INPUT", socket_type="NodeSocketString").identifier
    assert again != first
    assert nodes._input_identifier(ng, "A", "NodeSocketString") == again  # now after C
    ng.interface.remove(ng.interface.items_tree["A"])
    replaced = ng.interface.new_socket("A", in_out="INPUT", socket_type="NodeSocketString").identifier
    assert replaced != again  # the same names in the same order
    bpy.context.view_layer.update()  # the handler sees the node tree change
    assert nodes._input_identifier(ng, "A", "NodeSocketString") == replaced


def test_modifier_controls_of_the_wrong_type_are_ignored(ns):
    """nodes.controls gives no collection for an input whose type was changed in place (the
    identifier map is keyed by item names, which stay the same)."""
    target = ns.grid_cube(cuts=2)
    probe = ns.empty("P0", (0.3, 0.0, 0.0))
    deformer = ns.add_probe_deformer(target, [probe], radius=1.2)
    probe.hide_viewport = True  # named on the modifier: the depsgraph would not evaluate it otherwise
    bpy.context.view_layer.update()
    nodes = importlib.import_module(f"{ns.package}.blender.files.nodes")
    mod = nodes.find_modifier(target, ns.storage.offset_name(deformer.uid))
    cage, probes = nodes.controls(mod)
    assert cage is None and probe.name in probes.objects
    # A script changing a managed input's type in place: the item names stay the same.
    mod.node_group.interface.items_tree[nodes.PROBES_SOCKET].socket_type = "NodeSocketFloat"
    assert nodes.controls(mod) == (None, None)
