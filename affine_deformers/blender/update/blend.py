"""The kernel step of an update: each vertex's blend of its controls' parameters, as offsets from
the rest shape (OFFSET path) or as affine motions (MOTION path), recomputing only the vertices whose
result can change.

v' = φ(Σ_k w_vk P_idx(v,k)) v (the affine blend, MATH.md §5), or the linear blend
v' = (I + Σ_k w_vk (A_idx(v,k) − I)) v, followed by the kind's outer motion when it has one. Controls
in a hierarchy (Motions.chain: bones) blend down it instead, v' = F_0 ⋯ F_D v (MATH.md §14).
"""

from __future__ import annotations

import numpy as np

from ... import accel
from ...core import deform, hierarchy
from ..kinds import Motions
from . import params as parameters
from .bound import BindRecord

#: Above this fraction of the vertices, an update recomputes everything (gathering and scattering the
#: affected rows would cost more than it saves).
INCREMENTAL_MAX_FRACTION = 0.6


def redistribute(indices: np.ndarray, values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Weights with the slots of invalid controls zeroed and each row rescaled to its former sum, so a
    skipped control's weight goes to the vertex's other controls. Rows left with no valid control
    become zero (the vertex follows only `Motions.outer`)."""
    kept = np.where(valid[indices], values, 0.0)
    before, after = values.sum(axis=1), kept.sum(axis=1)
    scale = np.divide(before, after, out=np.zeros_like(before), where=after > 0.0)
    return kept * scale[:, None]


def _values(deformer, motions: Motions, bound: BindRecord) -> np.ndarray:
    """The bound weights at the deformer's strength, with skipped controls' weight redistributed (a
    pooled node, a mix of controls, is valid while any control of its mix is)."""
    if motions.valid is not None and not np.all(motions.valid):
        valid = motions.valid
        if bound.pooled:
            valid = np.append(valid, (pool_mix(motions, len(valid))[:, valid] > 0.0).any(axis=1))
        return redistribute(bound.indices, bound.values, valid) * deformer.strength
    return bound.scaled_values(deformer.strength)


def pool_mix(motions: Motions, m: int) -> np.ndarray:
    """The truncation's pooled nodes as mixes of the m controls (G, m) (MATH.md §12): `motions.pool`
    ((m,): one node, the probes' pooled control; (G, m): cage pool nodes, bones' children means), the
    controls alike when None."""
    if motions.pool is None:
        return np.full((1, m), 1.0 / m)
    return np.atleast_2d(np.asarray(motions.pool, dtype=np.float64))


def _pooled(table: np.ndarray, motions: Motions, bound: BindRecord) -> np.ndarray:
    """`table` (m, ...) — parameters, or matrices for the linear blend — with the truncation's pooled
    nodes appended as rows m … m + G − 1 when the bound weights point at them (MATH.md §12): each
    the mix Σ_i mix_gi table[i] (`pool_mix`) of the controls not skipped. A bone's pooled nodes mix
    its children (core.hierarchy.pool_mix: exact as weights on the controls, so the linear blend takes
    them as such; the affine blend down the hierarchy uses `_chain_inputs`)."""
    if not bound.pooled:
        return table
    m = len(table)
    mix = pool_mix(motions, m)
    if motions.valid is not None and not np.all(motions.valid):
        mix = np.where(motions.valid, mix, 0.0)
        total = mix.sum(axis=1, keepdims=True)
        mix = np.divide(mix, total, out=np.zeros_like(mix), where=total > 0.0)  # none valid: 0 anyway
    return np.concatenate([np.asarray(table, dtype=np.float64), np.tensordot(mix, table, axes=(1, 0))])


def blend_offsets(deformer, motions: Motions, bound: BindRecord,
                  state: tuple) -> tuple[np.ndarray, np.ndarray | None]:
    """(v' − v for every rest vertex (N, 3) float64, rows): exactly zero when every control is at rest.

    `rows` are the only vertices whose offsets may differ from the previous result of `bound` (None:
    any may); `state` is what the result is computed with (Snapshot.result_state). The returned
    array may be the result's own (`bound.result.offsets`): callers must not modify it.
    """
    result = bound.result
    result.prove(False)
    outer = parameters.outer_at_strength(motions, deformer.strength, deformer.branch_rule)
    points = bound.points
    if deformer.strength == 0.0 or len(motions.matrices) == 0 or (np.all(motions.at_rest) and outer is None):
        result.forget()
        return np.zeros(points.shape, dtype=np.float64), None
    if np.all(motions.at_rest):
        result.forget()
        deformed = points.copy()
    elif _plain_affine(deformer, motions, outer):
        if motions.chain is not None:
            return _offsets_chain(deformer, motions, bound, state)
        return _offsets_affine(deformer, motions, bound, state)
    else:
        result.forget()
        indices, values = bound.indices, _values(deformer, motions, bound)
        if deformer.blend_mode == "LINEAR":
            deformed = deform.blend_linear_sparse(points, _pooled(motions.matrices, motions, bound), indices,
                                                  values)
        else:
            params = _pooled(parameters.motions_to_params(motions, deformer.branch_rule), motions, bound)
            deformed = accel.deform_points_params(points, params, indices, values)
    if outer is not None:
        deformed = deformed @ outer[:3, :3].T + outer[:3, 3]
    return deformed - points, None


def _offsets_affine(deformer, motions: Motions, bound: BindRecord,
                    state: tuple) -> tuple[np.ndarray, np.ndarray | None]:
    """`blend_offsets` for the plain affine blend, recomputing only the vertices whose result can differ
    from the cached one: those with a non-zero weight on a control whose parameters changed bitwise.
    The others keep their cached offsets, which equal a recomputation bit for bit (a vertex's result
    depends only on its rest position, its weights and its controls' parameters; the kernel's rows
    are independent of how vertices are grouped). Controls at rest have zero parameters, so vertices
    that only they influence keep offset 0, exactly what φ(0) gives."""
    params = _pooled(parameters.motions_to_params(motions, deformer.branch_rule), motions, bound)
    values = bound.scaled_values(deformer.strength)
    points = bound.points
    key = (bound.serial, deformer.strength)
    result = bound.result
    rows = _changed_rows(bound, params, state, motions=False)
    if rows is not None:
        offsets = result.offsets
        if len(rows):
            # The kernel also rounds the rows it computes into the copy of the stored offsets, so the
            # write takes that copy as it is (result.Result.pending_offsets: keep in step).
            out32 = result.offsets_buffer(offsets.shape)
            accel.deform_points_params_rows(points, params, bound.indices, values, rows, offsets,
                                             offsets=True, key=key, out32=out32)
        result.advance(params)
        result.prove(_storable_by_bound(bound, params, deformer.strength, offsets=True))
        return offsets, rows
    result.forget()
    offsets = accel.deform_points_params(points, params, bound.indices, values, key=key)
    offsets -= points
    result.keep(state, params, offsets=offsets)
    result.prove(_storable_by_bound(bound, params, deformer.strength, offsets=True))
    return offsets, None


#: A result proven below this magnitude (a quarter of float32's largest) is stored without a pass
#: over it; the margin covers the kernel's rounding many times over.
PROVEN_LIMIT = 0.25 * float(np.finfo(np.float32).max)


def _storable_by_bound(bound: BindRecord, params: np.ndarray, strength: float, offsets: bool) -> bool:
    """Whether every vertex's result of the plain affine blend with `params` is provably finite and
    storable as float32 (core.deform.motion_bound over the bound points, or over unit columns for
    motions), so the output check needs no pass over the vertices. A cached row computed with
    older parameters passed this check or the full one when it was computed."""
    radius, weight_sum = bound.reach(strength)
    if offsets:
        return deform.motion_bound(params, weight_sum, radius) + radius < PROVEN_LIMIT
    return deform.motion_bound(params, weight_sum, 1.0) < PROVEN_LIMIT


def _changed_rows(bound: BindRecord, params: np.ndarray, state: tuple, motions: bool) -> np.ndarray | None:
    """The vertices to recompute when the last result (bound.result) was computed with the same
    `state` (the snapshot's result state: path, strength, branch rule, kernel backend — the two
    kernels agree to ~1e-15, not bit for bit, and an incremental update must equal a full recompute
    exactly): those with weight on a control whose parameter row changed bitwise. None: recompute
    everything (no usable previous result, or too many rows changed)."""
    changed = bound.result.changed_controls(state, params, motions=motions)
    if changed is None:
        return None
    return _rows_to_recompute(bound, changed, len(params), bound.affected_rows, bound.weighted_rows)


def _rows_to_recompute(bound: BindRecord, changed: np.ndarray, m: int, affected,
                       every=None) -> np.ndarray | None:
    """The rows an incremental update recomputes when the controls `changed` (of m) changed, or None
    for a full recompute; `affected(changed)` gives the vertices reading them, `every()` (default:
    every vertex) those reading any control.

    With the compiled kernel its row path is taken however many rows there are: it costs no more than
    a full pass and rounds the rows into the attribute's copy as it goes, so the write needs neither a
    cast nor a compare; when every control changed, `every()` lists the rows without forming the union.
    The numpy kernel recomputes everything above INCREMENTAL_MAX_FRACTION of the vertices (its gathers
    and scatters would cost more than they save). Either way the result is bit-identical."""
    compiled = accel.active()
    if compiled and m and len(changed) == m:
        return every() if every is not None else bound.every_row()
    rows = affected(changed)
    return rows if compiled or len(rows) <= INCREMENTAL_MAX_FRACTION * len(bound.points) else None


def blend_motions(deformer, motions: Motions, bound: BindRecord,
                  state: tuple) -> tuple[np.ndarray, np.ndarray | None]:
    """(each rest vertex's motion x ↦ M x + t as (4, N, 3) float32 columns M e_x, M e_y, M e_z, t,
    rows): the motion path's counterpart of `blend_offsets` (same rules, same `rows` meaning); exactly the
    identity when every control is at rest. The array may be the cache's own: do not modify it."""
    bound.result.prove(False)
    outer = parameters.outer_at_strength(motions, deformer.strength, deformer.branch_rule)
    n = len(bound.points)
    at_rest = deformer.strength == 0.0 or len(motions.matrices) == 0 or np.all(motions.at_rest)
    if _plain_affine(deformer, motions, outer) and not (at_rest and motions.chain is not None):
        if motions.chain is not None:
            return _motions_chain(deformer, motions, bound, state)
        return _motions_affine(deformer, motions, bound, state)
    bound.result.forget()
    if at_rest:
        result = _identity_motions(n)
    else:
        indices, values = bound.indices, _values(deformer, motions, bound)
        if deformer.blend_mode == "LINEAR":
            result = _linear_motions(_pooled(motions.matrices, motions, bound), indices, values)
        else:
            params = _pooled(parameters.motions_to_params(motions, deformer.branch_rule), motions, bound)
            result = accel.vertex_motions(params, indices, values)
    if outer is not None:
        result = _compose(outer, result)
    return np.ascontiguousarray(result, dtype=np.float32), None


_identity_motions = hierarchy.identity_motions


def _plain_affine(deformer, motions: Motions, outer: np.ndarray | None) -> bool:
    """Whether the update is the plain affine blend (no outer motion, no skipped control), the one
    with incremental updates."""
    return (deformer.blend_mode != "LINEAR" and outer is None
            and (motions.valid is None or bool(np.all(motions.valid))))


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


def _motions_affine(deformer, motions: Motions, bound: BindRecord,
                    state: tuple) -> tuple[np.ndarray, np.ndarray | None]:
    """`blend_motions` for the plain affine blend, recomputing only the vertices whose motion can
    differ from the cached one (the rule of `_offsets_affine`, for motions instead of offsets)."""
    params = _pooled(parameters.motions_to_params(motions, deformer.branch_rule), motions, bound)
    values = bound.scaled_values(deformer.strength)
    key = (bound.serial, deformer.strength)
    kept = bound.result
    rows = _changed_rows(bound, params, state, motions=True)
    if rows is not None:
        result = kept.motions
        if len(rows):
            accel.vertex_motions(params, bound.indices, values, out=result, rows=rows, key=key)
        kept.advance(params)
        kept.prove(_storable_by_bound(bound, params, deformer.strength, offsets=False))
        return result, rows
    kept.forget()
    result = accel.vertex_motions(params, bound.indices, values,
                                  out=np.empty((4, len(bound.points), 3), dtype=np.float32), key=key)
    kept.keep(state, params, motions=result)
    kept.prove(_storable_by_bound(bound, params, deformer.strength, offsets=False))
    return result, None


def _chain_inputs(deformer, motions: Motions, bound: BindRecord, state: tuple, as_motions: bool
                  ) -> tuple[np.ndarray, np.ndarray, hierarchy.ChainLayout, tuple, np.ndarray | None]:
    """(ψ(L_i), the prefix matrices (core.hierarchy.prefix_table), the weights' layout down the
    hierarchy, the result state, the rows to recompute or None for all): as `_changed_rows`, a vertex
    is recomputed when a control it reads changed bitwise — in its local parameters (a factor) or in
    its full motion (a prefix)."""
    chain = motions.chain
    params = parameters.chain_params(motions, deformer.branch_rule)
    matrices, parents = motions.matrices, chain.parents
    if bound.pooled:  # the pooled nodes below each bone and the roots (MATH.md §12)
        params, matrices = hierarchy.pool_tables(params, matrices, motions.pool)
        parents = hierarchy.pool_parents(parents)
    prefixes = hierarchy.prefix_table(matrices)
    layout = bound.chain_layout(parents, deformer.strength)
    state = (state, parents.tobytes())
    changed = bound.result.changed_controls(state, params, motions=as_motions, prefixes=prefixes)
    if changed is None:
        return params, prefixes, layout, state, None
    rows = _rows_to_recompute(bound, changed, len(params), layout.affected_rows)
    return params, prefixes, layout, state, rows


def _chain_args(bound: BindRecord, params: np.ndarray, prefixes: np.ndarray,
                layout: hierarchy.ChainLayout) -> tuple[tuple, dict]:
    """The arguments of accel.chain_points / chain_motions, with a key naming the bound points and
    the layout's passes for the kernel's argument checks: a layout is a pure function of the bound
    weights (`bound.serial`) and its cache key (parents, strength)."""
    key = ("chain", bound.serial, bound.layout_key())
    return (params, layout.indices, layout.values, layout.prefix, prefixes), {"key": key}


def _offsets_chain(deformer, motions: Motions, bound: BindRecord,
                   state: tuple) -> tuple[np.ndarray, np.ndarray | None]:
    """`blend_offsets` down a hierarchy (accel.chain_points), recomputing only the vertices that read
    a changed control (rows are independent: bit-identical to a full recompute)."""
    params, prefixes, layout, state, rows = _chain_inputs(deformer, motions, bound, state, False)
    args, key = _chain_args(bound, params, prefixes, layout)
    points = bound.points
    kept = bound.result
    if rows is not None and kept.offsets is not None:
        offsets = kept.offsets
        if len(rows):
            # The kernel rounds the rows it computes into the store's copy too, as in _offsets_affine.
            accel.chain_points(points, *args, rows, offsets, offsets=True,
                               out32=kept.offsets_buffer(offsets.shape), **key)
        kept.advance(params, prefixes)
        return offsets, rows
    kept.forget()
    offsets = accel.chain_points(points, *args, offsets=True, **key)
    kept.keep(state, params, offsets=offsets, prefixes=prefixes)
    return offsets, None


def _motions_chain(deformer, motions: Motions, bound: BindRecord,
                   state: tuple) -> tuple[np.ndarray, np.ndarray | None]:
    """`blend_motions` down a hierarchy (accel.chain_motions), incremental as `_offsets_chain`."""
    params, prefixes, layout, state, rows = _chain_inputs(deformer, motions, bound, state, True)
    args, key = _chain_args(bound, params, prefixes, layout)
    kept = bound.result
    if rows is not None and kept.motions is not None:
        result = kept.motions
        if len(rows):
            accel.chain_motions(*args, result, rows=rows, **key)
        kept.advance(params, prefixes)
        return result, rows
    kept.forget()
    result = accel.chain_motions(*args, np.empty((4, len(bound.points), 3), dtype=np.float32), **key)
    kept.keep(state, params, motions=result, prefixes=prefixes)
    return result, None
