"""Per-frame evaluation: gather control transforms → core → write the offset attribute.

For each deformer on a mesh: read the controls' current matrices from the evaluated depsgraph (bpy.data
is stale during renders), form A_i = C_i · C_rest,i⁻¹ in the target's local space (kinds.py), turn them
into blend parameters P_i = ψ(A_i) (`motions_to_params`, the single place for that), read the sparse
weights from the mesh, and write v' − v with v' = φ(Σ_k w_vk P_idx(v,k)) v (or the linear blend) as the
offset attribute our Geometry Nodes modifier adds. The result at frame f depends only on the inputs at
frame f; `_signatures` is a cache of those inputs (not bind data) so unchanged deformers cost nothing,
and `_bound` caches the bind data read from the mesh plus the last result, so an update recomputes
only the vertices influenced by controls that moved (bit-identical to a full recompute; `_Bound`).

Handlers are @persistent, guarded against re-entrancy, and never let an exception escape: bad input
becomes the deformer's `status` and zero offsets (the mesh shows its rest shape).
"""

from __future__ import annotations

import itertools
import traceback
from dataclasses import dataclass

import bpy
import numpy as np
from bpy.app.handlers import persistent

from .. import accel
from ..core import aff3, deform, unwrap
from . import binding, cage_kind, kinds, nodes, relations, storage
from .kinds import KINDS, Motions, reference_rotvecs

# Branch lift tolerances for Blender's float32 matrices (relative noise ~1e-7); core.unwrap's defaults
# suit exact input. Near a full turn the principal rotation is tiny, so its axis is noise/θ, which the
# lift multiplies by 2πk: below LIFT_AXIS_TOL radians the channels' axis is used instead (dropping at
# most that much genuine off-axis rotation). And V(ω) loses its in-plane gain there, so the float32
# residual of the translation (~1e-7·|pivot|) is divided by it: LIFT_DAMPING bounds the gain by
# 1/(2·LIFT_DAMPING). A probe turned 359.999° / 360° / 720° about a tilted axis, 6 units from the target's
# origin, was off by 3.5e-3 / 0.65 units with the core defaults, by < 2e-5 with these.
LIFT_AXIS_TOL = 3e-3
LIFT_DAMPING = 1e-3

#: Above this fraction of the vertices, an update recomputes everything (gathering and scattering the
#: affected rows would cost more than it saves).
INCREMENTAL_MAX_FRACTION = 0.6

_signatures: dict[tuple[int, str], tuple] = {}
_errors: dict[tuple[int, str], str] = {}
_bound: dict[tuple[int, str], _Bound] = {}
_serial = itertools.count(1)
_busy = False


@dataclass
class _Bound:
    """Bind data of one deformer read once per bind generation, plus its last result (a cache: the .blend
    holds the truth, and every value here is recomputed from it when the key no longer matches).

    key = (mesh session uid, bind generation, vertex count, control count); `rest32` is checked against
    the mesh on every evaluation (a cheap array compare), so edits of the rest shape (Edit Mode, Sculpt
    Mode, scripts) are seen without rebinding. `serial` changes whenever the entry is rebuilt.
    `written` is what this process last wrote to the offset attribute, so an update writes it
    without reading the attribute back (a write by anyone else to that attribute is not supported;
    undo and file load drop the cache). The last result (`state`, `params`, `offsets`) lets an
    update recompute only the vertices with a non-zero weight on a control whose blend parameters
    changed: every vertex's result depends only on its own rest position, weights and the parameters
    of its controls, so this is bit-identical to a full recompute.
    """

    key: tuple
    serial: int
    rest32: np.ndarray  # (N, 3) float32, exactly as stored in the mesh
    points: np.ndarray  # (N, 3) float64
    indices: np.ndarray  # (N, K) int32
    values: np.ndarray  # (N, K) float64, strength not applied
    scaled: tuple[float, np.ndarray] | None = None  # (strength, values · strength)
    csr: tuple[np.ndarray, np.ndarray] | None = None  # per control: the rows it influences
    state: tuple | None = None  # settings `params` and `offsets` were computed with
    params: np.ndarray | None = None  # (m, 12) blend parameters of the last result
    offsets: np.ndarray | None = None  # (N, 3) float64 last offsets
    written: np.ndarray | None = None  # (N, 3) float32 the offset attribute holds (None = unknown)
    motions: np.ndarray | None = None  # (4, N, 3) float32 last motions (motion path)
    motions_written: np.ndarray | None = None  # (4, N, 3) float32 the motion attributes hold (None = unknown)

    def scaled_values(self, strength: float) -> np.ndarray:
        if self.scaled is None or self.scaled[0] != strength:
            self.scaled = (strength, self.values * strength)
        return self.scaled[1]

    def affected_rows(self, controls: np.ndarray) -> np.ndarray:
        """Sorted vertices with a non-zero weight on any of `controls`; O(affected) to gather (plus
        one boolean pass over the vertices), from per-control row lists built once per generation."""
        if self.csr is None:
            m = len(self.params) if self.params is not None else int(self.indices.max(initial=-1)) + 1
            rows, slots = np.nonzero(self.values)
            cols = self.indices[rows, slots]
            order = np.argsort(cols, kind="stable")
            ptr = np.zeros(m + 1, dtype=np.intp)
            np.cumsum(np.bincount(cols, minlength=m), out=ptr[1:])
            self.csr = (ptr, rows[order].astype(np.intp))
        ptr, rows = self.csr
        if len(controls) == 1:  # one control's rows are already sorted and distinct
            return rows[ptr[controls[0]] : ptr[controls[0] + 1]]
        mask = np.zeros(len(self.points), dtype=bool)
        for i in controls:
            mask[rows[ptr[i] : ptr[i + 1]]] = True
        return np.flatnonzero(mask)

    def forget_result(self) -> None:
        self.state = self.params = self.offsets = self.motions = None


