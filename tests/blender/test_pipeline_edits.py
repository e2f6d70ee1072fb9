"""Issue 38's pipeline cases done to a rig in this process, on the rig asset of test_overrides (a
probe, a cage and a bone deformer with keyed controls; the asset's own positions at frames 1, 12 and 24
as the reference, and after its `pose`): Edit Mode (bmesh edits of a target and of the cage, a topology
change), positions written in Sculpt Mode, Shift+D and Alt+D with and without the controls selected,
Make Single User, undo and redo of Rebind / Remove / Apply and of deleting the controls, and renames."""

from __future__ import annotations

import bmesh
import bpy
import numpy as np
import pytest

from tests.blender.pipeline_rig import (
    BODIES,
    assert_plays_as,
    body_positions,
    by_name,
    open_rig,
    pose,
    save_and_reopen,
)
from tests.blender.test_stack import _expected_contract

CONTROLS = ("P1", "P2", "Cage", "Arm")
#: What a control item of each body names, by body.
CONTROL_OF = {"ProbeBody": "P1", "CageBody": "Cage", "BoneBody": "Arm"}


def _select(*objects) -> None:
    """Select `objects` only, the first active (what a click and Shift+clicks do)."""
    for obj in bpy.context.view_layer.objects:
        obj.select_set(False)
    for obj in objects:
        obj.select_set(True)
    bpy.context.view_layer.objects.active = objects[0]


def _control(body) -> bpy.types.Object:
    deformer = body.affine_deformers[0]
    return deformer.probes[0].object if deformer.kind == "PROBE" else deformer.cage or deformer.armature


def _sheared(points: np.ndarray) -> np.ndarray:
    """A rest-shape edit (z sheared along x), float32 as the mesh holds it."""
    edited = points.copy()
    edited[:, 2] += 0.15 * edited[:, 0]
    return edited


def _write_positions(obj, points: np.ndarray) -> None:
    obj.data.vertices.foreach_set("co", points.astype(np.float32).ravel())
    obj.data.update()


def _in_object_mode(bl, obj, points: np.ndarray, shown=None) -> np.ndarray:
    """The evaluated positions of `shown` (default: `obj`) with `points` written into the mesh of `obj`
    in Object Mode; the mesh is given its former positions back after."""
    shown = shown or obj
    former = bl.rest_positions(obj).copy()
    before = bl.evaluated_positions(shown).copy()
    _write_positions(obj, points)
    result = bl.evaluated_positions(shown).copy()
    _write_positions(obj, former)
    assert np.array_equal(bl.evaluated_positions(shown), before)
    return result


def _edit_mode(obj, edit) -> None:
    """Enter Edit Mode on `obj`, run `edit(bm)` on its edit mesh (bmesh), update it."""
    _select(obj)
    assert bpy.ops.object.mode_set(mode="EDIT") == {"FINISHED"}
    bm = bmesh.from_edit_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    edit(bm)
    bmesh.update_edit_mesh(obj.data)


def _object_mode() -> None:
    assert bpy.ops.object.mode_set(mode="OBJECT") == {"FINISHED"}


def _set_positions(points: np.ndarray):
    def edit(bm):
        for vert in bm.verts:
            vert.co = points[vert.index]
    return edit


# --------------------------------------------------------------------------------------------- edit mode


def test_edit_mode_shape_edits_of_each_target_deform_as_object_mode_writes(asset, bl, installed, tmp_path):
    """A rest-shape edit made with bmesh in Edit Mode keeps the binding: back in Object Mode each body
    shows what the same positions written in Object Mode give, which for the probe body is the core's
    contract on the edited rest shape."""
    reference = open_rig(asset, tmp_path)
    bpy.context.scene.frame_set(12)
    for name in BODIES:
        body = by_name(name)
        edited = _sheared(bl.rest_positions(body))
        expected = _in_object_mode(bl, body, edited)
        assert np.abs(expected - reference[f"{name}_12"]).max() > 0.05
        _edit_mode(body, _set_positions(edited))
        _object_mode()
        assert np.array_equal(bl.rest_positions(body), edited)
        assert np.abs(bl.evaluated_positions(body) - expected).max() <= 1e-6, name
        assert body.affine_deformers[0].status == ""
    body = by_name("ProbeBody")
    deformer = body.affine_deformers[0]
    probes = [item.object for item in deformer.probes]
    contract = _expected_contract(installed, body, deformer, probes, bl.rest_positions(body), bl)
    assert np.abs(bl.evaluated_positions(body) - contract).max() <= 1e-5


