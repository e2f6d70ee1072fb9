"""What the artist handles of a probe deformer (kinds/probe.py is the kind): the probe items
(`AffineDeformerProbe`, the deformer's `probes`), their painted groups and states, the operators
that add, remove and select probes, and the probe list.

* Group names: a probe item's `vertex_group` names the group holding its painted weights (empty: the
  group named after the probe). When a probe object is renamed, `follow_renames` (before every
  update) renames its group with it, as Blender renames vertex groups with bones, unless a group of
  the new name exists (then the item keeps tracking the old group by name), and updates the item's
  `name`. `group_name` resolves the same way before that has run.
* Probe state (`AffineDeformerProbe.state`): 'AT_REST', 'MOVING', 'INVALID' or 'NO_GROUP' (painted
  weights whose group is missing), written by `record_states` from each update's motions; only
  changes are written (a write tags the object).
"""

from __future__ import annotations

import traceback

import bpy
import numpy as np
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)
from mathutils import Vector

from ...core import aff3
from .. import caches
from ..ui.addressing import DeformerIndexed, active_deformer, addressed_deformer
from ..update.validation import rest_matrix_problem
from .base import IDENTITY16, OVERRIDABLE, ROTATION_MODES, BindError
from .services import on_item_weight_option, owner, reweight, search_vertex_groups, services
from .transforms import finite_transform, in_a_scene, local_matrix, relative_motion, world_matrix

PROBE = "PROBE"  # the kind's id (kinds.probe.ProbeKind.id)

PROBE_STATES = [
    ("AT_REST", "At Rest", "The probe is at its rest pose: it does not move the mesh"),
    ("MOVING", "Moving", "The probe moved from its rest pose: it deforms the mesh"),
    ("INVALID", "Invalid", "The probe cannot be used (no object, not in a scene, the target itself, "
                           "scaled to zero, mirrored or not finite): the deformer's status says why"),
    ("NO_GROUP", "No Group", "Painted weights: the probe's vertex group is missing, so it has no "
                             "influence (paint one, or pick it in Vertex Group)"),
]
STATE_ICONS = {"AT_REST": "PAUSE", "MOVING": "PLAY", "INVALID": "ERROR", "NO_GROUP": "GROUP_VERTEX"}
STATE_TEXT = {"AT_REST": "rest", "MOVING": "moving", "INVALID": "invalid", "NO_GROUP": "no group"}


def selected_probes(context: bpy.types.Context, target: bpy.types.Object) -> tuple[list, list]:
    """Selected Empties (the probes) and the other selected non-target objects (ignored)."""
    selected = list(getattr(context, "selected_objects", None) or [])
    probes = [o for o in selected if o != target and o.type == "EMPTY"]
    ignored = [o for o in selected if o != target and o.type != "EMPTY"]
    return probes, ignored


def new_probe(context: bpy.types.Context, target: bpy.types.Object, location=None,
              name: str = "Probe") -> bpy.types.Object:
    """An Empty at `location` (world space; default the target's origin), sized to the target, in the
    target's first collection."""
    probe = bpy.data.objects.new(f"{target.name}.{name}", None)
    probe.empty_display_type = "SPHERE"
    probe.empty_display_size = max(0.1, 0.25 * max(target.dimensions))
    # unparented: location is the world position
    probe.location = target.matrix_world.translation if location is None else location
    collections = target.users_collection
    (collections[0] if collections else context.scene.collection).objects.link(probe)
    return probe


def default_probes(context: bpy.types.Context, target: bpy.types.Object) -> list[bpy.types.Object]:
    """Two new Empties at the ends of the mesh's longest axis (the centres of the two faces of its
    bounding box across the axis that is longest once the object's scale is applied): what a new
    probe deformer gets when no Empty is selected, so it deforms at once (one probe alone only moves
    the mesh rigidly)."""
    corners = np.array([tuple(c) for c in target.bound_box], dtype=np.float64)
    low, high = corners.min(axis=0), corners.max(axis=0)
    scale = np.linalg.norm(np.array(target.matrix_world, dtype=np.float64)[:3, :3], axis=0)
    axis = int(np.argmax((high - low) * scale))
    centre = (low + high) / 2.0
    ends = []
    for side, value in (("A", low[axis]), ("B", high[axis])):
        local = centre.copy()
        local[axis] = value
        ends.append(new_probe(context, target, target.matrix_world @ Vector(local), f"Probe{side}"))
    return ends


def probe_label(item) -> str:
    obj = item.object
    return obj.name if obj is not None else (item.name or "?")


def group_name(obj: bpy.types.Object, item) -> str:
    """The vertex group holding the painted weights of probe `item`: its `vertex_group`, else the
    group named after the probe — or after its former name (`item.name`) while only that exists,
    i.e. the probe was renamed and `follow_renames` has not renamed the group yet."""
    if item.vertex_group:
        return item.vertex_group
    label = probe_label(item)
    groups = obj.vertex_groups
    if groups.get(label) is None and item.name and item.name != label and groups.get(item.name) is not None:
        return item.name
    return label


