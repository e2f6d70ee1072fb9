"""The per-control memos of an update (kinds.probe._rows: transforms → motions; params._param_rows:
motions → blend parameters) recompute only controls whose inputs changed, and give bit for bit what a
recompute from nothing gives, whatever the order in which controls moved before (history-free)."""

from __future__ import annotations

import importlib
import math

import bpy
import mathutils
import numpy as np
import pytest


def _rig(bl, n_probes: int = 5):
    target = bl.grid_cube(cuts=8)
    rng = np.random.default_rng(11)
    probes = [bl.empty(f"M{i}", tuple(rng.uniform(-1.0, 1.0, 3))) for i in range(n_probes)]
    deformer = bl.add_probe_deformer(target, probes, radius=1.5, weight_mode="FALLOFF")
    bpy.context.view_layer.update()
    return target, probes, deformer


def test_only_changed_controls_are_recomputed(bl, installed, monkeypatch):
    kinds = importlib.import_module(f"{installed.package}.blender.kinds.probe")
    evaluate = importlib.import_module(f"{installed.package}.blender.update.params")
    _target, probes, deformer = _rig(bl)
    probes[0].location.x += 0.2
    bpy.context.view_layer.update()
    rows, params = [], []
    real_rows, real_params = kinds._probe_rows, evaluate._params_of_rows
    monkeypatch.setattr(kinds, "_probe_rows", lambda *a: rows.extend(a[1].copy()) or real_rows(*a))
    monkeypatch.setattr(evaluate, "_params_of_rows",
                        lambda m, r, *a: params.append(r.tolist()) or real_params(m, r, *a))
    probes[2].rotation_euler.z += 0.4
    bpy.context.view_layer.update()
    assert len(rows) == 1  # the world matrix of the one probe that moved
    assert np.array_equal(rows[0], np.array(probes[2].matrix_world, dtype=np.float64))
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
        memoised = bl.stored_offsets(target, deformer)
        assert deformer.status == ""
        assert np.array_equal(memoised, bl.recomputed_offsets(target, deformer)), step
        bpy.context.view_layer.update()
    assert np.abs(memoised).max() > 0.05


@pytest.mark.attributes  # inspects the attribute store (conftest: skipped on POSITIONS)
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
    memoised = bl.stored_offsets(target, deformer)
    assert np.abs(memoised).max() > 0.05
    assert np.array_equal(memoised, bl.recomputed_offsets(target, deformer))


