"""Operators: add (probe / cage) / bind / remove / apply deformers, add / remove probes.

All are undoable, report clear messages, and work from background scripts through
`bpy.context.temp_override(active_object=..., object=..., selected_objects=[...])`; an ERROR report
makes `bpy.ops` raise RuntimeError carrying the message.
"""

from __future__ import annotations

import bpy
from bpy.props import IntProperty

from . import binding, cage_kind, evaluate, relations
from .kinds import BindError

UNDOABLE = {"REGISTER", "UNDO"}
#: Max Influences of a new probe deformer (the property's default, 4, stays for files of 0.1.0).
DEFAULT_PROBE_INFLUENCES = 6


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


def _selected_probes(context: bpy.types.Context, target: bpy.types.Object) -> tuple[list, list]:
    """Selected Empties (the probes) and the other selected non-target objects (ignored)."""
    selected = list(getattr(context, "selected_objects", None) or [])
    probes = [o for o in selected if o != target and o.type == "EMPTY"]
    ignored = [o for o in selected if o != target and o.type != "EMPTY"]
    return probes, ignored


def _new_probe(context: bpy.types.Context, target: bpy.types.Object) -> bpy.types.Object:
    """An Empty at the target's origin, sized to the target, in the target's first collection."""
    probe = bpy.data.objects.new(f"{target.name}.Probe", None)
    probe.empty_display_type = "SPHERE"
    probe.empty_display_size = max(0.1, 0.25 * max(target.dimensions))
    probe.location = target.matrix_world.translation  # unparented: location is the world position
    collections = target.users_collection
    (collections[0] if collections else context.scene.collection).objects.link(probe)
    return probe


def _lock_render_interface(context: bpy.types.Context) -> None:
    if context.scene is not None and not context.scene.render.use_lock_interface:
        context.scene.render.use_lock_interface = True


def _bind_new(op: bpy.types.Operator, context: bpy.types.Context, target: bpy.types.Object, deformer,
              created: bpy.types.Object | None = None) -> bool:
    """Bind a deformer the operator just created; on failure remove it again (and the Empty made for
    it), report why and return False, so a failed add leaves nothing behind."""
    try:
        binding.bind(target, deformer, context.evaluated_depsgraph_get())
    except (BindError, ValueError) as exc:
        binding.remove(target, binding.deformer_index(target, deformer))
        if created is not None:
            bpy.data.objects.remove(created, do_unlink=True)
        op.report({"ERROR"}, str(exc))
        return False
    _lock_render_interface(context)
    _refresh(context, target)
    return True


def _deformer(op: bpy.types.Operator, context: bpy.types.Context):
    """(object, deformer) addressed by op.index on the active object, or (None, None) after a report."""
    obj = active_target(context)
    problem = binding.target_problem(obj)
    if problem:
        op.report({"ERROR"}, problem)
        return None, None
    if not 0 <= op.index < len(obj.affine_deformers):
        op.report({"ERROR"}, f"'{obj.name}' has no affine deformer #{op.index} "
                  f"(it has {len(obj.affine_deformers)})")
        return None, None
    return obj, obj.affine_deformers[op.index]


def _refresh(context: bpy.types.Context, obj: bpy.types.Object) -> None:
    """Evaluate at once so status and offsets are current when the operator returns."""
    evaluate.evaluate_object(obj, context.evaluated_depsgraph_get())


class AFFINE_OT_probe_deformer_add(TargetPolled, bpy.types.Operator):
    """Add a probe deformer to the active mesh; the selected Empties become its probes (none selected:
    one new Empty at the mesh's origin). Their current poses become the rest pose"""

    bl_idname = "object.affine_probe_deformer_add"
    bl_label = "Add Probe Deformer"
    bl_options = UNDOABLE

    def execute(self, context: bpy.types.Context) -> set[str]:
        target = active_target(context)
        problem = binding.target_problem(target)
        if problem:
            self.report({"ERROR"}, problem)
            return {"CANCELLED"}
        probes, ignored = _selected_probes(context, target)
        created = None
        if not probes:
            created = _new_probe(context, target)
            probes = [created]
        deformer = binding.create(target, "PROBE", "Probe Deformer")
        with binding.quiet():  # bound below in one go
            # 6 influences: with 4, steps near points where the 5 strongest probes nearly tie reach
            # 5× the untruncated field's inside clouds of 8 probes (tests/core/test_probe_seams.py).
            deformer.max_influences = DEFAULT_PROBE_INFLUENCES
        for probe in probes:
            deformer.probes.add().object = probe
        if not _bind_new(self, context, target, deformer, created):
            return {"CANCELLED"}
        if ignored:
            self.report({"WARNING"}, "Ignored selected non-Empty objects: "
                        + ", ".join(o.name for o in ignored))
        made = f" (created '{created.name}')" if created is not None else ""
        self.report({"INFO"}, f"Added a probe deformer to '{target.name}' with {len(probes)} probe(s){made}")
        return {"FINISHED"}


