"""Weights an artist can see, start from and paint, driven like an artist does.

- the weight preview shows exactly the stored weights (active probe / cage face on the weight-paint
  ramp, or all controls as a colour map), never changes the deformation or a render, and leaves no
  trace when turned off (modifier, attributes, node group, active colour name);
- Weights → Vertex Groups writes the current weights into groups named after the probes and switches
  to painted weights with the same deformation (≤ 1e-6) for every normalisation, scale and mask;
  refuses existing groups unless asked to overwrite; undoable; not offered for cages;
- renaming a probe renames its painted group with it and keeps the deformation; painting a group
  changes the result (Update, or leaving Weight Paint mode);
- per-probe state (at rest / moving / invalid / no group) and the select button.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from types import SimpleNamespace

import bpy
import numpy as np
import pytest

PROBES = (("Top", (0.0, 0.0, 1.2)), ("Side", (1.2, 0.0, 0.0)), ("Back", (0.0, -1.2, -0.4)))


@pytest.fixture
def mods(installed):
    package = installed.package
    return SimpleNamespace(
        preview=importlib.import_module(f"{package}.blender.tools.weight_preview"),
        groups=importlib.import_module(f"{package}.blender.tools.weight_groups"),
        evaluate=installed.evaluate,
    )


def _rig(bl, **options):
    target = bl.grid_cube(cuts=8)
    probes = [bl.empty(name, location) for name, location in PROBES]
    bpy.context.view_layer.update()
    deformer = bl.add_probe_deformer(target, probes, **options)
    assert deformer.status == ""
    return target, probes, deformer


def _pose(probes) -> None:
    probes[0].location.z += 0.5
    probes[0].rotation_euler.z = 0.7
    probes[1].scale = (1.3, 0.8, 1.0)
    probes[2].location.x -= 0.4
    bpy.context.view_layer.update()


def _evaluated_colors(obj, name: str) -> np.ndarray:
    mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    attr = mesh.attributes[name]
    assert (attr.data_type, attr.domain) == ("FLOAT_COLOR", "POINT")
    out = np.empty(len(mesh.vertices) * 4, dtype=np.float32)
    attr.data.foreach_get("color", out)
    return out.reshape(-1, 4)


def _trace(obj) -> tuple:
    """Everything the preview could leave behind on the object and in the file."""
    mesh = obj.data
    colors = mesh.color_attributes
    return (sorted(a.name for a in mesh.attributes), [m.name for m in obj.modifiers],
            colors.active_color_name, colors.default_color_name,
            sorted(g.name for g in bpy.data.node_groups),
            [d.get("weight_preview_restore") for d in obj.affine_deformers])


def _output(obj, deformer, installed) -> tuple:
    storage = installed.storage
    offsets = storage.read_offsets(obj.data, deformer.uid)
    motions = storage.read_motions(obj.data, deformer.uid)
    return (None if offsets is None else offsets.copy(), None if motions is None else motions.copy())


# --------------------------------------------------------------------------------------- preview


def test_preview_shows_the_stored_weights_and_leaves_no_trace(bl, mods, installed):
    target, probes, deformer = _rig(bl)
    _pose(probes)
    before = _trace(target)
    positions = bl.evaluated_positions(target).copy()
    output = _output(target, deformer, installed)
    dense = bl.dense_weights(target, deformer)

    deformer.show_weights = True
    preview = mods.preview
    for active in (0, 2, 1):
        deformer.active_probe_index = active
        weights = preview.control_weights(target, deformer, active)
        assert np.array_equal(weights, dense[:, active]), "the preview shows the stored weights"
        colors = _evaluated_colors(target, preview.DISPLAY_NAME)
        assert np.array_equal(colors[:, :3], preview.ramp_colors(dense[:, active]))
    assert target.data.color_attributes.active_color_name == preview.DISPLAY_NAME
    assert preview.DISPLAY_NAME not in target.data.attributes, "shown on the evaluated mesh only"
    deformer.exponent = 3.5  # re-weights: the preview follows the new stored weights
    reweighted = bl.dense_weights(target, deformer)
    assert not np.array_equal(reweighted, dense)
    colors = _evaluated_colors(target, preview.DISPLAY_NAME)
    assert np.array_equal(colors[:, :3], preview.ramp_colors(reweighted[:, 1]))
    deformer.exponent = 2.0
    assert np.array_equal(bl.dense_weights(target, deformer), dense)
    # the ramp: weight 0 blue, 1 red (in display values)
    assert np.allclose(preview.ramp_colors(np.array([0.0, 1.0])), [[0, 0, 1], [1, 0, 0]])

    deformer.weight_preview = "ALL"
    colors = _evaluated_colors(target, preview.DISPLAY_NAME)[:, :3]
    indices, values = installed.storage.read_weights(target.data, deformer.uid, 3)
    expected = np.einsum("nk,nkc->nc", values, preview.control_palette(3)[indices])
    assert np.abs(colors - expected).max() < 1e-6  # weights sum to 1: no rest share
    dominant = np.argmax(dense, axis=1)
    assert np.abs(colors[dominant == 0].mean(0) - colors[dominant == 1].mean(0)).max() > 0.1

    posed_x = probes[0].location.x
    probes[0].location.x += 0.3  # the deformation goes on, unchanged by the preview
    bpy.context.view_layer.update()
    moved = bl.evaluated_positions(target).copy()
    preview_output = _output(target, deformer, installed)
    assert target.modifiers[-1].name == preview.PREVIEW_MODIFIER
    assert not target.modifiers[-1].show_render

    deformer.show_weights = False
    assert _trace(target) == before, "turning the preview off leaves no trace"
    assert np.array_equal(bl.evaluated_positions(target), moved)
    for a, b in zip(preview_output, _output(target, deformer, installed), strict=True):
        assert (a is None and b is None) or np.array_equal(a, b), "the saved deformation is the same"
    probes[0].location.x = posed_x
    bpy.context.view_layer.update()
    assert np.array_equal(bl.evaluated_positions(target), positions)
    for a, b in zip(output, _output(target, deformer, installed), strict=True):
        assert (a is None and b is None) or np.array_equal(a, b)


def test_preview_takes_the_place_of_an_existing_colour_attribute_in_the_viewport_only(bl, mods):
    target, _probes, deformer = _rig(bl)
    painted = target.data.color_attributes.new("Paint", "BYTE_COLOR", "CORNER")
    painted.data.foreach_set("color", np.full(len(painted.data) * 4, 0.5, dtype=np.float32))
    target.data.color_attributes.active_color = painted
    before = _trace(target)
    stored = np.empty(len(painted.data) * 4, dtype=np.float32)
    painted.data.foreach_get("color", stored)

    deformer.show_weights = True
    colors = _evaluated_colors(target, "Paint")
    dense = bl.dense_weights(target, deformer)
    assert np.array_equal(colors[:, :3], mods.preview.ramp_colors(dense[:, 0]))
    assert target.data.color_attributes.active_color_name == "Paint"
    after = np.empty_like(stored)
    target.data.color_attributes["Paint"].data.foreach_get("color", after)
    assert np.array_equal(after, stored), "the artist's colours are untouched"

    deformer.show_weights = False
    assert _trace(target) == before


def test_preview_of_a_cage_face_matches_its_weights(bl, mods, installed):
    target = bl.grid_cube(cuts=6)
    cage = bl.grid_cube(cuts=1, size=3.0, name="CageBox")
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, cage]):
        assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
    deformer = target.affine_deformers[0]
    preview = mods.preview
    deformer.weight_preview_face = 5
    deformer.show_weights = True
    weights = preview.control_weights(target, deformer, 5)
    # independently: the vertex's 8 grid nodes' weights times each node's weight on face 5
    faces = len(deformer["cage_loop_total"])
    node_weights = np.asarray(deformer["cage_node_weights"], dtype=np.float64).reshape(-1, faces)
    node_weights /= node_weights.sum(axis=1, keepdims=True)
    indices, values = installed.storage.read_weights(target.data, deformer.uid, len(node_weights))
    expected = (values * node_weights[indices, 5]).sum(axis=1)
    assert np.abs(weights - expected).max() < 1e-12
    assert weights.max() > 0.2 and weights.min() < 0.01
    colors = _evaluated_colors(target, preview.DISPLAY_NAME)
    assert np.array_equal(colors[:, :3], preview.ramp_colors(weights))
    deformer.weight_preview_fit = True  # one face of many: the ramp up to its largest weight
    colors = _evaluated_colors(target, preview.DISPLAY_NAME)
    assert np.array_equal(colors[:, :3], preview.ramp_colors(weights / weights.max()))
    deformer.weight_preview_face = -1  # the cage mesh's active face (picked in its Edit Mode)
    cage.data.polygons.active = 11
    bpy.context.view_layer.update()
    assert preview.preview_control(deformer) == 11
    weights = preview.control_weights(target, deformer, 11)
    colors = _evaluated_colors(target, preview.DISPLAY_NAME)
    assert np.array_equal(colors[:, :3], preview.ramp_colors(weights / weights.max()))
    deformer.weight_preview = "ALL"
    assert _evaluated_colors(target, preview.DISPLAY_NAME).std(axis=0)[:3].max() > 0.01
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.affine_deformer_remove(index=0) == {"FINISHED"}
    assert not [m for m in target.modifiers if m.type == "NODES"], "the preview went with its deformer"
    assert not [a.name for a in target.data.attributes if "affdef" in a.name]
    assert target.data.color_attributes.active_color_name == ""


def test_preview_is_one_per_object_and_survives_save_and_reload(bl, mods, tmp_path):
    target, probes, first = _rig(bl)
    before = _trace(target)
    second = bl.add_probe_deformer(target, probes[:2], weight_mode="FALLOFF", radius=2.0)
    first.show_weights = True
    second.show_weights = True
    assert not first.show_weights, "one deformer previews at a time"
    dense = bl.dense_weights(target, second)
    colors = _evaluated_colors(target, mods.preview.DISPLAY_NAME)
    assert np.array_equal(colors[:, :3], mods.preview.ramp_colors(dense[:, 0]))
    assert target.modifiers[-1].name == mods.preview.PREVIEW_MODIFIER, "kept last in the stack"

    path = tmp_path / "preview.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    target = bpy.data.objects["Cube"]
    second = target.affine_deformers[1]
    assert np.array_equal(_evaluated_colors(target, mods.preview.DISPLAY_NAME)[:, :3],
                          mods.preview.ramp_colors(dense[:, 0]))
    second.show_weights = False
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.affine_deformer_remove(index=1) == {"FINISHED"}
    assert _trace(target) == before


def _render(scene, path: Path) -> np.ndarray:
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(str(path))
    try:
        return np.array(image.pixels[:], dtype=np.float32)
    finally:
        bpy.data.images.remove(image)


def test_preview_never_changes_a_render(bl, mods, tmp_path, monkeypatch):
    """Workbench showing attribute colours is the renderer that would show a colour attribute: the
    render is pixel-equal with the preview on and off, for a mesh without colours and one whose
    active colours are painted; forcing the preview modifier into the render shows it would differ."""
    target, probes, deformer = _rig(bl)
    _pose(probes)
    other = bl.uv_sphere(location=(3.0, 0.0, 0.0))
    other_deformer = bl.add_probe_deformer(other, [bl.empty("P", (3.0, 0.0, 1.0))])
    paint = other.data.color_attributes.new("Paint", "FLOAT_COLOR", "POINT")
    paint.data.foreach_set("color", np.tile([0.8, 0.3, 0.1, 1.0], len(paint.data)).astype(np.float32))
    other.data.color_attributes.active_color = paint
    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "FLAT"
    scene.display.shading.color_type = "VERTEX"
    scene.render.resolution_x, scene.render.resolution_y = 96, 48
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.type = "ORTHO"
    camera.data.ortho_scale = 7.0
    camera.location = (1.5, -10.0, 0.0)
    camera.rotation_euler = (np.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera

    off = _render(scene, tmp_path / "off.png")
    deformer.show_weights = True
    other_deformer.show_weights = True
    on = _render(scene, tmp_path / "on.png")
    assert np.array_equal(on, off), "the preview never reaches a render"
    # What a leak would look like (the refresh would switch the modifier off in renders again):
    with monkeypatch.context() as patch:
        patch.setattr(mods.preview, "refresh", lambda *_args, **_kwargs: None)
        for obj in (target, other):
            mods.preview.find_modifier(obj).show_render = True
        leaked = _render(scene, tmp_path / "leaked.png")
    assert np.abs(leaked - off).max() > 0.2
    bpy.context.view_layer.update()
    assert not any(mods.preview.find_modifier(obj).show_render for obj in (target, other))
    deformer.show_weights = other_deformer.show_weights = False
    assert np.array_equal(_render(scene, tmp_path / "again.png"), off)


# ------------------------------------------------------------------------------ weights → groups


def _convert(obj, **kwargs):
    with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj]):
        return bpy.ops.object.affine_deformer_weights_to_groups(**kwargs)


@pytest.mark.parametrize("normalize, scales, masked", [
    ("SUM", (1.0, 1.0, 1.0), False),
    ("SUM", (1.7, 0.4, 1.0), True),
    ("SOFTMAX", (1.0, 2.0, 1.0), False),
    ("NONE", (2.5, 1.0, 0.6), True),
])
def test_weights_to_groups_gives_the_identical_deformation(bl, mods, normalize, scales, masked):
    target, probes, deformer = _rig(bl, normalize=normalize, max_influences=2)
    for item, scale in zip(deformer.probes, scales, strict=True):
        item.weight_scale = scale
    if masked:
        rest = bl.rest_positions(target)
        mask = target.vertex_groups.new(name="Mask")
        upper = np.flatnonzero(rest[:, 2] > -0.5).tolist()
        mask.add(upper, 1.0, "REPLACE")
        mask.add(np.flatnonzero(np.abs(rest[:, 0]) < 0.3).tolist(), 0.35, "REPLACE")
        deformer.mask_group = "Mask"
    _pose(probes)
    expected = bl.evaluated_positions(target).copy()
    stored = bl.dense_weights(target, deformer)

    assert _convert(target, index=0) == {"FINISHED"}
    assert deformer.weight_mode == "VERTEX_GROUPS"
    assert deformer.status == ""
    assert [item.vertex_group for item in deformer.probes] == [name for name, _ in PROBES]
    assert {g.name for g in target.vertex_groups} >= {name for name, _ in PROBES}
    assert deformer.mask_group == ("Mask" if masked else "")
    # raised where the truncation pooled weight (docs/MATH.md §12): those vertices blend all 3 probes
    assert deformer.max_influences == max(2, int(np.count_nonzero(stored, axis=1).max()))
    assert deformer.max_influences == (2 if normalize == "NONE" else 3), "the rig pools (the test can fail)"
    assert np.abs(bl.dense_weights(target, deformer) - stored).max() < 1e-6
    got = bl.evaluated_positions(target)
    assert np.abs(got - expected).max() <= 1e-6, "painted weights give the identical deformation"
    assert np.abs(expected - bl.rest_positions(target)).max() > 0.2

    painted = mods.groups.painted_equivalent  # painted mode reads back what was written
    groups, _scales, mode = painted(target, deformer)
    assert mode == ("NONE" if normalize == "NONE" else "SUM")
    assert groups.max() <= 1.0


def test_weights_to_groups_refuses_existing_groups_unless_overwrite_and_is_undoable(bl, mods):
    target, probes, deformer = _rig(bl)
    target.vertex_groups.new(name="Side").add([0, 1, 2], 1.0, "REPLACE")
    with pytest.raises(RuntimeError, match="Vertex groups named 'Side' exist already"):
        _convert(target, index=0)
    assert deformer.weight_mode == "INVERSE_DISTANCE"
    assert [g.name for g in target.vertex_groups] == ["Side"], "nothing changed"
    _pose(probes)
    expected = bl.evaluated_positions(target).copy()

    bpy.ops.ed.undo_push(message="before")
    assert _convert(target, index=0, overwrite=True) == {"FINISHED"}
    bpy.ops.ed.undo_push(message="converted")
    assert np.abs(bl.evaluated_positions(target) - expected).max() <= 1e-6
    assert sorted(g.name for g in target.vertex_groups) == ["Back", "Side", "Top"]
    bpy.ops.ed.undo()
    target = bpy.data.objects["Cube"]
    deformer = target.affine_deformers[0]
    assert deformer.weight_mode == "INVERSE_DISTANCE"
    assert [g.name for g in target.vertex_groups] == ["Side"]
    assert np.array_equal(bl.evaluated_positions(target), expected)
    bpy.ops.ed.redo()
    target = bpy.data.objects["Cube"]
    assert target.affine_deformers[0].weight_mode == "VERTEX_GROUPS"
    assert np.abs(bl.evaluated_positions(target) - expected).max() <= 1e-6


def test_weights_to_groups_refuses_probes_it_cannot_name(bl):
    target, probes, deformer = _rig(bl)
    target.vertex_groups.new(name="Top")
    deformer.mask_group = "Top"
    with pytest.raises(RuntimeError, match="The mask group 'Top' has a probe's name"):
        _convert(target, index=0, overwrite=True)
    deformer.mask_group = ""
    target.data.attributes.new("Side", "FLOAT", "POINT")
    with pytest.raises(RuntimeError, match="The mesh has attributes named 'Side'"):
        _convert(target, index=0, overwrite=True)
    target.data.attributes.remove(target.data.attributes["Side"])
    deformer.probes.add().object = probes[0]  # the same object twice
    with pytest.raises(RuntimeError, match="Several probes use 'Top'"):
        _convert(target, index=0, overwrite=True)
    assert deformer.weight_mode == "INVERSE_DISTANCE" and [g.name for g in target.vertex_groups] == ["Top"]


def test_weights_to_groups_is_greyed_out_with_a_reason_where_it_cannot_act(bl, mods):
    op = bpy.ops.object.affine_deformer_weights_to_groups
    target = bl.grid_cube(cuts=2)
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert not op.poll()
    cage = bl.grid_cube(cuts=1, size=3.0, name="CageBox")
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, cage]):
        assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
        assert not op.poll()
    with pytest.raises(RuntimeError, match="Cage deformers have no painted weights"):
        _convert(target, index=0)
    sphere = bl.uv_sphere(location=(4.0, 0.0, 0.0))
    deformer = bl.add_probe_deformer(sphere, [bl.empty("P", (4.0, 0.0, 0.0))])
    with bpy.context.temp_override(active_object=sphere, object=sphere, selected_objects=[sphere]):
        assert op.poll()
        assert not bpy.ops.object.affine_deformer_weights_update.poll()
        deformer.weight_mode = "VERTEX_GROUPS"
        assert not op.poll()
        assert bpy.ops.object.affine_deformer_weights_update.poll()
    reason = mods.groups.conversion_problem(sphere, deformer)
    assert "already come from vertex groups" in reason


# ------------------------------------------------------------------------------ renames, painting


def test_renaming_a_probe_keeps_its_painted_group_and_the_deformation(bl, mods):
    target, probes, deformer = _rig(bl)
    assert _convert(target, index=0) == {"FINISHED"}
    _pose(probes)
    expected = bl.evaluated_positions(target).copy()

    probes[0].name = "Head"
    bpy.context.view_layer.update()
    assert "Head" in target.vertex_groups and "Top" not in target.vertex_groups
    item = deformer.probes[0]
    assert (item.name, item.vertex_group) == ("Head", "Head")
    deformer.max_influences = 2  # re-weights from the groups
    deformer.max_influences = 6
    assert deformer.status == ""
    assert np.abs(bl.evaluated_positions(target) - expected).max() <= 1e-6

    # a group of the new name exists already: the probe keeps the group it was painted with
    target.vertex_groups.new(name="Flank")
    probes[1].name = "Flank"
    bpy.context.view_layer.update()
    assert deformer.probes[1].name == "Flank" and deformer.probes[1].vertex_group == "Side"
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.affine_deformer_weights_update(index=0) == {"FINISHED"}
    assert np.abs(bl.evaluated_positions(target) - expected).max() <= 1e-6

    # renamed before any update saw it: the group is still found by the former name
    probes[2].name = "Tail"
    deformer.max_influences = 2
    deformer.max_influences = 6
    assert np.abs(bl.evaluated_positions(target) - expected).max() <= 1e-6
    assert deformer.probes[2].name == "Tail" and "Tail" in target.vertex_groups


def test_a_renamed_probe_updates_its_item_name_with_any_weights(bl):
    target, probes, deformer = _rig(bl)
    target.vertex_groups.new(name="Back")  # painted by the artist for something else
    probes[2].name = "Rear"
    bpy.context.view_layer.update()
    assert deformer.probes[2].name == "Rear"
    assert deformer.probes[2].vertex_group == ""
    assert [g.name for g in target.vertex_groups] == ["Back"], "automatic weights rename no groups"


def test_a_renamed_probe_of_an_older_painted_file_follows_too(bl):
    """Painted by hand, named after the probes, no stored group name (as files from before groups
    were stored)."""
    target, probes, deformer = _rig(bl)
    n = len(target.data.vertices)
    for name, _location in PROBES:
        target.vertex_groups.new(name=name).add(list(range(n)), 0.5, "REPLACE")
    deformer.weight_mode = "VERTEX_GROUPS"
    _pose(probes)
    expected = bl.evaluated_positions(target).copy()
    probes[1].name = "Renamed"
    bpy.context.view_layer.update()
    assert "Renamed" in target.vertex_groups
    deformer.normalize = "NONE"
    deformer.normalize = "SUM"
    assert np.abs(bl.evaluated_positions(target) - expected).max() <= 1e-6


def test_painting_a_group_changes_the_result(bl, mods):
    target, probes, deformer = _rig(bl)
    assert _convert(target, index=0) == {"FINISHED"}
    _pose(probes)
    before = bl.evaluated_positions(target).copy()
    rest = bl.rest_positions(target)
    side = np.flatnonzero(rest[:, 0] > 0.6)
    target.vertex_groups["Top"].add(side.tolist(), 1.0, "REPLACE")  # a stroke: 'Top' on the +x side
    target.vertex_groups["Side"].remove(side.tolist())
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.affine_deformer_weights_update(index=0) == {"FINISHED"}
    after = bl.evaluated_positions(target)
    moved = np.abs(after - before).max(axis=1) > 1e-3
    assert moved[side].all(), "the painted vertices follow their new weights"
    assert not moved[rest[:, 0] < 0.0].any(), "and no others"
    dense = bl.dense_weights(target, deformer)
    assert np.allclose(dense[side, 0], 1.0 - dense[side, 2]) and (dense[side, 1] == 0).all()

    # leaving Weight Paint mode re-reads the groups (a timer after the update that saw it)
    target.vertex_groups["Top"].remove(side.tolist())
    bpy.context.view_layer.objects.active = target  # mode_set acts on the view layer's active object
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.mode_set(mode="WEIGHT_PAINT") == {"FINISHED"}
        bpy.context.view_layer.update()
        assert target.mode == "WEIGHT_PAINT"
        assert bpy.ops.object.mode_set(mode="OBJECT") == {"FINISHED"}
    bpy.context.view_layer.update()
    assert bpy.app.timers.is_registered(mods.groups._reweight_pending)
    bpy.app.timers.unregister(mods.groups._reweight_pending)
    mods.groups._reweight_pending()  # what the timer runs (timers need Blender's event loop)
    assert (bl.dense_weights(target, deformer)[side, 0] == 0).all()


# ----------------------------------------------------------------------------- probe states, select


def test_probe_states_and_the_select_button(bl, mods):
    target, probes, deformer = _rig(bl)
    assert [item.state for item in deformer.probes] == ["AT_REST"] * 3
    probes[1].location.x += 0.2
    bpy.context.view_layer.update()
    assert [item.state for item in deformer.probes] == ["AT_REST", "MOVING", "AT_REST"]
    probes[2].scale = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    assert "Probe 'Back' is scaled to zero" in deformer.status
    assert [item.state for item in deformer.probes] == ["AT_REST", "MOVING", "INVALID"]
    probes[2].scale = (1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert [item.state for item in deformer.probes] == ["AT_REST", "MOVING", "AT_REST"]

    assert _convert(target, index=0) == {"FINISHED"}
    target.vertex_groups.remove(target.vertex_groups["Top"])
    bpy.context.view_layer.update()
    assert [item.state for item in deformer.probes] == ["NO_GROUP", "MOVING", "AT_REST"]

    target.select_set(True)
    bpy.context.view_layer.objects.active = target
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target],
                                   view_layer=bpy.context.view_layer):
        assert bpy.ops.object.affine_deformer_probe_select(index=0, probe_index=2) == {"FINISHED"}
    assert [o.name for o in bpy.context.view_layer.objects if o.select_get()] == ["Back"]
    assert bpy.context.view_layer.objects.active == target, "the panel stays on the mesh"
    assert deformer.active_probe_index == 2
    probes[0].hide_set(True)
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]), \
            pytest.raises(RuntimeError, match="hidden or not selectable"):
        bpy.ops.object.affine_deformer_probe_select(index=0, probe_index=0)


def test_panel_draws_the_weight_tools(bl, installed):
    spec = importlib.util.spec_from_file_location("weight_ui", Path(__file__).with_name("test_ui.py"))
    ui = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ui)
    panels = importlib.import_module(f"{installed.package}.blender.ui.panels")
    target, _probes, deformer = _rig(bl)
    log = ui._draw_panel(panels, target)
    assert ("prop", "show_weights") in log and ("inactive", "weight_preview") in log
    assert ("operator", "object.affine_deformer_weights_to_groups") in log
    deformer.show_weights = True
    assert _convert(target, index=0) == {"FINISHED"}
    log = ui._draw_panel(panels, target)
    assert ("inactive", "weight_preview") not in log
    assert ("operator", "object.affine_deformer_weights_update") in log
    assert ("prop", "vertex_group") in log
    for probe in deformer.probes:
        row: list = []
        bpy.types.AFFINE_UL_probes.draw_item(None, None, ui.RecordingLayout(row), None, probe, 0, None, "", 1)
        assert ("operator", "object.affine_deformer_probe_select") in row
        assert ("label", "rest") in row
