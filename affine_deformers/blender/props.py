"""Property groups: the deformer stack stored on each Object as `Object.affine_deformers`.

Weight options (mode, radius, exponent, normalisation, influences, per-probe scale, cage weights)
re-weight the bound deformer immediately from its stored rest data: the artist sees the change live
and the rest pose is kept (re-weighting never makes the current probe poses the new rest; only Bind
does that).
Strength and blend mode act per frame and need no re-weighting.
"""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from . import binding, kinds, nodes, relations, storage, weight_groups, weight_preview
from .kinds import KindId

IDENTITY16 = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)

ROTATION_MODES = [
    ("QUATERNION", "Quaternion", ""),
    ("XYZ", "XYZ Euler", ""),
    ("XZY", "XZY Euler", ""),
    ("YXZ", "YXZ Euler", ""),
    ("YZX", "YZX Euler", ""),
    ("ZXY", "ZXY Euler", ""),
    ("ZYX", "ZYX Euler", ""),
    ("AXIS_ANGLE", "Axis Angle", ""),
]


def _on_cage_object(self: AffineDeformer, _context: bpy.types.Context) -> None:
    # A newly picked cage is bound at its current shape (like a newly picked probe).
    obj = self.id_data
    if binding.updates_suspended() or not isinstance(obj, bpy.types.Object) or self.kind != KindId.CAGE:
        return
    # A deformer bound before (even if the last pick failed to bind, e.g. a curve) binds the new cage,
    # so the status speaks of it, not of the object picked before.
    if self.cage is not None and (self.is_bound or self.bind_generation > 0):
        binding.rebind_safely(obj, self, "the new cage")
    else:
        relations.sync(obj, self)  # a cleared cage is no longer evaluated for this deformer


def _get_cage_weights(self: AffineDeformer) -> int:
    # Unset: 'HARMONIC' (0), except for a deformer bound before the option existed, whose stored
    # weights are inverse-distance ones (no grid nodes): it keeps them until switched or rebound.
    value = self.get("cage_weights_mode")
    if value is None:
        return 1 if self.bound_flag and self.kind == KindId.CAGE and "cage_node_points" not in self else 0
    return int(value)


def _set_cage_weights(self: AffineDeformer, value: int) -> None:
    self["cage_weights_mode"] = int(value)


def _poll_cage(self: AffineDeformer, candidate: bpy.types.Object) -> bool:
    return candidate.type == "MESH" and candidate != self.id_data


def _search_vertex_groups(self: AffineDeformer, _context: bpy.types.Context, _text: str) -> list[str]:
    obj = self.id_data
    return [g.name for g in obj.vertex_groups] if isinstance(obj, bpy.types.Object) else []


def _owner_deformer(item) -> tuple[bpy.types.Object, AffineDeformer, int] | None:
    """The object and deformer holding a probe or bone item, and its index (property groups do not
    know their parent)."""
    obj = item.id_data
    path = item.path_from_id()  # 'affine_deformers[i].probes[j]' or '….bones[j]'
    collection = next((c for c in (".probes[", ".bones[") if c in path), None)
    if not isinstance(obj, bpy.types.Object) or collection is None:
        return None
    deformer_path, index = path.rsplit(collection, 1)
    return obj, obj.path_resolve(deformer_path), int(index.rstrip("]"))


def _reweight(deformer: AffineDeformer) -> None:
    obj = deformer.id_data
    if binding.updates_suspended():
        return
    if deformer.is_bound and isinstance(obj, bpy.types.Object):
        binding.reweight_safely(obj, deformer)


def _on_weight_option(self: AffineDeformer, _context: bpy.types.Context) -> None:
    _reweight(self)


def _on_evaluation_option(self: AffineDeformer, _context: bpy.types.Context) -> None:
    # Python-defined properties do not tag their ID: tag it so the depsgraph handler re-evaluates.
    obj = self.id_data
    if isinstance(obj, bpy.types.Object):
        obj.update_tag()


def _on_probe_weight_option(self: AffineDeformerProbe, _context: bpy.types.Context) -> None:
    owner = _owner_deformer(self)
    if owner is not None:
        _reweight(owner[1])


def _on_probe_object(self: AffineDeformerProbe, _context: bpy.types.Context) -> None:
    # A newly picked probe object starts at rest: its current pose becomes its rest pose.
    owner = _owner_deformer(self)
    if binding.updates_suspended() or owner is None:
        return
    obj, deformer, index = owner
    if deformer.is_bound and self.object is not None:
        binding.rebind_probe_safely(obj, deformer, index)
    else:
        relations.sync(obj, deformer)


