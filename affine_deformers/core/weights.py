"""Per-vertex weights: distance kernels, falloff, normalisation and top-K sparsification in chunks.

The deformer needs, per vertex, the K strongest controls and their weights: `(indices (N, K) int32,
values (N, K) float64)`. Those are built chunk by chunk from any function that returns a dense
(chunk, m) weight block (`sparse_from_blocks`), so peak memory is O(N·K + chunk·m) however many
controls there are; the probe builder (`probe_weights`) and the painted-weights converter
(`top_k_dense`) are thin layers over it, and the cage code can pass its own distance function.

Kernels (d = distance to a control's rest position):

* inverse distance  w = (r / max(d, d_min))^p — finite and dominant on top of a control;
* smooth falloff    w = (1 − (d/R)²)^q for d < R, exactly 0 for d ≥ R (C^{q−1} at R, smooth at 0).

Truncation to K (`truncate`, MATH.md §12) is continuous and its slope is bounded near ties: each
kept weight is lowered by the (K+1)-th, w_j − w_{K+1}, and divided by D = max(S, c·T), S the sum of
the lowered weights and T a total the caller gives (by default the kept weights' sum). Where S < c·T
the kept weights sum to S/D < 1; the rest, the pooled weight λ = 1 − S/D, goes to a pooled control:
`sparse_from_blocks` stores it as one more column whose index is m (one past the last control), and
the deformer blends there the mean of all controls' parameters weighted by `pool_weights`
(`with_pool`), so a motion shared by all controls stays exact everywhere; with a `PoolColumns` (bones:
core.hierarchy.PoolPoint) the pooled weight goes to its columns of pooled nodes instead, each a fixed
mix of the controls. Nothing is pooled when m ≤ K.

Normalisation of the kept K weights of a row: 'NONE' (as is), 'SUM' (divide by the row sum; all-zero
rows stay zero), 'SOFTMAX' (exp(w − max w) over the row's positive entries, summing to 1; zero
entries stay zero, so a falloff's locality survives). With m > K, 'SUM' and 'SOFTMAX' weights are
truncated as above (the softmax numerators exp(w − max w) in place of w), 'NONE' ones by the raw rule
of `truncate`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32]
BlockFn = Callable[[int, int], ArrayLike]


class PoolColumns(Protocol):
    """Where a row's pooled weight λ goes, when not to one pooled control (index m): `width` columns
    of node indices and shares summing to 1, from the row's untruncated weights (the block `truncate`
    lowers). core.hierarchy.PoolPoint is the bones' (MATH.md §12)."""

    width: int

    def __call__(self, weights: FloatArray) -> tuple[IntArray, FloatArray]: ...


__all__ = [
    "NORMALIZE_MODES",
    "WEIGHT_MODES",
    "PoolColumns",
    "inverse_distance",
    "normalize",
    "pool_weights",
    "probe_weights",
    "smooth_falloff",
    "sparse_from_blocks",
    "top_k",
    "top_k_dense",
    "truncate",
    "with_pool",
]

NORMALIZE_MODES = ("NONE", "SUM", "SOFTMAX")
WEIGHT_MODES = ("INVERSE_DISTANCE", "FALLOFF", "VERTEX_GROUPS", "SURFACE")

