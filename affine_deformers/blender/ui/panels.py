"""User interface: Properties ▸ Modifiers ▸ Affine Deformer (the primary place: the deformer's settings
beside its modifier in the stack), Add Modifier ▸ Deform ▸ Affine Probes / Cage / Bones, Properties ▸
Object ▸ Affine Deformers (the deformer list of the object), and Object ▸ Affine Deformers in the 3D
view.

The panels draw what every deformer shares; each kind draws its own part (DeformerKind.draw_object,
draw_actions, draw_settings, draw_controls, draw_preview_options: its lists are kinds' classes too).
"""

from __future__ import annotations

import bpy

from .. import kinds
from ..files import instances, nodes, storage
from ..tools import weight_operators, weight_preview
from ..tools.bake import AFFINE_OT_deformer_bake, AFFINE_OT_deformer_unbake, bake_state
from ..update import shape_pass


class AFFINE_UL_deformers(bpy.types.UIList):
    """The deformers of an object, with a warning icon on those whose status is not empty."""

    def draw_item(self, _context, layout, _data, item, _icon, _active_data, _active_prop, _index=0):
        kind = kinds.get(item.kind)
        icon = kind.icon if kind is not None else "QUESTION"
        row = layout.row(align=True)
        row.prop(item, "name", text="", emboss=False, icon=icon)
        if item.status:
            row.label(text="", icon="ERROR")
        elif not item.is_bound:
            row.label(text="", icon="UNLINKED")
        row.prop(item, "show_viewport", text="", emboss=False,
                 icon="RESTRICT_VIEW_OFF" if item.show_viewport else "RESTRICT_VIEW_ON")
        row.prop(item, "show_render", text="", emboss=False,
                 icon="RESTRICT_RENDER_OFF" if item.show_render else "RESTRICT_RENDER_ON")


class AFFINE_PT_linked_instance(bpy.types.Panel):
    """On an Empty instancing a linked rig with deformers: why it does not play, and what to do."""

    bl_label = "Affine Deformers"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        obj = context.object
        return obj is not None and obj.type == "EMPTY" and bool(instances.instance_message(obj))

    def draw(self, context: bpy.types.Context) -> None:
        box = self.layout.box()
        for i, line in enumerate(_wrap(instances.instance_message(context.object), 60)):
            box.label(text=line, icon="ERROR" if i == 0 else "BLANK1")
        self.layout.operator("object.make_override_library", text="Make Library Override")


class AFFINE_PT_deformers(bpy.types.Panel):
    """Affine Deformers of the active object: its deformer list and the active deformer."""

    bl_label = "Affine Deformers"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.object is not None and context.object.type == "MESH"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        obj = context.object
        row = layout.row()
        row.template_list("AFFINE_UL_deformers", "", obj, "affine_deformers",
                          obj, "affine_deformers_active_index", rows=2)
        col = row.column(align=True)
        for kind in kinds.KINDS.values():
            col.operator(kinds.add_operator_id(kind.id), icon=kind.icon, text="")
        for kind in kinds.KINDS.values():
            kind.draw_object(layout, obj)
        index = obj.affine_deformers_active_index
        if not 0 <= index < len(obj.affine_deformers):
            return
        col.operator("object.affine_deformer_remove", icon="REMOVE", text="").index = index
        draw_deformer(layout, context, obj, index)


def modifier_deformer_index(obj: bpy.types.Object) -> int:
    """The deformer whose modifier is the active one of `obj`'s stack, else the active deformer of its
    list (-1: none)."""
    active = obj.modifiers.active
    if active is not None and active.type == "NODES":
        attr = nodes.offset_attribute(active)
        for i, deformer in enumerate(obj.affine_deformers):
            if deformer.uid and storage.offset_name(deformer.uid) == attr:
                return i
    index = obj.affine_deformers_active_index
    return index if 0 <= index < len(obj.affine_deformers) else -1


class AFFINE_PT_modifier(bpy.types.Panel):
    """The settings of the deformer whose modifier is active in the stack (click it to show it here),
    beside the modifiers, as a built-in deformer's settings are."""

    bl_label = "Affine Deformer"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "modifier"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        obj = context.object
        return obj is not None and obj.type == "MESH" and len(obj.affine_deformers) > 0

    def draw_header(self, context: bpy.types.Context) -> None:
        index = modifier_deformer_index(context.object)
        if index >= 0:
            deformer = context.object.affine_deformers[index]
            kind = kinds.get(deformer.kind)
            self.layout.label(text=deformer.name, icon=kind.icon if kind is not None else "MODIFIER")

    def draw(self, context: bpy.types.Context) -> None:
        obj = context.object
        index = modifier_deformer_index(obj)
        if index < 0:
            self.layout.label(text="Click an Affine deformer's modifier in the stack", icon="INFO")
            return
        draw_deformer(self.layout, context, obj, index)


