"""How operators and scripts address a deformer: the target checks, the lookup by stack position or
id, and the operator mixins built on them (every operator of the add-on and of its kinds uses these).

This module imports nothing of the add-on, so the kinds' own operators (kinds/) can use it too.
"""

from __future__ import annotations

import bpy
from bpy.props import IntProperty

UNDOABLE = {"REGISTER", "UNDO"}


def library_name(id_data: bpy.types.ID) -> str:
    """The file name of the library `id_data` comes from: its own, or its override reference's."""
    library = id_data.library
    override = id_data.override_library
    if library is None and override is not None and override.reference is not None:
        library = override.reference.library
    return bpy.path.basename(library.filepath) if library is not None else "this file"


def linked_mesh_problem(obj: bpy.types.Object, what: str = "rebind, re-weight or apply it") -> str:
    """Why the bind data of `obj` cannot be rewritten here ('' when they can): its mesh is linked from
    a library (or an override of one, whose mesh data Blender does not let a file change or save)."""
    mesh = obj.data
    if obj.type != "MESH" or (mesh.library is None and mesh.override_library is None):
        return ""
    return (f"The bind data of '{obj.name}' live on mesh '{mesh.name}' in library "
            f"'{library_name(mesh)}', which this file cannot change: {what} in that file (open it, "
            "then save it)" + ("" if "bake" in what else ", or bake it there"))


def target_problem(obj: bpy.types.Object | None) -> str:
    """Why `obj` cannot carry a deformer (or have its bind data rewritten), or '' when it can."""
    if obj is None:
        return "No active object: make the mesh to deform the active object"
    if obj.type != "MESH":
        kind = obj.type.replace("_", " ").lower()
        article = "an" if kind[:1] in "aeiou" else "a"
        return f"'{obj.name}' is {article} {kind}, not a mesh: the target must be a mesh"
    if obj.library is not None:
        return (f"'{obj.name}' is linked from library '{library_name(obj)}' and cannot be edited here: "
                "make a library override (Object ▸ Library Override ▸ Make) to pose its controls, or "
                "edit it in that file")
    problem = linked_mesh_problem(obj)
    if problem:
        return problem
    if obj.mode == "EDIT":
        return f"'{obj.name}' is in Edit Mode: switch to Object Mode first"
    return ""


def deformer_at(obj: bpy.types.Object, index: int):
    """Deformer `index` of `obj`; LookupError with a message for the artist when there is none (the
    one lookup by index: operators, bake and scripts address deformers by their stack position)."""
    count = len(obj.affine_deformers)
    if not 0 <= index < count:
        raise LookupError(f"'{obj.name}' has no affine deformer #{index} (it has {count})")
    return obj.affine_deformers[index]


def find_uid(obj: bpy.types.Object, uid: str):
    """(index, deformer) of the deformer with id `uid` on `obj` (positions change when others are
    removed); LookupError when it is gone."""
    for i, item in enumerate(obj.affine_deformers):
        if item.uid == uid:
            return i, item
    raise LookupError(f"The deformer was removed from '{obj.name}'")


def deformer_index(obj: bpy.types.Object, deformer) -> int:
    """The stack position of `deformer` on `obj` (LookupError when it is not there)."""
    return find_uid(obj, deformer.uid)[0]


def active_target(context: bpy.types.Context) -> bpy.types.Object | None:
    """The object operators act on: the active object, else the context object."""
    return context.active_object if context.active_object is not None else context.object


def active_deformer(context: bpy.types.Context):
    """(the target, its active deformer or None) for operator polls."""
    obj = active_target(context)
    if obj is None or not len(getattr(obj, "affine_deformers", ())):
        return obj, None
    index = obj.affine_deformers_active_index
    return obj, (obj.affine_deformers[index] if 0 <= index < len(obj.affine_deformers) else None)


def addressed_deformer(op: bpy.types.Operator, context: bpy.types.Context):
    """(object, deformer) addressed by op.index on the active object, or (None, None) after a report."""
    obj = active_target(context)
    problem = target_problem(obj)
    if problem:
        op.report({"ERROR"}, problem)
        return None, None
    try:
        return obj, deformer_at(obj, op.index)
    except LookupError as exc:
        op.report({"ERROR"}, str(exc))
        return None, None


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
    deformer (`target_problem`)."""

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        problem = target_problem(active_target(context))
        if problem:
            cls.poll_message_set(problem)
        return not problem
