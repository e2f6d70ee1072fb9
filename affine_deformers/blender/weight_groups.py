"""Painted weights the artist starts from and keeps: Weights → Vertex Groups, group names that follow
renamed probes, per-probe state, and the probe list's select button.

* `weights_to_groups` writes the weights a probe deformer uses now into one vertex group per probe,
  named after it, and switches the deformer to 'VERTEX_GROUPS' so that it deforms exactly as before
  (to float32 rounding) and the artist paints corrections on top. Painted mode takes, per vertex,
  the K largest of (group weight × weight scale), normalises them, then applies the mask
  (core.weights.probe_weights, binding.reweight); the conversion is exact because the groups hold
  at most K non-zero weights per vertex (the stored top-K, see Max Influences below), and the
  options are set so the rest of that pipeline is the identity on them:
    - Normalize Sum / Softmax: each group holds the stored weight divided by the vertex's stored sum
      (the weights before the mask: they summed to 1 before it was applied); Normalize becomes Sum
      (Softmax of softmaxed weights would change them) and every Weight Scale becomes 1 (the scales
      are in the groups);
    - Normalize None: each group holds the stored weight divided by the mask (where it is not 0)
      and by c_j = max(1, largest such weight of probe j) (a vertex group holds 0…1); Weight Scale j
      becomes c_j (1 unless a scale above 1 made weights above 1);
    - the Mask stays as it is, and so does Max Influences unless a vertex has more controls with
      weight than it: where the truncation pooled weight (MATH.md §12) it is spread over all the
      controls (probes: by the pooled mix; bones: the roots), and Max Influences is raised to keep
      them (exact up to the property's maximum of 16 controls per vertex).
  Groups are written vectorised: a FLOAT point attribute per probe (foreach_set), turned into a
  vertex group by `geometry.attribute_convert` (only non-zero weights are assigned).
  Cage deformers are not offered this: their controls are cage faces (hundreds of groups, and with
  harmonic weights grid nodes), and they have no painted mode; the weight preview shows them.
* Group names: a probe item's `vertex_group` names the group holding its painted weights (empty:
  the group named after the probe, as before). When a probe object is renamed, `follow_renames`
  (every update, before evaluation) renames its group with it, as Blender renames vertex groups with
  bones, unless a group of the new name exists (then the item keeps tracking the old group by name),
  and updates the item's `name`. `group_name` resolves the same way before that update has run.
* Probe state (`AffineDeformerProbe.state`): 'AT_REST', 'MOVING', 'INVALID' or 'NO_GROUP' (painted
  weights whose group is missing), written by `record_states` from each evaluation's motions; only
  changes are written (a write tags the object).
* Painted weights are read when the deformer re-weights: `AFFINE_OT_deformer_weights_update`, or
  automatically when the object leaves Weight Paint mode (a timer after the update that saw the mode
  change: reading vertex groups evaluates a temporary object, which must not happen inside a
  depsgraph handler).
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass

import bpy
import numpy as np

from ..core import aff3
from . import binding, storage, weight_preview
from .kinds import BindError, KindId
from .kinds.probe import group_name, pool_coefficients
from .kinds.transforms import finite_transform, in_a_scene, local_matrix, relative_motion, world_matrix

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

#: The caches below are keyed by session uids, which Blender never reuses within a session, so a
#: loaded file or an undo step cannot meet a stale entry of another object.
#: (object session uid) → its mode at the last update: transient UI state, to notice an object
#: leaving Weight Paint mode (nothing here needs saving: the weights are re-read from the groups).
_modes: dict[int, str] = {}
#: Names of objects whose painted weights are re-read by the next run of `_reweight_pending`.
_pending: set[str] = set()
#: (object session uid, deformer uid) → the inputs of the probe states written last: an unchanged
#: update (the common case: nothing at rest started moving) writes nothing and reads no item.
_recorded: dict[tuple[int, str], tuple] = {}


# ------------------------------------------------------------------------------------ group names


def reads_groups(deformer) -> bool:
    """Whether re-weighting `deformer` reads vertex groups (painted weights or a mask)."""
    painted = deformer.kind in (KindId.PROBE, KindId.BONE) and deformer.weight_mode == "VERTEX_GROUPS"
    return deformer.is_bound and (painted or bool(deformer.mask_group))


def group_targets(deformer) -> list[str]:
    """The names of the groups Weights → Vertex Groups writes: each probe's object's, each bone's."""
    if deformer.kind == KindId.BONE:
        return [item.name for item in deformer.bones]
    return [item.object.name for item in deformer.probes if item.object is not None]


