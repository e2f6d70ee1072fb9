"""The per-control memos of an update (kinds._rows: transforms → motions; evaluate._param_rows:
motions → blend parameters) recompute only controls whose inputs changed, and give bit for bit what a
recompute from nothing gives, whatever the order in which controls moved before (history-free)."""

from __future__ import annotations

import importlib
import math

import bpy
import numpy as np


def _rig(bl, n_probes: int = 5):
    target = bl.grid_cube(cuts=8)
    rng = np.random.default_rng(11)
    probes = [bl.empty(f"M{i}", tuple(rng.uniform(-1.0, 1.0, 3))) for i in range(n_probes)]
    deformer = bl.add_probe_deformer(target, probes, radius=1.5, weight_mode="FALLOFF")
    bpy.context.view_layer.update()
    return target, probes, deformer


def _offsets(installed, target, deformer) -> np.ndarray:
    return installed.storage.read_offsets(target.data, deformer.uid).copy()


def _fresh(installed, target, deformer) -> np.ndarray:
    installed.evaluate.forget()
    installed.evaluate.evaluate_object(target, bpy.context.evaluated_depsgraph_get())
    return _offsets(installed, target, deformer)


def test_only_changed_controls_are_recomputed(bl, installed, monkeypatch):
    kinds = importlib.import_module(f"{installed.package}.blender.kinds")
    evaluate = installed.evaluate
    _target, probes, deformer = _rig(bl)
    probes[0].location.x += 0.2
    bpy.context.view_layer.update()
    rows, params = [], []
    real_row, real_params = kinds._probe_row, evaluate._params_of_rows
    monkeypatch.setattr(kinds, "_probe_row", lambda *a: rows.append(a[0].name) or real_row(*a))
    monkeypatch.setattr(evaluate, "_params_of_rows",
                        lambda m, r, *a: params.append(r.tolist()) or real_params(m, r, *a))
    probes[2].rotation_euler.z += 0.4
    bpy.context.view_layer.update()
    assert rows == [probes[2].name]
    assert params == [[2]]
    assert deformer.status == ""


def test_memoised_updates_match_a_fresh_evaluation_bit_for_bit(bl, installed):
    """Probes turned by several full turns (lifted branches, per-row channel sampling), scaled, moved in
    different orders and back to earlier poses: every update equals a fresh evaluation."""
    target, probes, deformer = _rig(bl)
    deformer.branch_rule = "CHANNELS"
    probes[3].rotation_mode = "AXIS_ANGLE"
    probes[4].rotation_mode = "QUATERNION"
    rng = np.random.default_rng(5)
    poses = []
    for step in range(12):
        probe = probes[int(rng.integers(0, len(probes)))]
        if step in (6, 9) and poses:  # an earlier pose again (memo hits for every probe)
            for p, (loc, rot, scale) in zip(probes, poses[int(rng.integers(0, len(poses)))], strict=True):
                p.location, p.scale = loc, scale
                p.rotation_euler, p.rotation_axis_angle, p.rotation_quaternion = rot
        elif probe.rotation_mode == "AXIS_ANGLE":
            probe.rotation_axis_angle = (float(rng.uniform(-3, 3) * 2 * math.pi), 0.3, 0.2, 1.0)
        elif probe.rotation_mode == "QUATERNION":
            probe.rotation_quaternion = tuple(rng.normal(size=4))
        else:
            probe.rotation_euler.z += float(rng.uniform(2.0, 9.0))  # often past 180°, several turns
            probe.location.y += float(rng.normal(scale=0.1))
            probe.scale = tuple(rng.uniform(0.7, 1.3, 3))
        poses.append([(p.location.copy(), (p.rotation_euler.copy(), tuple(p.rotation_axis_angle),
                                           p.rotation_quaternion.copy()), p.scale.copy()) for p in probes])
        bpy.context.view_layer.update()
        memoised = _offsets(installed, target, deformer)
        assert deformer.status == ""
        assert np.array_equal(memoised, _fresh(installed, target, deformer)), step
        bpy.context.view_layer.update()
    assert np.abs(memoised).max() > 0.05


def test_updates_write_without_reading_the_offsets_back(bl, installed, monkeypatch):
    """After the first write the evaluate cache holds a copy of the offset attribute: an update writes
    from it without reading the attribute back, an unchanged result is not written again, and what the
    mesh holds still equals a fresh evaluation."""
    storage = installed.storage
    target, probes, deformer = _rig(bl)
    probes[1].location.z += 0.3
    bpy.context.view_layer.update()
    reads, writes = [], []
    real_read, real_write = storage.read_offsets, storage.write_offsets_unchecked
    monkeypatch.setattr(storage, "read_offsets", lambda *a: reads.append(a) or real_read(*a))
    monkeypatch.setattr(storage, "write_offsets_unchecked", lambda *a: writes.append(a) or real_write(*a))
    for step in range(3):
        probes[step].rotation_euler.x += 0.5
        probes[step].location.y -= 0.2
        bpy.context.view_layer.update()
    assert reads == []
    assert len(writes) == 3
    installed.evaluate.evaluate_object(target, bpy.context.evaluated_depsgraph_get())  # nothing changed
    assert len(writes) == 3
    monkeypatch.undo()
    memoised = _offsets(installed, target, deformer)
    assert np.abs(memoised).max() > 0.05
    assert np.array_equal(memoised, _fresh(installed, target, deformer))


def test_an_error_in_between_does_not_leave_a_stale_copy(bl, installed):
    """A probe scaled to zero makes the deformer write zeros without its cache; when it is fixed, the
    written offsets are those of a fresh evaluation again (not the cache's pre-error copy)."""
    target, probes, deformer = _rig(bl)
    probes[0].location.x += 0.4
    bpy.context.view_layer.update()
    before = _offsets(installed, target, deformer)
    probes[0].scale = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    assert deformer.status != ""
    assert not np.any(_offsets(installed, target, deformer))
    probes[0].scale = (1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert deformer.status == ""
    after = _offsets(installed, target, deformer)
    assert np.array_equal(after, before)
    assert np.array_equal(after, _fresh(installed, target, deformer))


def test_rest_shape_edit_by_script_is_seen_with_the_cached_copy(bl, installed):
    """Moving rest vertices by script (no rebind) recomputes everything from the new rest shape."""
    target, probes, deformer = _rig(bl)
    probes[2].location.x += 0.3
    bpy.context.view_layer.update()
    co = installed.storage.read_positions(target.data).copy()
    co[:, 2] += 0.25
    installed.storage.write_positions(target.data, co)
    bpy.context.view_layer.update()
    edited = _offsets(installed, target, deformer)
    assert np.array_equal(edited, _fresh(installed, target, deformer))
    probes[2].location.x -= 0.1
    bpy.context.view_layer.update()
    assert np.array_equal(_offsets(installed, target, deformer), _fresh(installed, target, deformer))
