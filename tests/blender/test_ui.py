"""The panel, lists and menu draw without error in every state, and everything they reference exists.

Background bpy has no windows, so drawing goes through a recording layout that checks each property
against the data's RNA and each operator (and the operator properties set on it) against bpy.ops.
"""

from __future__ import annotations

import importlib
from types import SimpleNamespace

import bpy
import pytest


class _OperatorProps:
    def __init__(self, idname: str) -> None:
        module, name = idname.split(".")
        rna = getattr(getattr(bpy.ops, module), name).get_rna_type()
        object.__setattr__(self, "_names", set(rna.properties.keys()))

    def __setattr__(self, key: str, value) -> None:
        assert key in self._names, f"operator has no property {key!r}"
        object.__setattr__(self, key, value)


class RecordingLayout:
    """Accepts the UILayout calls the add-on makes, validating their targets."""

    def __init__(self, log: list, parent: RecordingLayout | None = None) -> None:
        self.log = log
        self.parent = parent
        self.active = True

    def _child(self, *_args, **_kwargs) -> RecordingLayout:
        return RecordingLayout(self.log, self)

    row = column = box = split = _child

    def _is_active(self) -> bool:
        return self.active and (self.parent is None or self.parent._is_active())

    def prop(self, data, name: str, **_kwargs) -> None:
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        getattr(data, name)
        self.log.append(("prop", name))
        if not self._is_active():  # drawn greyed out
            self.log.append(("inactive", name))

    def operator(self, idname: str, **_kwargs) -> _OperatorProps:
        self.log.append(("operator", idname))
        return _OperatorProps(idname)

    def label(self, text: str = "", **_kwargs) -> None:
        self.log.append(("label", text))

    def template_list(self, list_type, _list_id, data, prop, active_data, active_prop, **_kwargs) -> None:
        assert hasattr(bpy.types, list_type), list_type
        assert prop in data.bl_rna.properties and active_prop in active_data.bl_rna.properties
        self.log.append(("list", prop))

    def menu(self, idname: str, **_kwargs) -> None:
        assert hasattr(bpy.types, idname), idname
        self.log.append(("menu", idname))

    def separator(self, **_kwargs) -> None:
        pass


@pytest.fixture
def panels(installed):
    return importlib.import_module(f"{installed.package}.blender.ui.panels")


def _draw_panel(panels, obj) -> list:
    log: list = []
    panel = SimpleNamespace(layout=RecordingLayout(log))
    context = SimpleNamespace(object=obj, active_object=obj)
    assert panels.AFFINE_PT_deformers.poll(context)
    panels.AFFINE_PT_deformers.draw(panel, context)
    return log


def test_panel_draws_in_every_state(bl, panels):
    target = bl.uv_sphere()
    log = _draw_panel(panels, target)
    assert log == [
        ("list", "affine_deformers"),
        ("operator", "object.affine_probe_deformer_add"),
        ("operator", "object.affine_cage_deformer_add"),
        ("operator", "object.affine_bone_deformer_add"),
    ]
    probes = [bl.empty("A"), bl.empty("B", (0, 0, 1))]
    deformer = bl.add_probe_deformer(target, probes)
    for mode in ("INVERSE_DISTANCE", "FALLOFF", "VERTEX_GROUPS", "SURFACE"):
        deformer.weight_mode = mode
        log = _draw_panel(panels, target)
        assert (("prop", "radius") in log) == (mode in ("INVERSE_DISTANCE", "FALLOFF"))
        assert (("prop", "exponent") in log) == (mode in ("INVERSE_DISTANCE", "SURFACE"))
        assert ("operator", "object.affine_deformer_apply") in log
    probes[0].scale = (0, 0, 0)
    bpy.context.evaluated_depsgraph_get()
    log = _draw_panel(panels, target)
    status_lines = " ".join(text for kind, text in log if kind == "label")
    assert "Probe 'A' is scaled to zero" in status_lines

    for item in target.affine_deformers:
        panels.AFFINE_UL_deformers.draw_item(None, None, RecordingLayout([]), None, item, 0, None, "")
        for probe in item.probes:
            bpy.types.AFFINE_UL_probes.draw_item(None, None, RecordingLayout([]), None, probe, 0, None, "")


def test_turns_rule_is_shown_for_both_kinds_and_greyed_out_where_it_cannot_matter(bl, panels):
    target = bl.grid_cube(cuts=2)
    cage = bl.grid_cube(cuts=1, size=3.0, name="CageBox")
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, cage]):
        assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
    deformer = target.affine_deformers[0]
    log = _draw_panel(panels, target)
    # at strength 1 the cage object's motion is applied exactly: no branch to choose
    assert ("prop", "branch_rule") in log and ("inactive", "branch_rule") in log
    assert ("list", "probes") not in log
    deformer.strength = 0.5
    log = _draw_panel(panels, target)
    assert ("prop", "branch_rule") in log and ("inactive", "branch_rule") not in log
    deformer.blend_mode = "LINEAR"  # the object motion is still scaled in the log space
    assert ("inactive", "branch_rule") not in _draw_panel(panels, target)
    panels.AFFINE_UL_deformers.draw_item(None, None, RecordingLayout([]), None, deformer, 0, None, "")

    sphere = bl.uv_sphere()
    probe_deformer = bl.add_probe_deformer(sphere, [bl.empty("P")])
    log = _draw_panel(panels, sphere)
    assert ("prop", "branch_rule") in log and ("inactive", "branch_rule") not in log
    probe_deformer.blend_mode = "LINEAR"  # a linear blend of probe matrices has no branches
    assert ("inactive", "branch_rule") in _draw_panel(panels, sphere)


