"""The operators and panel part of painted weights (weight_groups.py holds what they do): Weights →
Vertex Groups and Update Painted Weights, for the kinds that paint groups. (A kind's own list and its
buttons, e.g. the probe list's select button, are the kind's: kinds/.)"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty

from .. import binding, kinds
from ..files import storage
from ..kinds import BindError
from ..ui.addressing import DeformerIndexed, active_deformer, addressed_deformer
from ..update import evaluate
from .weight_groups import conversion_problem, group_targets, reads_groups, weights_to_groups


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
        obj, deformer = active_deformer(context)
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
        obj, deformer = active_deformer(context)
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


CLASSES = (AFFINE_OT_deformer_weights_to_groups, AFFINE_OT_deformer_weights_update)


# -------------------------------------------------------------------------------------------- UI


def draw(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """The weights row of a deformer whose kind paints groups: Weights → Groups (or, when painted,
    Update)."""
    kind = kinds.get(deformer.kind)
    if kind is None or not kind.paints_groups:
        return
    row = layout.row(align=True)
    if deformer.weight_mode == "VERTEX_GROUPS":
        row.operator(AFFINE_OT_deformer_weights_update.bl_idname, text="Update Painted Weights",
                     icon="FILE_REFRESH").index = index
        return
    row.operator(AFFINE_OT_deformer_weights_to_groups.bl_idname, text="Weights to Vertex Groups",
                 icon="GROUP_VERTEX").index = index
