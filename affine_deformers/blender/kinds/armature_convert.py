"""Upgrade an Armature modifier to a bone deformer (kinds/bone.py), and back: the bone kind's.

Convert: a bone deformer with the modifier's armature, its deform bones and the vertex groups named
after them (as the Armature modifier reads them: weights normalised per vertex), its mask group, in
the modifier's place in the stack (directly below it); the Armature modifier is kept but disabled in
the viewport and in renders, so the artist can compare by toggling the two. Restore: the Armature
modifier gets its toggles back and the bone deformer is removed.
"""

from __future__ import annotations

import bpy
from bpy.props import StringProperty

from ..files import nodes, storage
from ..ui.addressing import (
    UNDOABLE,
    DeformerIndexed,
    active_target,
    deformer_at,
    deformer_index,
    target_problem,
)
from .base import BindError
from .bone_tools import BONE, DEFAULT_INFLUENCES, deform_bones
from .services import services

CONVERTED_KEY = "affdef_converted_from"  # ID property on the deformer item: the modifier and its toggles


def armature_modifiers(obj: bpy.types.Object | None) -> list[bpy.types.Modifier]:
    """The object's Armature modifiers that name an armature."""
    if obj is None or obj.type != "MESH":
        return []
    return [m for m in obj.modifiers if m.type == "ARMATURE" and m.object is not None]


def convert(obj: bpy.types.Object, modifier: bpy.types.Modifier, depsgraph: bpy.types.Depsgraph):
    """Add the bone deformer replacing `modifier` (see the module docstring); returns (deformer,
    warnings). BindError, with nothing changed, when it cannot be made."""
    problem = target_problem(obj)
    if problem:
        raise BindError(problem)
    armature = modifier.object
    if armature is None:
        raise BindError(f"'{modifier.name}' names no armature")
    if not modifier.use_vertex_groups:
        raise BindError(f"'{modifier.name}' deforms by bone envelopes only: the bone deformer reads vertex "
                        "groups (enable Vertex Groups on it, or add a bone deformer with distance weights)")
    if not deform_bones(armature):
        raise BindError(f"Armature '{armature.name}' has no deform bones")
    warnings = []
    if modifier.use_bone_envelopes:
        warnings.append(f"'{modifier.name}' also uses bone envelopes: the bone deformer reads only the "
                        "vertex groups")
    if modifier.vertex_group and modifier.invert_vertex_group:
        warnings.append(f"'{modifier.name}' inverts its mask group: the bone deformer masks without "
                        "inverting")
    provided = services()
    deformer = provided.create(obj, BONE, f"{modifier.name} (Affine)")
    with provided.quiet():  # bound below in one go
        deformer.armature = armature
        for name in deform_bones(armature):
            deformer.bones.add().name = name
        deformer.weight_mode = "VERTEX_GROUPS"
        deformer.normalize = "SUM"
        deformer.max_influences = DEFAULT_INFLUENCES
        deformer.mask_group = modifier.vertex_group
    try:
        provided.bind(obj, deformer, depsgraph)
    except (BindError, ValueError):
        provided.remove(obj, deformer_index(obj, deformer))
        raise
    take_over(obj, deformer, modifier)
    return deformer, warnings


def take_over(obj: bpy.types.Object, deformer, modifier: bpy.types.Modifier) -> None:
    """Put the bound bone deformer's modifier directly below the Armature modifier `modifier` and turn
    that off (kept, so Restore can turn it back on), so the mesh is not deformed twice."""
    ours = nodes.find_modifier(obj, storage.offset_name(deformer.uid))
    stack = list(obj.modifiers)
    if ours is not None:
        obj.modifiers.move(stack.index(ours), stack.index(modifier) + 1)
    deformer[CONVERTED_KEY] = {"modifier": modifier.name, "show_viewport": bool(modifier.show_viewport),
                               "show_render": bool(modifier.show_render)}
    modifier.show_viewport = modifier.show_render = False


def take_over_doubling(obj: bpy.types.Object, deformer, armature: bpy.types.Object) -> str:
    """After a bone deformer was added and bound: an enabled Armature modifier of the same armature
    would deform the mesh a second time, so the deformer takes its place as Convert does (`take_over`;
    'Back to' undoes it). Returns what to add to the add operator's report."""
    replaced = doubling_modifiers(obj, armature)
    if not replaced:
        return ""
    take_over(obj, deformer, replaced[0])
    return (f"; '{replaced[0].name}' is turned off (it would deform the mesh a second time; 'Back to' "
            "turns it on again)")


def modifier_armature(target: bpy.types.Object) -> bpy.types.Object | None:
    """The armature of `target`'s first enabled Armature modifier that names one (None: none)."""
    for mod in target.modifiers:
        if mod.type == "ARMATURE" and mod.object is not None and (mod.show_viewport or mod.show_render):
            return mod.object
    return None


