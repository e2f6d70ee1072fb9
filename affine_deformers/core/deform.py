"""The per-vertex kernel: v ↦ φ(Σ_k w_k P_idx(k)) v, vectorised over vertices (MATH.md §1), and the
motion map p_v ↦ φ(p_v) itself (`vertex_motions`: the columns of M = R(ω) exp(Y) and t = V(ω) u).

Parameters follow docs/DEVELOPING.md: P = (ω, u, Y₆) ∈ R¹²; for a point v

    v' = R(ω) · exp(Y) v + V(ω) u.

This module is the module-level API (docs/DEVELOPING.md; one kernel per calling thread) and the
script contract's `deform_points`. Its docstrings are the kernel entries' contract, written once:
the kernel class (core/kernel.py: chunks, scratch rows, caches and thread pool) and the compiled
backend (affine_deformers.accel, which falls back to these functions) refer to them, and both check
arguments with core/checks.py. The stages of the map on rows are core/kernel_stages.py.

Accuracy: ≤ 2e-15 relative to ‖M‖‖v‖ + ‖t‖ against aff3.phi on an adversarial parameter set (tests).

Throughput, where the time goes and why (memory traffic between scratch rows, not arithmetic): the
'Kernel performance' section of docs/DEVELOPING.md (measurements belong there, not in code).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Hashable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .aff3 import params_from_matrices
from .kernel import DEFAULT_CHUNK as DEFAULT_CHUNK
from .kernel import DENSE_BLEND_MAX_CONTROLS as DENSE_BLEND_MAX_CONTROLS
from .kernel import DENSE_CACHE_MAX_ENTRIES as DENSE_CACHE_MAX_ENTRIES
from .kernel import MAX_DEFAULT_THREADS as MAX_DEFAULT_THREADS
from .kernel import ROW_SET_MAX_ENTRIES as ROW_SET_MAX_ENTRIES
from .kernel import ROW_SETS_KEPT as ROW_SETS_KEPT
from .kernel import THREADS_ENV as THREADS_ENV
from .kernel import WEIGHTS_CACHE_SIZE as WEIGHTS_CACHE_SIZE
from .kernel import DeformKernel
from .kernel import default_threads as default_threads
from .kernel_stages import SMALL_Y as SMALL_Y
from .kernel_stages import FloatArray

# The `X as X` imports re-export the kernel's settings and thread count as core.deform.X (the
# accel package, tests and benchmarks read them here).

__all__ = [
    "DeformKernel",
    "blend_linear_sparse",
    "blend_params",
    "deform_points",
    "deform_points_params",
    "deform_points_params_rows",
    "motion_bound",
    "vertex_motions",
]

# ----------------------------------------------------------------------------------------------
# module-level API (docs/DEVELOPING.md)

_local = threading.local()


def _kernel() -> DeformKernel:
    k = getattr(_local, "kernel", None)
    if k is None:
        k = _local.kernel = DeformKernel()
    return k


def deform_points_params(
    points: ArrayLike,
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    out: FloatArray | None = None,
    *,
    cache_weights: bool = True,
    key: Hashable | None = None,
) -> FloatArray:
    """Sparse hot path: v' = φ(p_v) v with p_v = Σ_k values[v, k] · params[indices[v, k]].

    points (N, 3), params (m, 12) (layout of docs/DEVELOPING.md), indices (N, K) integer in [0, m),
    values (N, K) (unused slots: value 0, any valid index). Returns (N, 3) float64 (`out` if given;
    it may be `points` itself). All-zero params return the input bit for bit. Each row's result
    depends only on that row (not on N, chunking or threads), so a subset of rows gives bit-identical
    values. cache_weights=False skips the weights cache (for one-off subsets that would evict the
    weights that come back every frame). `key`: a hashable token the caller guarantees names these
    exact points, indices and values (never reused for other contents, e.g. a bind generation); a
    call with a key seen before skips re-validating the points and comparing the weights.
    """
    return _kernel().deform(points, params, indices, values, out, cache_weights=cache_weights, key=key)


def deform_points_params_rows(
    points: ArrayLike,
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    rows: ArrayLike,
    out: FloatArray,
    *,
    offsets: bool = False,
    key: Hashable | None = None,
) -> FloatArray:
    """`deform_points_params` for the vertices `rows` only: out[v] = φ(p_v) points[v] (minus points[v]
    when `offsets`) for v in rows; other rows of `out` (float64, (N, 3)) are left as they are.

    Takes the full (N, ...) arrays so the weights cache applies. Each written row is bit-identical to
    the same row of a full call, so an incremental update (recompute the vertices a changed control
    influences, keep the rest) equals a full recompute exactly. With a `key` (see
    `deform_points_params`) the gathered inputs of the last few row sets are kept, so dragging one
    control (the same rows every update) does not gather them again.
    """
    return _kernel().deform_rows(points, params, indices, values, rows, out, offsets=offsets, key=key)


def vertex_motions(
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    out: FloatArray | NDArray[np.float32] | None = None,
    *,
    rows: ArrayLike | None = None,
    key: Hashable | None = None,
) -> FloatArray | NDArray[np.float32]:
    """Each vertex's affine map φ(p_v): x ↦ M_v x + t_v, p_v = Σ_k values[v, k] · params[indices[v, k]],
    M_v = R(ω) exp(Y), t_v = V(ω) u (the map `deform_points_params` applies to points[v]).

    params (m, 12), indices (N, K) integer in [0, m), values (N, K) as in `deform_points_params`.
    `out`: (4, N, 3) float64 or float32 (default: a new float64 array), planar: out[0, v], out[1, v],
    out[2, v] are the columns M_v e_x, M_v e_y, M_v e_z and out[3, v] = t_v, so
    φ(p_v) x = x₀ out[0, v] + x₁ out[1, v] + x₂ out[2, v] + out[3, v] and each out[c] is one (N, 3)
    block (C-contiguous when out is). A float32 out gets the float64 value rounded once (what
    .astype(np.float32) gives; ±inf beyond its range). `rows`: None for every vertex, else a 1-D
    integer array: only out[:, rows] is written, the other rows are left as they are, and each written
    row is bit-identical to the same row of a full call (a row depends only on its own inputs, not on
    N, chunking, threads or the other rows). All-zero params give the identity exactly. `key`: as in
    `deform_points_params` (here naming the indices and values); with a key the gathered inputs of
    the last few row sets are kept, as in `deform_points_params_rows`. Returns out.
    """
    return _kernel().motions(params, indices, values, out, rows=rows, key=key)


def blend_params(params: ArrayLike, indices: ArrayLike, values: ArrayLike) -> FloatArray:
    """The per-vertex blended parameters Σ_k values[v, k] params[indices[v, k]] -> (N, 12)."""
    return _kernel().blend(params, indices, values)


#: `motion_bound` gives up (returns inf) when the stretch factor e^{W·‖Y‖} would pass e^{MAX_BOUND_EXPONENT}.
MAX_BOUND_EXPONENT = 700.0


#: Rows of `motion_bound`'s product: ‖Y‖_F² (off-diagonal entries twice), |u|², |ω|².
_BOUND_ROWS = np.zeros((3, 12))
_BOUND_ROWS[0, 6:9], _BOUND_ROWS[0, 9:12] = 1.0, 2.0
_BOUND_ROWS[1, 3:6] = 1.0
_BOUND_ROWS[2, 0:3] = 1.0


def motion_bound(params: ArrayLike, weight_sum: float, radius: float) -> float:
    """An upper bound on |φ(Σ_k w_k P_k) x| for every |x| ≤ radius and weights with Σ_k |w_k| ≤
    weight_sum, from the parameter rows P_k = (ω, u, Y₆) alone (m, 12): e^{W·max ‖Y_k‖_F}·radius +
    W·max |u_k|, W = weight_sum.

    φ(ω, u, Y) x = R(ω) exp(Y) x + V(ω) u with ‖R‖ = 1, ‖exp(Y)‖ = e^{λ_max(Y)} ≤ e^{‖Y‖_F}, and
    ‖V(ω)‖ ≤ 1 for every ω (V is normal, with eigenvalues 1 and (e^{±iθ} − 1)/(±iθ), of modulus
    |sin(θ/2)/(θ/2)| ≤ 1); the blend is linear in the rows, so ‖Σ w_k Y_k‖ ≤ W max ‖Y_k‖ and
    |Σ w_k u_k| ≤ W max |u_k|. It proves a whole result finite in O(m) instead of a pass over N
    vertices. inf when a row is not finite or the exponent passes MAX_BOUND_EXPONENT."""
    P = np.asarray(params, dtype=np.float64).reshape(-1, 12)
    if P.shape[0] == 0:
        return float(radius)
    # One pass: every row's ‖Y‖_F², |u|² and |ω|² as one product with _BOUND_ROWS, in which each entry
    # has a non-zero coefficient in its own row, so a non-finite entry leaves that row's max non-finite
    # (max keeps NaN) and the test below gives up. (3, m), not (m, 3): numpy reduces contiguous rows
    # several times faster than strided columns.
    with np.errstate(all="ignore"):
        y_sq, u_sq, omega_sq = (_BOUND_ROWS @ np.square(P).T).max(axis=1)
    exponent = weight_sum * math.sqrt(y_sq)
    if not (exponent <= MAX_BOUND_EXPONENT and math.isfinite(u_sq) and math.isfinite(omega_sq)):
        return math.inf
    return math.exp(exponent) * radius + weight_sum * math.sqrt(u_sq)


def deform_points(points: ArrayLike, transforms: ArrayLike, weights: ArrayLike) -> FloatArray:
    """Script contract: (N, 3) = φ(Σ_i weights[v, i] ψ(transforms[i])) v for each row v of points.

    transforms (m, 4, 4) in Aff+(3) (ValueError naming the first bad one), weights (N, m) dense.
    """
    table = params_from_matrices(np.asarray(transforms, dtype=np.float64))
    if table.ndim != 2:
        raise ValueError(f"transforms must have shape (m, 4, 4), got {np.shape(transforms)}")
    return _kernel().deform_dense(points, table, weights)


def blend_linear_sparse(
    points: ArrayLike,
    transforms: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    out: FloatArray | None = None,
) -> FloatArray:
    """'LINEAR' comparison mode: v' = (Σ_k w_k A_idx(k) + (1 − Σ_k w_k) I) v = v + Σ_k w_k (A_idx(k) − I) v.

    The identity carries the leftover weight, so zero weight means "stays put", as in the affine mode.
    transforms (m, 4, 4) must be finite (bottom rows are ignored; any determinant is accepted).
    """
    return _kernel().linear(points, transforms, indices, values, out)