#: Dense block size (chunk · m entries) processed at a time by `sparse_from_blocks`.
BLOCK_ELEMENTS = 1 << 18
#: Default distance floor of `inverse_distance`, relative to its reference distance r.
MIN_DISTANCE_FRACTION = 1e-6
#: Max Influences of a new probe deformer (kinds/probe.py sets it; the property's own default, 4,
#: stays for files saved by 0.1.0, which store no value when it was left alone). 8 keeps every probe
#: of rigs of up to 8 (a ring of 8, the corners of a cube: no truncation at all) and passes the tie
#: tests beyond (tests/core/test_field_ties.py; 6 left steps of 3.7× the untruncated field's along
#: the mid-planes of a 3×3×3 grid). Each influence beyond costs the compiled kernel a blend row per
#: vertex; the numpy kernel's dense blend (≤ 48 probes) does not depend on it
#: (bench/influence_cost.py).
PROBE_INFLUENCES = 8
#: c in the truncation's divisor D = max(S, c·T) (MATH.md §12) for probe weights (bones:
#: hierarchy.BONE_POOL_FLOOR; cages use this c with T their 16 nearest faces' weight), T the
#: row's total weight over every control: the kept weights are renormalised exactly (nothing pooled)
#: wherever their excess over the (K+1)-th keeps half of the total weight, and no slope exceeds
#: about 2(1 + K)/c times the untruncated field's. Measured on rings, grids and a mirrored bar
#: (tests/core/test_field_ties.py): relative to the kept weights' sum instead of T, steps through
#: the 8-probe ties of a 3×3×3 grid reach 10× the untruncated field's at K = 4; c = 1 pools weight
#: at every truncated vertex, which carries the mean of far probes' motions into all of them (MATH.md
#: §12 has the numbers).
POOL_FLOOR = 0.5


def inverse_distance(
    distances: ArrayLike, exponent: float = 2.0, reference: float = 1.0, min_distance: float | None = None
) -> FloatArray:
    """w = (reference / max(d, min_distance))^exponent.

    The floor (default MIN_DISTANCE_FRACTION · reference) keeps a vertex sitting on a control finite,
    with a weight that dominates every other control after normalisation.
    """
    if not exponent > 0.0:
        raise ValueError(f"exponent must be positive, got {exponent}")
    if not reference > 0.0:
        raise ValueError(f"reference distance must be positive, got {reference}")
    floor = MIN_DISTANCE_FRACTION * reference if min_distance is None else float(min_distance)
    if not floor > 0.0:
        raise ValueError(f"min_distance must be positive, got {min_distance}")
    d = np.maximum(np.asarray(distances, dtype=np.float64), floor)
    return (reference / d) ** exponent


def smooth_falloff(distances: ArrayLike, radius: float, power: int = 2) -> FloatArray:
    """w = (1 − (d/R)²)^power for d < R, exactly 0 for d ≥ R; 1 at d = 0.

    power = 2 is C¹ at R, power = 3 is C². As a function of position it is smooth at the centre too
    (it depends on d², so there is no cusp under the control).
    """
    if not radius > 0.0:
        raise ValueError(f"radius must be positive, got {radius}")
    if power < 1:
        raise ValueError(f"power must be at least 1, got {power}")
    # min(d/R, 1) also maps d = inf to exactly 0 without overflow warnings
    x = np.minimum(np.asarray(distances, dtype=np.float64) / radius, 1.0)
    return (1.0 - x * x) ** power


def normalize(W: ArrayLike, mode: str = "SUM", temperature: float = 1.0) -> FloatArray:
    """Row-wise normalisation of non-negative weights (..., m); see the module docstring.

    'SOFTMAX' uses exp((w − max w)/temperature) over the positive entries of each row.
    """
    W = np.asarray(W, dtype=np.float64)
    if mode == "NONE":
        return W.copy()
    if mode == "SUM":
        total = W.sum(axis=-1, keepdims=True)
        ok = total > 0.0
        return np.where(ok, W / np.where(ok, total, 1.0), 0.0)
    if mode == "SOFTMAX":
        if not temperature > 0.0:
            raise ValueError(f"temperature must be positive, got {temperature}")
        e = _softmax_numerators(W, temperature)
        total = e.sum(axis=-1, keepdims=True)
        return np.where(total > 0.0, e / np.where(total > 0.0, total, 1.0), 0.0)
    raise ValueError(f"normalize mode must be one of {NORMALIZE_MODES}, got {mode!r}")