def test_an_error_in_between_does_not_leave_a_stale_copy(bl, installed):
    """A probe with a non-finite transform makes the deformer write zeros without its cache; when it is
    fixed, the written offsets are those of a fresh evaluation again (not the cache's pre-error copy)."""
    target, probes, deformer = _rig(bl)
    probes[0].location.x += 0.4
    bpy.context.view_layer.update()
    before = bl.stored_offsets(target, deformer)
    probes[0].scale = (float("nan"), 1.0, 1.0)
    bpy.context.view_layer.update()
    assert deformer.status != ""
    assert not np.any(bl.stored_offsets(target, deformer))
    probes[0].scale = (1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert deformer.status == ""
    after = bl.stored_offsets(target, deformer)
    assert np.array_equal(after, before)
    assert np.array_equal(after, bl.recomputed_offsets(target, deformer))


def test_rest_shape_edit_by_script_is_seen_with_the_cached_copy(bl, installed):
    """Moving rest vertices by script (no rebind) recomputes everything from the new rest shape."""
    target, probes, deformer = _rig(bl)
    probes[2].location.x += 0.3
    bpy.context.view_layer.update()
    co = installed.storage.read_positions(target.data).copy()
    co[:, 2] += 0.25
    installed.storage.write_positions(target.data, co)
    bpy.context.view_layer.update()
    edited = bl.stored_offsets(target, deformer)
    assert np.array_equal(edited, bl.recomputed_offsets(target, deformer))
    probes[2].location.x -= 0.1
    bpy.context.view_layer.update()
    assert np.array_equal(bl.stored_offsets(target, deformer), bl.recomputed_offsets(target, deformer))


def test_finiteness_check_of_changed_rows(installed):
    """Only the recomputed rows are checked on an incremental result (the rest were checked before);
    a full result is checked whole; NaN, ±inf and float32-overflowing offsets are all caught."""
    outputs = importlib.import_module(f"{installed.package}.blender.update.outputs")
    offsets = np.zeros((100, 3))
    assert outputs.finite_offsets(offsets, None)
    assert outputs.finite_offsets(offsets, np.array([], dtype=np.intp))
    for bad in (np.nan, np.inf, -np.inf, 1e200, 1e39):  # 1e39: beyond float32, stored as inf
        offsets[37, 1] = bad
        assert not outputs.finite_offsets(offsets, None)
        assert not outputs.finite_offsets(offsets, np.array([3, 37]))  # few rows: gathered
        assert not outputs.finite_offsets(offsets, np.arange(30, 90))  # many rows: whole pass
        assert outputs.finite_offsets(offsets, np.array([3, 38]))  # row 37 unchanged: checked earlier
    offsets[37, 1] = 3e38
    assert outputs.finite_offsets(offsets, None)


def test_bounded_results_skip_the_pass_and_overflow_is_still_caught(bl, installed, monkeypatch):
    """An ordinary update is proven storable from its parameters (core.deform.motion_bound) and is
    written without the pass over its vertices; a probe scaled so far that the offsets overflow
    float32 is not proven, takes the full check, and the deformer says so and passes its input
    through (offsets zero)."""
    outputs = importlib.import_module(f"{installed.package}.blender.update.outputs")
    target, probes, deformer = _rig(bl, n_probes=2)
    passes = []
    real = outputs.finite_offsets
    monkeypatch.setattr(outputs, "finite_offsets", lambda *a: passes.append(1) or real(*a))
    probes[0].location.x += 0.2
    probes[0].rotation_euler.z += 0.3
    bpy.context.view_layer.update()
    assert deformer.status == "" and passes == []
    assert np.abs(bl.stored_offsets(target, deformer)).max() > 0.01
    me = target.data
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    me.vertices.foreach_set("co", co * 1e17)  # far from the probes' rest frames: huge arms
    me.update()
    probes[0].scale = (1e22, 1e22, 1e22)
    bpy.context.view_layer.update()
    assert passes, "an unbounded result must take the full check"
    assert "not finite" in deformer.status
    assert not np.abs(bl.stored_offsets(target, deformer)).any()


def test_scene_membership_and_cached_modifier_lookup(bl, installed):
    transforms = importlib.import_module(f"{installed.package}.blender.kinds.transforms")
    target, probes, deformer = _rig(bl, n_probes=2)
    assert transforms.in_a_scene(probes[0])
    loose = bpy.data.objects.new("Loose", None)
    assert not transforms.in_a_scene(loose) and not loose.users_scene
    mod = target.modifiers[0]
    mod.name = "Renamed by the user"  # the cached name is stale: found again by content
    probes[0].location.x += 0.3
    bpy.context.view_layer.update()
    assert deformer.status == ""
    target.modifiers.remove(mod)
    probes[0].location.x += 0.3
    bpy.context.view_layer.update()
    assert "modifier was removed" in deformer.status


def test_channel_frame_shared_solve_matches_the_public_function(bl, installed):
    """The per-probe frame (from the one solve shared with the local matrix) equals channel_frame's
    own computation for a sheared parent and a non-uniformly scaled, rotated target."""
    kinds = importlib.import_module(f"{installed.package}.blender.kinds")
    transforms = importlib.import_module(f"{installed.package}.blender.kinds.transforms")
    target, probes, deformer = _rig(bl, n_probes=3)
    target.scale = (1.3, 0.8, 1.1)
    target.rotation_euler = (0.2, -0.4, 0.7)
    parent = bl.empty("Parent", (0.3, 0.1, -0.2))
    parent.scale = (1.0, 2.0, 0.5)
    parent.rotation_euler = (0.5, 0.1, -0.3)
    child = bl.empty("Child", (0.0, 0.0, 0.0))
    child.parent = parent
    child.rotation_euler = (0.3, 0.2, 0.1)
    grand = probes[1]
    grand.parent = child  # non-uniform scale of a rotated parent: the frame is sheared
    grand.rotation_mode = "QUATERNION"
    grand.rotation_quaternion = (0.9, 0.1, -0.3, 0.2)
    grand.scale = (0.7, 1.4, 1.0)
    grand.delta_scale = (1.2, 1.0, 0.9)
    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    motions = kinds.KINDS["PROBE"].current_motions(target, deformer, depsgraph)
    target_world = transforms.world_matrix(target, depsgraph)
    for i, probe in enumerate(probes):
        expected = transforms.channel_frame(probe.evaluated_get(depsgraph), target_world)
        assert np.allclose(motions.turns.frames[i], expected, rtol=0.0, atol=1e-12), i
        assert np.allclose(expected.T @ expected, np.eye(3), atol=1e-12)
        assert np.linalg.det(expected) > 0.0
    assert motions.error == "" and not np.allclose(motions.turns.frames[1], np.eye(3), atol=0.1)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_incremental_updates_write_the_float32_of_a_fresh_evaluation(bl, installed, monkeypatch, compiled):
    """An incremental update has the kernel round the rows it recomputes straight into the cached
    copy of the attribute (no cast of the whole array): after a sequence of them, with rows shared
    between updates and rows no update touched, the attribute is bit for bit float32 of a fresh full
    evaluation, on both backends."""
    accel = importlib.import_module(f"{installed.package}.blender.update.blend").accel
    monkeypatch.setattr(accel._state, "enabled", compiled)
    if accel.active() != compiled:
        pytest.skip(f"backend: {accel.backend()}")
    target, probes, deformer = _rig(bl)
    deformer.radius = 1.0
    probes[0].location.x += 0.2  # the first result is a full one: it makes the copy
    bpy.context.view_layer.update()
    bound = importlib.import_module(f"{installed.package}.blender.update.bound")._bound[
        (target.session_uid, deformer.uid)]
    copy = bound.result.written
    assert copy is not None
    calls = []
    real = accel.deform_points_params_rows

    def spy(*args, **kwargs):
        calls.append((len(args[4]), kwargs.get("out32") is bound.result.written))
        return real(*args, **kwargs)

    monkeypatch.setattr(accel, "deform_points_params_rows", spy)
    rng = np.random.default_rng(23)
    for step in range(8):
        probe = probes[(2 * step) % len(probes)]
        probe.location += mathutils.Vector(rng.normal(scale=0.15, size=3))
        probe.rotation_euler.z += float(rng.uniform(0.2, 1.0))
        probe.scale.x *= float(rng.uniform(0.8, 1.2))
        bpy.context.view_layer.update()
        assert deformer.status == ""
    assert len(calls) == 8, calls  # one incremental kernel call per update ...
    assert all(n > 0 and fused for n, fused in calls), calls  # ... filling the copy
    assert max(n for n, _ in calls) < len(bound.points)
    assert bound.result.written is copy  # written in place, never reallocated
    attribute = bl.stored_offsets(target, deformer)
    assert np.array_equal(attribute.view(np.uint32), copy.view(np.uint32))
    cached = bound.result.offsets.astype(np.float32)
    fresh = bl.recomputed_offsets(target, deformer)
    assert np.abs(fresh).max() > 0.05
    assert np.array_equal(attribute.view(np.uint32), fresh.view(np.uint32))
    assert np.array_equal(cached.view(np.uint32), fresh.view(np.uint32))


@pytest.mark.attributes  # inspects the attribute store (conftest: skipped on POSITIONS)
def test_two_scenes_at_different_frames_do_not_fight_over_the_mesh(bl, installed, monkeypatch):
    """An object shown by two scenes at different frames: updates of the other scene's viewport leave
    the mesh to the scene the artist is in (one write, not one per alternate update); a render of the
    other scene still evaluates it there, and a scene that alone shows the object deforms it."""
    storage = installed.storage
    handlers = importlib.import_module(f"{installed.package}.blender.update.handlers")
    target, probes, deformer = _rig(bl)
    scene_a = bpy.context.scene
    probes[0].keyframe_insert("location", frame=1)
    probes[0].location.x += 0.8
    probes[0].keyframe_insert("location", frame=10)
    scene_b = bpy.data.scenes.new("B")
    for obj in (target, *probes):
        scene_b.collection.objects.link(obj)
    scene_a.frame_set(1)
    scene_b.frame_set(10)
    writes = []
    real_write = storage.write_offsets_unchecked
    monkeypatch.setattr(storage, "write_offsets_unchecked", lambda *a: writes.append(a) or real_write(*a))
    graph_a = scene_a.view_layers[0].depsgraph
    graph_b = scene_b.view_layers[0].depsgraph
    graph_b.update()
    at_frame_1 = bl.evaluated_positions(target).copy()
    for _ in range(10):
        handlers.on_depsgraph_update_post(scene_b, graph_b)
        handlers.on_depsgraph_update_post(scene_a, graph_a)
    assert len(writes) <= 1
    assert np.array_equal(bl.evaluated_positions(target), at_frame_1)
    assert deformer.status == ""
    # A scene that alone shows the object (the artist's scene does not) deforms it as usual.
    scene_a.collection.objects.unlink(target)
    handlers.on_depsgraph_update_post(scene_b, graph_b)
    assert len(writes) >= 1


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_probe_rows_in_a_batch_equal_each_alone_bit_for_bit(installed, monkeypatch, compiled):
    """kinds.probe._probe_rows computes the probes that moved in one batch: every row must get the bits
    it gets alone (the memo stores rows whatever batch made them), on either backend of the frames'
    polar split, the at-rest test must see the bits local_matrix gives (those of the stored rest
    matrices), and a probe with a problem gets its message."""
    kinds = importlib.import_module(f"{installed.package}.blender.kinds.probe")
    monkeypatch.setattr(kinds.accel._state, "enabled", compiled)
    if kinds.accel.active() != compiled:
        pytest.skip(f"backend: {kinds.accel.backend()}")
    transforms = importlib.import_module(f"{installed.package}.blender.kinds.transforms")
    rng = np.random.default_rng(21)

    def affine(scale: float) -> np.ndarray:
        q = mathutils.Quaternion(rng.normal(size=4)).normalized()
        m = np.eye(4)
        m[:3, :3] = np.array(q.to_matrix()) @ np.diag(rng.uniform(0.5, 2.0, 3) * scale)
        m[:3, 3] = rng.normal(size=3) * 3.0
        return np.float32(m).astype(np.float64)  # Blender's matrices are float32

    target = affine(1.0)
    n = 9
    worlds = np.stack([affine(1.0) for _ in range(n)])
    modes = ["XYZ", "ZXY", "QUATERNION", "AXIS_ANGLE", "XYZ", "YZX", "QUATERNION", "XYZ", "XYZ"]
    channels = [tuple(rng.normal(size=4) * 4.0) if mode != "XYZ" else (*rng.normal(size=3) * 7.0, 0.0)
                for mode in modes]
    scales = [tuple(rng.uniform(0.5, 2.0, 6)) for _ in range(n)]
    rests = np.stack([transforms.local_matrix(target, affine(1.0)) for _ in range(n)])
    rest_rotations = rng.normal(size=(n, 4))
    rest_modes = list(modes)
    rests[1] = transforms.local_matrix(target, worlds[1])  # probe 1 at rest (its channels too)
    rest_rotations[1] = np.float32(np.array(channels[1])).astype(np.float64)
    worlds[4, 0, 3] = np.nan  # probe 4: not finite
    worlds[7, :3, :3] *= -1.0  # probe 7: mirrored
    batch = kinds._probe_rows(target, worlds, channels, modes, scales, rests, rest_modes, rest_rotations)
    for i in range(n):
        alone = kinds._probe_rows(target, worlds[i : i + 1], channels[i : i + 1], modes[i : i + 1],
                                  scales[i : i + 1], rests[i : i + 1], rest_modes[i : i + 1],
                                  rest_rotations[i : i + 1])[0]
        row = batch[i]
        assert row.error == alone.error and row.at_rest == alone.at_rest and row.mode == alone.mode, i
        for a, b in ((row.matrix, alone.matrix), (row.frame, alone.frame), (row.pivot, alone.pivot)):
            assert a.tobytes() == b.tobytes(), i
        assert row.rotation == alone.rotation
        if not row.error:  # the per-probe function agrees (to rounding: it is another formula)
            single = kinds._probe_row(target, worlds[i], channels[i], modes[i], scales[i], rests[i],
                                      rest_modes[i], rest_rotations[i])
            assert single.at_rest == row.at_rest
            assert np.allclose(single.matrix, row.matrix, rtol=0, atol=1e-12)
            assert np.allclose(single.frame, row.frame, rtol=0, atol=1e-12)
            assert single.pivot.tobytes() == row.pivot.tobytes()
    assert batch[1].at_rest and np.array_equal(batch[1].matrix, np.eye(4))
    assert "non-finite" in batch[4].error and "mirrored" in batch[7].warning and batch[7].skip
    assert not any(batch[i].error for i in (0, 2, 3, 5, 6, 8))
    current, _ = transforms.local_solves(target, worlds[[0, 2, 3]])
    for j, i in enumerate((0, 2, 3)):
        assert current[j].tobytes() == transforms.local_matrix(target, worlds[i]).tobytes()


def test_viewport_updates_list_the_named_controls_only_for_a_disabled_probe(bl, installed, monkeypatch):
    """The viewport's per-probe test is one flag: while every probe passes it, an update does not list
    the controls the modifier names (nodes.named_controls); a probe disabled in viewports is checked
    against that list, and is fine when the modifier names it."""
    nodes = importlib.import_module(f"{installed.package}.blender.files.nodes")
    target, probes, deformer = _rig(bl, n_probes=3)
    calls = []
    real = nodes.named_controls
    monkeypatch.setattr(nodes, "named_controls", lambda *a: calls.append(a[0].name) or real(*a))
    for step in range(3):
        probes[step].location.z += 0.2
        bpy.context.view_layer.update()
    assert calls == [] and deformer.status == ""
    probes[1].hide_viewport = True
    probes[0].location.z += 0.2
    bpy.context.view_layer.update()
    assert calls and set(calls) == {target.name}
    assert deformer.status == ""
    assert np.array_equal(bl.stored_offsets(target, deformer), bl.recomputed_offsets(target, deformer))


def test_probe_rows_are_memoised_per_backend(bl, installed, monkeypatch):
    """The frames' polar split runs in the compiled kernel when it is active, in numpy's SVD otherwise
    (~1e-15 apart): a row memoised under one backend is not served under the other, so after a switch
    the motions have the bits a fresh evaluation on the new backend gives."""
    kinds = importlib.import_module(f"{installed.package}.blender.kinds.probe")
    kind = importlib.import_module(f"{installed.package}.blender.kinds").KINDS["PROBE"]
    accel = kinds.accel
    if not accel.active():
        pytest.skip(f"backend: {accel.backend()}")
    target, probes, deformer = _rig(bl, n_probes=4)
    target.rotation_euler = (0.3, -0.2, 0.9)
    target.scale = (1.2, 0.9, 1.1)
    rng = np.random.default_rng(41)
    for probe in probes:
        probe.rotation_euler = tuple(rng.uniform(-3.0, 3.0, 3))
        probe.scale = tuple(rng.uniform(0.6, 1.5, 3))
    bpy.context.view_layer.update()

    def frames() -> bytes:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        motions = kind.current_motions(target, deformer, depsgraph)
        assert motions.error == ""
        return motions.turns.frames.tobytes()

    compiled = frames()  # the memo now holds rows made with the compiled split
    monkeypatch.setattr(accel._state, "enabled", False)
    switched = frames()
    kinds._rows.clear()
    assert switched == frames()  # what numpy gives from nothing
    assert switched != compiled  # the backends differ in the last bits here (else this test is void)
    monkeypatch.setattr(accel._state, "enabled", True)
    kinds._rows.clear()
    assert frames() == compiled


def test_a_disabled_deformer_costs_nothing_and_catches_up_when_enabled(bl, installed, monkeypatch):
    """As a disabled built-in modifier: the handlers skip a deformer whose modifier is off in the
    viewport (a baked crowd, a deformer muted for speed), and enabling it again shows the shape of the
    controls' current poses, moved while it was off."""
    evaluate = importlib.import_module(f"{installed.package}.blender.update.evaluate")
    target, probes, deformer = _rig(bl)
    rest = bl.rest_positions(target)
    calls = []
    real = evaluate._begin
    monkeypatch.setattr(evaluate, "_begin", lambda o, d, *a: calls.append(d.uid) or real(o, d, *a))
    deformer.show_viewport = False
    bpy.context.view_layer.update()
    for step in range(3):
        probes[step].location.z += 0.3
        probes[step].rotation_euler.x += 0.5
        bpy.context.view_layer.update()
    assert calls == []
    assert np.array_equal(bl.evaluated_positions(target), rest)  # Blender skips the disabled modifier
    deformer.show_viewport = True
    bpy.context.view_layer.update()
    assert calls and deformer.status == ""
    shown = bl.evaluated_positions(target)
    assert np.abs(shown - rest).max() > 0.05
    kept = bl.stored_offsets(target, deformer)
    np.testing.assert_array_equal(kept, bl.recomputed_offsets(target, deformer))
    # Disabled in the viewport only: a render's update still evaluates it.
    deformer.show_viewport = False
    depsgraph = bpy.context.evaluated_depsgraph_get()
    assert evaluate.disabled(target, deformer, depsgraph)
    assert deformer.show_render


def test_an_update_of_many_deformed_objects_shares_their_probes_numerics(bl, installed, monkeypatch):
    """One update of several deformed objects computes the rows of all their moved probes in one batch,
    their parameters in one batch per branch treatment (evaluate._prefetch) and their vertices in one
    kernel batch (accel.KernelBatch: one hand-over to the kernel's threads), and every object gets
    bit for bit the offsets it gets evaluated alone; a deformer with a bad probe reports it and leaves
    the others alone."""
    kinds = importlib.import_module(f"{installed.package}.blender.kinds.probe")
    params = importlib.import_module(f"{installed.package}.blender.update.params")
    batch = importlib.import_module(f"{installed.package}.accel.batch")
    rng = np.random.default_rng(3)
    rigs = []
    layouts = [("CHANNELS", ["XYZ", "QUATERNION", "AXIS_ANGLE"]), ("SHORTEST", ["ZXY", "XYZ"]),
               ("CHANNELS", ["XYZ", "XYZ", "YZX", "XYZ"])]
    for n, (rule, modes) in enumerate(layouts):
        target = bl.grid_cube(cuts=4, name=f"Body{n}")
        target.location = (4.0 * n, 0.0, 0.0)
        target.rotation_euler = (0.2 * n, 0.0, 0.3)
        target.scale = (1.0, 1.0 + 0.5 * n, 1.0)
        probes = [bl.empty(f"P{n}{i}", (4.0 * n + rng.uniform(-1, 1), *rng.uniform(-1, 1, 2)))
                  for i in range(len(modes))]
        for probe, mode in zip(probes, modes, strict=True):
            probe.rotation_mode = mode
        deformer = bl.add_probe_deformer(target, probes, radius=1.5, weight_mode="FALLOFF")
        deformer.branch_rule = rule
        rigs.append((target, probes, deformer))
    bad_target = bl.grid_cube(cuts=4, name="Bad")
    bad_target.location = (-4.0, 0.0, 0.0)
    bad_probe = bl.empty("BadProbe", (-4.0, 0.0, 1.0))
    bad = bl.add_probe_deformer(bad_target, [bad_probe], radius=1.5, weight_mode="FALLOFF")
    bpy.context.view_layer.update()
    for _target, probes, _deformer in rigs:  # an update after the bind's: the next ones are incremental
        probes[0].location.x += 0.01
    bpy.context.view_layer.update()

    batches, param_batches, kernel_batches = [], [], []
    real_rows, real_params = kinds._probe_rows, params._params_of_rows
    real_run = batch.KernelBatch.run

    def run(self) -> None:
        if len(self):
            kernel_batches.append(len(self))
        real_run(self)

    monkeypatch.setattr(batch.KernelBatch, "run", run)
    monkeypatch.setattr(kinds, "_probe_rows", lambda *a: batches.append(len(a[1])) or real_rows(*a))
    monkeypatch.setattr(params, "_params_of_rows",
                        lambda m, r, *a: param_batches.append(len(r)) or real_params(m, r, *a))
    for _target, probes, _deformer in rigs:
        for probe in probes:
            probe.location.z += rng.uniform(0.1, 0.4)
            if probe.rotation_mode == "QUATERNION":
                probe.rotation_quaternion = (0.6, 0.2, 0.7, 0.3)
            elif probe.rotation_mode == "AXIS_ANGLE":
                probe.rotation_axis_angle = (9.0, 0.2, 0.3, 1.0)
            else:
                probe.rotation_euler = tuple(rng.uniform(-7.0, 7.0, 3))  # past full turns: lifted branches
    bad_probe.scale.x = -1.0  # mirrored: its deformer reports it
    bpy.context.view_layer.update()
    moved = sum(len(probes) for _t, probes, _d in rigs)
    assert batches == [moved + 1], "every moved probe, the bad one too, in one batch"
    assert len(param_batches) == 2, "one batch per branch treatment (lifted, shortest)"
    if importlib.import_module(f"{installed.package}.accel").active():
        assert kernel_batches == [len(rigs)], "every moved object's vertices in one kernel batch"
    assert "mirrored" in bad.status
    shown = [bl.stored_offsets(target, deformer) for target, _p, deformer in rigs]
    assert all(deformer.status == "" for _t, _p, deformer in rigs)
    for (target, _probes, deformer), offsets in zip(rigs, shown, strict=True):
        assert np.abs(offsets).max() > 0.05
        alone = bl.recomputed_offsets(target, deformer)  # every cache dropped, this object alone
        assert offsets.tobytes() == alone.tobytes(), target.name


def test_a_kernel_batch_that_fails_leaves_every_deformer_right(bl, installed):
    """Should the update's kernel batch fail (evaluate._Update.finish), each deformer is blended again
    on its own from a full recompute: every object shows what it shows evaluated alone, no status."""
    batch = importlib.import_module(f"{installed.package}.accel.batch")
    rigs = []
    for n in range(3):
        target = bl.grid_cube(cuts=4, name=f"Body{n}")
        target.location = (4.0 * n, 0.0, 0.0)
        probes = [bl.empty(f"P{n}{i}", (4.0 * n + 0.5 * i, 0.0, 0.8)) for i in range(2)]
        deformer = bl.add_probe_deformer(target, probes, radius=1.5, weight_mode="FALLOFF")
        rigs.append((target, probes, deformer))
    failed: list[int] = []

    def run(self) -> None:  # the rows collected are never computed
        if len(self):
            failed.append(len(self))
            raise MemoryError("no scratch memory")

    for step in range(3):  # the batch fails in the third update, incremental by then
        for _target, probes, _deformer in rigs:
            probes[0].location.z += 0.2
            probes[1].rotation_euler.x += 0.3
        with pytest.MonkeyPatch.context() as patch:
            if step == 2:
                patch.setattr(batch.KernelBatch, "run", run)
            bpy.context.view_layer.update()
    if importlib.import_module(f"{installed.package}.accel").active():
        assert failed == [len(rigs)]
    shown = [bl.stored_offsets(target, deformer) for target, _probes, deformer in rigs]
    for (target, _probes, deformer), offsets in zip(rigs, shown, strict=True):
        assert deformer.status == ""
        assert np.abs(offsets).max() > 0.05
        assert offsets.tobytes() == bl.recomputed_offsets(target, deformer).tobytes(), target.name