def test_edit_mode_edits_of_the_cage_deform_live_and_after(asset, bl, tmp_path):
    """Cage vertices moved in the cage's Edit Mode: the target follows while the cage is in Edit Mode,
    and back in Object Mode shows what the same cage positions written in Object Mode give."""
    open_rig(asset, tmp_path)
    bpy.context.scene.frame_set(12)
    body, cage = by_name("CageBody"), by_name("Cage")
    moved = bl.rest_positions(cage).copy()
    moved[4] += (0.2, -0.1, 0.4)  # the top corner
    before = bl.evaluated_positions(body).copy()
    expected = _in_object_mode(bl, cage, moved, shown=body)
    assert np.abs(expected - before).max() > 0.05
    _edit_mode(cage, _set_positions(moved))
    live = bl.evaluated_positions(body).copy()
    _object_mode()
    assert np.abs(live - expected).max() <= 1e-6, "live in the cage's Edit Mode"
    assert np.abs(bl.evaluated_positions(body) - expected).max() <= 1e-6, "back in Object Mode"
    assert body.affine_deformers[0].status == ""


def test_a_topology_change_in_edit_mode_is_reported_and_rebind_recovers(asset, bl, tmp_path):
    """Edges subdivided in Edit Mode: back in Object Mode each body's status says the topology changed
    and asks for a rebind, the mesh shows its rest shape; Rebind deforms it again."""
    open_rig(asset, tmp_path)
    scene = bpy.context.scene
    scene.frame_set(12)
    for name in BODIES:
        body = by_name(name)
        count = len(body.data.vertices)
        _edit_mode(body, lambda bm: bmesh.ops.subdivide_edges(bm, edges=bm.edges[:6], cuts=1))
        scene.frame_set(13)  # an update while in Edit Mode leaves the object alone
        _object_mode()
        assert len(body.data.vertices) > count
        scene.frame_set(12)
        status = body.affine_deformers[0].status
        assert "topology changed" in status and "rebind" in status, (name, status)
        assert np.array_equal(bl.evaluated_positions(body), bl.rest_positions(body)), name
        assert bl.run_op(bpy.ops.object.affine_deformer_bind, body, index=0) == {"FINISHED"}
        scene.frame_set(24)
        assert body.affine_deformers[0].status == ""
        assert np.abs(bl.evaluated_positions(body) - bl.rest_positions(body)).max() > 0.05, name


# -------------------------------------------------------------------------------------------- sculpt mode


def test_positions_written_in_sculpt_mode_deform_as_in_object_mode(asset, bl, tmp_path):
    """A script (or tool) writing the mesh's positions while it is in Sculpt Mode: the deformers keep
    their binding and show what the same write gives in Object Mode, in Sculpt Mode and after."""
    open_rig(asset, tmp_path)
    bpy.context.scene.frame_set(12)
    for name in BODIES:
        body = by_name(name)
        edited = _sheared(bl.rest_positions(body))
        expected = _in_object_mode(bl, body, edited)
        _select(body)
        assert bpy.ops.object.mode_set(mode="SCULPT") == {"FINISHED"}
        _write_positions(body, edited)
        sculpting = bl.evaluated_positions(body).copy()
        _object_mode()
        assert np.abs(sculpting - expected).max() <= 1e-6, f"{name} in Sculpt Mode"
        assert np.abs(bl.evaluated_positions(body) - expected).max() <= 1e-6, f"{name} after"
        assert body.affine_deformers[0].status == ""


# --------------------------------------------------------------------------------------------- duplicates


def _duplicate(linked: bool, with_controls: bool):
    """Shift+D (or Alt+D) of the three bodies, with or without their controls selected; returns the
    lookup of a copy by its original's name."""
    names = list(BODIES) + (list(CONTROLS) if with_controls else [])
    _select(*(by_name(name) for name in names))
    assert bpy.ops.object.duplicate(linked=linked) == {"FINISHED"}
    assert {obj.name for obj in bpy.context.selected_objects} == {f"{name}.001" for name in names}

    def copy(name):
        return by_name(f"{name}.001")

    for name in BODIES:
        assert (copy(name).data == by_name(name).data) == linked
        control = CONTROL_OF[name] + (".001" if with_controls else "")
        assert _control(copy(name)).name == control, "a copy follows the controls copied with it"
    return copy