def forget(obj: bpy.types.Object | None = None, uid: str | None = None) -> None:
    """Drop cached signatures (all, or those of one deformer) so the next evaluation recomputes."""
    if obj is None:
        _signatures.clear()
        _errors.clear()
        _bound.clear()
        _param_rows.clear()
        _modifiers.clear()
        kinds.forget()
        cage_kind.forget()
    else:
        _signatures.pop((obj.session_uid, uid), None)
        _errors.pop((obj.session_uid, uid), None)
        _bound.pop((obj.session_uid, uid), None)
        _modifiers.pop((obj.session_uid, uid), None)
        cage_kind.forget((obj.session_uid, uid))


def _bind_data(obj: bpy.types.Object, deformer, n_controls: int) -> _Bound:
    """The cached bind data of `deformer`, re-read when the bind generation, mesh, vertex or control
    count changed or the rest positions differ from the cached ones. Raises storage.StorageError."""
    mesh = obj.data
    rest = storage.read_positions(mesh)
    key = (mesh.session_uid, deformer.bind_generation, len(rest), n_controls)
    cache_key = (obj.session_uid, deformer.uid)
    bound = _bound.get(cache_key)
    if bound is not None and bound.key == key and np.array_equal(bound.rest32, rest):
        return bound
    _bound.pop(cache_key, None)
    _check_vertices(mesh, deformer, rest)
    indices, values = storage.read_weights(mesh, deformer.uid, n_controls)
    bound = _Bound(key, next(_serial), rest, rest.astype(np.float64), indices, values)
    _bound[cache_key] = bound
    return bound


def motions_to_params(motions: Motions, deformer) -> np.ndarray:
    """Blend parameters (m, 12) of the controls' motions: ψ(A_i) in the layout of docs/DEVELOPING.md.

    Controls exactly at rest get exactly zero parameters. Kinds that give their own parameters (cage
    faces average several tetrahedra) have them used as they are.

    The rotation log is multivalued (ω + 2πk·ω/|ω|); ψ as printed takes |ω| ≤ π, so a control turned
    past 180° flips the blend. With `branch_rule` 'CHANNELS' each ω is lifted to the branch nearest the
    control's own rotation channels (kinds.reference_rotvecs: Rotation Z keyed 0 → 720° gives 720°;
    turns from parents or constraints take the nearest branch) and u is recomputed about the control's
    origin (core.unwrap.lift_params). The reference comes from the current frame alone, so any frame
    evaluates the same in any order or process. 'SHORTEST' keeps the principal branch.
    """
    m = len(motions.matrices)
    if m == 0:
        return np.zeros((0, 12))
    if motions.params is not None:
        params = np.array(motions.params, dtype=np.float64)
        params[motions.at_rest] = 0.0
        return params
    lift = deformer.branch_rule == "CHANNELS" and len(motions.rotation_modes) == m
    pivots = motions.pivots if len(motions.pivots) == m else None
    keys = _param_keys(motions, lift, pivots)
    params = np.empty((m, 12))
    missing = []
    for i, key in enumerate(keys):
        row = _param_rows.get(key)
        if row is None:
            missing.append(i)
        else:
            params[i] = row
    if missing:
        params[missing] = _params_of_rows(motions, np.array(missing), lift, pivots)
        if len(_param_rows) + len(missing) > PARAM_MEMO_SIZE:
            _param_rows.clear()
        for i in missing:
            _param_rows[keys[i]] = params[i].copy()
    return params


