"""Bad input never crashes and never corrupts the mesh: each case gives a clear message, the mesh data
is untouched and the evaluated mesh shows the exact rest shape, or, for a control gone degenerate
(deleted, scaled to zero, mirrored), only what that control holds changes (issue 55); fixing the input
recovers."""

from __future__ import annotations

import bpy
import numpy as np
import pytest


@pytest.fixture
def rig(bl):
    target = bl.uv_sphere(segments=24, rings=12)
    probes = [bl.empty("Alpha", (0.0, 0.0, 1.0)), bl.empty("Beta", (0.0, 0.0, -1.0))]
    deformer = bl.add_probe_deformer(target, probes)
    rest = bl.rest_positions(target).copy()
    probes[1].rotation_euler.x = 0.7  # a live deformation that the bad input must switch off
    assert np.abs(bl.evaluated_positions(target) - rest).max() > 0.05
    return target, probes, deformer, rest


def _assert_intact(bl, target, rest):
    assert np.array_equal(bl.rest_positions(target), rest), "mesh data must never change"
    assert np.array_equal(bl.evaluated_positions(target), rest), "evaluated mesh must show the rest shape"


def _follows_beta(bl, target, rest):
    """Every vertex follows 'Beta' alone (the rig's other probe, turned 0.7 about X at (0, 0, −1)): the
    weight of a probe that is gone went to it (issue 55: only what the bad probe holds changes)."""
    assert np.array_equal(bl.rest_positions(target), rest), "mesh data must never change"
    c, s = np.cos(0.7), np.sin(0.7)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    pivot = np.array([0.0, 0.0, -1.0])
    expected = (rest.astype(np.float64) - pivot) @ turn.T + pivot
    assert np.abs(bl.evaluated_positions(target) - expected).max() < 1e-5


def test_deleted_probe(bl, rig):
    target, probes, deformer, rest = rig
    bpy.data.objects.remove(probes[0], do_unlink=True)
    _follows_beta(bl, target, rest)
    assert "Probe 'Alpha' was deleted" in deformer.status and "follow the other probes" in deformer.status
    assert deformer.probes[0].object is None


def test_probe_deleted_from_the_scene_but_kept_by_the_pointer(bl, rig):
    target, probes, deformer, rest = rig
    with bpy.context.temp_override(selected_objects=[probes[0]], active_object=probes[0], object=probes[0]):
        bpy.ops.object.delete()
    _follows_beta(bl, target, rest)
    assert "Probe 'Alpha' is not in any scene" in deformer.status


def test_probe_scaled_to_zero(bl, rig):
    target, probes, deformer, rest = rig
    probes[0].scale = (1e-6, 1e-6, 1e-6)
    bpy.context.view_layer.update()
    near = bl.evaluated_positions(target).astype(np.float64)
    probes[0].scale = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    got = bl.evaluated_positions(target).astype(np.float64)
    assert np.array_equal(bl.rest_positions(target), rest), "mesh data must never change"
    assert np.abs(got - near).max() <= 0.01 * 2.0, "the limit of the nearby scales (issue 55)"
    assert np.isfinite(got).all() and np.abs(got).max() < 2.0, "collapsed towards its probes, not flung"
    assert "Probe 'Alpha'" in deformer.status and "scaled to zero" in deformer.status
    probes[0].scale = (1.0, 1.0, 1.0)  # fixing the input recovers without rebinding
    assert np.abs(bl.evaluated_positions(target) - rest).max() > 0.05
    assert deformer.status == ""


def test_probe_mirrored(bl, rig):
    target, probes, deformer, rest = rig
    probes[1].scale = (-1.0, 1.0, 1.0)
    _assert_intact(bl, target, rest)
    assert "Probe 'Beta'" in deformer.status and "mirrored" in deformer.status


def test_nan_in_a_probe_matrix(bl, rig):
    target, probes, deformer, rest = rig
    probes[0].location.y = float("nan")
    _assert_intact(bl, target, rest)
    assert "Probe 'Alpha'" in deformer.status and "non-finite" in deformer.status