@pytest.mark.parametrize("with_controls", [False, True], ids=["alone", "with-controls"])
@pytest.mark.parametrize("linked", [False, True], ids=["shift-d", "alt-d"])
def test_a_duplicate_plays_as_the_original_and_follows_its_controls(asset, bl, tmp_path, linked,
                                                                     with_controls):
    """Each body duplicated (its own mesh, or Alt+D: the same mesh) plays as the asset at every frame
    beside its unchanged original. Copied with its controls it follows them: posing them poses the copy
    alone, and moving the copies away together keeps their shapes. Copied alone it follows the
    original's controls with the original."""
    reference = open_rig(asset, tmp_path)
    copy = _duplicate(linked, with_controls)
    assert_plays_as(body_positions(bl, copy), reference)
    assert_plays_as(body_positions(bl), reference)
    bpy.context.scene.frame_set(12)
    pose(copy if with_controls else by_name)
    assert_plays_as(body_positions(bl, copy), reference, "posed_")
    assert_plays_as(body_positions(bl), reference, "" if with_controls else "posed_")
    if with_controls:
        for name in BODIES + CONTROLS:  # a delta: keyed locations stay as keyed
            copy(name).delta_location = (0.0, -8.0, 3.0)
        assert_plays_as(body_positions(bl, copy), reference, "posed_")
        assert_plays_as(body_positions(bl), reference)
    save_and_reopen(tmp_path / "duplicated.blend")
    assert_plays_as(body_positions(bl, copy), reference, "posed_")
    assert_plays_as(body_positions(bl), reference, "" if with_controls else "posed_")


def test_make_single_user_after_alt_d_keeps_both_results(asset, bl, tmp_path):
    """Alt+D with the controls, the copies' controls posed and played, then Object ▸ Relations ▸ Make
    Single User (object and data) on the copies: every frame of every body is the same as before, also
    after save and reopen."""
    reference = open_rig(asset, tmp_path)
    copy = _duplicate(linked=True, with_controls=True)
    bpy.context.scene.frame_set(12)
    pose(copy)
    shared = {"copy": body_positions(bl, copy), "original": body_positions(bl)}
    assert_plays_as(shared["copy"], reference, "posed_")
    assert_plays_as(shared["original"], reference)
    assert bpy.ops.object.make_single_user(type="SELECTED_OBJECTS", object=True, obdata=True) == {"FINISHED"}
    assert all(copy(name).data != by_name(name).data for name in BODIES)
    for reopened in (False, True):
        if reopened:
            save_and_reopen(tmp_path / "single.blend")
        for label, got in (("copy", body_positions(bl, copy)), ("original", body_positions(bl))):
            for key, value in got.items():
                assert np.array_equal(value, shared[label][key]), (label, key, reopened)


# ------------------------------------------------------------------------------------------- undo / redo


def _state(bl) -> dict:
    """What each body holds: its deformers, modifiers and mesh positions."""
    return {name: ([(d.uid, d.is_bound) for d in by_name(name).affine_deformers],
                   [m.type for m in by_name(name).modifiers], bl.rest_positions(by_name(name)).tobytes())
            for name in BODIES}


def _result_of(operator: str, name: str, rest: np.ndarray, reference: dict) -> np.ndarray:
    """A body's shape at frame 12 after `operator` there: Rebind makes the current pose the rest (the
    bone kind's rest is the armature's: it deforms as before), Remove leaves the rest shape, Apply
    writes the deformed shape into the mesh."""
    if operator == "apply" or (operator == "bind" and name == "BoneBody"):
        return reference[f"{name}_12"]
    return rest


@pytest.mark.parametrize("operator", ["bind", "remove", "apply"])
def test_undo_and_redo_of_rebind_remove_and_apply(asset, bl, tmp_path, operator):
    """Rebind, Remove or Apply on every body at frame 12, pushed as an undo step: Undo gives back the
    deformers, bind data and mesh (every frame plays as the asset), Redo the operator's result."""
    reference = open_rig(asset, tmp_path)
    bpy.context.scene.frame_set(12)
    before = _state(bl)
    rest = {name: bl.rest_positions(by_name(name)).copy() for name in BODIES}
    bpy.ops.ed.undo_push(message="before")
    for name in BODIES:
        op = getattr(bpy.ops.object, f"affine_deformer_{operator}")
        assert bl.run_op(op, by_name(name), index=0) == {"FINISHED"}
    bpy.ops.ed.undo_push(message=operator)
    after, done = _state(bl), body_positions(bl, frames=(12, 24))
    for name in BODIES:
        expected = _result_of(operator, name, rest[name], reference)
        assert np.abs(done[f"{name}_12"] - expected).max() <= 1e-6, name
        assert (len(by_name(name).affine_deformers) == 1) == (operator == "bind"), name
    bpy.ops.ed.undo()
    assert _state(bl) == before
    assert_plays_as(body_positions(bl), reference)
    bpy.ops.ed.redo()
    assert _state(bl) == after
    redone = body_positions(bl, frames=(12, 24))
    for key, value in done.items():
        assert np.array_equal(redone[key], value), key