def doubling_modifiers(obj: bpy.types.Object, armature: bpy.types.Object | None) -> list[bpy.types.Modifier]:
    """The enabled (viewport or render) Armature modifiers of `obj` that name `armature`: beside a bone
    deformer of the same armature they deform the mesh a second time."""
    if armature is None or obj.type != "MESH":
        return []
    return [m for m in obj.modifiers if m.type == "ARMATURE" and m.object == armature
            and (m.show_viewport or m.show_render)]


def doubling_warning(obj: bpy.types.Object, armature: bpy.types.Object | None) -> str:
    """The status naming an Armature modifier that deforms by the same armature as a bone deformer
    ('' when there is none)."""
    doubled = doubling_modifiers(obj, armature)
    if not doubled:
        return ""
    names = ", ".join(f"'{m.name}'" for m in doubled)
    return (f"The Armature modifier {names} also deforms '{obj.name}' by '{armature.name}': the mesh is "
            "deformed twice (turn it off, or add the bone deformer with Convert)")


def restore(obj: bpy.types.Object, index: int) -> str:
    """Give the Armature modifier a converted deformer replaced its toggles back and remove the
    deformer; returns a summary. BindError when the deformer was not converted or its modifier is gone."""
    deformer = deformer_at(obj, index)
    state = deformer.get(CONVERTED_KEY)
    if state is None:
        raise BindError(f"'{deformer.name}' was not converted from an Armature modifier")
    modifier = obj.modifiers.get(state["modifier"])
    if modifier is None or modifier.type != "ARMATURE":
        raise BindError(f"The Armature modifier '{state['modifier']}' is gone: remove the deformer instead")
    modifier.show_viewport = bool(state["show_viewport"])
    modifier.show_render = bool(state["show_render"])
    name = deformer.name
    services().remove(obj, index)
    return f"Removed '{name}' and turned '{modifier.name}' back on"


class AFFINE_OT_armature_convert(bpy.types.Operator):
    """Replace an Armature modifier with an affine bone deformer (same armature, vertex groups and stack
    position); the Armature modifier is kept, disabled, to compare"""

    bl_idname = "object.affine_armature_convert"
    bl_label = "Convert Armature Modifier"
    bl_options = UNDOABLE

    modifier: StringProperty(name="Modifier",
                             description="The Armature modifier to convert (empty: the first)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        obj = active_target(context)
        problem = target_problem(obj)
        if not problem and not armature_modifiers(obj):
            problem = f"'{obj.name}' has no Armature modifier with an armature"
        if problem:
            cls.poll_message_set(problem)
        return not problem

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj = active_target(context)
        problem = target_problem(obj)
        if problem:
            self.report({"ERROR"}, problem)
            return {"CANCELLED"}
        candidates = armature_modifiers(obj)
        modifier = next((m for m in candidates if m.name == self.modifier), None) if self.modifier else (
            candidates[0] if candidates else None)
        if modifier is None:
            self.report({"ERROR"}, f"'{obj.name}' has no Armature modifier "
                        + (f"named '{self.modifier}'" if self.modifier else "with an armature"))
            return {"CANCELLED"}
        try:
            deformer, warnings = convert(obj, modifier, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        services().evaluate(obj, context.evaluated_depsgraph_get())
        for warning in warnings:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, f"Converted '{modifier.name}' to '{deformer.name}' ({len(deformer.bones)} "
                    f"bones); '{modifier.name}' is kept, disabled")
        return {"FINISHED"}


class AFFINE_OT_armature_restore(DeformerIndexed, bpy.types.Operator):
    """Turn the Armature modifier this bone deformer was converted from back on, and remove the deformer"""

    bl_idname = "object.affine_armature_restore"
    bl_label = "Back to the Armature Modifier"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj = active_target(context)
        try:
            summary = restore(obj, self.index)
        except (BindError, LookupError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, summary)
        return {"FINISHED"}


def draw_convert(layout: bpy.types.UILayout, obj: bpy.types.Object) -> None:
    """Convert buttons for the object's Armature modifiers (nothing when it has none)."""
    for modifier in armature_modifiers(obj):
        if modifier.show_viewport or modifier.show_render:
            layout.operator(AFFINE_OT_armature_convert.bl_idname, text=f"Convert '{modifier.name}'",
                            icon="ARMATURE_DATA").modifier = modifier.name


def draw_restore(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """The 'back' button of a deformer converted from an Armature modifier."""
    state = deformer.get(CONVERTED_KEY)
    if state is not None:
        layout.operator(AFFINE_OT_armature_restore.bl_idname, text=f"Back to '{state['modifier']}'",
                        icon="LOOP_BACK").index = index


CLASSES = (AFFINE_OT_armature_convert, AFFINE_OT_armature_restore)