def group_names(obj: bpy.types.Object, deformer) -> list[str]:
    """The painted-weight group of every probe of `deformer` (what 'VERTEX_GROUPS' reads)."""
    return [group_name(obj, item) for item in deformer.probes]


# ----------------------------------------------------------------------------------- the items


def _on_probe_object(self: AffineDeformerProbe, _context: bpy.types.Context) -> None:
    # A newly picked probe object starts at rest: its current pose becomes its rest pose.
    found = owner(self)
    provided = services()
    if provided.updates_suspended() or found is None:
        return
    obj, deformer, index = found
    if deformer.is_bound and self.object is not None:
        provided.rebind_control_safely(obj, deformer, index)
    else:
        provided.sync(obj, deformer)


def _on_probe_group(self: AffineDeformerProbe, _context: bpy.types.Context) -> None:
    # Another painted group: re-weight, but only when the weights are painted ones.
    found = owner(self)
    if found is not None and found[1].weight_mode == "VERTEX_GROUPS":
        reweight(found[1])


class AffineDeformerProbe(bpy.types.PropertyGroup):
    """One probe: a control object and its rest pose in the target's local space (float32, as stored)."""

    object: PointerProperty(
        name="Probe", override=OVERRIDABLE, type=bpy.types.Object, update=_on_probe_object,
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
        name="Weight Scale", default=1.0, min=0.0, soft_max=4.0, update=on_item_weight_option,
        description="Multiplies this probe's raw weight before normalisation")
    vertex_group: StringProperty(
        name="Vertex Group", search=search_vertex_groups, update=_on_probe_group,
        description="Vertex group holding this probe's painted weights (Weights: Vertex Groups); empty: "
                    "the group named after the probe. Renaming the probe renames its group with it")
    state: EnumProperty(
        name="State", items=PROBE_STATES, default="AT_REST",
        description="What the probe does at the last update (set by the add-on)")


def follow_renames(obj: bpy.types.Object, deformer) -> None:
    """Keep painted groups and item names in step with renamed probe objects (see module doc)."""
    groups = obj.vertex_groups
    for item in deformer.probes:
        probe = item.object
        if probe is None or probe.name == item.name:
            continue
        old, new = item.name, probe.name
        if old and (deformer.weight_mode == "VERTEX_GROUPS" or item.vertex_group):
            tracked = item.vertex_group or old
            group = groups.get(tracked)
            if group is not None and tracked == old and groups.get(new) is None:
                group.name = new  # like a bone's groups: the group follows its probe
                item.vertex_group = new
            elif group is not None and item.vertex_group != tracked:
                item.vertex_group = tracked  # a group of the new name exists: keep the painted one
        item.name = new


# ---------------------------------------------------------------------------------- probe states

#: (object session uid, deformer uid) → the inputs of the probe states written last: an unchanged
#: update (the common case: nothing at rest started moving) writes nothing and reads no item. Session
#: uids are never reused within a session, so a loaded file or an undo step cannot meet a stale entry.
_recorded: dict[caches.Key, tuple] = {}


@caches.register
def _forget(key: caches.Key | None) -> None:
    caches.drop(_recorded, key)


def _probe_state(obj: bpy.types.Object, item, target_world: np.ndarray,
                 depsgraph: bpy.types.Depsgraph) -> str:
    """'INVALID', 'AT_REST' or 'MOVING' of one probe on its own, for a deformer whose evaluation
    failed (its motions then say nothing per probe): the checks of kinds.probe.ProbeKind.current_motions."""
    probe = item.object
    if probe is None or probe == obj or not in_a_scene(probe):
        return "INVALID"
    world = world_matrix(probe, depsgraph)
    if not finite_transform(world):
        return "INVALID"
    current = local_matrix(target_world, world)
    rest = np.array(item.rest_matrix, dtype=np.float32).reshape(4, 4)
    if rest_matrix_problem("", rest, mirrored=True):  # damaged stored data: the deformer's status says how
        return "INVALID"
    if np.array_equal(current, rest):
        return "AT_REST"
    try:
        with np.errstate(all="ignore"):
            aff3.validate_affine(relative_motion(current.astype(np.float64), rest.astype(np.float64)))
    except (ValueError, np.linalg.LinAlgError):
        return "INVALID"
    return "MOVING"


def probe_states(obj: bpy.types.Object, deformer, motions, error: str,
                 depsgraph: bpy.types.Depsgraph) -> list[str] | None:
    """The state of each probe of `deformer` after an evaluation (motions: kinds.Motions or None,
    error: the evaluation's error); None when they cannot be told (the target's own transform is
    bad: the probes keep their states)."""
    m = len(deformer.probes)
    if not deformer.is_bound:
        states = ["INVALID" if item.object is None else "AT_REST" for item in deformer.probes]
    elif motions is not None and not error and not motions.warning and len(motions.at_rest) == m:
        states = ["AT_REST" if at_rest else "MOVING" for at_rest in motions.at_rest.tolist()]
    else:
        try:
            target_world = world_matrix(obj, depsgraph)
            if not finite_transform(target_world):
                return None
            states = [_probe_state(obj, item, target_world, depsgraph) for item in deformer.probes]
        except np.linalg.LinAlgError:  # the target is scaled to zero
            return None
    if deformer.weight_mode == "VERTEX_GROUPS":
        groups = obj.vertex_groups
        for i, item in enumerate(deformer.probes):
            if states[i] != "INVALID" and groups.get(group_name(obj, item)) is None:
                states[i] = "NO_GROUP"
    return states


