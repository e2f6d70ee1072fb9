"""Property groups: the deformer stack stored on each Object as `Object.affine_deformers`.

`AffineDeformer` holds the options every kind shares; each kind adds its own properties (its
controls, their rest data, its options: `DeformerKind.properties`), merged into the class's
annotations before it is registered, so their RNA paths (`deformer.probes`, `deformer.cage`, …) are
those of the saved files. The kinds' control item groups are registered before it (kinds.CLASSES).

Weight options (mode, radius, exponent, normalisation, influences, per-control scale, cage weights)
re-weight the bound deformer immediately from its stored rest data: the artist sees the change live
and the rest pose is kept (re-weighting never makes the current control poses the new rest; only
Bind does that). Strength and blend mode act per frame and need no re-weighting.
"""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    StringProperty,
)

from ..core import arap
from . import kinds
from .files import nodes, storage
from .kinds.base import OVERRIDABLE
from .kinds.services import on_preview_option, on_weight_option, search_vertex_groups
from .tools import weight_preview


def _on_evaluation_option(self: AffineDeformer, _context: bpy.types.Context) -> None:
    # Python-defined properties do not tag their ID: tag it so the depsgraph handler re-evaluates.
    obj = self.id_data
    if isinstance(obj, bpy.types.Object):
        obj.update_tag()


def _on_show_weights(self: AffineDeformer, _context: bpy.types.Context) -> None:
    weight_preview.on_show_weights(self)


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
    weight_mode: EnumProperty(
        name="Weights", default="INVERSE_DISTANCE", update=on_weight_option,
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
        update=on_weight_option,
        description="Falloff: where a probe's weight reaches zero. Inverse distance: where it is 1")
    exponent: FloatProperty(
        name="Exponent", default=2.0, min=0.01, soft_max=8.0, update=on_weight_option,
        description="Inverse distance power, and the power Surface weights are raised to: larger "
                    "values localise each probe's influence")
    normalize: EnumProperty(
        name="Normalize", default="SUM", update=on_weight_option,
        items=[("NONE", "None", "Use raw weights (where they are small the mesh stays put)"),
               ("SUM", "Sum", "Weights of each vertex sum to 1: a motion shared by all probes is exact"),
               ("SOFTMAX", "Softmax", "Softmax of the raw weights")])
    mask_group: StringProperty(
        name="Mask", search=search_vertex_groups, update=on_weight_option,
        description="Vertex group scaling each vertex's weights (empty: no mask). Repainting needs a "
                    "re-weight: change an option or rebind")
    strength: FloatProperty(
        name="Strength", override=OVERRIDABLE, default=1.0, min=0.0, soft_max=1.0, max=10.0, subtype="FACTOR",
        update=_on_evaluation_option,
        description="Scales every weight (0 = rest shape)")
    max_influences: IntProperty(
        name="Max Influences", default=4, min=1, max=16, update=on_weight_option,
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
    preserve_shape: BoolProperty(
        name="Preserve Shape", default=False, override=OVERRIDABLE, update=_on_evaluation_option,
        description="After the blend, solve for the vertex positions whose triangles best follow the "
                    "blended maps, the vertices nearest the controls held in place: keeps volume and "
                    "detail under large bends and twists. The first update factors the mesh's system "
                    "once (seconds on a large mesh); each update is then one solve")
    shape_iterations: IntProperty(
        name="Iterations", default=1, min=1, max=5, override=OVERRIDABLE, update=_on_evaluation_option,
        description="Preserve Shape: each further iteration keeps the blended stretch and takes the "
                    "rotations from the previous solve (stiffer under large bends; one solve each)")
    shape_anchor: FloatProperty(
        name="Anchor Strength", default=arap.ANCHOR_STRENGTH, min=0.0, soft_max=1000.0,
        override=OVERRIDABLE, update=_on_evaluation_option,
        description="Preserve Shape: how firmly the vertices nearest each control keep the per-vertex "
                    "field's positions (changing it factors the system again)")
    show_viewport: BoolProperty(
        name="Viewport", get=_mirrored_getter("show_viewport"), set=_mirrored_setter("show_viewport"),
        description="Show the deformer in the viewport (mirrors the modifier's toggle)")
    show_render: BoolProperty(
        name="Render", get=_mirrored_getter("show_render"), set=_mirrored_setter("show_render"),
        description="Use the deformer in renders (mirrors the modifier's toggle)")
    bake_record: StringProperty(
        options={"HIDDEN"}, override=OVERRIDABLE,
        description="What the last bake created, as JSON, on library overrides (whose ID properties "
                    "on library items are not saved): read by Un-bake")
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
        name="Weight Preview", default="ACTIVE", update=on_preview_option,
        items=[("ACTIVE", "Active Control",
                "The weight of the active probe or bone (or of one cage face) on the weight-paint colours: "
                "blue 0, green 0.5, red 1"),
               ("ALL", "All Controls",
                "Every control in its own colour, mixed by the weights (dark: a share no control moves)")])
    weight_preview_fit: BoolProperty(
        name="Fit Range", default=False, update=on_preview_option,
        description="Stretch the colours from 0 to the largest weight shown instead of 0 to 1 (one face "
                    "of a cage, or a weak probe, is otherwise all blue)")


def _kind_property(name: str):
    """The bpy.props definition of the kind property `name`, made anew whenever Blender evaluates its
    annotation (at each registration) and not kept, like this module's own annotations (strings, by
    `from __future__ import annotations`): a definition with an update callback still alive when the
    interpreter exits crashes bpy 4.2 (as a module) there."""
    return kinds.properties()[name].prop


def _add_kind_properties() -> None:
    """Add every kind's own properties to AffineDeformer's annotations (before registration), as
    expressions evaluated in this module like the others."""
    annotations = AffineDeformer.__annotations__
    for name in kinds.properties():
        if name in annotations:
            raise ValueError(f"Kind property '{name}' would replace a common deformer property")
        annotations[name] = f"_kind_property({name!r})"


_add_kind_properties()

CLASSES = (AffineDeformer,)


def register_properties() -> None:
    # Overridable, as is every control pointer below it (the kinds' properties): a library override
    # of the rig then keeps its deformers' controls pointed at the overridden controls (carrier.py).
    bpy.types.Object.affine_deformers = CollectionProperty(type=AffineDeformer, override=OVERRIDABLE)
    bpy.types.Object.affine_deformers_active_index = IntProperty(name="Active Deformer", default=0, min=0)


def unregister_properties() -> None:
    for name in ("affine_deformers_active_index", "affine_deformers"):
        if hasattr(bpy.types.Object, name):
            delattr(bpy.types.Object, name)