def test_deleting_the_controls_is_reported_and_undo_brings_them_back(asset, bl, tmp_path):
    """The probe, the cage and the armature deleted (X): each body says which control is gone; the cage
    and bone bodies, whose only control it was, show their rest shape, the probe body's vertices
    follow its other probe, which does not move (issue 55); Undo brings the controls and the
    deformation back (every frame plays as the asset); Redo deletes them again."""
    reference = open_rig(asset, tmp_path)
    bpy.context.scene.frame_set(12)
    bpy.ops.ed.undo_push(message="before")
    _select(*(by_name(CONTROL_OF[name]) for name in BODIES))
    assert bpy.ops.object.delete() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="deleted")

    def check_deleted():
        for frame in (12, 24):
            bpy.context.scene.frame_set(frame)  # the scene of this undo step
            for name in BODIES:
                body = by_name(name)
                status = body.affine_deformers[0].status
                assert f"'{CONTROL_OF[name]}'" in status, (name, status)
                shown, rest = bl.evaluated_positions(body), bl.rest_positions(body)
                if name == "ProbeBody":  # its vertices follow P2, which turns away (issue 55)
                    assert "follow the other probes" in status and len(body.affine_deformers[0].probes) > 1
                    # P2 alone moves it, a rigid motion (P2 turns and moves, unscaled): distances kept
                    gaps = np.linalg.norm(shown[:, None] - shown[None], axis=-1)
                    rest_gaps = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
                    assert np.isfinite(shown).all() and np.abs(gaps - rest_gaps).max() < 1e-4, (name, status)
                else:
                    assert np.array_equal(shown, rest), name

    check_deleted()
    bpy.ops.ed.undo()
    assert all(by_name(control).users_scene for control in CONTROLS)
    assert_plays_as(body_positions(bl), reference)
    bpy.ops.ed.redo()
    check_deleted()


# ------------------------------------------------------------------------------------------------ renames

RENAMED = {"ProbeBody": "Statue", "CageBody": "Crate", "BoneBody": "Tail", "P1": "Left", "P2": "Right",
           "Cage": "Box", "Arm": "Skeleton"}


def test_renaming_targets_controls_and_modifiers_changes_nothing(asset, bl, tmp_path):
    """Every body, its mesh and its modifier, and every control (probes, cage, armature) renamed after
    the rig has played: it plays and poses as the asset, also after save and reopen."""
    reference = open_rig(asset, tmp_path)
    assert_plays_as(body_positions(bl), reference)
    for old, new in RENAMED.items():
        obj = by_name(old)
        obj.name = new
        if obj.data is not None:
            obj.data.name = f"{new} data"
    for name in BODIES:
        modifier = by_name(RENAMED[name]).modifiers[0]
        modifier.name = f"Deform {RENAMED[name]}"

    def renamed(name):
        return by_name(RENAMED[name])

    assert_plays_as(body_positions(bl, renamed), reference)
    bpy.context.scene.frame_set(12)
    pose(renamed)
    assert_plays_as(body_positions(bl, renamed), reference, "posed_")
    save_and_reopen(tmp_path / "renamed.blend")
    assert_plays_as(body_positions(bl, renamed), reference, "posed_")


def test_every_operator_of_ours_is_undoable_from_the_interface(installed):
    """The interface pushes an undo step after an operator whose bl_options hold UNDO (the tests here
    push them by hand): every operator of ours has it, so Ctrl+Z after any of them in the UI restores
    what these tests restore."""
    ours = [name for name in dir(bpy.types) if "_OT_affine_" in name]  # registered as <MODULE>_OT_<name>
    assert len(ours) >= 14
    missing = [name for name in ours if not {"REGISTER", "UNDO"} <= set(getattr(bpy.types, name).bl_options)]
    assert missing == []
