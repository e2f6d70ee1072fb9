"""Operators: add (one per kind) / bind / remove / apply deformers. The kinds' own operators (add or
remove probes and bones, convert an Armature modifier, …) are in their modules in kinds/.

All are undoable, report clear messages, and work from background scripts through
`bpy.context.temp_override(active_object=..., object=..., selected_objects=[...])`; an ERROR report
makes `bpy.ops` raise RuntimeError carrying the message.
"""

from __future__ import annotations

from typing import ClassVar

import bpy

from .. import binding, kinds
from ..kinds import BindError
from ..update import evaluate
from .addressing import UNDOABLE, DeformerIndexed, TargetPolled, active_target, addressed_deformer


def _lock_render_interface(context: bpy.types.Context) -> None:
    if context.scene is not None and not context.scene.render.use_lock_interface:
        context.scene.render.use_lock_interface = True


def _bind_new(op: bpy.types.Operator, context: bpy.types.Context, target: bpy.types.Object, deformer,
              created: list[bpy.types.Object]) -> bool:
    """Bind a deformer the operator just created; on failure remove it again (and the Empty made for
    it), report why and return False, so a failed add leaves nothing behind."""
    try:
        binding.bind(target, deformer, context.evaluated_depsgraph_get())
    except (BindError, ValueError) as exc:
        binding.remove(target, binding.deformer_index(target, deformer))
        for made in created:
            bpy.data.objects.remove(made, do_unlink=True)
        op.report({"ERROR"}, str(exc))
        return False
    _lock_render_interface(context)
    _refresh(context, target)
    return True


def _refresh(context: bpy.types.Context, obj: bpy.types.Object) -> None:
    """Evaluate at once so status and offsets are current when the operator returns."""
    evaluate.evaluate_object(obj, context.evaluated_depsgraph_get())


class AddDeformer(TargetPolled):
    """Add a deformer of the kind `kind_id` to the active mesh, its controls taken from the selection
    (DeformerKind.adopt_selection), and bind it; a failed add leaves nothing behind."""

    bl_options = UNDOABLE
    kind_id: ClassVar[str]

    def execute(self, context: bpy.types.Context) -> set[str]:
        target = active_target(context)
        problem = binding.target_problem(target)
        if problem:
            self.report({"ERROR"}, problem)
            return {"CANCELLED"}
        kind = kinds.get(self.kind_id)
        try:
            adopted = kind.adopt_selection(context, target)
        except BindError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        deformer = binding.create(target, kind.id, f"{kind.label} Deformer")
        with binding.quiet():  # bound below in one go
            kind.set_up(deformer, adopted)
        if not _bind_new(self, context, target, deformer, adopted.created):
            return {"CANCELLED"}
        finished = kind.after_add(target, deformer, adopted)
        for warning in (adopted.warning, deformer.bind_warning):
            if warning:
                self.report({"WARNING"}, warning)
        self.report({"INFO"}, kind.added_message(target, deformer, adopted) + finished)
        if finished:
            _refresh(context, target)
        return {"FINISHED"}


def add_operator(kind: type) -> type:
    """The add operator of a kind: object.affine_<kind>_deformer_add (AFFINE_OT_<kind>_deformer_add)."""
    name = kind.id.lower()
    return type(f"AFFINE_OT_{name}_deformer_add", (AddDeformer, bpy.types.Operator), {
        "bl_idname": kinds.add_operator_id(kind.id),
        "bl_label": f"Add {kind.label} Deformer",
        "bl_description": kind.add_description,
        "kind_id": kind.id,
        "__doc__": kind.add_description,
    })


#: One add operator per registered kind (the interface lists them in this order).
ADD_OPERATORS = tuple(add_operator(kind) for kind in kinds.REGISTERED)


class AFFINE_OT_deformer_bind(DeformerIndexed, bpy.types.Operator):
    """Rebind: the controls' current poses become the rest pose and the weights are recomputed"""

    bl_idname = "object.affine_deformer_bind"
    bl_label = "Bind Affine Deformer"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        try:
            binding.bind(obj, deformer, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _lock_render_interface(context)
        _refresh(context, obj)
        if deformer.bind_warning:
            self.report({"WARNING"}, deformer.bind_warning)
        self.report({"INFO"}, f"Bound '{deformer.name}' on '{obj.name}' "
                    f"({deformer.bound_vertex_count} vertices)")
        return {"FINISHED"}


class AFFINE_OT_deformer_remove(DeformerIndexed, bpy.types.Operator):
    """Remove the deformer (its modifier and stored data): the mesh shows its exact rest shape"""

    bl_idname = "object.affine_deformer_remove"
    bl_label = "Remove Affine Deformer"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj = active_target(context)
        try:
            name = binding.deformer_at(obj, self.index).name
        except LookupError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if obj.mode == "EDIT":
            self.report({"ERROR"}, f"'{obj.name}' is in Edit Mode: switch to Object Mode first")
            return {"CANCELLED"}
        try:
            binding.remove(obj, self.index)
        except BindError as exc:  # a library override: refused before anything changed
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Removed '{name}' from '{obj.name}'")
        return {"FINISHED"}


class AFFINE_OT_deformer_apply(DeformerIndexed, bpy.types.Operator):
    """Write the current deformed shape into the mesh and remove the deformer"""

    bl_idname = "object.affine_deformer_apply"
    bl_label = "Apply Affine Deformer"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        evaluate.forget(obj, deformer.uid)
        evaluate.evaluate_deformer(obj, deformer, context.evaluated_depsgraph_get())
        error = evaluate.blocking_error(obj, deformer)
        if error:
            self.report({"ERROR"}, f"Cannot apply '{deformer.name}': {error}")
            return {"CANCELLED"}
        name = deformer.name
        try:
            binding.apply(obj, self.index)
        except BindError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Applied '{name}' to '{obj.name}'")
        return {"FINISHED"}


CLASSES = (
    *ADD_OPERATORS,
    AFFINE_OT_deformer_bind,
    AFFINE_OT_deformer_remove,
    AFFINE_OT_deformer_apply,
)