def top_k(W: ArrayLike, k: int) -> tuple[IntArray, FloatArray]:
    """The k largest entries of each row of W (n, m) -> (indices (n, K) int32, values (n, K)), K = min(k, m).

    Rows are ordered by value (descending), ties by control index, so the result depends on the row
    alone (chunking cannot change it).
    """
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2:
        raise ValueError(f"weights must have shape (n, m), got {W.shape}")
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    n, m = W.shape
    K = min(int(k), m)
    part = np.argpartition(-W, K - 1, axis=1)[:, :K] if m > K else np.broadcast_to(np.arange(m), (n, m))
    # Sort the kept candidates by (−value, index) so ties resolve the same way in every chunk.
    part = np.sort(part, axis=1)
    vals = np.take_along_axis(W, part, axis=1)
    order = np.argsort(-vals, axis=1, kind="stable")
    idx = np.take_along_axis(part, order, axis=1).astype(np.int32)
    return idx, np.take_along_axis(vals, order, axis=1)


def truncate(
    W: ArrayLike,
    k: int,
    raw: bool = False,
    total: ArrayLike | None = None,
    floor: float = POOL_FLOOR,
    with_pooled: bool = False,
) -> tuple[IntArray, FloatArray] | tuple[IntArray, FloatArray, FloatArray]:
    """Continuous top-K of non-negative weights W (n, m) with a bounded slope -> (indices (n, K) int32,
    values (n, K) ≥ 0), K = min(k, m), ordered as `top_k` (MATH.md §12).

    Plain top-K jumps where the K-th and (K+1)-th controls swap: the one leaving drops from w_K to 0.
    Here every kept value is a function of (w_j, w_{K+1}, …) that vanishes at w_j = w_{K+1}, and
    w_{K+1} is an order statistic, a continuous function of W, so a control fades out as it leaves:

    * raw=False: v_j = e_j / D with e_j = max(w_j − w_{K+1}, 0), S = Σ_{j≤K} e_j and
      D = max(S, floor·T), T = `total` (n,) (the row's weight over all controls, ≥ the kept weights'
      sum; default: the kept weights' sum Σ_{j≤K} w_j). Σ_j v_j = S/D ≤ 1, with equality (the kept
      weights renormalised, as 'SUM' does) wherever S ≥ floor·T; the caller gives the rest
      λ = 1 − S/D to a pooled control (`sparse_from_blocks`). Dividing by S alone would make
      ∂v_K/∂w_K = 1/S unbounded where the K+1 strongest nearly tie (S → 0: the centre of a ring of
      probes, all of whose weights tie); with D ≥ floor·T every slope is bounded: with
      γ = max_i |∇w_i|, |∇e_j| ≤ 2γ and |∇D| = |∇S| ≤ 2Kγ where D = S, floor·|∇T| elsewhere, so
      |∇v_j| ≤ (|∇e_j| + v_j |∇D|)/D ≤ 2(1 + K v_j) γ / (floor·T) + v_j |∇T| / T. Where all K+1 tie
      exactly every value is 0 (λ = 1), the limit of its neighbourhood. With m ≤ k nothing is
      lowered: v = w / max(Σw, floor·T). All-zero rows stay zero. with_pooled=True returns λ (n,)
      as a third array (exactly 0 where S ≥ floor·T and in all-zero rows).
    * raw=True (for weights used as they are, normalisation 'NONE'): v_j = min(w_j, 2 (w_j − w_{K+1})):
      a weight at least twice the first dropped one is kept exactly (a vertex on a probe still follows
      it fully), smaller ones ramp linearly to 0; never above w_j, slope at most 2: continuous
      everywhere (ties included: all values are then 0, the vertex stays at rest as raw weights
      that small leave it). `total` and `floor` are not used; with m ≤ k the values are W's.
    """
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2:
        raise ValueError(f"weights must have shape (n, m), got {W.shape}")
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    if not 0.0 < floor <= 1.0:
        raise ValueError(f"floor must be in (0, 1], got {floor}")
    m = W.shape[1]
    K = min(int(k), m)
    idx, vals = top_k(W, K + 1) if m > K else top_k(W, K)
    kept = vals[:, :K]
    if raw:
        if with_pooled:
            raise ValueError("raw truncation pools nothing")
        if m <= K:
            return idx, kept
        return idx[:, :K].copy(), np.minimum(kept, 2.0 * np.maximum(kept - vals[:, K:], 0.0))
    excess = np.maximum(kept - vals[:, K:], 0.0) if m > K else kept
    if total is None:
        total = kept.sum(axis=1)
    values, pooled = _lowered(excess, total, floor)
    if with_pooled:
        return idx[:, :K].copy(), values, pooled
    return idx[:, :K].copy(), values