def _controls(deformer):
    """The items whose weights become groups: probes, or bones (whose groups are named after them)."""
    return deformer.bones if deformer.kind == KindId.BONE else deformer.probes


def follow_renames(obj: bpy.types.Object) -> None:
    """Keep painted groups and item names in step with renamed probe objects (see module doc)."""
    if obj.library is not None or obj.type != "MESH" or obj.data.library is not None:
        return
    groups = obj.vertex_groups
    for deformer in obj.affine_deformers:
        if deformer.kind != KindId.PROBE:
            continue
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


# ------------------------------------------------------------------------------------ probe states


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
    elif motions is not None and not error and len(motions.at_rest) == m:
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
    if deformer.kind != KindId.PROBE or obj.library is not None:
        return
    try:
        key = None
        if motions is not None and not error and deformer.weight_mode != "VERTEX_GROUPS":
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


# ---------------------------------------------------------------------------------- update hooks


def before_evaluate(obj: bpy.types.Object) -> None:
    """Called by the evaluation before an object's deformers are evaluated: follow renamed probes,
    notice the object leaving Weight Paint mode, refresh the weight preview. Never raises."""
    try:
        follow_renames(obj)
        _notice_mode(obj)
    except Exception:  # a handler must never raise
        traceback.print_exc()
    weight_preview.refresh(obj)


def _notice_mode(obj: bpy.types.Object) -> None:
    mode = obj.mode
    before = _modes.get(obj.session_uid)
    if before == mode:
        return
    _modes[obj.session_uid] = mode
    if before == "WEIGHT_PAINT" and any(reads_groups(d) for d in obj.affine_deformers):
        _pending.add(obj.name)
        if not bpy.app.timers.is_registered(_reweight_pending):
            bpy.app.timers.register(_reweight_pending, first_interval=0.0)


def _reweight_pending() -> None:
    """Timer: re-read the painted weights of the objects that left Weight Paint mode."""
    names = sorted(_pending)
    _pending.clear()
    for name in names:
        obj = bpy.data.objects.get(name)
        if obj is None or obj.mode == "WEIGHT_PAINT" or binding.target_problem(obj):
            continue
        for deformer in obj.affine_deformers:
            if reads_groups(deformer):
                binding.reweight_safely(obj, deformer)
        obj.update_tag()  # the depsgraph update that follows evaluates it (handlers.py)


# --------------------------------------------------------------------------- weights → groups


@dataclass
class Conversion:
    """What `weights_to_groups` did: the groups written, the options it changed, and the largest
    difference between the weights stored before and after (float32 rounding)."""

    groups: list[str]
    changes: list[str]
    max_difference: float


def conversion_problem(obj: bpy.types.Object | None, deformer) -> str:
    """Why `deformer` of `obj` cannot be converted to vertex groups ('' when it can)."""
    problem = binding.target_problem(obj)
    if problem:
        return problem
    if deformer.kind not in (KindId.PROBE, KindId.BONE):
        return ("Cage deformers have no painted weights: their controls are cage faces (hundreds of "
                "groups); Show Weights shows them")
    if not deformer.is_bound:
        return "Not bound: press Bind first"
    if deformer.weight_mode == "VERTEX_GROUPS":
        return "The weights already come from vertex groups: paint them"
    return ""