def draw_deformer(layout: bpy.types.UILayout, context: bpy.types.Context, obj: bpy.types.Object,
                  index: int) -> None:
    """One deformer's status, actions, settings and controls (both panels)."""
    deformer = obj.affine_deformers[index]
    if deformer.status:
        box = layout.box()
        for i, line in enumerate(_wrap(deformer.status, 60)):
            box.label(text=line, icon="ERROR" if i == 0 else "BLANK1")

    row = layout.row(align=True)
    row.operator("object.affine_deformer_bind", text="Rebind" if deformer.is_bound else "Bind",
                 icon="LINKED").index = index
    row.operator("object.affine_deformer_apply", text="Apply", icon="CHECKMARK").index = index
    if deformer.is_bound:
        layout.label(text=f"Bound to {deformer.bound_vertex_count} vertices", icon="INFO")
        draw_bake(layout, deformer, index)

    kind = kinds.get(deformer.kind)
    if kind is None:
        return
    weight_preview.draw(layout, context, deformer)
    weight_operators.draw(layout, deformer, index)
    kind.draw_actions(layout, deformer, index)
    col = layout.column()
    col.use_property_split = True
    kind.draw_settings(col, deformer)
    col.prop(deformer, "mask_group", icon="GROUP_VERTEX")
    col.prop(deformer, "strength")
    col.prop(deformer, "blend_mode")
    sub = col.column()
    sub.active = kind.branch_rule_active(deformer)
    sub.prop(deformer, "branch_rule")
    if kind.shape_pass:
        draw_shape_pass(col, obj, deformer)
    kind.draw_controls(layout, deformer, index)


def draw_shape_pass(col: bpy.types.UILayout, obj: bpy.types.Object, deformer) -> None:
    """Preserve Shape and its settings, with what its factor holds once built."""
    col.prop(deformer, "preserve_shape")
    sub = col.column()
    sub.active = deformer.preserve_shape
    sub.prop(deformer, "shape_iterations")
    sub.prop(deformer, "shape_anchor")
    built = shape_pass.summary(obj, deformer) if deformer.preserve_shape else ""
    if built:
        sub.label(text=built, icon="INFO")


def draw_bake(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """The Bake section of the deformer panel."""
    state = bake_state(deformer)
    col = layout.column(align=True)
    if state is None:
        row = col.row(align=True)
        op = row.operator(AFFINE_OT_deformer_bake.bl_idname, text="Bake PC2", icon="FILE_CACHE")
        op.index, op.mode = index, "PC2"
        op = row.operator(AFFINE_OT_deformer_bake.bl_idname, text="Bake Shape Keys", icon="SHAPEKEY_DATA")
        op.index, op.mode = index, "SHAPE_KEYS"
        return
    what = state.get("filepath") if state.get("mode") == "PC2" else "shape keys"
    col.label(text=f"Baked to {what}, frames {state.get('frame_start')}..{state.get('frame_end')}",
              icon="FILE_CACHE")
    if deformer.show_viewport or deformer.show_render:
        col.label(text="The live deformer is on too: the motion is applied twice", icon="ERROR")
    row = col.row(align=True)
    op = row.operator(AFFINE_OT_deformer_bake.bl_idname, text="Re-bake", icon="FILE_REFRESH")
    op.index, op.mode = index, state.get("mode", "PC2")
    if state.get("mode") == "PC2":
        op.filepath = state.get("filepath", "")
    row.operator(AFFINE_OT_deformer_unbake.bl_idname, text="Un-bake", icon="X").index = index


def _wrap(text: str, width: int) -> list[str]:
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return [*lines, line] if line else lines


class AFFINE_MT_object(bpy.types.Menu):
    """Object ▸ Affine Deformers."""

    bl_label = "Affine Deformers"
    bl_idname = "AFFINE_MT_object"

    def draw(self, _context: bpy.types.Context) -> None:
        for kind in kinds.KINDS.values():
            self.layout.operator(kinds.add_operator_id(kind.id), icon=kind.icon)


def draw_object_menu(self, _context: bpy.types.Context) -> None:
    self.layout.separator()
    self.layout.menu(AFFINE_MT_object.bl_idname)


def draw_modifier_menu(self, context: bpy.types.Context) -> None:
    """Add Modifier ▸ Deform: one entry per kind, beside Hook, Lattice and Mesh Deform (meshes only)."""
    obj = getattr(context, "object", None)
    if obj is None or obj.type != "MESH":
        return
    layout = self.layout
    layout.separator()
    for kind in kinds.KINDS.values():
        label = f"Affine {kind.menu_label or kind.label}"
        layout.operator(kinds.add_operator_id(kind.id), text=label, icon=kind.icon)


CLASSES = (AFFINE_UL_deformers, AFFINE_PT_modifier, AFFINE_PT_deformers, AFFINE_PT_linked_instance,
           AFFINE_MT_object)