#: Per-control memo of `motions_to_params`: a control whose inputs (its motion, at-rest flag, rotation
#: channels and modes, channel frame, pivot, and whether it is lifted) are bitwise unchanged gets its
#: previous parameter row back. Every row of ψ and of the lift is computed independently of the other
#: rows (tests/core/test_psi_batch.py), so this is a pure-function memo: the result of a frame does not
#: depend on which controls were computed together before. Bounded: cleared when full.
PARAM_MEMO_SIZE = 4096
_param_rows: dict[tuple, np.ndarray] = {}


def _param_keys(motions: Motions, lift: bool, pivots: np.ndarray | None) -> list[tuple]:
    """One hashable key per control holding the exact bits of everything its parameter row depends on."""
    m = len(motions.matrices)
    parts = [motions.matrices.reshape(m, 16), motions.at_rest.reshape(m, 1).astype(np.float64)]
    framed = len(motions.channel_frames) == m
    if lift:
        parts += [motions.rest_rotations.reshape(m, -1), motions.current_rotations.reshape(m, -1)]
        if framed:
            parts.append(motions.channel_frames.reshape(m, 9))
        if pivots is not None:
            parts.append(pivots.reshape(m, 3))
    bits = np.ascontiguousarray(np.concatenate(parts, axis=1, dtype=np.float64))
    if not lift:
        return [(row.tobytes(),) for row in bits]
    return [(row.tobytes(), rest_mode, mode, framed, pivots is None)
            for row, rest_mode, mode in zip(bits, motions.rest_rotation_modes, motions.rotation_modes,
                                            strict=True)]


def _params_of_rows(motions: Motions, rows: np.ndarray, lift: bool, pivots: np.ndarray | None) -> np.ndarray:
    """ψ(A_i), lifted to the channels' branch when `lift`, of the controls `rows` (zero at rest)."""
    try:
        params = np.asarray(aff3.params_from_matrices(motions.matrices[rows]), dtype=np.float64)
    except ValueError:
        # The core names the row within this batch of changed controls: name the control instead.
        for i in rows:
            try:
                aff3.params_from_matrices(motions.matrices[i : i + 1])
            except ValueError as exc:
                raise ValueError(f"control {int(i) + 1}: {exc}") from None
        raise
    if lift:
        framed = len(motions.channel_frames) == len(motions.matrices)
        reference = reference_rotvecs([motions.rest_rotation_modes[i] for i in rows],
                                      motions.rest_rotations[rows], [motions.rotation_modes[i] for i in rows],
                                      motions.current_rotations[rows],
                                      motions.channel_frames[rows] if framed else None)
        params = unwrap.lift_params(params, reference, None if pivots is None else pivots[rows],
                                    damping=LIFT_DAMPING, axis_tol=LIFT_AXIS_TOL)
    params[motions.at_rest[rows]] = 0.0
    return params


def _set_status(deformer, message: str) -> None:
    # Writing a property tags the object for update; only write real changes to avoid update loops.
    if deformer.status != message:
        deformer.status = message


def _precheck(obj: bpy.types.Object, deformer) -> str:
    if obj.type != "MESH":
        return f"'{obj.name}' is not a mesh: the deformer has no effect"
    if deformer.kind not in KINDS:
        return f"Deformer kind '{deformer.kind}' is not available in this version"
    if not deformer.is_bound:
        return "Not bound: press Bind" + (f" ({deformer.bind_warning})" if deformer.bind_warning else "")
    if not _has_modifier(obj, deformer.uid):
        return "The deformer's modifier was removed or applied: Rebind to recreate it"
    n = len(obj.data.vertices)
    if n != deformer.bound_vertex_count:
        return (f"The mesh has {n} vertices but was bound with {deformer.bound_vertex_count}: "
                "the topology changed, rebind the deformer")
    return ""


def _check_vertices(mesh: bpy.types.Mesh, deformer, rest32: np.ndarray) -> None:
    """Raise StorageError when the mesh's vertices are no longer the ones the weights were bound to.

    Compared with the signature stored at bind (storage.topology_signature): a change of the shape
    alone (Edit / Sculpt Mode moves) or of the connectivity alone (faces added or deleted, vertices in
    place) keeps the vertices and is accepted — the stored signature follows it; both at once, as
    deleting one vertex and adding another gives, means the indices were renumbered. Called only
    when the rest positions differ from the cached ones (or on the first read), so updates pay nothing.
    """
    stored = deformer.bound_topology
    if not stored:  # bound by 0.1.0
        return
    now = storage.topology_signature(mesh, rest32)
    if now == stored:
        return
    connectivity, shape = stored.split(":")
    connectivity_now, shape_now = now.split(":")
    if connectivity != connectivity_now and shape != shape_now:
        raise storage.StorageError("The mesh's vertices changed since bind (deleted and added?): the "
                                   "topology changed, rebind the deformer")
    deformer.bound_topology = now


#: (object session uid, deformer uid) → name of the modifier `nodes.find_modifier` found last time.
_modifiers: dict[tuple[int, str], str] = {}