def _on_probe_group(self: AffineDeformerProbe, _context: bpy.types.Context) -> None:
    # Another painted group: re-weight, but only when the weights are painted ones.
    owner = _owner_deformer(self)
    if owner is not None and owner[1].weight_mode == "VERTEX_GROUPS":
        _reweight(owner[1])


def _on_show_weights(self: AffineDeformer, _context: bpy.types.Context) -> None:
    weight_preview.on_show_weights(self)


def _on_preview_option(self: AffineDeformer, _context: bpy.types.Context) -> None:
    weight_preview.on_option(self)


class AffineDeformerProbe(bpy.types.PropertyGroup):
    """One probe: a control object and its rest pose in the target's local space (float32, as stored)."""

    object: PointerProperty(
        name="Probe", type=bpy.types.Object, update=_on_probe_object,
        description="Object whose motion drives the deformation (a new pick is bound at its current pose)")
    rest_matrix: FloatVectorProperty(
        name="Rest Matrix", size=16, default=IDENTITY16,
        description="Probe matrix at bind, in the target's local space (row-major 4x4)")
    rest_rotation_mode: EnumProperty(
        name="Rest Rotation Mode", items=ROTATION_MODES, default="XYZ",
        description="Rotation mode of the probe at bind")
    rest_rotation: FloatVectorProperty(
        name="Rest Rotation", size=4, default=(0.0, 0.0, 0.0, 0.0),
        description="Rotation channels at bind: quaternion WXYZ, axis-angle (angle, X, Y, Z) or Euler XYZ")
    weight_scale: FloatProperty(
        name="Weight Scale", default=1.0, min=0.0, soft_max=4.0, update=_on_probe_weight_option,
        description="Multiplies this probe's raw weight before normalisation")
    vertex_group: StringProperty(
        name="Vertex Group", search=_search_vertex_groups, update=_on_probe_group,
        description="Vertex group holding this probe's painted weights (Weights: Vertex Groups); empty: "
                    "the group named after the probe. Renaming the probe renames its group with it")
    state: EnumProperty(
        name="State", items=weight_groups.PROBE_STATES, default="AT_REST",
        description="What the probe does at the last update (set by the add-on)")


class AffineDeformerBone(bpy.types.PropertyGroup):
    """One bone control of a bone deformer: `name` is the bone's name in the deformer's armature (its
    painted weights are the vertex group of that name, as the Armature modifier reads them)."""

    weight_scale: FloatProperty(
        name="Weight Scale", default=1.0, min=0.0, soft_max=4.0, update=_on_probe_weight_option,
        description="Multiplies this bone's raw weight before normalisation")


def _poll_armature(self: AffineDeformer, candidate: bpy.types.Object) -> bool:
    return candidate.type == "ARMATURE"


def _on_armature(self: AffineDeformer, _context: bpy.types.Context) -> None:
    # A newly picked armature is bound at once (its deform bones become the controls).
    obj = self.id_data
    if binding.updates_suspended() or not isinstance(obj, bpy.types.Object) or self.kind != KindId.BONE:
        return
    if self.armature is not None and (self.is_bound or self.bind_generation > 0):
        binding.rebind_safely(obj, self, "the new armature")
    else:
        relations.sync(obj, self)


def _modifier(deformer: AffineDeformer) -> bpy.types.Modifier | None:
    obj = deformer.id_data
    if not isinstance(obj, bpy.types.Object) or not deformer.uid:
        return None
    return nodes.find_modifier(obj, storage.offset_name(deformer.uid))


def _mirrored_getter(flag: str):
    def get(self: AffineDeformer) -> bool:
        mod = _modifier(self)
        return getattr(mod, flag) if mod is not None else bool(self.get(f"stored_{flag}", True))
    return get


def _mirrored_setter(flag: str):
    def set_(self: AffineDeformer, value: bool) -> None:
        self[f"stored_{flag}"] = bool(value)
        mod = _modifier(self)
        if mod is not None and getattr(mod, flag) != bool(value):
            setattr(mod, flag, bool(value))
    return set_