def _planned_names(obj: bpy.types.Object, deformer, overwrite: bool) -> list[str]:
    """The group name of every probe (its object's name), checked: every probe has an object, no
    two share one, the mask is not one of them, no mesh attribute has such a name, and no group has
    one unless `overwrite`."""
    names = []
    for i, item in enumerate(_controls(deformer)):
        if deformer.kind == KindId.BONE:
            names.append(item.name)  # the Armature modifier's convention: a group per bone name
            continue
        if item.object is None:
            raise BindError(f"Probe {i + 1} ('{item.name or '?'}') has no object: pick one or remove it")
        names.append(item.object.name)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise BindError("Several probes use " + ", ".join(f"'{n}'" for n in repeated)
                        + ": remove the duplicates first (they would share one group)")
    if deformer.mask_group in names:
        raise BindError(f"The mask group '{deformer.mask_group}' has a probe's name: rename one of them "
                        "(the probe's weights would replace the mask)")
    clashes = [n for n in names if obj.data.attributes.get(n) is not None]
    if clashes:
        raise BindError("The mesh has attributes named " + ", ".join(f"'{n}'" for n in clashes)
                        + ": rename them or the probes (a vertex group cannot share an attribute's name)")
    existing = [n for n in names if obj.vertex_groups.get(n) is not None]
    if existing and not overwrite:
        raise BindError("Vertex groups named " + ", ".join(f"'{n}'" for n in existing)
                        + " exist already: enable Overwrite to replace them")
    return names


def dense_weights(obj: bpy.types.Object, deformer) -> np.ndarray:
    """The stored weights of a probe deformer as a dense (N, m) float64 array (mask included); a share
    pooled by the truncation (index m, MATH.md §12) is spread over the probes by the pooled mix."""
    m = len(_controls(deformer))
    pooled_ok = deformer.kind == KindId.PROBE  # bones give pooled weight to their roots at bind
    indices, values = storage.read_weights(obj.data, deformer.uid, m + pooled_ok)
    dense = np.zeros((len(indices), m + 1))
    rows = np.arange(len(indices))
    for k in range(indices.shape[1]):  # a pass per column (a root bone may repeat a kept one: summed)
        dense[rows, indices[:, k]] += values[:, k]
    if pooled_ok and dense[:, m].any():
        dense[:, :m] += dense[:, m:] * pool_coefficients(deformer)[None, :]
    return dense[:, :m]


def painted_equivalent(obj: bpy.types.Object, deformer) -> tuple[np.ndarray, np.ndarray, str]:
    """(group weights (N, m) in [0, 1] float32, weight scales (m,), normalize mode) with which
    'VERTEX_GROUPS' reproduces the stored weights (see the module doc)."""
    dense = dense_weights(obj, deformer)
    if deformer.normalize in ("SUM", "SOFTMAX"):
        total = dense.sum(axis=1, keepdims=True)
        groups = np.divide(dense, total, out=np.zeros_like(dense), where=total > 0.0)
        return np.clip(groups, 0.0, 1.0).astype(np.float32), np.ones(dense.shape[1]), "SUM"
    mask, _warning = binding.mask_weights(obj, deformer)
    if mask is not None:
        dense = np.divide(dense, mask[:, None], out=np.zeros_like(dense), where=mask[:, None] > 0.0)
        # before the mask a weight is at most its probe's scale (raw weights are at most 1)
        scales = np.array([item.weight_scale for item in _controls(deformer)])
        dense = np.minimum(dense, scales[None, :])
    factors = np.maximum(dense.max(axis=0, initial=0.0), 1.0)
    return np.clip(dense / factors, 0.0, 1.0).astype(np.float32), factors, "NONE"