def test_menu_draws(panels):
    log: list = []
    menu = SimpleNamespace(layout=RecordingLayout(log))
    panels.AFFINE_MT_object.draw(menu, None)
    panels.draw_object_menu(menu, None)
    assert ("operator", "object.affine_probe_deformer_add") in log and ("menu", "AFFINE_MT_object") in log


def test_bone_deformer_panel_and_convert_buttons(bl, panels):
    target = bl.grid_cube(cuts=2)
    data = bpy.data.armatures.new("Rig")
    arm = bpy.data.objects.new("Rig", data)
    bpy.context.scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    bone = data.edit_bones.new("Bone")
    bone.head, bone.tail = (0.0, 0.0, -1.0), (0.0, 0.0, 1.0)
    bpy.ops.object.mode_set(mode="OBJECT")
    native = target.modifiers.new("Armature", "ARMATURE")
    native.object = arm
    log = _draw_panel(panels, target)
    assert ("operator", "object.affine_armature_convert") in log
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.affine_armature_convert() == {"FINISHED"}
    log = _draw_panel(panels, target)
    assert ("list", "bones") in log and ("prop", "armature") in log
    assert ("operator", "object.affine_armature_restore") in log
    assert ("operator", "object.affine_armature_convert") not in log  # the modifier is disabled now
    deformer = target.affine_deformers[0]
    for item in deformer.bones:
        bpy.types.AFFINE_UL_bones.draw_item(None, None, RecordingLayout([]), deformer, item, 0, None, "")
    panels.AFFINE_UL_deformers.draw_item(None, None, RecordingLayout([]), None, deformer, 0, None, "")


def test_panel_hidden_for_non_mesh(bl, panels):
    assert not panels.AFFINE_PT_deformers.poll(SimpleNamespace(object=bl.empty("E")))


def test_add_modifier_deform_lists_every_kind_for_meshes_only(bl, panels):
    """Add Modifier ▸ Deform, beside Hook, Lattice and Mesh Deform: one entry per kind (meshes only)."""
    assert panels.draw_modifier_menu in bpy.types.OBJECT_MT_modifier_add_deform._dyn_ui_initialize()
    log: list = []
    menu = SimpleNamespace(layout=RecordingLayout(log))
    panels.draw_modifier_menu(menu, SimpleNamespace(object=bl.uv_sphere()))
    assert [entry for entry in log if entry[0] == "operator"] == [
        ("operator", "object.affine_probe_deformer_add"),
        ("operator", "object.affine_cage_deformer_add"),
        ("operator", "object.affine_bone_deformer_add"),
    ]
    log.clear()
    panels.draw_modifier_menu(menu, SimpleNamespace(object=bl.empty("E")))
    assert log == []


def test_the_modifier_tab_shows_the_deformer_of_the_active_modifier(bl, panels):
    target = bl.grid_cube(cuts=2)
    first = bl.add_probe_deformer(target, [bl.empty("A", (1.5, 0, 0)), bl.empty("B", (-1.5, 0, 0))])
    second = bl.add_probe_deformer(target, [bl.empty("C", (0, 1.5, 0))])
    first.name, second.name = "First", "Second"
    context = SimpleNamespace(object=target, active_object=target)
    assert panels.AFFINE_PT_modifier.poll(context)
    for deformer in (first, second):
        target.modifiers.active = next(m for m in target.modifiers
                                       if panels.nodes.offset_attribute(m) == f"affdef_{deformer.uid}_offset")
        log: list = []
        panel = SimpleNamespace(layout=RecordingLayout(log))
        panels.AFFINE_PT_modifier.draw_header(panel, context)
        panels.AFFINE_PT_modifier.draw(panel, context)
        assert ("label", deformer.name) in log, log
        assert ("prop", "strength") in log and ("operator", "object.affine_deformer_bind") in log
    assert not panels.AFFINE_PT_modifier.poll(SimpleNamespace(object=bl.uv_sphere()))


def test_adding_without_controls_makes_sensible_ones(bl):
    """No Empty selected: two probes at the ends of the mesh's longest axis; no armature selected: the
    armature of the mesh's Armature modifier, else a message saying what to select."""
    bar = bl.grid_cube(cuts=3, name="Bar")
    bar.scale = (3.0, 0.5, 0.5)
    bar.location = (1.0, 2.0, 0.0)
    bpy.context.view_layer.update()
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_probe_deformer_add() == {"FINISHED"}
    probes = [item.object for item in bar.affine_deformers[0].probes]
    assert len(probes) == 2
    ends = sorted(tuple(round(v, 5) for v in p.location) for p in probes)
    assert ends == [(-2.0, 2.0, 0.0), (4.0, 2.0, 0.0)], ends

    body = bl.grid_cube(cuts=2, name="Body")
    with (bpy.context.temp_override(active_object=body, object=body, selected_objects=[body]),
          pytest.raises(RuntimeError, match="Armature modifier")):
        bpy.ops.object.affine_bone_deformer_add()
    assert len(body.affine_deformers) == 0
    data = bpy.data.armatures.new("Rig")
    arm = bpy.data.objects.new("Rig", data)
    bpy.context.scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    bone = data.edit_bones.new("Bone")
    bone.head, bone.tail = (0.0, 0.0, -1.0), (0.0, 0.0, 1.0)
    bpy.ops.object.mode_set(mode="OBJECT")
    body.modifiers.new("Armature", "ARMATURE").object = arm
    with bpy.context.temp_override(active_object=body, object=body, selected_objects=[body]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    assert body.affine_deformers[0].armature == arm and body.affine_deformers[0].status == ""