@pytest.mark.parametrize("which", ["probe", "target"])
def test_an_infinite_location_is_refused_not_followed(bl, rig, which):
    """Blender clamps location = inf to 3.4e38: the mesh must not be sent there."""
    target, probes, deformer, rest = rig
    obj = probes[0] if which == "probe" else target
    obj.location.x = float("inf")
    bpy.context.view_layer.update()
    assert "non-finite" in deformer.status, deformer.status
    if which == "probe":
        _assert_intact(bl, target, rest)
    else:  # the target itself is far away; its mesh keeps the rest shape
        assert np.array_equal(bl.evaluated_positions(target), rest)


def test_a_probe_pointed_at_its_own_target_keeps_its_message(bl, rig):
    target, probes, deformer, rest = rig
    deformer.probes[0].object = target
    for frame in (2, 3):
        bpy.context.scene.frame_set(frame)
        assert "cannot be a probe of itself" in deformer.status
    assert np.array_equal(bl.rest_positions(target), rest)
    deformer.probes[0].object = probes[0]
    bpy.context.scene.frame_set(4)
    assert deformer.status == ""


def test_topology_changed_after_bind(bl, rig):
    import bmesh

    target, _probes, deformer, _rest = rig
    bm = bmesh.new()
    bm.from_mesh(target.data)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:8], cuts=1)
    bm.to_mesh(target.data)
    bm.free()
    target.data.update()
    changed_rest = bl.rest_positions(target).copy()
    assert len(changed_rest) != deformer.bound_vertex_count
    _assert_intact(bl, target, changed_rest)
    assert "topology changed" in deformer.status and "rebind" in deformer.status
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    assert deformer.status == "" and deformer.bound_vertex_count == len(changed_rest)


def test_renumbered_vertices_with_the_same_count_are_detected(bl, rig):
    """One vertex deleted and one loose vertex added: the count is the same, the vertices are not."""
    import bmesh

    target, _probes, deformer, _rest = rig
    n = len(target.data.vertices)
    bm = bmesh.new()
    bm.from_mesh(target.data)
    bm.verts.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[bm.verts[5]], context="VERTS")
    bm.verts.new((0.1, 0.2, 0.3))
    bm.to_mesh(target.data)
    bm.free()
    target.data.update()
    assert len(target.data.vertices) == n
    changed_rest = bl.rest_positions(target).copy()
    _assert_intact(bl, target, changed_rest)
    assert "topology changed" in deformer.status and "rebind" in deformer.status
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    assert deformer.status == ""


def test_shape_or_face_edits_alone_keep_the_binding(bl, rig, tmp_path):
    """Moving vertices (a rest-shape edit), or deleting a face with its vertices left in place, keeps
    the vertex indices: no rebind is asked for, also after saving and reopening."""
    import bmesh

    target, probes, deformer, _rest = rig
    probes[0].location.x += 0.3
    co = bl.rest_positions(target)
    co[:, 2] *= 1.2
    target.data.vertices.foreach_set("co", co.ravel())
    target.data.update()
    bl.evaluated_positions(target)
    assert deformer.status == ""
    bm = bmesh.new()
    bm.from_mesh(target.data)
    bm.faces.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[bm.faces[0]], context="FACES_ONLY")
    bm.to_mesh(target.data)
    bm.free()
    target.data.update()
    bl.evaluated_positions(target)
    assert deformer.status == ""
    path = tmp_path / "edited.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    assert str(bl.reopened_positions(path, target.name, (1,), tmp_path / "p.npz")["status"]) == ""


def test_non_mesh_target(bl):
    bpy.ops.curve.primitive_bezier_curve_add()
    curve = bpy.context.active_object
    points = [tuple(p.co) for p in curve.data.splines[0].bezier_points]
    probe = bl.empty("P")
    with (bpy.context.temp_override(active_object=curve, object=curve, selected_objects=[curve, probe]),
          pytest.raises(RuntimeError, match="not a mesh")):
        bpy.ops.object.affine_probe_deformer_add()
    assert len(curve.affine_deformers) == 0 and len(curve.modifiers) == 0
    assert [tuple(p.co) for p in curve.data.splines[0].bezier_points] == points
    # a deformer item put on a curve by a script: a message at evaluation, no exception
    curve.affine_deformers.add().probes.add().object = probe
    bpy.context.scene.frame_set(2)
    assert "is not a mesh" in curve.affine_deformers[0].status
    assert [tuple(p.co) for p in curve.data.splines[0].bezier_points] == points