def _write_group(obj: bpy.types.Object, name: str, weights: np.ndarray) -> None:
    """A vertex group `name` holding `weights` (N,) (vertices with weight 0 unassigned), vectorised:
    a FLOAT point attribute converted by Blender's attribute-convert operator."""
    mesh = obj.data
    attr = mesh.attributes.new(name, "FLOAT", "POINT")
    if attr is None or attr.name != name:
        if attr is not None:
            mesh.attributes.remove(attr)
        raise BindError(f"Could not create the vertex group '{name}'")
    attr.data.foreach_set("value", np.ascontiguousarray(weights, dtype=np.float32))
    mesh.attributes.active = attr
    with bpy.context.temp_override(object=obj, active_object=obj):
        result = bpy.ops.geometry.attribute_convert(mode="VERTEX_GROUP")
    if result != {"FINISHED"} or obj.vertex_groups.get(name) is None:
        leftover = mesh.attributes.get(name)
        if leftover is not None:
            mesh.attributes.remove(leftover)
        raise BindError(f"Could not create the vertex group '{name}'")


def weights_to_groups(obj: bpy.types.Object, deformer, overwrite: bool = False) -> Conversion:
    """Write the probe deformer's current weights into vertex groups named after its probes and switch
    it to painted weights with the same deformation (module doc). BindError (nothing changed) when it
    cannot: a cage, not bound, painted already, a probe without object, name clashes, existing groups
    without `overwrite`."""
    problem = conversion_problem(obj, deformer)
    if problem:
        raise BindError(problem)
    names = _planned_names(obj, deformer, overwrite)
    mesh = obj.data
    if len(mesh.vertices) != deformer.bound_vertex_count:
        raise BindError("The mesh's vertex count changed since bind: rebind the deformer first")
    before = dense_weights(obj, deformer)
    groups, scales, normalize = painted_equivalent(obj, deformer)
    active_attribute = mesh.attributes.active.name if mesh.attributes.active is not None else ""
    created: list[str] = []
    try:
        for j, name in enumerate(names):
            old = obj.vertex_groups.get(name)
            if old is not None:
                obj.vertex_groups.remove(old)
            _write_group(obj, name, groups[:, j])
            created.append(name)
    except Exception:
        for name in created:  # leave no half-made set of groups behind
            group = obj.vertex_groups.get(name)
            if group is not None:
                obj.vertex_groups.remove(group)
        raise
    finally:
        restored = mesh.attributes.get(active_attribute) if active_attribute else None
        if restored is not None:
            mesh.attributes.active = restored
    changes = ["Weights: Vertex Groups"]
    if deformer.normalize != normalize:
        changes.append(f"Normalize: {normalize.title()}")
    # Painted weights keep each vertex's K largest: where the truncation pooled weight (MATH.md §12)
    # a vertex has more controls than Max Influences, so it is raised to keep them all (as far as the
    # property allows; beyond, `max_difference` says how far the conversion is from exact).
    needed = int(np.count_nonzero(groups, axis=1).max(initial=0))
    most = deformer.bl_rna.properties["max_influences"].hard_max
    influences = min(max(needed, deformer.max_influences), most)
    if influences != deformer.max_influences:
        changes.append(f"Max Influences: {influences} (pooled weight spread over the controls)")
    if any(item.weight_scale != float(s) for item, s in zip(_controls(deformer), scales, strict=True)):
        changes.append("Weight Scale: in the groups")
    with binding.quiet():  # re-weighted once below
        deformer.weight_mode = "VERTEX_GROUPS"
        deformer.normalize = normalize
        deformer.max_influences = influences
        for item, name, scale in zip(_controls(deformer), names, scales, strict=True):
            item.weight_scale = float(scale)
            if deformer.kind == KindId.PROBE:
                item.vertex_group = name
                item.name = name
    binding.reweight(obj, deformer)
    active = deformer.active_bone_index if deformer.kind == KindId.BONE else deformer.active_probe_index
    obj.vertex_groups.active_index = obj.vertex_groups[names[min(active, len(names) - 1)]].index
    after = dense_weights(obj, deformer)
    difference = float(np.abs(after - before).max(initial=0.0))
    return Conversion(names, changes, difference)
