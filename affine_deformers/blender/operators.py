"""Operators: add (probe / cage) / bind / remove / apply deformers, add / remove probes.

All are undoable, report clear messages, and work from background scripts through
`bpy.context.temp_override(active_object=..., object=..., selected_objects=[...])`; an ERROR report
makes `bpy.ops` raise RuntimeError carrying the message.
"""

from __future__ import annotations

from typing import ClassVar

import bpy
from bpy.props import IntProperty, StringProperty

from . import binding, evaluate, kinds, relations
from .kinds import BindError, KindId
from .kinds import probe as probe_kind

UNDOABLE = {"REGISTER", "UNDO"}


class DeformerIndexed:
    """Mixin for operators that address one deformer of the active object by `index`; undoable.

    The index has no hard minimum: Blender clamps an out-of-range value to the minimum, so index=-1
    would silently address deformer #0; instead every index outside the stack is refused by name.
    Greyed out (poll, with the reason as tooltip) while the active object has no deformers."""

    bl_options = UNDOABLE

    index: IntProperty(name="Index", default=0, soft_min=0, description="Deformer index on the active object")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        obj = active_target(context)
        if obj is None:
            cls.poll_message_set("No active object")
            return False
        if not len(getattr(obj, "affine_deformers", ())):
            cls.poll_message_set(f"'{obj.name}' has no affine deformers")
            return False
        return True


class TargetPolled:
    """Mixin for the add operators: greyed out (with the reason) unless the active object can carry a
    deformer (binding.target_problem)."""

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        problem = binding.target_problem(active_target(context))
        if problem:
            cls.poll_message_set(problem)
        return not problem


def active_target(context: bpy.types.Context) -> bpy.types.Object | None:
    """The object operators act on: the active object, else the context object."""
    return context.active_object if context.active_object is not None else context.object


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


def addressed_deformer(op: bpy.types.Operator, context: bpy.types.Context):
    """(object, deformer) addressed by op.index on the active object, or (None, None) after a report."""
    obj = active_target(context)
    problem = binding.target_problem(obj)
    if problem:
        op.report({"ERROR"}, problem)
        return None, None
    try:
        return obj, binding.deformer_at(obj, op.index)
    except LookupError as exc:
        op.report({"ERROR"}, str(exc))
        return None, None


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
        if adopted.warning:
            self.report({"WARNING"}, adopted.warning)
        self.report({"INFO"}, kind.added_message(target, deformer, adopted))
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
        binding.remove(obj, self.index)
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


class AFFINE_OT_deformer_probe_add(DeformerIndexed, bpy.types.Operator):
    """Add the selected Empties (none selected: a new Empty at the mesh's origin) as probes of the
    deformer; their current poses become their rest poses, the other probes keep theirs"""

    bl_idname = "object.affine_deformer_probe_add"
    bl_label = "Add Probes"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        if deformer.kind != KindId.PROBE:
            self.report({"ERROR"}, f"'{deformer.name}' is not a probe deformer")
            return {"CANCELLED"}
        existing = {item.object for item in deformer.probes}
        probes, _ignored = probe_kind.selected_probes(context, obj)
        probes = [p for p in probes if p not in existing]
        created = None
        if not probes:
            created = probe_kind.new_probe(context, obj)
            probes = [created]
        first = len(deformer.probes)
        with binding.quiet():  # bound below in one go
            for probe in probes:
                deformer.probes.add().object = probe
        try:
            binding.bind(obj, deformer, context.evaluated_depsgraph_get(),
                         only=list(range(first, len(deformer.probes))))
        except (BindError, ValueError) as exc:
            while len(deformer.probes) > first:
                deformer.probes.remove(len(deformer.probes) - 1)
            relations.sync(obj, deformer)  # bind named the new probes on the modifier already
            if created is not None:
                bpy.data.objects.remove(created, do_unlink=True)
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _refresh(context, obj)
        self.report({"INFO"}, f"Added {len(probes)} probe(s) to '{deformer.name}'")
        return {"FINISHED"}