def _modifier(obj: bpy.types.Object, uid: str) -> bpy.types.Modifier | None:
    """`nodes.find_modifier(obj, offset attribute of uid)`, trying the modifier found last time first:
    it still counts when it is still ours and still reads this deformer's attribute (the same test
    find_modifier applies), otherwise the stack is searched again."""
    key = (obj.session_uid, uid)
    offset_attr = storage.offset_name(uid)
    name = _modifiers.get(key)
    if name is not None:
        mod = obj.modifiers.get(name)
        if nodes.is_modifier_for(mod, offset_attr):
            return mod
    mod = nodes.find_modifier(obj, offset_attr)
    if mod is None:
        _modifiers.pop(key, None)
        return None
    _modifiers[key] = mod.name
    return mod


def _has_modifier(obj: bpy.types.Object, uid: str) -> bool:
    return _modifier(obj, uid) is not None


def redistribute(indices: np.ndarray, values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Weights with the slots of invalid controls zeroed and each row rescaled to its former sum, so a
    skipped control's weight goes to the vertex's other controls. Rows left with no valid control
    become zero (the vertex follows only `Motions.outer`)."""
    kept = np.where(valid[indices], values, 0.0)
    before, after = values.sum(axis=1), kept.sum(axis=1)
    scale = np.divide(before, after, out=np.zeros_like(before), where=after > 0.0)
    return kept * scale[:, None]


def _values(deformer, motions: Motions, bound: _Bound) -> np.ndarray:
    """The bound weights at the deformer's strength, with skipped controls' weight redistributed."""
    if motions.valid is not None and not np.all(motions.valid):
        return redistribute(bound.indices, bound.values, motions.valid) * deformer.strength
    return bound.scaled_values(deformer.strength)


def _outer(motions: Motions, deformer) -> np.ndarray | None:
    """The motion applied after the blend, at strength s: φ(s·ψ(G)) (exactly G at s = 1).

    With `branch_rule` 'CHANNELS' and a reference from the kind (Motions.outer_reference: the cage
    object's own turn since bind), ψ(G) is lifted to the rotation-log branch nearest it about the
    object's origin, exactly as probes are (`motions_to_params`): a cage keyed 0 → 720° at s = 0.5
    turns the target 0 → 360° without a flip at 180°.
    """
    strength = deformer.strength
    if motions.outer is None or strength == 1.0:
        return motions.outer
    params = aff3.params_from_matrices(motions.outer)
    if deformer.branch_rule == "CHANNELS" and motions.outer_reference is not None:
        params = unwrap.lift_params(params, motions.outer_reference, motions.outer_pivot,
                                    damping=LIFT_DAMPING, axis_tol=LIFT_AXIS_TOL)
    return aff3.matrices_from_params(strength * params)


def _offsets(deformer, motions: Motions, bound: _Bound) -> tuple[np.ndarray, np.ndarray | None]:
    """(v' − v for every rest vertex (N, 3) float64, rows): exactly zero when every control is at rest.

    `rows` are the only vertices whose offsets may differ from the previous result of `bound` (None:
    any may). The returned array may be the cache's own (`bound.offsets`): callers must not modify it.
    """
    outer = _outer(motions, deformer)
    points = bound.points
    if deformer.strength == 0.0 or len(motions.matrices) == 0 or (np.all(motions.at_rest) and outer is None):
        bound.forget_result()
        return np.zeros(points.shape, dtype=np.float64), None
    if np.all(motions.at_rest):
        bound.forget_result()
        deformed = points.copy()
    elif (deformer.blend_mode != "LINEAR" and outer is None
          and (motions.valid is None or np.all(motions.valid))):
        return _offsets_affine(deformer, motions, bound)
    else:
        bound.forget_result()
        indices, values = bound.indices, _values(deformer, motions, bound)
        if deformer.blend_mode == "LINEAR":
            deformed = deform.blend_linear_sparse(points, motions.matrices, indices, values)
        else:
            deformed = accel.deform_points_params(points, motions_to_params(motions, deformer), indices,
                                                   values)
    if outer is not None:
        deformed = deformed @ outer[:3, :3].T + outer[:3, 3]
    return deformed - points, None


def _offsets_affine(deformer, motions: Motions, bound: _Bound) -> tuple[np.ndarray, np.ndarray | None]:
    """`_offsets` for the plain affine blend, recomputing only the vertices whose result can differ
    from the cached one: those with a non-zero weight on a control whose parameters changed bitwise.
    The others keep their cached offsets, which equal a recomputation bit for bit (a vertex's result
    depends only on its rest position, its weights and its controls' parameters; the kernel's rows
    are independent of how vertices are grouped). Controls at rest have zero parameters, so vertices
    that only they influence keep offset 0, exactly what φ(0) gives."""
    params = motions_to_params(motions, deformer)
    values = bound.scaled_values(deformer.strength)
    points = bound.points
    # The backend is part of the state: the two kernels agree to ~1e-15, not bit for bit, and an
    # incremental update must equal a full recompute exactly.
    state = (deformer.strength, deformer.branch_rule, accel.active())
    offsets = bound.offsets
    if offsets is not None and bound.state == state and bound.params.shape == params.shape:
        changed = np.flatnonzero((params.view(np.int64) != bound.params.view(np.int64)).any(axis=1))
        rows = bound.affected_rows(changed)
        if len(rows) <= INCREMENTAL_MAX_FRACTION * len(points):
            if len(rows):
                # The kernel also rounds the rows it computes into the copy of the attribute, so
                # `_write_offsets` writes that copy as it is (same condition there: keep in step).
                written = bound.written
                out32 = written if written is not None and written.shape == offsets.shape else None
                accel.deform_points_params_rows(points, params, bound.indices, values, rows, offsets,
                                                 offsets=True, key=(bound.serial, deformer.strength),
                                                 out32=out32)
            bound.params = params
            return offsets, rows
    bound.forget_result()
    offsets = accel.deform_points_params(points, params, bound.indices, values,
                                          key=(bound.serial, deformer.strength))
    offsets -= points
    bound.state, bound.params, bound.offsets = state, params, offsets
    return offsets, None


def _motions(deformer, motions: Motions, bound: _Bound) -> tuple[np.ndarray, np.ndarray | None]:
    """(each rest vertex's motion x ↦ M x + t as (4, N, 3) float32 columns M e_x, M e_y, M e_z, t,
    rows): the motion path's counterpart of `_offsets` (same rules, same `rows` meaning); exactly the
    identity when every control is at rest. The array may be the cache's own: do not modify it."""
    outer = _outer(motions, deformer)
    n = len(bound.points)
    if (deformer.blend_mode != "LINEAR" and outer is None
            and (motions.valid is None or np.all(motions.valid))):
        return _motions_affine(deformer, motions, bound)
    bound.forget_result()
    if deformer.strength == 0.0 or len(motions.matrices) == 0 or np.all(motions.at_rest):
        result = _identity_motions(n)
    else:
        indices, values = bound.indices, _values(deformer, motions, bound)
        if deformer.blend_mode == "LINEAR":
            result = _linear_motions(motions.matrices, indices, values)
        else:
            result = accel.vertex_motions(motions_to_params(motions, deformer), indices, values)
    if outer is not None:
        result = _compose(outer, result)
    return np.ascontiguousarray(result, dtype=np.float32), None


def _identity_motions(n: int) -> np.ndarray:
    result = np.zeros((4, n, 3))
    for c in range(3):
        result[c, :, c] = 1.0
    return result


def _linear_motions(matrices: np.ndarray, indices: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The 'LINEAR' blend as motions: M = I + Σ_k w_k (M_k − I), t = Σ_k w_k t_k (the identity carries
    the leftover weight, as in deform.blend_linear_sparse), (4, N, 3) float64."""
    m = len(matrices)
    table = (matrices[:, :3, :] - np.eye(3, 4)).transpose(0, 2, 1).reshape(m, 12)
    blended = deform.blend_params(table, indices, values).reshape(-1, 4, 3).transpose(1, 0, 2)
    return blended + _identity_motions(len(indices))


def _compose(outer: np.ndarray, motions: np.ndarray) -> np.ndarray:
    """Motions (4, N, 3) followed by the affine map `outer` (4, 4): columns G₃ M e_c, and G₃ t + g."""
    result = np.asarray(motions, dtype=np.float64) @ outer[:3, :3].T
    result[3] += outer[:3, 3]
    return result


def _motions_affine(deformer, motions: Motions, bound: _Bound) -> tuple[np.ndarray, np.ndarray | None]:
    """`_motions` for the plain affine blend, recomputing only the vertices whose motion can differ
    from the cached one (see `_offsets_affine`: the same rule, for motions instead of offsets)."""
    params = motions_to_params(motions, deformer)
    values = bound.scaled_values(deformer.strength)
    state = ("MOTION", deformer.strength, deformer.branch_rule, accel.active())
    key = (bound.serial, deformer.strength)
    result = bound.motions
    if result is not None and bound.state == state and bound.params.shape == params.shape:
        changed = np.flatnonzero((params.view(np.int64) != bound.params.view(np.int64)).any(axis=1))
        rows = bound.affected_rows(changed)
        if len(rows) <= INCREMENTAL_MAX_FRACTION * len(bound.points):
            if len(rows):
                accel.vertex_motions(params, bound.indices, values, out=result, rows=rows, key=key)
            bound.params = params
            return result, rows
    bound.forget_result()
    result = accel.vertex_motions(params, bound.indices, values,
                                  out=np.empty((4, len(bound.points), 3), dtype=np.float32), key=key)
    bound.state, bound.params, bound.motions = state, params, result
    return result, None


def _write_motions(mesh: bpy.types.Mesh, uid: str, result: np.ndarray, rows: np.ndarray | None,
                   bound: _Bound | None) -> None:
    """Write `result` (4, N, 3) float32 to the motion attributes unless they already hold it (as
    `_write_offsets`: an incremental result is written when rows changed, a full one when it differs
    from what this process wrote last, or from what the mesh holds when that is unknown), and drop the
    offset attribute, which would add to the motion."""
    if storage.remove_output(mesh, uid, keep="MOTION"):
        mesh.update_tag()
        if bound is not None:
            bound.written = None
    known = bound.motions_written if bound is not None else None
    if known is not None and known.shape == result.shape:
        if rows is not None and len(rows) == 0 and known is result:
            return
        if rows is None and known is not result and np.array_equal(known, result):
            if bound.motions is result:
                bound.motions = known  # keep one array: later incremental updates write into it
            return
    elif rows is None:
        stored = storage.read_motions(mesh, uid)
        if stored is not None and np.array_equal(stored, result):
            if bound is not None:
                bound.motions_written = result
            return
    storage.write_motions(mesh, uid, result)
    if bound is not None:
        bound.motions_written = result


def _finite_motions(result: np.ndarray, rows: np.ndarray | None) -> bool:
    """Whether the motions (4, N, 3) are all finite, given that only `rows` changed (see `_finite`)."""
    # A float32 dot product (BLAS): it also overflows to inf for entries beyond ~1e19, which a float32
    # position could not use either.
    if rows is not None:
        if len(rows) == 0:
            return True
        if 4 * len(rows) < result.shape[1]:
            changed = np.take(result, rows, axis=1).reshape(-1)
            return bool(np.isfinite(np.dot(changed, changed)))
    flat = result.reshape(-1)
    return bool(np.isfinite(np.dot(flat, flat)))


#: Modifier types that rebuild the mesh from scratch and drop its point attributes: a deformer after
#: one of them receives no motions (measured on 4.2 and 5.0; Subdivision, Multires, Mirror, Array,
#: Bevel, Solidify, Triangulate, Decimate, Weld, Edge Split, Screw, Wireframe and Boolean keep or
#: interpolate them).
DROPS_ATTRIBUTES = frozenset({"REMESH", "SKIN", "OCEAN"})


def output_path(obj: bpy.types.Object, deformer, rest32: np.ndarray) -> tuple[str, str]:
    """('OFFSET' or 'MOTION', error) for the deformer's modifier where it stands in the stack.

    OFFSET (v' − v from the rest shape, 3 floats per vertex) is exact only when the positions that
    reach the modifier are the mesh's own (`rest32`, as stored): no modifier before it is enabled in
    the viewport or in renders, and the mesh has no shape keys, or only its reference key holding
    exactly those positions (a Basis nothing is keyed on yet). Otherwise MOTION: each vertex's affine
    map, applied to whatever reaches the modifier. A modifier before it that drops point attributes is
    an error naming it (the modifier then passes its input through)."""
    mod = _modifier(obj, deformer.uid)
    before = []
    for other in obj.modifiers:
        if other == mod:
            break
        if other.show_viewport or other.show_render:
            before.append(other)
    if not before and _keys_keep_rest(obj.data, rest32):
        return "OFFSET", ""
    for other in before:
        if other.type in DROPS_ATTRIBUTES:
            return "MOTION", (f"'{other.name}' rebuilds the mesh before '{mod.name}', which then gets no "
                              f"per-vertex motions: move '{other.name}' below '{mod.name}' in the stack "
                              "(until then the deformer has no effect)")
    return "MOTION", ""


def _keys_keep_rest(mesh: bpy.types.Mesh, rest32: np.ndarray) -> bool:
    """Whether the shape keys (if any) leave the mesh's stored positions as they are: none, or only the
    reference key, holding exactly `rest32`."""
    key = mesh.shape_keys
    if key is None:
        return True
    if len(key.key_blocks) != 1:
        return False
    basis = np.empty(rest32.size, dtype=np.float32)
    key.key_blocks[0].data.foreach_get("co", basis)
    return np.array_equal(basis.reshape(rest32.shape), rest32)


def evaluate_deformer(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> str:
    """Evaluate one deformer and write its output when it changed. Returns its status ('' = fine)."""
    error = _precheck(obj, deformer)
    motions = None
    if not error:
        motions = KINDS[deformer.kind].current_motions(obj, deformer, depsgraph)
        error = motions.error
    if obj.type != "MESH":
        _set_status(deformer, error)
        return error
    mesh = obj.data
    bound = None
    if not error:
        try:
            bound = _bind_data(obj, deformer, len(motions.matrices))
        except storage.StorageError as exc:
            error = str(exc)
    path = "OFFSET"
    if not error:
        path, error = output_path(obj, deformer, bound.rest32)
    signature = (
        mesh.session_uid, None if bound is None else bound.serial, error, path, deformer.strength,
        deformer.blend_mode, deformer.branch_rule, deformer.bind_generation,
        None if motions is None else (motions.matrices.tobytes(), motions.at_rest.tobytes(),
                                      motions.current_rotations.tobytes(), tuple(motions.rotation_modes),
                                      motions.channel_frames.tobytes(),
                                      *(None if a is None else a.tobytes()
                                        for a in (motions.params, motions.outer, motions.valid,
                                                  motions.outer_reference, motions.outer_pivot)),
                                      motions.warning),
    )
    key = (obj.session_uid, deformer.uid)
    if _signatures.get(key) == signature:
        return deformer.status
    output, rows = None, None
    if not error:
        compute, finite = (_motions, _finite_motions) if path == "MOTION" else (_offsets, _finite)
        try:
            output, rows = compute(deformer, motions, bound)
        except storage.StorageError as exc:
            error = str(exc)
        except ValueError as exc:  # core refuses to blend (e.g. a motion too degenerate for its log)
            error = f"The controls' motions cannot be blended ({exc}): the mesh shows its rest shape"
        if not error and not finite(output, rows):
            error = "The deformation is not finite: the mesh shows its rest shape"
        if error:
            bound.forget_result()  # start the next update from a full recompute
    if error:
        # Zero offsets and no motions: the modifier passes its input through, wherever it stands.
        path, output, rows = "OFFSET", np.zeros((len(mesh.vertices), 3)), None
        cached = _bound.get((obj.session_uid, deformer.uid))
        if cached is not None:
            cached.written = cached.motions_written = None  # written below without them
    if mesh.library is None:
        if path == "MOTION":
            _write_motions(mesh, deformer.uid, output, rows, bound)
        else:
            if storage.remove_output(mesh, deformer.uid, keep="OFFSET") and bound is not None:
                bound.motions_written = None
            _write_offsets(mesh, deformer.uid, output, rows, None if error else bound)
    elif bound is not None:
        bound.written = bound.motions_written = None
    status = error or "; ".join(m for m in (motions.warning if motions else "", deformer.bind_warning) if m)
    _set_status(deformer, status)
    _signatures[key] = signature
    _errors[key] = error
    return status


def _finite(offsets: np.ndarray, rows: np.ndarray | None) -> bool:
    """Whether `offsets` (N, 3) float64 are all finite, given that only `rows` (None: any) changed since
    they were last found finite (an incremental result starts from a checked one: a failed check
    drops it, see evaluate_deformer).

    One dot product x·x instead of a (N, 3) boolean array: NaN and ±inf propagate into it, and it only
    overflows for some |x| > 1.3e154, which float32 storage would turn into ±inf anyway.
    """
    if rows is not None:
        if len(rows) == 0:
            return True
        if 4 * len(rows) < len(offsets):  # a gather of few rows costs less than a pass over all
            changed = np.take(offsets, rows, axis=0).reshape(-1)
            return bool(np.isfinite(np.dot(changed, changed)))
    flat = offsets.reshape(-1)
    return bool(np.isfinite(np.dot(flat, flat)))


def _write_offsets(mesh: bpy.types.Mesh, uid: str, offsets: np.ndarray, rows: np.ndarray | None,
                   bound: _Bound | None) -> None:
    """Write `offsets` to the offset attribute unless it already holds them (a write tags the mesh,
    which triggers another depsgraph update).

    With `bound`'s copy of the attribute nothing is read back from the mesh: an incremental result
    (`rows` not None) is written when rows were recomputed (their parameters changed, so they almost
    always moved; an identical write only costs one more, signature-cached, update) and skipped when
    none were; a full result is compared with the copy. Without a copy the attribute is read back.
    An incremental result's rows are already in the copy: `_offsets_affine` had the kernel round them
    into it (float32(offset), what a cast of the whole array would give), so nothing is converted here.
    """
    if bound is not None and bound.written is not None and bound.written.shape == offsets.shape:
        if rows is not None and len(rows) == 0:
            return
        if rows is None:
            fresh = offsets.astype(np.float32)
            if np.array_equal(bound.written, fresh):
                return
            bound.written = fresh
        storage.write_offsets_unchecked(mesh, uid, bound.written)
        return
    fresh = np.array(offsets, dtype=np.float32, order="C")  # always a copy: `offsets` may be a cache's
    storage.write_offsets(mesh, uid, fresh)  # compares with what the mesh holds
    if bound is not None:
        bound.written = fresh


def blocking_error(obj: bpy.types.Object, deformer) -> str:
    """The error of the deformer's last evaluation ('' when it deformed, possibly with a warning)."""
    return _errors.get((obj.session_uid, deformer.uid), "")


def evaluate_object(obj: bpy.types.Object, depsgraph: bpy.types.Depsgraph | None = None) -> list[str]:
    """Evaluate every deformer of `obj`; returns their statuses. Objects in Edit Mode are left alone
    (their mesh data is not in sync). For scripts: call `bpy.context.evaluated_depsgraph_get()`
    afterwards to see the written offsets in the evaluated mesh."""
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    if obj.mode == "EDIT":
        return [d.status for d in obj.affine_deformers]
    try:
        binding.separate_shared_ids(obj)  # linked duplicates must not share output attributes
    except Exception:  # never let it stop the evaluation; the ids stay shared and the next update retries
        traceback.print_exc()
    statuses = []
    for deformer in obj.affine_deformers:
        try:
            statuses.append(evaluate_deformer(obj, deformer, depsgraph))
        except Exception as exc:  # never let bad data take the handler (or Blender) down
            message = f"Internal error ({type(exc).__name__}: {exc}): the mesh shows its rest shape"
            if deformer.status != message:  # print once, not at every depsgraph update
                traceback.print_exc()
            try:
                _bound.pop((obj.session_uid, deformer.uid), None)  # its copy of the attribute is stale
                if obj.type == "MESH" and obj.data.library is None:
                    storage.remove_output(obj.data, deformer.uid, keep="OFFSET")
                    storage.write_offsets(obj.data, deformer.uid, np.zeros((len(obj.data.vertices), 3)))
                _set_status(deformer, message)
            except Exception:
                traceback.print_exc()
            statuses.append(message)
    return statuses


def evaluate_all(scene: bpy.types.Scene | None = None, depsgraph: bpy.types.Depsgraph | None = None) -> None:
    """Evaluate every deformer in `scene` (default: the context scene and its evaluated depsgraph)."""
    if scene is None:
        scene = bpy.context.scene
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    _run(scene, depsgraph)


def _run(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None) -> None:
    global _busy
    if _busy or scene is None or depsgraph is None:
        return
    _busy = True
    try:
        shown = _shown_elsewhere(scene, depsgraph)
        for obj in scene.objects:
            if len(obj.affine_deformers) and not shown(obj):
                evaluate_object(obj, depsgraph)
    except Exception:
        traceback.print_exc()
    finally:
        _busy = False


def _shown_elsewhere(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph):
    """A test for objects whose viewport update from `scene` is skipped: those the context's scene
    shows too, when `scene` is another one. A deformer's output lives on the mesh, which holds one
    shape at a time, so two scenes at different frames would rewrite it on every alternate update;
    the scene the artist is in wins. Renders are never skipped."""
    active = getattr(bpy.context, "scene", None)
    if depsgraph.mode == "RENDER" or active is None or active == scene:
        return lambda _obj: False
    objects = active.objects
    return lambda obj: objects.get(obj.name) == obj


@persistent
def on_frame_change_post(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None = None) -> None:
    _run(scene, depsgraph)


@persistent
def on_depsgraph_update_post(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None = None) -> None:
    _run(scene, depsgraph)


@persistent
def on_load_post(*_args) -> None:
    forget()
    try:
        relations.upgrade_all()  # versioning: node groups and control inputs of older files
    except Exception:
        traceback.print_exc()
    try:
        if bpy.context.scene is not None:
            _run(bpy.context.scene, bpy.context.evaluated_depsgraph_get())
    except Exception:
        traceback.print_exc()


@persistent
def on_undo_redo(*_args) -> None:
    # Undo restores mesh attributes and transforms together; cached signatures may describe neither.
    forget()


@persistent
def on_render_start(scene: bpy.types.Scene, *_args) -> None:
    # Handlers write mesh data during renders: the interface must be locked or Blender may crash.
    try:
        if not scene.render.use_lock_interface:
            scene.render.use_lock_interface = True
    except Exception:
        traceback.print_exc()


HANDLERS = (
    ("frame_change_post", on_frame_change_post),
    ("depsgraph_update_post", on_depsgraph_update_post),
    ("load_post", on_load_post),
    ("undo_post", on_undo_redo),
    ("redo_post", on_undo_redo),
    ("render_init", on_render_start),
    ("render_pre", on_render_start),
)


def register_handlers() -> None:
    unregister_handlers()
    for name, func in HANDLERS:
        getattr(bpy.app.handlers, name).append(func)


def unregister_handlers() -> None:
    # Match by qualified name too: after a reload the old function objects are different objects.
    ours = {(f.__module__, f.__name__) for _, f in HANDLERS}
    for name, _func in HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        stale = [h for h in handlers if (getattr(h, "__module__", ""), getattr(h, "__name__", "")) in ours]
        for h in stale:
            handlers.remove(h)
    forget()