def test_no_active_object(bl):
    with (bpy.context.temp_override(active_object=None, object=None, selected_objects=[]),
          pytest.raises(RuntimeError, match="No active object")):
        bpy.ops.object.affine_probe_deformer_add()


def test_bad_deformer_index(bl, rig):
    target, *_ = rig
    with pytest.raises(RuntimeError, match="no affine deformer #3"):
        bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=3)


def test_negative_indices_are_refused_not_clamped(bl, rig):
    """Blender clamps an IntProperty to its minimum: index=-1 must not address deformer #0."""
    target, *_ = rig
    second = bl.add_probe_deformer(target, [bl.empty("Q", (0.0, 0.0, 2.0))])
    names = [d.name for d in target.affine_deformers]
    assert len(names) == 2
    for op in (bpy.ops.object.affine_deformer_remove, bpy.ops.object.affine_deformer_bind,
               bpy.ops.object.affine_deformer_apply):
        with pytest.raises(RuntimeError, match="#-1"):
            bl.run_op(op, target, index=-1)
    with pytest.raises(RuntimeError, match="no probe #-1"):
        bl.run_op(bpy.ops.object.affine_deformer_probe_remove, target, index=1, probe_index=-1)
    assert [d.name for d in target.affine_deformers] == names and len(second.probes) == 1


def test_operators_are_greyed_out_with_the_reason(bl):
    """poll() refuses with the reason as the message (the tooltip of a greyed-out button)."""
    cube = bl.grid_cube(cuts=1)
    e = bl.empty("E")
    with (bpy.context.temp_override(active_object=e, object=e, selected_objects=[e]),
          pytest.raises(RuntimeError, match="'E' is an empty, not a mesh")):
        bpy.ops.object.affine_probe_deformer_add()
    for op in (bpy.ops.object.affine_deformer_remove, bpy.ops.object.affine_deformer_bake,
               bpy.ops.object.affine_deformer_probe_add):
        with pytest.raises(RuntimeError, match="'Cube' has no affine deformers"):
            bl.run_op(op, cube)
    with bpy.context.temp_override(active_object=cube, object=cube, selected_objects=[cube]):
        assert bpy.ops.object.affine_probe_deformer_add.poll()
        assert not bpy.ops.object.affine_deformer_bind.poll()


def test_binding_a_zero_scaled_probe_is_refused_and_rolled_back(bl):
    target = bl.uv_sphere()
    probe = bl.empty("Flat")
    probe.scale = (1.0, 0.0, 1.0)
    with (bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, probe]),
          pytest.raises(RuntimeError, match="Probe 'Flat' has a zero scale")):
        bpy.ops.object.affine_probe_deformer_add()
    assert len(target.affine_deformers) == 0 and len(target.modifiers) == 0
    assert not [a.name for a in target.data.attributes if "affdef" in a.name]


def test_an_unexpected_exception_is_contained(bl, rig, installed, monkeypatch):
    """A bug in a kind must not escape the frame / depsgraph handlers: status + rest shape."""
    import importlib

    target, probes, deformer, rest = rig
    kinds = importlib.import_module(f"{installed.package}.blender.kinds")

    def broken(*_args, **_kwargs):
        raise ZeroDivisionError("simulated bug")

    monkeypatch.setattr(kinds.ProbeKind, "current_motions", broken)
    probes[0].location.x = 0.3
    bpy.context.scene.frame_set(2)
    _assert_intact(bl, target, rest)
    assert deformer.status.startswith("Internal error (ZeroDivisionError: simulated bug)")
    monkeypatch.undo()
    probes[0].location.x = 0.2
    assert np.abs(bl.evaluated_positions(target) - rest).max() > 0.05
    assert deformer.status == ""


# --------------------------------------------- settings and stored data a script or a damaged file set (#47)


def _deforms(bl, target, rest, deformer):
    assert np.abs(bl.evaluated_positions(target) - rest).max() > 0.05
    assert deformer.status == ""


@pytest.mark.parametrize("way", ["interface", "ID property"])
def test_a_nan_weight_scale_is_named_with_its_value(bl, rig, capfd, way):
    """Was 'Internal error (ValueError …)' and a traceback."""
    target, _probes, deformer, rest = rig
    item = deformer.probes[0]
    if way == "interface":
        item.weight_scale = float("nan")  # NaN passes the interface's clamp
    else:
        item["weight_scale"] = float("nan")
        bpy.context.scene.frame_set(2)
    _assert_intact(bl, target, rest)
    assert deformer.status == ("Probe 'Alpha': Weight Scale is nan (must be a finite number from 0 to "
                               "1e+06): the mesh shows its input")
    assert "Traceback" not in capfd.readouterr().err
    item.weight_scale = 1.0
    _deforms(bl, target, rest, deformer)


