"""Painted weights the artist starts from and keeps: Weights → Vertex Groups, renamed controls' groups,
the controls' states, and re-reading the groups when the object leaves Weight Paint mode. Kind-agnostic:
what a kind offers (its control items, its active control, whether it paints groups, the group each
control's weights go into) comes from its `DeformerKind` methods.

* `weights_to_groups` writes the weights a deformer whose kind paints groups (probes, bones) uses now
  into one vertex group per control (`DeformerKind.control_groups`: named after the probe, or the
  bone), and switches the deformer to 'VERTEX_GROUPS' so that it deforms exactly as before (to
  float32 rounding) and the artist paints corrections on top. Painted mode takes, per vertex, the K
  largest of (group weight × weight scale), normalises them, then applies the mask
  (core.weights.probe_weights, binding.reweight); the conversion is exact because the groups hold
  at most K non-zero weights per vertex (the stored top-K), and the options are set so the rest of
  that pipeline is the identity on them:
    - Normalize Sum / Softmax: each group holds the stored weight divided by the vertex's stored sum
      (the weights before the mask: they summed to 1 before it was applied); Normalize becomes Sum
      (Softmax of softmaxed weights would change them) and every Weight Scale becomes 1 (the scales
      are in the groups);
    - Normalize None: each group holds the stored weight divided by the mask (where it is not 0)
      and by c_j = max(1, largest such weight of control j) (a vertex group holds 0…1); Weight Scale
      j becomes c_j (1 unless a scale above 1 made weights above 1);
    - the Mask stays as it is, and so does Max Influences unless a vertex has more controls with
      weight than it: where the truncation pooled weight (MATH.md §12) it is spread over the
      controls of its pooled nodes (probes: all, by the pooled mix; bones: a bone's children or the
      roots, core.hierarchy.pool_mix), and Max Influences is raised to keep them (exact up to the
      property's maximum of 16 controls per vertex).
  Groups are written vectorised: a FLOAT point attribute per control (foreach_set), turned into a
  vertex group by `geometry.attribute_convert` (only non-zero weights are assigned).
  Kinds that do not paint groups (cages: their controls are cage faces, hundreds of groups, and
  with harmonic weights grid nodes) are not offered this; the weight preview shows them.
* Before every update (an explicit hook, hooks.before_object) each kind follows renamed controls
  (`DeformerKind.follow_renames`: a renamed probe renames its group), the object's leaving Weight
  Paint mode is noticed, and the weight preview refreshed; once a deformer's inputs are read
  (hooks.inputs_read) its kind records its controls' states (`DeformerKind.record_states`).
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

from .. import binding, caches, kinds
from ..kinds import BindError
from ..update import hooks
from . import weight_preview

#: (object session uid) → its mode at the last update: transient UI state, to notice an object
#: leaving Weight Paint mode (nothing here needs saving: the weights are re-read from the groups).
#: Session uids are never reused within a session, so a loaded file cannot meet a stale entry.
_modes: dict[int, str] = {}
#: Names of objects whose painted weights are re-read by the next run of `_reweight_pending`.
_pending: set[str] = set()


@caches.register
def _forget(key: caches.Key | None) -> None:
    """Everything at a full forget (undo, file load: the names may be another file's objects); the
    modes are per object, not per deformer."""
    if key is None:
        _modes.clear()
        _pending.clear()


# ------------------------------------------------------------------------------------ group names


def reads_groups(deformer) -> bool:
    """Whether re-weighting `deformer` reads vertex groups (painted weights or a mask)."""
    kind = kinds.get(deformer.kind)
    painted = kind is not None and kind.paints_groups and deformer.weight_mode == "VERTEX_GROUPS"
    return deformer.is_bound and (painted or bool(deformer.mask_group))


def group_targets(deformer) -> list[str]:
    """The names of the groups Weights → Vertex Groups writes, of the controls that name one now."""
    kind = kinds.get(deformer.kind)
    return kind.control_groups(deformer) if kind is not None else []


def follow_renames(obj: bpy.types.Object) -> None:
    """Keep names the deformers store in step with renamed controls (DeformerKind.follow_renames)."""
    if obj.library is not None or obj.type != "MESH" or obj.data.library is not None:
        return
    for deformer in obj.affine_deformers:
        kind = kinds.get(deformer.kind)
        if kind is not None:
            kind.follow_renames(obj, deformer)


# ---------------------------------------------------------------------------------- update hooks


@hooks.before_object
def before_evaluate(obj: bpy.types.Object) -> None:
    """Before an object's deformers are evaluated: follow renamed controls, notice the object leaving
    Weight Paint mode, refresh the weight preview. Never raises."""
    try:
        follow_renames(obj)
        _notice_mode(obj)
    except Exception:  # a handler must never raise
        traceback.print_exc()
    weight_preview.refresh(obj)


@hooks.inputs_read
def record_states(obj: bpy.types.Object, deformer, snapshot, depsgraph: bpy.types.Depsgraph) -> None:
    """Once a deformer's inputs are read: its kind shows its controls' states (never raises)."""
    kind = kinds.get(deformer.kind)
    if kind is not None and obj.library is None:
        kind.record_states(obj, deformer, snapshot.motions, snapshot.error, depsgraph)


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
    kind = kinds.get(deformer.kind)
    if kind is None:
        return f"{deformer.kind.title()} deformers are not available in this version"
    if not kind.paints_groups:
        note = f": {kind.groups_note}" if kind.groups_note else ""
        return f"{kind.label} deformers have no painted weights{note}"
    if not deformer.is_bound:
        return "Not bound: press Bind first"
    if deformer.weight_mode == "VERTEX_GROUPS":
        return "The weights already come from vertex groups: paint them"
    return ""


def _planned_names(obj: bpy.types.Object, deformer, overwrite: bool) -> list[str]:
    """The group name of every control (DeformerKind.control_groups), checked: every control names
    one, no two share one, the mask is not one of them, no mesh attribute has such a name, and no
    group has one unless `overwrite`."""
    names = kinds.get(deformer.kind).control_groups(deformer, complete=True)
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
    """The stored weights of a deformer as a dense (N, m) float64 array (mask included); a share the
    truncation pooled (MATH.md §12) is spread over the controls by the kind's pooled mix."""
    kind = kinds.get(deformer.kind)
    m = kind.control_count(deformer)
    indices, values, node_weights = kind.stored_weights(obj, deformer)
    rows = np.arange(len(indices))
    if node_weights is not None:  # the pooled column: its weight spread by the mix
        dense = np.zeros((len(indices), m))
        for k in range(indices.shape[1]):
            dense += values[:, k, None] * node_weights[indices[:, k]]
        return dense
    dense = np.zeros((len(indices), m))
    for k in range(indices.shape[1]):  # a pass per column (a root bone may repeat a kept one: summed)
        dense[rows, indices[:, k]] += values[:, k]
    return dense


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
        scales = np.array([item.weight_scale for item in kinds.get(deformer.kind).control_items(deformer)])
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
    """Write the deformer's current weights into vertex groups named after its controls and switch it
    to painted weights with the same deformation (module doc). BindError (nothing changed) when it
    cannot: a kind that does not paint groups, not bound, painted already, a probe without object,
    name clashes, existing groups without `overwrite`."""
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
    kind = kinds.get(deformer.kind)
    items = kind.control_items(deformer)
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
    if any(item.weight_scale != float(s) for item, s in zip(items, scales, strict=True)):
        changes.append("Weight Scale: in the groups")
    with binding.quiet():  # re-weighted once below
        deformer.weight_mode = "VERTEX_GROUPS"
        deformer.normalize = normalize
        deformer.max_influences = influences
        for item, scale in zip(items, scales, strict=True):
            item.weight_scale = float(scale)
        kind.groups_written(deformer, names)
    binding.reweight(obj, deformer)
    active = kind.active_control(deformer)
    obj.vertex_groups.active_index = obj.vertex_groups[names[min(active, len(names) - 1)]].index
    after = dense_weights(obj, deformer)
    difference = float(np.abs(after - before).max(initial=0.0))
    return Conversion(names, changes, difference)
