"""User interface: Properties ▸ Object ▸ Affine Deformers, and Object ▸ Affine Deformers in the 3D view."""

from __future__ import annotations

import bpy

from . import bake


class AFFINE_UL_deformers(bpy.types.UIList):
    """The deformers of an object, with a warning icon on those whose status is not empty."""

    def draw_item(self, _context, layout, _data, item, _icon, _active_data, _active_prop, _index=0):
        icon = "EMPTY_AXIS" if item.kind == "PROBE" else "MESH_CUBE"
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


class AFFINE_UL_probes(bpy.types.UIList):
    """The probes of a deformer: object and weight scale."""

    def draw_item(self, _context, layout, _data, item, _icon, _active_data, _active_prop, _index=0):
        row = layout.row(align=True)
        if item.object is None:
            row.label(text=f"{item.name or '?'} (missing)", icon="ERROR")
        else:
            row.prop(item, "object", text="", emboss=False, icon="EMPTY_AXIS")
        row.prop(item, "weight_scale", text="")


class AFFINE_PT_deformers(bpy.types.Panel):
    """Affine Deformers of the active object."""

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
        col.operator("object.affine_probe_deformer_add", icon="EMPTY_AXIS", text="")
        col.operator("object.affine_cage_deformer_add", icon="MESH_CUBE", text="")
        index = obj.affine_deformers_active_index
        if not 0 <= index < len(obj.affine_deformers):
            return
        col.operator("object.affine_deformer_remove", icon="REMOVE", text="").index = index
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
            bake.draw_bake(layout, deformer, index)

        col = layout.column()
        col.use_property_split = True
        if deformer.kind == "CAGE":
            col.prop(deformer, "cage")
            col.prop(deformer, "cage_weights")
            if deformer.cage_weights == "INVERSE_DISTANCE":
                col.prop(deformer, "exponent")
                col.prop(deformer, "half_space")
        else:
            col.prop(deformer, "weight_mode")
            # Surface weights have no length scale (radius): their exponent sharpens them
            if deformer.weight_mode in ("INVERSE_DISTANCE", "FALLOFF"):
                col.prop(deformer, "radius")
            if deformer.weight_mode in ("INVERSE_DISTANCE", "SURFACE"):
                col.prop(deformer, "exponent")
            col.prop(deformer, "normalize")
        if deformer.kind != "CAGE" or deformer.cage_weights == "INVERSE_DISTANCE":
            col.prop(deformer, "max_influences")  # harmonic cage weights: always 8 grid nodes
        col.prop(deformer, "mask_group", icon="GROUP_VERTEX")
        col.prop(deformer, "strength")
        col.prop(deformer, "blend_mode")
        sub = col.column()
        # A linear blend of probes has no rotation branches; a cage's object motion is scaled in the
        # log space in both modes, but its branch only matters at a strength other than 1.
        sub.active = (deformer.blend_mode == "AFFINE_LOG" if deformer.kind == "PROBE"
                      else deformer.strength != 1.0)
        sub.prop(deformer, "branch_rule")

        if deformer.kind == "PROBE":
            layout.label(text="Probes")
            row = layout.row()
            row.template_list("AFFINE_UL_probes", "", deformer, "probes", deformer, "active_probe_index",
                              rows=2)
            col = row.column(align=True)
            col.operator("object.affine_deformer_probe_add", icon="ADD", text="").index = index
            op = col.operator("object.affine_deformer_probe_remove", icon="REMOVE", text="")
            op.index, op.probe_index = index, deformer.active_probe_index


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
        self.layout.operator("object.affine_probe_deformer_add", icon="EMPTY_AXIS")
        self.layout.operator("object.affine_cage_deformer_add", icon="MESH_CUBE")


def draw_object_menu(self, _context: bpy.types.Context) -> None:
    self.layout.separator()
    self.layout.menu(AFFINE_MT_object.bl_idname)


CLASSES = (AFFINE_UL_deformers, AFFINE_UL_probes, AFFINE_PT_deformers, AFFINE_MT_object)