class AFFINE_OT_deformer_probe_remove(DeformerIndexed, bpy.types.Operator):
    """Remove a probe from the deformer and recompute the weights (the other rest poses are kept)"""

    bl_idname = "object.affine_deformer_probe_remove"
    bl_label = "Remove Probe"

    probe_index: IntProperty(name="Probe", default=0, soft_min=0, description="Probe index in the deformer")

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        if not 0 <= self.probe_index < len(deformer.probes):
            self.report({"ERROR"}, f"'{deformer.name}' has no probe #{self.probe_index}")
            return {"CANCELLED"}
        if len(deformer.probes) == 1:
            self.report({"ERROR"}, "Cannot remove the last probe: remove the deformer instead")
            return {"CANCELLED"}
        name = deformer.probes[self.probe_index].name
        deformer.probes.remove(self.probe_index)
        deformer.active_probe_index = min(deformer.active_probe_index, len(deformer.probes) - 1)
        try:
            binding.reweight(obj, deformer)
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _refresh(context, obj)
        self.report({"INFO"}, f"Removed probe '{name}' from '{deformer.name}'")
        return {"FINISHED"}


def _bone_deformer(op: bpy.types.Operator, context: bpy.types.Context):
    """(object, deformer) like `addressed_deformer`, refusing (reported) a deformer that is not a bone one."""
    obj, deformer = addressed_deformer(op, context)
    if deformer is not None and deformer.kind != KindId.BONE:
        op.report({"ERROR"}, f"'{deformer.name}' is not a bone deformer")
        return None, None
    return obj, deformer


def _unlisted_bones(self, context: bpy.types.Context, _text: str) -> list[str]:
    obj = active_target(context)
    if obj is None or not 0 <= self.index < len(obj.affine_deformers):
        return []
    deformer = obj.affine_deformers[self.index]
    listed = {item.name for item in deformer.bones}
    armature = deformer.armature
    return [b.name for b in armature.data.bones if b.name not in listed] if armature is not None else []


class AFFINE_OT_deformer_bone_add(DeformerIndexed, bpy.types.Operator):
    """Add a bone of the armature to the bone deformer's controls and recompute the weights"""

    bl_idname = "object.affine_deformer_bone_add"
    bl_label = "Add Bone"

    bone: StringProperty(name="Bone", search=_unlisted_bones, description="Bone of the deformer's armature")

    def invoke(self, context: bpy.types.Context, _event: bpy.types.Event) -> set[str]:
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = _bone_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        armature = deformer.armature
        if armature is None or armature.data.bones.get(self.bone) is None:
            self.report({"ERROR"}, f"The deformer's armature has no bone named '{self.bone}'")
            return {"CANCELLED"}
        if any(item.name == self.bone for item in deformer.bones):
            self.report({"ERROR"}, f"'{self.bone}' is already a control of '{deformer.name}'")
            return {"CANCELLED"}
        with binding.quiet():
            deformer.bones.add().name = self.bone
        try:
            binding.bind(obj, deformer, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            deformer.bones.remove(len(deformer.bones) - 1)
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _refresh(context, obj)
        self.report({"INFO"}, f"Added bone '{self.bone}' to '{deformer.name}'")
        return {"FINISHED"}


class AFFINE_OT_deformer_bone_remove(DeformerIndexed, bpy.types.Operator):
    """Remove a bone from the bone deformer's controls and recompute the weights"""

    bl_idname = "object.affine_deformer_bone_remove"
    bl_label = "Remove Bone"

    bone_index: IntProperty(name="Bone", default=0, soft_min=0, description="Bone index in the deformer")

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = _bone_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        if not 0 <= self.bone_index < len(deformer.bones):
            self.report({"ERROR"}, f"'{deformer.name}' has no bone #{self.bone_index}")
            return {"CANCELLED"}
        if len(deformer.bones) == 1:
            self.report({"ERROR"}, "Cannot remove the last bone: remove the deformer instead")
            return {"CANCELLED"}
        name = deformer.bones[self.bone_index].name
        deformer.bones.remove(self.bone_index)
        deformer.active_bone_index = min(deformer.active_bone_index, len(deformer.bones) - 1)
        try:
            binding.bind(obj, deformer, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _refresh(context, obj)
        self.report({"INFO"}, f"Removed bone '{name}' from '{deformer.name}'")
        return {"FINISHED"}


CLASSES = (
    *ADD_OPERATORS,
    AFFINE_OT_deformer_bind,
    AFFINE_OT_deformer_remove,
    AFFINE_OT_deformer_apply,
    AFFINE_OT_deformer_probe_add,
    AFFINE_OT_deformer_probe_remove,
    AFFINE_OT_deformer_bone_add,
    AFFINE_OT_deformer_bone_remove,
)
