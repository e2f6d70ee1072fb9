"""The operators and panel parts of painted weights (weight_groups.py holds what they do): Weights →
Vertex Groups, Update Painted Weights, the probe list's select button and its rows."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, IntProperty

from . import binding, evaluate, storage
from .kinds import BindError, KindId
from .kinds.probe import group_name, probe_label
from .operators import DeformerIndexed, active_target, addressed_deformer
from .weight_groups import (
    STATE_ICONS,
    STATE_TEXT,
    conversion_problem,
    group_targets,
    reads_groups,
    weights_to_groups,
)


def _active_deformer(context: bpy.types.Context):
    obj = active_target(context)
    if obj is None or not len(getattr(obj, "affine_deformers", ())):
        return obj, None
    index = obj.affine_deformers_active_index
    return obj, (obj.affine_deformers[index] if 0 <= index < len(obj.affine_deformers) else None)


class AFFINE_OT_deformer_weights_to_groups(DeformerIndexed, bpy.types.Operator):
    """Write the current automatic weights into vertex groups named after the probes and switch the
    deformer to painted weights (same deformation), to paint corrections on top"""

    bl_idname = "object.affine_deformer_weights_to_groups"
    bl_label = "Weights to Vertex Groups"

    overwrite: BoolProperty(
        name="Overwrite", default=False, options={"SKIP_SAVE"},
        description="Replace vertex groups that already have the probes' names (from the panel: "
                    "after a confirmation)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if not super().poll(context):
            return False
        obj, deformer = _active_deformer(context)
        problem = conversion_problem(obj, deformer) if deformer is not None else "No active deformer"
        if problem:
            cls.poll_message_set(problem)
        return not problem

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        # From the panel: groups of those names are replaced only once the artist confirms it.
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        existing = [name for name in group_targets(deformer) if obj.vertex_groups.get(name) is not None]
        if not existing or self.overwrite:
            return self.execute(context)
        self.overwrite = True
        return context.window_manager.invoke_confirm(
            self, event, title="Replace Vertex Groups",
            message="Replace the vertex groups " + ", ".join(f"'{n}'" for n in existing)
                    + " with the deformer's weights?", confirm_text="Replace", icon="WARNING")

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        try:
            result = weights_to_groups(obj, deformer, self.overwrite)
        except (BindError, storage.StorageError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        evaluate.evaluate_object(obj, context.evaluated_depsgraph_get())
        self.report({"INFO"}, f"Wrote {len(result.groups)} vertex group(s) ("
                    + ", ".join(result.groups) + "); " + ", ".join(result.changes)
                    + f"; weights reproduced to {result.max_difference:.1g}")
        return {"FINISHED"}


class AFFINE_OT_deformer_weights_update(DeformerIndexed, bpy.types.Operator):
    """Read the painted vertex groups (and the mask) again and re-weight; also done when the object
    leaves Weight Paint mode"""

    bl_idname = "object.affine_deformer_weights_update"
    bl_label = "Update Painted Weights"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if not super().poll(context):
            return False
        obj, deformer = _active_deformer(context)
        problem = binding.target_problem(obj)
        if not problem and (deformer is None or not reads_groups(deformer)):
            problem = "The deformer reads no vertex groups (painted weights or a mask)"
        if problem:
            cls.poll_message_set(problem)
        return not problem

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        try:
            binding.reweight(obj, deformer)
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        evaluate.evaluate_object(obj, context.evaluated_depsgraph_get())
        self.report({"INFO"}, f"Re-weighted '{deformer.name}' from its vertex groups")
        return {"FINISHED"}


def _selectable_problem(context: bpy.types.Context, probe: bpy.types.Object | None) -> str:
    if probe is None:
        return "The probe has no object"
    view_layer = getattr(context, "view_layer", None)
    if view_layer is None or view_layer.objects.get(probe.name) != probe:
        return f"'{probe.name}' is not in the current view layer"
    if probe.hide_select or not probe.visible_get(view_layer=view_layer):
        return f"'{probe.name}' is hidden or not selectable"
    return ""


class AFFINE_OT_deformer_probe_select(DeformerIndexed, bpy.types.Operator):
    """Select the probe's object alone (the mesh stays active, so this panel stays; move it with G, R,
    S in the 3D view). Shift: make the probe the active object too"""

    bl_idname = "object.affine_deformer_probe_select"
    bl_label = "Select Probe"

    probe_index: IntProperty(name="Probe", default=0, soft_min=0, description="Probe index in the deformer")
    make_active: BoolProperty(name="Make Active", default=False,
                              description="Also make the probe the active object")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if not super().poll(context):
            return False
        _obj, deformer = _active_deformer(context)
        if deformer is None or deformer.kind != KindId.PROBE:
            cls.poll_message_set("The active deformer has no probes")
            return False
        return True

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        self.make_active = event.shift
        return self.execute(context)

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        if deformer.kind != KindId.PROBE or not 0 <= self.probe_index < len(deformer.probes):
            self.report({"ERROR"}, f"'{deformer.name}' has no probe #{self.probe_index}")
            return {"CANCELLED"}
        probe = deformer.probes[self.probe_index].object
        problem = _selectable_problem(context, probe)
        if problem:
            self.report({"ERROR"}, problem)
            return {"CANCELLED"}
        for other in list(context.selected_objects):
            other.select_set(False)
        probe.select_set(True)
        if self.make_active:
            context.view_layer.objects.active = probe
        deformer.active_probe_index = self.probe_index
        return {"FINISHED"}


CLASSES = (AFFINE_OT_deformer_weights_to_groups, AFFINE_OT_deformer_weights_update,
           AFFINE_OT_deformer_probe_select)


# -------------------------------------------------------------------------------------------- UI


def draw(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """The weights row of a probe or bone deformer: Weights → Groups (or, when painted, Update)."""
    if deformer.kind not in (KindId.PROBE, KindId.BONE):
        return
    row = layout.row(align=True)
    if deformer.weight_mode == "VERTEX_GROUPS":
        row.operator(AFFINE_OT_deformer_weights_update.bl_idname, text="Update Painted Weights",
                     icon="FILE_REFRESH").index = index
        return
    row.operator(AFFINE_OT_deformer_weights_to_groups.bl_idname, text="Weights to Vertex Groups",
                 icon="GROUP_VERTEX").index = index


def draw_probe_item(layout: bpy.types.UILayout, item, index: int) -> None:
    """One row of the probe list: object, state, weight scale, select button."""
    row = layout.row(align=True)
    if item.object is None:
        row.label(text=f"{item.name or '?'} (missing)", icon="ERROR")
    else:
        row.prop(item, "object", text="", emboss=False, icon="EMPTY_AXIS")
    row.label(text=STATE_TEXT.get(item.state, ""), icon=STATE_ICONS.get(item.state, "NONE"))
    row.prop(item, "weight_scale", text="")
    path = item.path_from_id()  # 'affine_deformers[i].probes[j]'
    deformer_index = int(path[path.index("[") + 1 : path.index("]")])
    sub = row.row(align=True)
    sub.enabled = item.object is not None
    op = sub.operator(AFFINE_OT_deformer_probe_select.bl_idname, text="", icon="RESTRICT_SELECT_OFF",
                      emboss=False)
    op.index, op.probe_index = deformer_index, index


def draw_probe_details(layout: bpy.types.UILayout, obj: bpy.types.Object, deformer) -> None:
    """Below the probe list, painted weights: the active probe's vertex group (searchable)."""
    if deformer.kind != KindId.PROBE or deformer.weight_mode != "VERTEX_GROUPS" or not len(deformer.probes):
        return
    item = deformer.probes[min(deformer.active_probe_index, len(deformer.probes) - 1)]
    col = layout.column()
    col.prop(item, "vertex_group", icon="GROUP_VERTEX", text=f"Group of '{probe_label(item)}'")
    if not item.vertex_group:
        col.label(text=f"Empty: reads '{group_name(obj, item)}'", icon="BLANK1")