def _lowered(excess: FloatArray, total: ArrayLike, floor: float) -> tuple[FloatArray, FloatArray]:
    """(v = excess / D, λ) with D = max(S, floor·total), S = Σ excess per row, and the pooled weight
    λ = 1 − S/D: exactly 0 where S ≥ floor·total (nothing pooled there, so such rows never read the
    pooled control) and in all-zero rows."""
    S = excess.sum(axis=1)
    T = np.asarray(total, dtype=np.float64).reshape(-1)
    if T.shape != S.shape:
        raise ValueError(f"total must have one value per row ({S.size}), got shape {T.shape}")
    F = floor * T
    D = np.maximum(S, F)
    ok = D > 0.0
    safe = np.where(ok, D, 1.0)
    values = np.where(ok[:, None], excess / safe[:, None], 0.0)
    pooled = np.where(ok & (S < F), 1.0 - S / safe, 0.0)
    return values, pooled


def pool_weights(scales: ArrayLike) -> FloatArray:
    """The pooled control's coefficients a_i = s_i / Σ s (m,) for controls scaled by `scales` (m,)
    (weight scales, ≥ 0): the mix of motions a row takes where all its controls tie exactly in
    distance (untruncated weights are then proportional to the scales). Uniform if all are 0."""
    s = np.asarray(scales, dtype=np.float64).reshape(-1)
    if s.size == 0 or not np.all(np.isfinite(s)) or np.any(s < 0.0):
        raise ValueError("scales must be at least one finite non-negative number")
    total = s.sum()
    return s / total if total > 0.0 else np.full(s.size, 1.0 / s.size)


def with_pool(table: ArrayLike, coefficients: ArrayLike) -> FloatArray:
    """`table` (m, ...) (blend parameters (m, 12), or motion matrices for a linear blend) with the
    pooled control's row Σ_i a_i table[i] appended -> (m + 1, ...): what index m of pooled weights
    (`sparse_from_blocks`) reads. A motion G shared by all controls gives the pooled row ψ(G) too
    (Σ a_i = 1), so a vertex blending it with any weights summing to 1 gets exactly G."""
    table = np.asarray(table, dtype=np.float64)
    a = np.asarray(coefficients, dtype=np.float64).reshape(-1)
    if table.shape[:1] != a.shape:
        raise ValueError(f"{a.size} pool coefficients for a table of {table.shape[0]} rows")
    pooled = np.tensordot(a, table, axes=(0, 0))
    return np.concatenate([table, pooled[None]], axis=0)