def record_states(obj: bpy.types.Object, deformer, motions, error: str,
                  depsgraph: bpy.types.Depsgraph) -> None:
    """Store each probe's state on its item after an evaluation (only changes; never raises)."""
    try:
        key = None
        if (motions is not None and not error and not motions.warning
                and deformer.weight_mode != "VERTEX_GROUPS"):
            key = (motions.at_rest.tobytes(), deformer.bind_generation, len(deformer.probes))
            if _recorded.get((obj.session_uid, deformer.uid)) == key:
                return
        states = probe_states(obj, deformer, motions, error, depsgraph)
        if states is None:
            return
        for item, state in zip(deformer.probes, states, strict=True):
            if item.state != state:
                item.state = state
        _recorded[(obj.session_uid, deformer.uid)] = key
    except Exception:  # a handler must never raise; states are informative only
        traceback.print_exc()


# ------------------------------------------------------------------------------------- operators


def _refresh(context: bpy.types.Context, obj: bpy.types.Object) -> None:
    """Evaluate at once so status and offsets are current when the operator returns."""
    services().evaluate(obj, context.evaluated_depsgraph_get())


class AFFINE_OT_deformer_probe_add(DeformerIndexed, bpy.types.Operator):
    """Add the selected Empties (none selected: a new Empty at the mesh's origin) as probes of the
    deformer; their current poses become their rest poses, the other probes keep theirs"""

    bl_idname = "object.affine_deformer_probe_add"
    bl_label = "Add Probes"

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        if deformer.kind != PROBE:
            self.report({"ERROR"}, f"'{deformer.name}' is not a probe deformer")
            return {"CANCELLED"}
        provided = services()
        existing = {item.object for item in deformer.probes}
        probes, _ignored = selected_probes(context, obj)
        probes = [p for p in probes if p not in existing]
        created = None
        if not probes:
            created = new_probe(context, obj)
            probes = [created]
        first = len(deformer.probes)
        with provided.quiet():  # bound below in one go
            for probe in probes:
                deformer.probes.add().object = probe
        try:
            provided.bind(obj, deformer, context.evaluated_depsgraph_get(),
                          only=list(range(first, len(deformer.probes))))
        except (BindError, ValueError) as exc:
            while len(deformer.probes) > first:
                deformer.probes.remove(len(deformer.probes) - 1)
            provided.sync(obj, deformer)  # bind named the new probes on the modifier already
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
            services().reweight(obj, deformer)
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _refresh(context, obj)
        self.report({"INFO"}, f"Removed probe '{name}' from '{deformer.name}'")
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
        _obj, deformer = active_deformer(context)
        if deformer is None or deformer.kind != PROBE:
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
        if deformer.kind != PROBE or not 0 <= self.probe_index < len(deformer.probes):
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


# -------------------------------------------------------------------------------------------- UI


class AFFINE_UL_probes(bpy.types.UIList):
    """The probes of a deformer: object, state (at rest / moving / invalid / no group), weight scale
    and a select button."""

    def draw_item(self, _context, layout, _data, item, _icon, _active_data, _active_prop, _index=0):
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
        op.index, op.probe_index = deformer_index, _index


def draw_controls(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """The probe list with its add / remove buttons and, with painted weights, the active probe's
    vertex group (searchable)."""
    layout.label(text="Probes")
    row = layout.row()
    row.template_list(AFFINE_UL_probes.__name__, "", deformer, "probes", deformer, "active_probe_index",
                      rows=2)
    col = row.column(align=True)
    col.operator(AFFINE_OT_deformer_probe_add.bl_idname, icon="ADD", text="").index = index
    op = col.operator(AFFINE_OT_deformer_probe_remove.bl_idname, icon="REMOVE", text="")
    op.index, op.probe_index = index, deformer.active_probe_index
    if deformer.weight_mode != "VERTEX_GROUPS" or not len(deformer.probes):
        return
    obj = deformer.id_data
    item = deformer.probes[min(deformer.active_probe_index, len(deformer.probes) - 1)]
    col = layout.column()
    col.prop(item, "vertex_group", icon="GROUP_VERTEX", text=f"Group of '{probe_label(item)}'")
    if not item.vertex_group:
        col.label(text=f"Empty: reads '{group_name(obj, item)}'", icon="BLANK1")


CLASSES = (AffineDeformerProbe, AFFINE_OT_deformer_probe_add, AFFINE_OT_deformer_probe_remove,
           AFFINE_OT_deformer_probe_select, AFFINE_UL_probes)
