"""What the artist handles of a bone deformer (kinds/bone.py is the kind): the bone items
(`AffineDeformerBone`, the deformer's `bones`), the operators that add and remove bones, and the bone
list. Converting an Armature modifier into a bone deformer: kinds/armature_convert.py.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.props import FloatProperty, IntProperty, StringProperty

from ..ui.addressing import DeformerIndexed, active_target, addressed_deformer
from ..update.validation import coordinates_problem, stored_array
from .base import BindError
from .services import on_item_weight_option, services

BONE = "BONE"  # the kind's id (kinds.bone.BoneKind.id)
#: Max Influences of a new bone deformer (painted weights keep their K largest: as many bones as a
#: vertex of a typical skin is painted with).
DEFAULT_INFLUENCES = 8


def deform_bones(armature: bpy.types.Object) -> list[str]:
    """The names of the armature's deform bones, in its bone order."""
    return [bone.name for bone in armature.data.bones if bone.use_deform]


class AffineDeformerBone(bpy.types.PropertyGroup):
    """One bone control of a bone deformer: `name` is the bone's name in the deformer's armature (its
    painted weights are the vertex group of that name, as the Armature modifier reads them)."""

    weight_scale: FloatProperty(
        name="Weight Scale", default=1.0, min=0.0, soft_max=4.0, update=on_item_weight_option,
        description="Multiplies this bone's raw weight before normalisation")


def _bone_deformer(op: bpy.types.Operator, context: bpy.types.Context):
    """(object, deformer) like `addressed_deformer`, refusing (reported) a deformer that is not a bone one."""
    obj, deformer = addressed_deformer(op, context)
    if deformer is not None and deformer.kind != BONE:
        op.report({"ERROR"}, f"'{deformer.name}' is not a bone deformer")
        return None, None
    return obj, deformer


def _refresh(context: bpy.types.Context, obj: bpy.types.Object) -> None:
    """Evaluate at once so status and offsets are current when the operator returns."""
    services().evaluate(obj, context.evaluated_depsgraph_get())


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
        provided = services()
        with provided.quiet():
            deformer.bones.add().name = self.bone
        try:
            provided.bind(obj, deformer, context.evaluated_depsgraph_get())
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
            services().bind(obj, deformer, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _refresh(context, obj)
        self.report({"INFO"}, f"Removed bone '{name}' from '{deformer.name}'")
        return {"FINISHED"}


class AFFINE_UL_bones(bpy.types.UIList):
    """The bones of a bone deformer: name (a missing bone is flagged) and weight scale."""

    def draw_item(self, _context, layout, data, item, _icon, _active_data, _active_prop, _index=0):
        row = layout.row(align=True)
        armature = data.armature
        found = armature is not None and armature.data.bones.get(item.name) is not None
        if found:
            row.label(text=item.name, icon="BONE_DATA")
        else:
            row.label(text=f"{item.name} (missing)", icon="ERROR")
        row.prop(item, "weight_scale", text="")


def draw_controls(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """The bone list with its add / remove buttons."""
    layout.label(text=f"Bones ({len(deformer.bones)})")
    row = layout.row()
    row.template_list(AFFINE_UL_bones.__name__, "", deformer, "bones", deformer, "active_bone_index", rows=3)
    col = row.column(align=True)
    col.operator(AFFINE_OT_deformer_bone_add.bl_idname, icon="ADD", text="").index = index
    op = col.operator(AFFINE_OT_deformer_bone_remove.bl_idname, icon="REMOVE", text="")
    op.index, op.bone_index = index, deformer.active_bone_index


CLASSES = (AffineDeformerBone, AFFINE_OT_deformer_bone_add, AFFINE_OT_deformer_bone_remove, AFFINE_UL_bones)


REST_SEGMENTS = "bone_rest_segments"  # ID property: (m, 2, 3) float64 heads and tails, target space


def stored_segments(deformer) -> tuple[np.ndarray | None, str]:
    """(the bones' stored rest segments (m, 2, 3) — heads, tails in the target's space —, '') or
    (None, what is damaged: not a float array of 6 values per bone, or a coordinate that is not
    finite or not below MAX_COORDINATE in magnitude)."""
    stored, problem = stored_array(deformer, REST_SEGMENTS, integer=False)
    if not problem and stored.size != 6 * len(deformer.bones):
        problem = f"'{REST_SEGMENTS}' holds {stored.size} values for {len(deformer.bones)} bones (6 each)"
    if not problem:
        problem = coordinates_problem(f"'{REST_SEGMENTS}'", stored)
    if problem:
        return None, f"The bone deformer's rest data is damaged ({problem})"
    return stored.reshape(-1, 2, 3), ""


#: A stored rest segment and a bone's current one match within this share of the segments' extent.
RENAME_MATCH = 1e-4


def follow_renames(obj: bpy.types.Object, deformer) -> None:
    """Follow bones renamed in the armature (B1 → Forearm, as riggers name sides): each item whose
    bone is gone takes the name of the deform bone no item names whose rest segment, carried into the
    target's space by the objects' current transforms, is its stored one (`stored_segments`, read
    only when a bone is missing); a lone missing item and a
    lone unnamed deform bone match without it. Its vertex group follows too where Blender did not
    rename it (a mesh without an Armature modifier or parent of that armature). Runs before every
    update; costs a dict lookup per bone when nothing was renamed."""
    armature = deformer.armature
    if armature is None or armature.type != "ARMATURE":
        return
    bones = armature.data.bones
    missing = [i for i, item in enumerate(deformer.bones) if bones.get(item.name) is None]
    if not missing:
        return
    named = {item.name for item in deformer.bones}
    free = [name for name in deform_bones(armature) if name not in named]
    if not free:
        return
    found: dict[int, str] = {}
    segments = stored_segments(deformer)[0]
    if segments is not None and len(segments) == len(deformer.bones):
        try:
            frame = np.linalg.solve(np.array(obj.matrix_world), np.array(armature.matrix_world))
        except np.linalg.LinAlgError:
            frame = None
        if frame is not None:
            extent = max(float(np.ptp(segments.reshape(-1, 3), axis=0).max()), 1e-9)
            for i in missing:
                for name in free:
                    bone = bones[name]
                    now = np.array([frame[:3, :3] @ np.array(point) + frame[:3, 3]
                                    for point in (bone.head_local, bone.tail_local)])
                    close = np.abs(now - segments[i]).max() <= RENAME_MATCH * extent
                    if close and name not in found.values():
                        found[i] = name
                        break
    if not found and len(missing) == 1 and len(free) == 1:
        found[missing[0]] = free[0]
    groups = obj.vertex_groups
    for i, name in found.items():
        item = deformer.bones[i]
        old = item.name
        group = groups.get(old)
        if group is not None and groups.get(name) is None:
            group.name = name
        item.name = name