def _softmax_numerators(W: FloatArray, temperature: float) -> FloatArray:
    """exp((w − max w)/temperature) on each row's positive entries, 0 elsewhere (`normalize`'s
    'SOFTMAX' before its division): monotone in w, so the top K of W are the top K of these."""
    positive = W > 0.0
    top = np.max(np.where(positive, W, -np.inf), axis=-1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    return np.where(positive, np.exp((np.where(positive, W, top) - top) / temperature), 0.0)


def sparse_from_blocks(
    n_points: int,
    n_controls: int,
    block: BlockFn,
    k: int,
    normalize_mode: str = "SUM",
    chunk_size: int | None = None,
    temperature: float = 1.0,
    continuous: bool = True,
    floor: float = POOL_FLOOR,
    pool: PoolColumns | None = None,
) -> tuple[IntArray, FloatArray]:
    """Build sparse top-K weights from `block(lo, hi)` -> dense non-negative (hi − lo, n_controls).

    With K = min(k, n_controls) ≥ n_controls every control is kept and the row is normalised. With
    more controls, each chunk's block is truncated continuously (`truncate`, MATH.md §12):

    * 'SUM': v_j = max(w_j − w_{K+1}, 0) / max(S, floor·T), T = Σ_i w_i over all controls;
      'SOFTMAX': the same on the softmax numerators exp((w − max w)/temperature) of the positive
      entries. The pooled weight λ = 1 − Σ_j v_j goes to one more column, index n_controls (the
      pooled control: the mean of all controls' parameters, `with_pool`), so a row still sums to 1
      (0 for an all-zero row). With `pool`, λ goes to its `width` columns instead, λ times the shares
      it gives each row (bones: a point on their tree, core.hierarchy.PoolPoint). The pooled
      columns are left out when no row pools anything. (With floor = 1,
      D = T: each kept weight would be the untruncated weight w_j/T lowered by w_{K+1}/T, and what is
      taken off all weights, min(w_i, w_{K+1})/T each, pooled at every truncated row; POOL_FLOOR says
      why the default is 1/2.)
    * 'NONE': the raw rule of `truncate` (values as they are, the rest stays at rest).
    * continuous=False: the K largest as they are, then normalised (for painted weights, whose values
      the artist chose; nothing is pooled).

    Peak memory is O(n_points · K + chunk · n_controls); the result does not depend on chunk_size.
    ValueError if a block has the wrong shape, negative or non-finite entries.
    """
    if normalize_mode not in NORMALIZE_MODES:
        raise ValueError(f"normalize mode must be one of {NORMALIZE_MODES}, got {normalize_mode!r}")
    if n_controls < 1:
        raise ValueError("at least one control is needed")
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    if normalize_mode == "SOFTMAX" and not temperature > 0.0:
        raise ValueError(f"temperature must be positive, got {temperature}")
    K = min(int(k), n_controls)
    chunk = int(chunk_size) if chunk_size else max(1, BLOCK_ELEMENTS // n_controls)
    if chunk < 1:
        raise ValueError(f"chunk_size must be positive, got {chunk_size}")
    pooled = continuous and normalize_mode != "NONE" and n_controls > K
    width = (1 if pool is None else int(pool.width)) if pooled else 0
    indices = np.zeros((n_points, K + width), dtype=np.int32)
    values = np.zeros((n_points, K + width), dtype=np.float64)
    if pooled:
        indices[:, K:] = n_controls
    for lo in range(0, n_points, chunk):
        hi = min(lo + chunk, n_points)
        W = np.asarray(block(lo, hi), dtype=np.float64)
        if W.shape != (hi - lo, n_controls):
            raise ValueError(
                f"weight block for rows {lo}:{hi} has shape {W.shape}, expected {(hi - lo, n_controls)}"
            )
        if not np.all(np.isfinite(W)):
            raise ValueError(f"weights for rows {lo}:{hi} contain non-finite values")
        if np.any(W < 0.0):
            raise ValueError(f"weights for rows {lo}:{hi} contain negative values")
        if not continuous:
            idx, val = top_k(W, K)
            val = normalize(val, normalize_mode, temperature)
        elif normalize_mode == "NONE":
            idx, val = truncate(W, K, raw=True)
        elif not pooled:  # every control kept: plain normalisation, as the untruncated field
            idx, val = top_k(W, K)
            val = normalize(val, normalize_mode, temperature)
        else:
            E = W if normalize_mode == "SUM" else _softmax_numerators(W, temperature)
            idx, top = top_k(E, K + 1)
            val, lam = _lowered(np.maximum(top[:, :K] - top[:, K:], 0.0), E.sum(axis=1), floor)
            if pool is None:
                values[lo:hi, K] = lam
            else:
                indices[lo:hi, K:], shares = pool(E)
                values[lo:hi, K:] = lam[:, None] * shares
            idx = idx[:, :K]
        indices[lo:hi, :K] = idx
        values[lo:hi, :K] = val
    if pooled and not np.any(values[:, K:]):
        return indices[:, :K].copy(), values[:, :K].copy()
    return indices, values


def top_k_dense(
    W: ArrayLike, k: int, normalize: str = "SUM", chunk_size: int | None = None
) -> tuple[IntArray, FloatArray]:
    """Dense painted weights (N, m) -> sparse (indices (N, K) int32, values (N, K)), normalised: the K
    largest of each row as painted (no continuous truncation: the values are the artist's)."""
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2:
        raise ValueError(f"weights must have shape (N, m), got {W.shape}")
    return sparse_from_blocks(W.shape[0], W.shape[1], lambda lo, hi: W[lo:hi], k, normalize, chunk_size,
                              continuous=False)


def point_distances(points: FloatArray, centers: FloatArray) -> FloatArray:
    """|p_n − c_i| (N, m) for points (N, 3) and centers (m, 3)."""
    diff = points[:, None, :] - centers[None, :, :]
    return np.sqrt(np.einsum("nmi,nmi->nm", diff, diff))


def segment_distances(points: FloatArray, heads: FloatArray, tails: FloatArray) -> FloatArray:
    """Distances (N, m) from points (N, 3) to the segments heads[i] → tails[i] (m, 3): to the closest
    point h + t (e − h), t = clamp((p − h)·(e − h)/|e − h|², 0, 1) (a zero-length segment: its head)."""
    axis = tails - heads
    length2 = np.einsum("mi,mi->m", axis, axis)
    diff = points[:, None, :] - heads[None, :, :]
    t = np.einsum("nmi,mi->nm", diff, axis) / np.where(length2 > 0.0, length2, 1.0)
    np.clip(t, 0.0, 1.0, out=t)
    diff -= t[:, :, None] * axis[None, :, :]
    return np.sqrt(np.einsum("nmi,nmi->nm", diff, diff))


def _control_inputs(points: ArrayLike, centers: ArrayLike, tails: ArrayLike | None,
                    scales: ArrayLike | None) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray]:
    """`probe_weights`' inputs checked and as float64: (points, centers, tails or None, scales)."""
    pts = np.asarray(points, dtype=np.float64)
    ctr = np.asarray(centers, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if ctr.ndim != 2 or ctr.shape[1] != 3 or ctr.shape[0] < 1:
        raise ValueError(f"centers must have shape (m, 3) with m ≥ 1, got {ctr.shape}")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(ctr))):
        raise ValueError("points or probe positions contain non-finite coordinates")
    m = ctr.shape[0]
    ends = None if tails is None else np.asarray(tails, dtype=np.float64)
    if ends is not None and (ends.shape != ctr.shape or not np.all(np.isfinite(ends))):
        raise ValueError(f"tails must be finite with the shape of centers {ctr.shape}, got {ends.shape}")
    scale = np.ones(m) if scales is None else np.asarray(scales, dtype=np.float64)
    if scale.shape != (m,) or not np.all(np.isfinite(scale)) or np.any(scale < 0.0):
        raise ValueError(f"scales must be {m} finite non-negative numbers")
    return pts, ctr, ends, scale


