"""The fast paths of the frame handler give exactly what a full recompute gives.

bound.py caches bind data per bind generation and recomputes only the vertices influenced by
controls whose blend parameters changed; these tests drive random sequences of control changes and
compare every result bit for bit with a recompute from nothing (caches dropped), so the result still
depends only on the current inputs."""

from __future__ import annotations

import importlib
from types import SimpleNamespace

import bpy
import numpy as np
import pytest


@pytest.fixture
def ns(bl, installed) -> SimpleNamespace:
    """The test helpers plus the installed layer's evaluate, storage, bind-data and blend modules."""
    return SimpleNamespace(**vars(bl), evaluate=installed.evaluate, storage=installed.storage,
                           bound=importlib.import_module(f"{installed.package}.blender.bound"),
                           blend=importlib.import_module(f"{installed.package}.blender.blend"))


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
    first = bound.offsets
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
    assert bound.offsets is first  # updated in place
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
    """`BoundData.affected_rows` (the rows an incremental update recomputes): the sorted vertices with
    a non-zero weight on any of the given controls, whether it gathers per-control row lists (few
    controls) or tags every row-list entry with its control's flag (many: a cage's faces or nodes)."""
    rng = np.random.default_rng(11)
    n, m, k = 5000, 300, 6
    indices = np.argsort(rng.random((n, m)), axis=1)[:, :k].astype(np.int32)  # distinct per row, as bound
    values = np.where(rng.random((n, k)) < 0.3, 0.0, rng.random((n, k)))
    points = rng.normal(size=(n, 3))
    bound = ns.bound.BoundData(("test",), 1, points.astype(np.float32), points, indices, values)
    for size in (1, 2, 5, 32, 33, 80, 299, 300):
        controls = np.sort(rng.choice(m, size=size, replace=False))
        want = np.flatnonzero((np.isin(indices, controls) & (values != 0.0)).any(axis=1))
        got = bound.affected_rows(controls)
        assert np.array_equal(got, want), size