def test_preserve_shape_settings_are_named_with_their_value(bl, rig):
    """Anchor Strength NaN was 'strength must be ≥ 0'; Iterations written past its range would have
    run 2³¹ − 1 solves."""
    target, _probes, deformer, rest = rig
    deformer.preserve_shape = True
    _deforms(bl, target, rest, deformer)
    deformer.shape_anchor = float("nan")
    _assert_intact(bl, target, rest)
    assert deformer.status == ("Anchor Strength is nan (must be a finite number from 0 to 1e+06): the mesh "
                               "shows its input")
    deformer.shape_anchor = 100.0
    _deforms(bl, target, rest, deformer)
    deformer["shape_iterations"] = 2**31 - 1  # a script or a damaged file: no clamp
    bpy.context.scene.frame_set(2)
    _assert_intact(bl, target, rest)
    assert deformer.status == "Iterations 2147483647 is out of range (1 to 5): the mesh shows its input"
    deformer.shape_iterations = 1
    _deforms(bl, target, rest, deformer)


@pytest.mark.parametrize("how", ["location", "scale"])
def test_a_probe_far_away_is_out_of_range_not_non_finite(bl, rig, how):
    target, probes, deformer, rest = rig
    if how == "location":
        probes[0].location.x = 1e30
    else:
        probes[0].scale.x = 1e30
    _assert_intact(bl, target, rest)
    assert deformer.status == ("Probe 'Alpha' has a transform out of range (an entry of 1e+30; entries must "
                               "stay below 1e+30 in magnitude): the mesh shows its rest shape")
    probes[0].location.x, probes[0].scale.x = 0.0, 1.0
    _deforms(bl, target, rest, deformer)


@pytest.mark.parametrize("way", ["interface", "ID property"])
def test_a_stored_rest_matrix_sent_far_away_is_named_and_the_mesh_keeps_its_input(bl, rig, way):
    """Was: the mesh flung 1e30 away, no status."""
    target, _probes, deformer, rest = rig
    item = deformer.probes[0]
    stored = list(item.rest_matrix)
    if way == "interface":
        item.rest_matrix = [1e30 if i == 3 else v for i, v in enumerate(stored)]  # its x translation
    else:
        item["rest_matrix"][3] = 1e30
    bpy.context.scene.frame_set(2)
    _assert_intact(bl, target, rest)
    assert deformer.status == ("Probe 'Alpha': Rest Matrix has an entry of 1e+30, out of range (entries must "
                               "stay below 1e+30 in magnitude): the mesh shows its rest shape; rebind the "
                               "deformer")
    assert item.state == "INVALID"
    item.rest_matrix = stored  # no update callback: the next frame change reads it
    bpy.context.scene.frame_set(3)
    _deforms(bl, target, rest, deformer)


def test_a_stored_rest_matrix_mirrored_against_its_probe_is_named(bl, rig):
    target, _probes, deformer, rest = rig
    item = deformer.probes[0]
    item.rest_matrix = [-v if i == 0 else v for i, v in enumerate(item.rest_matrix)]
    bpy.context.scene.frame_set(2)
    _assert_intact(bl, target, rest)  # the deformer's own data: it shows its rest shape
    assert deformer.status == ("Probe 'Alpha' is mirrored relative to its Rest Matrix (determinant -1, "
                               "now 1): the mesh shows its rest shape")


def test_a_probe_mirrored_at_bind_still_drives_the_mesh(bl):
    """A probe's rest may be mirrored (an Empty scaled by −1, as mirrored rigs are): its motion is not."""
    target = bl.uv_sphere(segments=24, rings=12)
    probe = bl.empty("Mirrored", (0.0, 0.0, 1.0))
    probe.scale.x = -1.0
    deformer = bl.add_probe_deformer(target, [probe, bl.empty("Other", (0.0, 0.0, -1.0))])
    rest = bl.rest_positions(target).copy()
    probe.location.x = 0.3
    _deforms(bl, target, rest, deformer)