def probe_weights(
    points: ArrayLike,
    centers: ArrayLike,
    *,
    mode: str = "INVERSE_DISTANCE",
    radius: float = 1.0,
    exponent: float = 2.0,
    normalize: str = "SUM",
    k: int = 4,
    scales: ArrayLike | None = None,
    dense: ArrayLike | None = None,
    solved: ArrayLike | None = None,
    tails: ArrayLike | None = None,
    chunk_size: int | None = None,
    floor: float = POOL_FLOOR,
    pool: PoolColumns | None = None,
) -> tuple[IntArray, FloatArray]:
    """Sparse probe weights for points (N, 3) and probe rest positions centers (m, 3).

    With `tails` (m, 3) each control is the segment centers[i] → tails[i] (a bone: head → tail) and
    d is the distance to that segment, |p − (c + t (e − c))| with t = clamp((p − c)·(e − c)/|e − c|², 0, 1);
    without, the distance to the point centers[i].

    mode 'INVERSE_DISTANCE': (radius/d)^exponent (radius is the reference distance, d floored);
    with normalize 'NONE' it is capped at 1 — a raw weight above 1 would apply a probe's motion more
    than once (up to 1e12 times on top of it) — so vertices within `radius` follow the probe fully
    and farther ones less. 'FALLOFF': smooth_falloff(d, radius) (exactly 0 at and beyond radius);
    'VERTEX_GROUPS': the dense painted weights `dense` (N, m) (negative paint is clamped to 0).
    'SURFACE': on the rows where `solved` (N,) is True, the harmonic weights h = `dense` (N, m)
    (core.surface) sharpened by the exponent, h_i^p / Σ_j h_j^p (still a partition of unity; p = 1
    keeps them harmonic, larger p localises like the inverse-distance power: a probe's share where
    another dominates drops faster); inverse-distance weights as above on the other rows (loose
    parts without a probe).
    `scales` (m,) multiplies each probe's weight before the top-K selection. Distance and surface
    weights are truncated continuously with a bounded slope (`sparse_from_blocks` with `floor`; with
    more than k probes and normalize 'SUM' or 'SOFTMAX' a row may have one more column, index m:
    the pooled control, whose parameters are `with_pool`'s mean with `pool_weights(scales)`; with
    `pool`, its columns instead: bones), painted ones keep their K largest values as painted. Returns
    (indices (N, K, K + 1 or K + pool.width) int32, values).
    """
    pts, ctr, ends, scale = _control_inputs(points, centers, tails, scales)
    m = ctr.shape[0]

    if mode == "VERTEX_GROUPS":
        if dense is None:
            raise ValueError("mode 'VERTEX_GROUPS' needs the dense painted weights")
        D = np.asarray(dense, dtype=np.float64)
        if D.shape != (pts.shape[0], m):
            raise ValueError(f"painted weights must have shape {(pts.shape[0], m)}, got {D.shape}")
        if not np.all(np.isfinite(D)):
            raise ValueError("painted weights contain non-finite values")

        def block(lo: int, hi: int) -> FloatArray:
            return np.maximum(D[lo:hi], 0.0) * scale

    elif mode in ("INVERSE_DISTANCE", "FALLOFF", "SURFACE"):
        if not radius > 0.0:
            raise ValueError(f"radius must be positive, got {radius}")
        if mode == "SURFACE":
            if not exponent > 0.0:
                raise ValueError(f"exponent must be positive, got {exponent}")
            if dense is None or solved is None:
                raise ValueError("mode 'SURFACE' needs the harmonic weights and the rows they hold")
            H = np.asarray(dense, dtype=np.float64)
            done = np.asarray(solved, dtype=bool)
            if H.shape != (pts.shape[0], m) or done.shape != (pts.shape[0],):
                raise ValueError(f"harmonic weights must have shape {(pts.shape[0], m)}, "
                                 "with one flag per row")

        def distance_block(p: FloatArray) -> FloatArray:
            d = segment_distances(p, ctr, ends) if ends is not None else point_distances(p, ctr)
            if mode == "FALLOFF":
                return smooth_falloff(d, radius) * scale
            w = inverse_distance(d, exponent, radius)
            if normalize == "NONE":
                np.minimum(w, 1.0, out=w)
            return w * scale

        def block(lo: int, hi: int) -> FloatArray:
            if mode != "SURFACE":
                return distance_block(pts[lo:hi])
            loose = ~done[lo:hi]
            sharp = np.maximum(H[lo:hi], 0.0) ** exponent
            total = sharp.sum(axis=1, keepdims=True)
            out = np.where(total > 0.0, sharp / np.where(total > 0.0, total, 1.0), 0.0) * scale
            if loose.any():
                out[loose] = distance_block(pts[lo:hi][loose])
            return out

    else:
        raise ValueError(f"weight mode must be one of {WEIGHT_MODES}, got {mode!r}")
    return sparse_from_blocks(pts.shape[0], m, block, k, normalize, chunk_size,
                              continuous=mode != "VERTEX_GROUPS", floor=floor, pool=pool)