class AFFINE_OT_cage_deformer_add(TargetPolled, bpy.types.Operator):
    """Add a cage deformer to the active mesh; the other selected mesh is the cage (closed, normals
    outward). Its current shape becomes the rest shape"""

    bl_idname = "object.affine_cage_deformer_add"
    bl_label = "Add Cage Deformer"
    bl_options = UNDOABLE

    def execute(self, context: bpy.types.Context) -> set[str]:
        target = active_target(context)
        problem = binding.target_problem(target)
        if problem:
            self.report({"ERROR"}, problem)
            return {"CANCELLED"}
        selected = list(getattr(context, "selected_objects", None) or [])
        cages = [o for o in selected if o != target and o.type == "MESH"]
        if len(cages) != 1:
            found = ", ".join(f"'{o.name}'" for o in cages)
            self.report({"ERROR"}, "Select exactly one other mesh as the cage, with the target active "
                        + (f"(selected: {found})" if cages else "(none selected)"))
            return {"CANCELLED"}
        cage = cages[0]
        deformer = binding.create(target, "CAGE", "Cage Deformer")
        with binding.quiet():  # bound below in one go
            deformer.cage = cage
            deformer.max_influences = 8
        if not _bind_new(self, context, target, deformer):
            return {"CANCELLED"}
        ignored = [o for o in selected if o not in (target, cage)]
        if ignored:
            self.report({"WARNING"}, "Ignored selected non-mesh objects: "
                        + ", ".join(o.name for o in ignored))
        faces = len(deformer[cage_kind.LOOP_TOTAL])
        self.report({"INFO"}, f"Added a cage deformer to '{target.name}' driven by '{cage.name}' "
                    f"({faces} faces)")
        return {"FINISHED"}


class AFFINE_OT_deformer_bind(DeformerIndexed, bpy.types.Operator):
    """Rebind: the controls' current poses become the rest pose and the weights are recomputed"""

    bl_idname = "object.affine_deformer_bind"
    bl_label = "Bind Affine Deformer"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = _deformer(self, context)
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
        if obj is None or not 0 <= self.index < len(obj.affine_deformers):
            self.report({"ERROR"}, f"No affine deformer #{self.index} on the active object")
            return {"CANCELLED"}
        if obj.mode == "EDIT":
            self.report({"ERROR"}, f"'{obj.name}' is in Edit Mode: switch to Object Mode first")
            return {"CANCELLED"}
        name = obj.affine_deformers[self.index].name
        binding.remove(obj, self.index)
        self.report({"INFO"}, f"Removed '{name}' from '{obj.name}'")
        return {"FINISHED"}


class AFFINE_OT_deformer_apply(DeformerIndexed, bpy.types.Operator):
    """Write the current deformed shape into the mesh and remove the deformer"""

    bl_idname = "object.affine_deformer_apply"
    bl_label = "Apply Affine Deformer"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = _deformer(self, context)
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
        obj, deformer = _deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        if deformer.kind != "PROBE":
            self.report({"ERROR"}, f"'{deformer.name}' is not a probe deformer")
            return {"CANCELLED"}
        existing = {item.object for item in deformer.probes}
        probes, _ignored = _selected_probes(context, obj)
        probes = [p for p in probes if p not in existing]
        created = None
        if not probes:
            created = _new_probe(context, obj)
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
        obj, deformer = _deformer(self, context)
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


CLASSES = (
    AFFINE_OT_probe_deformer_add,
    AFFINE_OT_cage_deformer_add,
    AFFINE_OT_deformer_bind,
    AFFINE_OT_deformer_remove,
    AFFINE_OT_deformer_apply,
    AFFINE_OT_deformer_probe_add,
    AFFINE_OT_deformer_probe_remove,
)