class AffineDeformer(bpy.types.PropertyGroup):
    """One deformer on the object (`name` comes from PropertyGroup)."""

    uid: StringProperty(
        name="ID", options={"HIDDEN"},
        description="Stable short id used in the names of the deformer's mesh attributes")
    kind: EnumProperty(
        name="Kind", items=kinds.enum_items(), default=kinds.REGISTERED[0].id)
    probes: CollectionProperty(type=AffineDeformerProbe)
    active_probe_index: IntProperty(name="Active Probe", default=0, min=0, update=_on_preview_option)
    armature: PointerProperty(
        name="Armature", type=bpy.types.Object, poll=_poll_armature, update=_on_armature,
        description="Armature whose pose bones drive the target (its deform bones, at their rest pose "
                    "in Edit Mode, are the rest)")
    bones: CollectionProperty(type=AffineDeformerBone)
    active_bone_index: IntProperty(name="Active Bone", default=0, min=0, update=_on_preview_option)
    cage: PointerProperty(
        name="Cage", type=bpy.types.Object, poll=_poll_cage, update=_on_cage_object,
        description="Closed mesh with outward normals whose faces drive the target (a new pick is bound "
                    "at its current shape)")
    cage_rest_matrix: FloatVectorProperty(
        name="Cage Rest Matrix", size=16, default=IDENTITY16,
        description="Cage object matrix at bind, in the target's local space (row-major 4x4)")
    cage_rest_rotation_mode: EnumProperty(
        name="Cage Rest Rotation Mode", items=ROTATION_MODES, default="XYZ",
        description="Rotation mode of the cage object at bind")
    cage_rest_rotation: FloatVectorProperty(
        name="Cage Rest Rotation", size=4, default=(0.0, 0.0, 0.0, 0.0),
        description="Rotation channels of the cage object at bind: quaternion WXYZ, axis-angle "
                    "(angle, X, Y, Z) or Euler XYZ (unset in files bound before they were stored: the "
                    "cage's turns then take the shortest way)")
    half_space: BoolProperty(
        name="Half-Space Rule", default=True, update=_on_weight_option,
        description="A cage face has no influence on vertices outside it (in its outer half-space): "
                    "keeps opposite sides of a thin part apart")
    cage_weights: EnumProperty(
        name="Cage Weights", get=_get_cage_weights, set=_set_cage_weights, update=_on_weight_option,
        items=[("HARMONIC", "Harmonic",
                "Smooth, local weights solved inside the cage on a grid (like Mesh Deform): a local "
                "edit of the cage moves the mesh near it smoothly", 0),
               ("INVERSE_DISTANCE", "Inverse Distance",
                "Inverse distance to each face with the half-space rule, Exponent and Max Influences "
                "(the weights of version 0.1)", 1)],
        description="How the cage's faces are weighted on the target (changing it re-weights)")
    weight_mode: EnumProperty(
        name="Weights", default="INVERSE_DISTANCE", update=_on_weight_option,
        items=[("INVERSE_DISTANCE", "Inverse Distance",
                "Weight (Radius/distance)^Exponent to each probe at rest"),
               ("FALLOFF", "Falloff", "Smooth falloff reaching zero at Radius from each probe at rest"),
               ("VERTEX_GROUPS", "Vertex Groups",
                "Painted weights from the vertex groups named after the probes"),
               ("SURFACE", "Surface (Harmonic)",
                "Harmonic weights along the mesh surface (cotangent Laplacian): each probe fully moves "
                "the surface clearly closest to it and influence spreads only along the surface, so it "
                "does not jump across gaps (fingers, lips). Exponent sharpens them. Loose parts without "
                "a probe use inverse distance (the status says so)"),
               ])
    radius: FloatProperty(
        name="Radius", default=1.0, min=1e-6, soft_max=100.0, subtype="DISTANCE", unit="LENGTH",
        update=_on_weight_option,
        description="Falloff: where a probe's weight reaches zero. Inverse distance: where it is 1")
    exponent: FloatProperty(
        name="Exponent", default=2.0, min=0.01, soft_max=8.0, update=_on_weight_option,
        description="Inverse distance power, and the power Surface weights are raised to: larger "
                    "values localise each probe's influence")
    normalize: EnumProperty(
        name="Normalize", default="SUM", update=_on_weight_option,
        items=[("NONE", "None", "Use raw weights (where they are small the mesh stays put)"),
               ("SUM", "Sum", "Weights of each vertex sum to 1: a motion shared by all probes is exact"),
               ("SOFTMAX", "Softmax", "Softmax of the raw weights")])
    mask_group: StringProperty(
        name="Mask", search=_search_vertex_groups, update=_on_weight_option,
        description="Vertex group scaling each vertex's weights (empty: no mask). Repainting needs a "
                    "re-weight: change an option or rebind")
    strength: FloatProperty(
        name="Strength", default=1.0, min=0.0, soft_max=1.0, max=10.0, subtype="FACTOR",
        update=_on_evaluation_option,
        description="Scales every weight (0 = rest shape)")
    max_influences: IntProperty(
        name="Max Influences", default=4, min=1, max=16, update=_on_weight_option,
        description="Number of strongest controls kept per vertex")
    blend_mode: EnumProperty(
        name="Blend", default="AFFINE_LOG", update=_on_evaluation_option,
        items=[("AFFINE_LOG", "Affine (Log)", "Blend in the Aff+(3) parameter space: no collapse"),
               ("LINEAR", "Linear", "Blend the matrices linearly (for comparison)")])
    branch_rule: EnumProperty(
        name="Turns", default="CHANNELS", update=_on_evaluation_option,
        items=[("CHANNELS", "Follow Rotation Channels",
                "A probe (or a cage object, at a strength other than 1) turned past 180° twists by the "
                "full angle of its own rotation channels since bind (Rotation Z = 400° twists 400°); "
                "turns from parents or constraints take the nearest way. Quaternion channels hold at "
                "most one turn. After a rotation mode change turns are counted from the rest "
                "orientation in the new mode"),
               ("SHORTEST", "Shortest",
                "Every probe or cage object motion is blended as its shortest rotation (at most 180°): "
                "a twist flips when it passes 180°")])
    show_viewport: BoolProperty(
        name="Viewport", get=_mirrored_getter("show_viewport"), set=_mirrored_setter("show_viewport"),
        description="Show the deformer in the viewport (mirrors the modifier's toggle)")
    show_render: BoolProperty(
        name="Render", get=_mirrored_getter("show_render"), set=_mirrored_setter("show_render"),
        description="Use the deformer in renders (mirrors the modifier's toggle)")
    bound_flag: BoolProperty(options={"HIDDEN"}, default=False)
    is_bound: BoolProperty(
        name="Bound", get=lambda self: self.bound_flag, description="Rest data and weights are stored")
    status: StringProperty(name="Status", description="Last error or warning ('' when fine)")
    bind_warning: StringProperty(options={"HIDDEN"}, description="Warning left by the last (re)weighting")
    bound_vertex_count: IntProperty(name="Bound Vertices", default=0, min=0)
    bound_topology: StringProperty(
        options={"HIDDEN"},
        description="CRCs of the connectivity and of the rest positions at bind (weights belong to "
                    "vertex indices; empty in files bound before it was stored)")
    bind_generation: IntProperty(
        options={"HIDDEN"}, default=0, description="Bumped at every (re)weighting: evaluation cache key")
    show_weights: BoolProperty(
        name="Show Weights", default=False, update=_on_show_weights,
        description="Show this deformer's weights as vertex colours in the viewport (Solid shading, "
                    "Color: Attribute). Viewport only: renders and the deformation are unchanged, and "
                    "turning it off removes every trace. One deformer per object at a time")
    weight_preview: EnumProperty(
        name="Weight Preview", default="ACTIVE", update=_on_preview_option,
        items=[("ACTIVE", "Active Control",
                "The weight of the active probe or bone (or of one cage face) on the weight-paint colours: "
                "blue 0, green 0.5, red 1"),
               ("ALL", "All Controls",
                "Every control in its own colour, mixed by the weights (dark: a share no control moves)")])
    weight_preview_face: IntProperty(
        name="Preview Face", default=-1, min=-1, update=_on_preview_option,
        description="Cage face whose weights the preview shows (-1: the cage mesh's active face, picked "
                    "in its Edit Mode)")
    weight_preview_fit: BoolProperty(
        name="Fit Range", default=False, update=_on_preview_option,
        description="Stretch the colours from 0 to the largest weight shown instead of 0 to 1 (one face "
                    "of a cage, or a weak probe, is otherwise all blue)")


CLASSES = (AffineDeformerProbe, AffineDeformerBone, AffineDeformer)


def register_properties() -> None:
    bpy.types.Object.affine_deformers = CollectionProperty(type=AffineDeformer)
    bpy.types.Object.affine_deformers_active_index = IntProperty(name="Active Deformer", default=0, min=0)


def unregister_properties() -> None:
    for name in ("affine_deformers_active_index", "affine_deformers"):
        if hasattr(bpy.types.Object, name):
            delattr(bpy.types.Object, name)
