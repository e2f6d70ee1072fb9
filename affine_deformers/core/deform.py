"""The per-vertex kernel: v ↦ φ(Σ_k w_k P_idx(k)) v, vectorised over vertices (MATH.md §1), and the
motion map p_v ↦ φ(p_v) itself (`vertex_motions`: the columns of M = R(ω) exp(Y) and t = V(ω) u).

Parameters follow docs/DEVELOPING.md: P = (ω, u, Y₆) ∈ R¹²; for a point v

    v' = R(ω) · exp(Y) v + V(ω) u.

Both maps run the same stages (module-level functions on rows, named as the compiled kernel's
pieces): `_exp_sym_coeffs` (spectrum of Y → E, α', g', Z), then `_exp_sym_apply` (exp(Y) v) or
`_exp_sym_matrix` (exp(Y) = E I + α' Z + g' Z²), `_rotation_coeffs` (A, B, C, cos θ, with the exact
fallback past 1.8π) and `_rigid` (R e + V u; the motion map calls it with u = 0 on the columns of
exp(Y) and with e = 0 for t). Scratch rows go from stage to stage through `_FreeRows`.

No 3×3 matrix is formed per vertex. Vertices are processed in chunks, as structure-of-arrays rows
(12, n) in preallocated scratch rows, with in-place ufuncs only:

* blend: the sparse bind weights become a dense (m, N) matrix (cached while the same weights come
  back, see `DeformKernel._sparse_weights`) and one BLAS product per chunk gives p_v; with many
  controls the parameter rows are gathered instead;
* exp(Y) v = e^{e₁} (v + α Z v + g Z² v), Z = Y − e₁ I, from the closed-form spectrum of Y
  (trigonometric cubic on the traceless part) and the divided differences of aff3, written with
  e₁ the middle eigenvalue, x = e₀ − e₁ ≤ 0 ≤ y = e₂ − e₁, g = (y h2(y) − x h2(x))/(y − x),
  α = 1 + x (h2(x) − g), h2(z) = (eᶻ − 1 − z)/z²;
* R w + V u = cos θ w + A u + ω × (A w + B u) + (B ω·w + C ω·u) ω with A = sin θ/θ,
  B = (1 − cos θ)/θ², C = (θ − sin θ)/θ³ (R = cos θ I + A ω̂ + B ωωᵀ, V = A I + B ω̂ + C ωωᵀ).

numpy's float64 sin/cos are scalar code, ~50× slower per element than a multiply; the kernel uses a
Taylor polynomial for sin(θ/4)/(θ/4) in θ²/16 (θ ≤ 1.8π; beyond, a np.sin fallback on those rows),
cos(θ/4) = √(1 − sin²(θ/4)) and double-angle formulas; the eigen-angle a = arccos(r)/3 ≤ π/3 gets
sin a from the same polynomial and cos a = √(1 − sin² a). Branches near 0 are replaced by clamps
whose error is bounded where they are applied, so there is no masked work.

Accuracy: ≤ 2e-15 relative to ‖M‖‖v‖ + ‖t‖ against aff3.phi on an adversarial parameter set (tests).

Throughput, where the time goes and why (memory traffic between scratch rows, not arithmetic): the
'Kernel performance' section of docs/DEVELOPING.md (measurements belong there, not in code).
"""

from __future__ import annotations

import functools
import math
import os
import threading
from collections.abc import Callable, Hashable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .aff3 import params_from_matrices
from .checks import (
    check_given_out,
    check_indices,
    check_motion_indices,
    check_motion_out,
    check_out,
    check_points,
    check_rows,
    check_table,
    identity_motions,
    unchanged,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32]

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

#: Vertices per chunk: 40-odd scratch rows of this length stay in a core's L2 cache.
DEFAULT_CHUNK = 16384
#: Above this many controls the blend gathers parameter rows instead of a dense (m, chunk) product.
DENSE_BLEND_MAX_CONTROLS = 48
#: Dense weight entries (controls × vertices) a kernel keeps between calls, in total (64 MiB) ...
DENSE_CACHE_MAX_ENTRIES = 1 << 23
#: ... for at most this many weight sets (deformers evaluated in turn).
WEIGHTS_CACHE_SIZE = 4
#: Gathered row subsets kept for incremental updates (`DeformKernel._row_set`), and their size limit
#: in array entries each (16 MiB).
ROW_SETS_KEPT = 2
ROW_SET_MAX_ENTRIES = 1 << 21

# The quarter-angle polynomials are used for θ ≤ 1.8π, where cos(θ/4) = √(1 − sin²(θ/4)) ≥ 0.15 is
# well conditioned; larger θ (lifted rotations past ±324°) take the np.sin/np.cos fallback.
_POLY_MAX_S = (1.8 * math.pi) ** 2
#: Rows whose blended Y has every |entry| ≤ SMALL_Y (rigid controls: Y is float32 rounding noise,
#: ~1e-8) take exp(Y) from its cubic Taylor polynomial, whose truncation Y⁴/24 is ≤ (3 SMALL_Y)⁴/24
#: < 1e-17 relative: as accurate as the closed form, without the spectrum (`_small_y`).
SMALL_Y = 4e-5
_TINY = np.finfo(np.float64).tiny
_SQRT3 = math.sqrt(3.0)

# Taylor coefficients in z = x² of sin(x)/x = Σ (−z)^k/(2k+1)!. Degree 9 keeps the truncation below
# 2e-17 for x ≤ 0.45π (z ≤ 2, the quarter angle of θ ≤ 1.8π); degree 8 does for the eigen-angle
# a ≤ π/3 (z ≤ 1.1). (Chebyshev-economised coefficients would save one degree but carry ~1e-15 of
# rounding from the change of basis.)
_SINC_COEFFS = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(10))
_SINC_EIG_COEFFS = _SINC_COEFFS[:9]
# Clamps that replace series branches (see the error bounds where they are used).
_C_CLAMP_S = 1e-14
_H2_CLAMP = 1e-5


def _horner(out: FloatArray, coeffs: tuple[float, ...], z: FloatArray) -> FloatArray:
    """out = Σ coeffs[k] z^k (in place; out must not alias z)."""
    np.multiply(z, coeffs[-1], out=out)
    for c in coeffs[-2:0:-1]:
        out += c
        out *= z
    out += coeffs[0]
    return out


class _Rows:
    """Float64 rows of one padded length in a single buffer, reused between calls.

    The row stride is the chunk length plus one cache line: with power-of-two chunks, rows 64 KiB
    apart alias in the L1 cache (same address bits below 4 KiB), and a ufunc reading one row while
    writing another then runs up to 4× slower. The pad also keeps rows from touching, which the
    bits depend on: numpy runs arccos, exp and expm1 through SIMD loops, but falls back to scalar
    code (which rounds some values differently) when an input row and the output row are adjacent
    in memory (see `_by_form`).
    """

    PAD = 8

    def __init__(self, n_rows: int, length: int) -> None:
        self.stride = length + self.PAD
        self.buf = np.empty((n_rows, self.stride))
        self._next = 0

    def block(self, n: int, count: int) -> FloatArray:
        """The next `count` rows, trimmed to n, as one (count, n) view."""
        rows = self.buf[self._next : self._next + count, :n]
        self._next += count
        return rows

    def take(self, n: int, count: int) -> list[FloatArray]:
        return list(self.block(n, count))


_N_ROWS = 48  # 12 parameters + 3 points + 3 results + scratch


@dataclass
class _WeightsEntry:
    """A set of sparse weights the kernel has seen (copies), its dense (m, N) form once built, and the
    caller's key for it (None: found by comparing contents only)."""

    idx: IntArray
    val: FloatArray
    m: int
    dense: FloatArray | None
    key: Hashable | None


@dataclass
class _RowSet:
    """Inputs of a subset of rows, gathered once: `rows` (n,), their points as rows (3, n) (None until
    a call with points needs them: `vertex_motions` has none) and either their dense weight columns
    (m, n) or their sparse (idx, val) rows (n, K)."""

    key: Hashable | None
    rows: NDArray[np.intp]
    points_t: FloatArray | None
    weights: FloatArray | None
    idx: IntArray | None
    val: FloatArray | None

    @property
    def size(self) -> int:
        return sum(a.size for a in (self.points_t, self.weights, self.idx, self.val) if a is not None)


class DeformKernel:
    """Reusable per-vertex kernel with its scratch buffers; not for concurrent use (one per thread).

    Work is split into chunks of `chunk_size` vertices; with `threads` > 1, contiguous runs of chunks
    go to helper kernels on a shared thread pool (numpy releases the GIL inside each ufunc, so the
    runs overlap). Results do not depend on chunk_size or threads.
    """

    def __init__(self, chunk_size: int = DEFAULT_CHUNK, threads: int | None = None) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        self.chunk_size = int(chunk_size)
        self.threads = default_threads() if threads is None else max(1, int(threads))
        self._rows = _Rows(_N_ROWS, self.chunk_size)
        self._dense: FloatArray = np.empty(0)
        self._arange = np.arange(self.chunk_size, dtype=np.intp)
        self._helpers: list[DeformKernel] = []
        self._weights_cache: list[_WeightsEntry] = []
        self._row_sets: list[_RowSet] = []
        self._checked_key: Hashable | None = None

    def _param_rows(self, n: int) -> FloatArray:
        """The (12, n) parameter rows of the current chunk."""
        return self._rows.buf[0:12, :n]

    def _point_rows(self, n: int) -> FloatArray:
        return self._rows.buf[12:15, :n]

    def _result_rows(self, n: int) -> FloatArray:
        return self._rows.buf[15:18, :n]

    def _scratch(self) -> _Rows:
        self._rows._next = 18
        return self._rows

    def _run(self, n_total: int, chunk: Callable[[DeformKernel, int, int], None]) -> None:
        """chunk(kernel, a, b) for every chunk [a, b) of [0, n_total); contiguous runs of chunks go to
        different threads, each with its own kernel (scratch buffers)."""

        def work(kernel: DeformKernel, lo: int, hi: int) -> None:
            for a in range(lo, hi, kernel.chunk_size):
                chunk(kernel, a, min(a + kernel.chunk_size, hi))

        n_chunks = -(-n_total // self.chunk_size)
        n_runs = min(self.threads, n_chunks)
        if n_runs <= 1:
            work(self, 0, n_total)
            return
        while len(self._helpers) < n_runs - 1:
            self._helpers.append(DeformKernel(self.chunk_size, threads=1))
        edges = [min(n_total, (i * n_chunks // n_runs) * self.chunk_size) for i in range(n_runs + 1)]
        pool = _pool()
        futures = [
            pool.submit(work, helper, lo, hi)
            for helper, lo, hi in zip(self._helpers, edges[1:-1], edges[2:], strict=False)
        ]
        try:
            work(self, edges[0], edges[1])
        finally:
            for f in futures:
                f.result()

    # ------------------------------------------------------------------------------------------
    # public entry points

    def deform(
        self,
        points: ArrayLike,
        params: ArrayLike,
        indices: ArrayLike,
        values: ArrayLike,
        out: FloatArray | None = None,
        *,
        cache_weights: bool = True,
        key: Hashable | None = None,
    ) -> FloatArray:
        """Sparse hot path; see `deform_points_params`."""
        table = check_table(params, 12, "params")
        if cache_weights:
            pts, idx, val, dense = self._inputs(points, indices, values, table.shape[0], key)
        else:
            pts = check_points(points)
            idx, val = check_indices(indices, values, pts.shape[0], table.shape[0])
            dense = None
        out = check_out(out, pts)
        if not table.any():
            return unchanged(pts, out)
        table_t = np.ascontiguousarray(table.T)

        def work(kernel: DeformKernel, a: int, b: int) -> None:
            P = kernel._param_rows(b - a)
            kernel._blend(table_t, idx, val, dense, a, b, P)
            kernel._apply_chunk(pts[a:b], P, out[a:b])

        self._run(pts.shape[0], work)
        return out

    def deform_rows(
        self,
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
        """Only the listed rows; see `deform_points_params_rows`."""
        table = check_table(params, 12, "params")
        pts, idx, val, dense = self._inputs(points, indices, values, table.shape[0], key)
        check_given_out(out, pts)
        sel = check_rows(rows, pts.shape[0])
        rs = self._row_set(key, sel, pts, idx, val, dense)
        points_t = rs.points_t
        assert points_t is not None  # _row_set gathers them when given points
        table_t = np.ascontiguousarray(table.T)

        def work(kernel: DeformKernel, a: int, b: int) -> None:
            n = b - a
            P = kernel._param_rows(n)
            kernel._row_set_blend(table_t, rs, a, b, P)
            V = points_t[:, a:b]
            O = kernel._result_rows(n)
            kernel._apply_soa(V, P, O)
            if offsets:
                O -= V
            out[rs.rows[a:b]] = O.T

        self._run(sel.shape[0], work)
        return out

    def motions(
        self,
        params: ArrayLike,
        indices: ArrayLike,
        values: ArrayLike,
        out: FloatArray | NDArray[np.float32] | None = None,
        *,
        rows: ArrayLike | None = None,
        key: Hashable | None = None,
    ) -> FloatArray | NDArray[np.float32]:
        """The per-vertex affine maps; see `vertex_motions`."""
        table = check_table(params, 12, "params")
        m = table.shape[0]
        n_total = check_motion_indices(indices, values, m)
        idx, val, dense = self._sparse_weights(indices, values, n_total, m, key)
        out = check_motion_out(out, n_total)
        sel = None if rows is None else check_rows(rows, n_total)
        if not table.any():  # every control at rest (also m = 0)
            return identity_motions(out, sel)
        table_t = np.ascontiguousarray(table.T)
        if sel is None:

            def work(kernel: DeformKernel, a: int, b: int) -> None:
                P = kernel._param_rows(b - a)
                kernel._blend(table_t, idx, val, dense, a, b, P)
                kernel._motion_chunk(P, out, slice(a, b))

            self._run(n_total, work)
            return out
        rs = self._row_set(key, sel, None, idx, val, dense)

        def work_rows(kernel: DeformKernel, a: int, b: int) -> None:
            P = kernel._param_rows(b - a)
            kernel._row_set_blend(table_t, rs, a, b, P)
            kernel._motion_chunk(P, out, rs.rows[a:b])

        self._run(sel.shape[0], work_rows)
        return out

    def _row_set_blend(self, table_t: FloatArray, rs: _RowSet, a: int, b: int, P: FloatArray) -> None:
        """P (12, b − a) = the blended parameters of the row set's entries a:b."""
        if rs.weights is not None:
            # The same product as the full call's, on gathered columns: same values per row.
            np.matmul(table_t, rs.weights[:, a:b], out=P)
        else:
            self._blend_sparse(table_t, rs.idx[a:b], rs.val[a:b], P)

    def _inputs(
        self, points: ArrayLike, indices: ArrayLike, values: ArrayLike, m: int, key: Hashable | None
    ) -> tuple[FloatArray, IntArray, FloatArray, FloatArray | None]:
        """Checked (points, indices, values) and the dense weights when cached (`_sparse_weights`).

        With a `key` seen before, the points are not re-validated and the weights are found by the key
        instead of by comparing their contents (the caller vouches that a key names fixed data)."""
        if key is not None and key == self._checked_key:
            pts = np.asarray(points, dtype=np.float64)
        else:
            pts = check_points(points)
        idx, val, dense = self._sparse_weights(indices, values, pts.shape[0], m, key)
        if key is not None:
            self._checked_key = key
        return pts, idx, val, dense

    def _row_set(
        self, key: Hashable | None, sel: NDArray[np.integer], pts: FloatArray | None, idx: IntArray,
        val: FloatArray, dense: FloatArray | None,
    ) -> _RowSet:
        """The gathered inputs of the rows `sel`, kept between calls with the same key and rows: an
        interactive drag recomputes the same rows every update, and gathering them (points transposed
        to rows, the weight columns) costs about as much as the map itself. pts None: no points
        (`motions`); a kept set gathered without them gets them when a call with points finds it."""
        for i, rs in enumerate(self._row_sets):
            if rs.key == key and rs.rows.shape == sel.shape and np.array_equal(rs.rows, sel):
                self._row_sets.insert(0, self._row_sets.pop(i))
                if pts is not None and rs.points_t is None:
                    rs.points_t = np.ascontiguousarray(pts[rs.rows].T)
                return rs
        rows = sel.astype(np.intp)
        rs = _RowSet(
            key,
            rows,
            None if pts is None else np.ascontiguousarray(pts[rows].T),
            None if dense is None else np.take(dense, rows, axis=1),
            None if dense is not None else idx[rows],
            None if dense is not None else val[rows],
        )
        if key is not None and rs.size <= ROW_SET_MAX_ENTRIES:
            self._row_sets.insert(0, rs)
            del self._row_sets[ROW_SETS_KEPT:]
        return rs

    def _dense_block(self, m: int, n: int) -> FloatArray:
        """An (m, n) view of the scratch used for per-chunk dense weights (padded row stride)."""
        stride = self._rows.stride
        if self._dense.size < m * stride:
            self._dense = np.empty(m * stride)
        return self._dense[: m * stride].reshape(m, stride)[:, :n]

    def deform_dense(self, points: ArrayLike, params: ArrayLike, weights: ArrayLike) -> FloatArray:
        """v' = φ(Σ_i weights[v, i] params[i]) v with dense weights (N, m)."""
        pts = check_points(points)
        table = check_table(params, 12, "params")
        W = np.asarray(weights, dtype=np.float64)
        if W.shape != (pts.shape[0], table.shape[0]):
            raise ValueError(f"weights must have shape {(pts.shape[0], table.shape[0])}, got {W.shape}")
        if not np.all(np.isfinite(W)):
            raise ValueError("weights contain non-finite values")
        out = np.empty_like(pts)
        table_t = np.ascontiguousarray(table.T)

        def work(kernel: DeformKernel, a: int, b: int) -> None:
            P = kernel._param_rows(b - a)
            np.matmul(table_t, W[a:b].T, out=P)
            kernel._apply_chunk(pts[a:b], P, out[a:b])

        self._run(pts.shape[0], work)
        return out

    def blend(self, table: ArrayLike, indices: ArrayLike, values: ArrayLike) -> FloatArray:
        """Σ_k values[v, k] table[indices[v, k]] for every row v -> (N, c) (c = table columns)."""
        tab = np.asarray(table, dtype=np.float64)
        if tab.ndim != 2:
            raise ValueError(f"table must have shape (m, c), got {tab.shape}")
        idx, val = check_indices(indices, values, None, tab.shape[0])
        N = idx.shape[0]
        res = np.empty((N, tab.shape[1]))
        tab_t = np.ascontiguousarray(tab.T)
        for lo in range(0, N, self.chunk_size):
            hi = min(lo + self.chunk_size, N)
            buf = np.empty((tab.shape[1], hi - lo))
            self._blend_sparse(tab_t, idx[lo:hi], val[lo:hi], buf)
            res[lo:hi] = buf.T
        return res

    def linear(
        self,
        points: ArrayLike,
        transforms: ArrayLike,
        indices: ArrayLike,
        values: ArrayLike,
        out: FloatArray | None = None,
    ) -> FloatArray:
        """'LINEAR' comparison mode; see `blend_linear_sparse`."""
        T = np.asarray(transforms, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"transforms must have shape (m, 4, 4), got {T.shape}")
        D = (T[:, :3, :] - np.eye(3, 4)).reshape(T.shape[0], 12)  # row-major (3, 4) offsets from I
        pts = check_points(points)
        table = check_table(D, 12, "transforms")
        out = check_out(out, pts)
        idx, val, dense = self._sparse_weights(indices, values, pts.shape[0], table.shape[0])
        if not table.any():
            return unchanged(pts, out)
        table_t = np.ascontiguousarray(table.T)

        def work(kernel: DeformKernel, a: int, b: int) -> None:
            n = b - a
            Dv = kernel._param_rows(n)
            kernel._blend(table_t, idx, val, dense, a, b, Dv)
            V = kernel._point_rows(n)
            np.copyto(V, pts[a:b].T)
            O = kernel._result_rows(n)
            tmp = kernel._scratch().take(n, 1)[0]
            for i in range(3):
                np.multiply(Dv[4 * i], V[0], out=O[i])
                np.multiply(Dv[4 * i + 1], V[1], out=tmp)
                O[i] += tmp
                np.multiply(Dv[4 * i + 2], V[2], out=tmp)
                O[i] += tmp
                O[i] += Dv[4 * i + 3]
                O[i] += V[i]
            np.copyto(out[a:b], O.T)

        self._run(pts.shape[0], work)
        return out

    # ------------------------------------------------------------------------------------------
    # blend

    def _sparse_weights(
        self, indices: ArrayLike, values: ArrayLike, n_points: int, m: int, key: Hashable | None = None
    ) -> tuple[IntArray, FloatArray, FloatArray | None]:
        """Checked (indices, values) and, when they were seen before, their dense (m, N) form.

        Bind data comes back unchanged frame after frame. The first call with a set of weights
        blends chunk by chunk (scatter + product) and keeps a copy of the sparse arrays; a later call
        with equal contents (two linear scans), or with the same caller `key`, builds the dense weights
        once and from then on the blend is one BLAS product per chunk. A few sets are kept (deformers
        evaluated in turn), least recently used first out, with at most DENSE_CACHE_MAX_ENTRIES dense
        entries in total.
        """
        idx = np.asarray(indices)
        val = np.asarray(values, dtype=np.float64)
        if idx.ndim != 2 or idx.shape[0] != n_points:
            raise ValueError(f"indices must have shape ({n_points}, K), got {idx.shape}")
        cache = self._weights_cache
        for i, entry in enumerate(cache):
            if entry.m != m or entry.idx.shape != idx.shape or entry.idx.dtype != idx.dtype:
                continue
            if (key is not None and entry.key == key) or (
                np.array_equal(entry.idx, idx) and np.array_equal(entry.val, val)
            ):
                if entry.dense is None:  # only eligible sets are kept
                    entry.dense = _dense_weights(entry.idx, entry.val, m)
                if key is not None:
                    entry.key = key
                cache.insert(0, cache.pop(i))
                self._trim_weights_cache()
                return entry.idx, entry.val, entry.dense
        idx, val = check_indices(idx, val, n_points, m)
        if m <= DENSE_BLEND_MAX_CONTROLS and m * n_points <= DENSE_CACHE_MAX_ENTRIES:
            cache.insert(0, _WeightsEntry(idx.copy(), val.copy(), m, None, key))
            self._trim_weights_cache()
        return idx, val, None

    def _trim_weights_cache(self) -> None:
        budget = DENSE_CACHE_MAX_ENTRIES
        for i, entry in enumerate(self._weights_cache):
            budget -= 0 if entry.dense is None else entry.dense.size
            if i >= WEIGHTS_CACHE_SIZE or (budget < 0 and i > 0):
                del self._weights_cache[i:]
                return

    def _blend(
        self,
        table_t: FloatArray,
        idx: IntArray,
        val: FloatArray,
        dense: FloatArray | None,
        a: int,
        b: int,
        P: FloatArray,
    ) -> None:
        """P (c, b − a) = blended table columns for vertices a:b."""
        if dense is not None:
            np.matmul(table_t, dense[:, a:b], out=P)
        else:
            self._blend_sparse(table_t, idx[a:b], val[a:b], P)

    def _blend_sparse(self, table_t: FloatArray, idx: IntArray, val: FloatArray, P: FloatArray) -> None:
        """P (c, n) = table_t (c, m) · W (m, n), W the chunk's sparse weights made dense."""
        m = table_t.shape[1]
        n, K = idx.shape
        if m <= DENSE_BLEND_MAX_CONTROLS:
            dense = self._dense_block(m, n)
            dense.fill(0.0)
            _scatter_weights(self._dense, self._rows.stride, self._arange[:n], idx, val)
            np.matmul(table_t, dense, out=P)
        else:
            gathered = np.empty_like(P)
            np.take(table_t, idx[:, 0], axis=1, out=P)
            P *= val[:, 0]
            for k in range(1, K):
                np.take(table_t, idx[:, k], axis=1, out=gathered)
                gathered *= val[:, k]
                P += gathered

    # ------------------------------------------------------------------------------------------
    # the per-vertex maps: φ(p) v (points) and φ(p) itself (motions), from the same stages

    def _free_rows(self, start: int, n: int) -> _FreeRows:
        """The kernel's rows from `start` on, trimmed to n, as the free scratch of one chunk."""
        return _FreeRows(self._rows.buf[start:_N_ROWS, :n])

    def _apply_chunk(self, pts: FloatArray, P: FloatArray, out: FloatArray) -> None:
        """out (n, 3) = φ(P) pts for blended parameters P (12, n) (structure of arrays)."""
        n = P.shape[1]
        V = self._point_rows(n)
        np.copyto(V, pts.T)
        O = self._result_rows(n)
        self._apply_soa(V, P, O)
        np.copyto(out, O.T)

    def _apply_soa(self, V: FloatArray, P: FloatArray, O: FloatArray) -> None:
        """O (3, n) = φ(P) V for points V (3, n) and blended parameters P (12, n), all as rows:
        v' = R(ω) (exp(Y) v) + V(ω) u.

        O must not overlap V or P; V may be any (3, n) rows (the kernel's point rows or cached ones).
        """
        free = self._free_rows(18, P.shape[1])
        ew = _by_form(P[6:12], (V,), free, _exp_sym_small_apply, _exp_sym_closed_apply)
        theta = _rotation_coeffs(P[0:3], free)
        _rigid(P[0:3], P[3:6], ew, theta, O, free)

    def _motion_chunk(self, P: FloatArray, out: FloatArray, where: slice | NDArray[np.intp]) -> None:
        """out[:, where] = φ(P) as (columns of M, t) for blended parameters P (12, n) (see
        `vertex_motions`); out float64 or float32 (one rounding of the float64 value)."""
        n = P.shape[1]
        O = self._rows.buf[12:24, :n]  # no point rows here: 12 result rows
        self._motion_soa(P, O)
        # One component at a time: a strided store from a contiguous row is ~5× faster than a
        # transposing copy of three rows (and than a fancy-indexed row assignment).
        with np.errstate(over="ignore"):  # a float32 out takes ±inf beyond its range, as astype does
            for c in range(4):
                for t in range(3):
                    out[c, where, t] = O[3 * c + t]

    def _motion_soa(self, P: FloatArray, O: FloatArray) -> None:
        """O (12, n) = the map φ(P) for blended parameters P (12, n): rows 3c … 3c+2 hold M e_c
        (c = 0, 1, 2), rows 9 … 11 hold t, M = R(ω) exp(Y), t = V(ω) u. O must not overlap P."""
        free = self._free_rows(24, P.shape[1])
        xx, yy, zz, xy, xz, yz = _by_form(P[6:12], (), free, _exp_sym_small_matrix, _exp_sym_closed_matrix)
        theta = _rotation_coeffs(P[0:3], free)
        w = P[0:3]
        for c, column in enumerate(((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))):  # exp(Y) is symmetric
            _rigid(w, None, column, theta, O[3 * c : 3 * c + 3], free)  # R(ω) exp(Y) e_c
        _rigid(w, P[3:6], None, theta, O[9:12], free)  # V(ω) u


class _FreeRows:
    """Scratch rows of one chunk not in use: a stage takes the rows it needs and gives back those it
    does not return (last given, first taken: the rows most recently written are the warm ones)."""

    def __init__(self, rows: FloatArray) -> None:
        self._rows = list(rows)

    def take(self, count: int) -> list[FloatArray]:
        if count > len(self._rows):
            raise RuntimeError("kernel scratch exhausted")  # a programming error, not an input error
        taken = self._rows[len(self._rows) - count :]
        del self._rows[len(self._rows) - count :]
        return taken

    def give(self, *rows: FloatArray) -> None:
        self._rows.extend(rows)


# ----------------------------------------------------------------------------------------------
# stages of the map, on (n,) rows with in-place ufuncs (the compiled kernel's `_exp_sym_coeffs`,
# `_stretch`, `_exp_sym_matrix`, `_rotation_coeffs_poly`, `_rigid`, in the same order)


def _eigen_gaps(ang: FloatArray, p: FloatArray, x: FloatArray, y: FloatArray, t1: FloatArray) -> None:
    """The eigenvalue gaps of a symmetric 3×3 from its spread p and angle a = arccos(r)/3, into x
    and y: x = e0 − e1 = −2√3 p sin a ≤ 0, y = e2 − e1 = 2√3 p sin(π/3 − a) ≥ 0. sin a comes from
    its polynomial; cos a = √(1 − sin² a) ≥ ½ (a ≤ π/3) is well conditioned, and
    sin(π/3 − a) = (√3/2) cos a − ½ sin a. Overwrites p (with 2√3 p) and t1."""
    mul = np.multiply
    mul(ang, ang, out=t1)
    _horner(x, _SINC_EIG_COEFFS, t1)
    x *= ang
    mul(x, x, out=t1)
    np.subtract(1.0, t1, out=t1)
    np.sqrt(t1, out=t1)
    mul(t1, 0.5 * _SQRT3, out=y)
    mul(x, 0.5, out=t1)
    y -= t1
    p *= -2.0 * _SQRT3
    x *= p
    np.negative(p, out=p)
    y *= p


_TAYLOR_SCRATCH = 13  # rows the larger Taylor form needs (`_exp_sym_small_matrix`)


def _by_form(
    Y: FloatArray,
    extra: tuple[FloatArray, ...],
    free: _FreeRows,
    small_form: Callable[..., tuple[FloatArray, ...]],
    closed_form: Callable[..., tuple[FloatArray, ...]],
) -> tuple[FloatArray, ...]:
    """form(Y, *extra, free) per row: `small_form` (Taylor) where `_small_y`, `closed_form` elsewhere.

    A chunk of one kind runs one form. A mixed chunk runs the closed form on all its rows, in place,
    and the Taylor form on its small rows, gathered. Each row's value then comes from its own form
    and does not depend on its neighbours: the Taylor form is products and sums only, exact in any
    layout, while the closed form is always computed in the kernel's own padded rows. numpy's
    arccos, exp and expm1 have SIMD loops (AVX-512) that round differently from the scalar code it
    falls back to when an input row and the output row touch in memory, as adjacent rows of an
    unpadded buffer do: there ~25 % of the values differed in the last bit (measured), so a closed
    form on gathered rows would give rows other bits than in place."""
    small = _small_y(Y, free)
    count = int(np.count_nonzero(small))
    if count == small.size:
        return small_form(Y, *extra, free)
    out = closed_form(Y, *extra, free)
    if count:
        sel = np.flatnonzero(small)
        # take() gathers ~3× faster than fancy indexing
        gathered = (a.take(sel, axis=1) for a in (Y, *extra))
        part = small_form(*gathered, _FreeRows(np.empty((_TAYLOR_SCRATCH, sel.size))))
        for row, row_part in zip(out, part, strict=True):
            row[sel] = row_part
    return out


def _exp_sym_closed_apply(Y: FloatArray, V: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) v by the spectrum (`_exp_sym_coeffs`, `_exp_sym_apply`). Returns three rows of `free`."""
    coeffs = _exp_sym_coeffs(Y, free)
    ew = _exp_sym_apply(Y[3:6], coeffs, V, free)
    free.give(*coeffs)
    return ew


def _exp_sym_closed_matrix(Y: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) by the spectrum (`_exp_sym_coeffs`, `_exp_sym_matrix`). Returns six rows of `free`."""
    coeffs = _exp_sym_coeffs(Y, free)
    e = _exp_sym_matrix(Y[3:6], coeffs, free)
    free.give(*coeffs)
    return e


def _small_y(Y: FloatArray, free: _FreeRows) -> NDArray[np.bool_]:
    """Rows whose Y (6, n) has every |entry| ≤ SMALL_Y (NaN: not small): a plain comparison, nothing
    rounded, so any chunking decides a row alike."""
    m, t = free.take(2)
    np.abs(Y[0], out=m)
    for y in Y[1:]:
        np.abs(y, out=t)
        np.maximum(m, t, out=m)  # propagates NaN
    small = m <= SMALL_Y
    free.give(m, t)
    return small


def _exp_sym_small_apply(Y: FloatArray, V: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) v ≈ v + Y(v + Y(½v + Y(v/6))) for points V (3, n) and small Y (6, n) (SMALL_Y: the
    first term left out is < 1e-17 relative). Returns three rows taken from `free`."""
    a = free.take(3)
    b = free.take(3)
    (t,) = free.take(1)
    for ai, vi in zip(a, V, strict=True):
        np.multiply(vi, 1.0 / 6.0, out=ai)
    for step in (0.5, 1.0, 1.0):  # a ← step v + Y a
        _sym_matvec(*Y, *a, *b, t)
        for ai, bi, vi in zip(a, b, V, strict=True):
            np.multiply(vi, step, out=ai)
            ai += bi
    free.give(*b, t)
    return a[0], a[1], a[2]


def _exp_sym_small_matrix(Y: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) ≈ I + Y(I + Y(½I + Y/6)) as six rows (xx, yy, zz, xy, xz, yz), for small Y (6, n)
    (the truncation of `_exp_sym_small_apply`). Returns six rows taken from `free`."""
    S = free.take(6)
    T = free.take(6)
    (t,) = free.take(1)
    for si, yi in zip(S, Y, strict=True):
        np.multiply(yi, 1.0 / 6.0, out=si)
    for d in S[:3]:
        d += 0.5
    for _ in range(2):  # S ← I + Y S
        _sym_product(Y, S, T, t)
        S, T = T, S
        for d in S[:3]:
            d += 1.0
    free.give(*T, t)
    return tuple(S)


def _sym_product(Y: FloatArray, S: list[FloatArray], out: list[FloatArray], tmp: FloatArray) -> None:
    """out = Y S as six rows (xx, yy, zz, xy, xz, yz) for symmetric Y, S (6, n) that commute (S a
    polynomial in Y): Y S is then symmetric, and its upper triangle is all of it."""
    # (i, j) of Y S = Σ_k Y_ik S_kj, with the six-row slot of each symmetric entry:
    slot = ((0, 3, 4), (3, 1, 5), (4, 5, 2))
    for o, (i, j) in zip(out, ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)), strict=True):
        np.multiply(Y[slot[i][0]], S[slot[0][j]], out=o)
        for k in (1, 2):
            np.multiply(Y[slot[i][k]], S[slot[k][j]], out=tmp)
            o += tmp


def _exp_sym_coeffs(Y: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """The spectral coefficients of exp(Y) for Y (6, n) = (Yxx, Yyy, Yzz, Yxy, Yxz, Yyz) rows:
    (E, α', g', z0, z1, z2) with exp(Y) = E I + α' Z + g' Z², Z = Y − e₁ I (z0 … z2 its diagonal,
    its off-diagonal is Y's), E = e^{e₁}, α' = E α, g' = E g (module doc). Takes 13 rows of `free`,
    returns six of them and gives the other seven back."""
    mul, add, sub = np.multiply, np.add, np.subtract
    yxx, yyy, yzz, yxy, yxz, yyz = Y
    q, b0, b1, b2, p2, p, det, t0, t1, x, y, h2x, h2y = free.take(13)

    # ---- spectrum of Y: q = tr/3, B = Y − qI, p = √(tr B²/6), cos 3a = det B/(2p³) ---------------
    add(yxx, yyy, out=q)
    q += yzz
    q *= 1.0 / 3.0
    sub(yxx, q, out=b0)
    sub(yyy, q, out=b1)
    sub(yzz, q, out=b2)
    # det B = b0 b1 b2 + 2 xy xz yz − b0 yz² − b1 xz² − b2 xy²;  6 p² = Σ b² + 2 Σ off²
    mul(b0, b1, out=det)
    det *= b2
    mul(yxy, yxz, out=t0)
    t0 *= yyz
    t0 += t0
    det += t0
    mul(b0, b0, out=p2)
    for bi, oi in ((b0, yyz), (b1, yxz), (b2, yxy)):
        mul(oi, oi, out=t0)
        mul(bi, t0, out=t1)
        det -= t1
        t0 += t0
        p2 += t0
    mul(b1, b1, out=t0)
    p2 += t0
    mul(b2, b2, out=t0)
    p2 += t0
    p2 *= 1.0 / 6.0
    np.sqrt(p2, out=p)
    # r = det B/(2p³); a zero spread gives det = 0 and r = 0 (adding TINY only avoids 0/0).
    mul(p2, p, out=t1)
    t1 += t1
    t1 += _TINY
    r = t0
    np.divide(det, t1, out=r)
    np.minimum(r, 1.0, out=r)
    np.maximum(r, -1.0, out=r)
    ang = det
    np.arccos(r, out=ang)
    ang *= 1.0 / 3.0
    _eigen_gaps(ang, p, x, y, t1)
    e1 = q
    add(x, y, out=t1)
    t1 *= 1.0 / 3.0
    e1 -= t1

    # ---- exp(Y) = E (I + α Z + g Z²), Z = Y − e1 I ---------------------------------------------
    # g = (y h2(y) − x h2(x))/(y − x) ≥ 0 is a weighted mean of h2 values (no cancellation);
    # α = h1(x) − x g = 1 + x (h2(x) − g). h2 = (eᶻ − 1 − z)/z² is evaluated at z clamped away
    # from 0 (x ≤ −c, y ≥ c, c = _H2_CLAMP): the interpolant then still matches e^y at y and 1
    # at 0 exactly, and misses eˣ by x²·|h2(−c) − h2(x)| ≤ c³/3 ≈ 3e-16. Unclamped, the
    # direct formula's relative error ε/|z| is harmless for the same reason (it is multiplied
    # by z²), so no series branch is needed.
    np.minimum(x, -_H2_CLAMP, out=t0)
    _h2_direct(t0, h2x, t1)
    np.maximum(y, _H2_CLAMP, out=t0)
    _h2_direct(t0, h2y, t1)
    g = p2
    mul(y, h2y, out=g)
    mul(x, h2x, out=t0)
    g -= t0
    sub(y, x, out=t0)
    t0 += _TINY  # y − x ≥ 0; only x = y = 0 (then g multiplies Z = 0) needs the guard
    g /= t0
    alpha = h2x
    alpha -= g
    alpha *= x
    alpha += 1.0
    E = p
    np.exp(e1, out=E)
    alpha *= E
    g *= E
    z0, z1, z2 = b0, b1, b2
    sub(yxx, e1, out=z0)
    sub(yyy, e1, out=z1)
    sub(yzz, e1, out=z2)
    free.give(e1, ang, t0, t1, x, y, h2y)
    return E, alpha, g, z0, z1, z2


def _exp_sym_apply(
    Y_off: FloatArray, coeffs: tuple[FloatArray, ...], V: FloatArray, free: _FreeRows
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """exp(Y) v = (α' Z v + g' Z² v) + E v for points V (3, n), from `_exp_sym_coeffs`; Y_off the
    off-diagonal rows (Yxy, Yxz, Yyz). Returns three rows taken from `free`."""
    E, alpha, g, z0, z1, z2 = coeffs
    yxy, yxz, yyz = Y_off
    v0, v1, v2 = V
    zv0, zv1, zv2, zzv0, zzv1, zzv2, t0 = free.take(7)
    _sym_matvec(z0, z1, z2, yxy, yxz, yyz, v0, v1, v2, zv0, zv1, zv2, t0)
    _sym_matvec(z0, z1, z2, yxy, yxz, yyz, zv0, zv1, zv2, zzv0, zzv1, zzv2, t0)
    ew0, ew1, ew2 = zv0, zv1, zv2  # exp(Y) v, in place of Z v
    for ew, vi, zzvi in ((ew0, v0, zzv0), (ew1, v1, zzv1), (ew2, v2, zzv2)):
        ew *= alpha
        np.multiply(zzvi, g, out=t0)
        ew += t0
        np.multiply(vi, E, out=t0)
        ew += t0
    free.give(zzv0, zzv1, zzv2, t0)
    return ew0, ew1, ew2


def _exp_sym_matrix(
    Y_off: FloatArray, coeffs: tuple[FloatArray, ...], free: _FreeRows
) -> tuple[FloatArray, ...]:
    """exp(Y) = (α' Z + g' Z²) + E I as its six rows (xx, yy, zz, xy, xz, yz), from
    `_exp_sym_coeffs`; Y_off the off-diagonal rows (Yxy, Yxz, Yyz). Returns six rows of `free`."""
    E, alpha, g, z0, z1, z2 = coeffs
    a, b, c = Y_off  # Z = [[z0, a, b], [a, z1, c], [b, c, z2]]
    mul = np.multiply
    xx, yy, zz, xy, xz, yz, t0, t1 = free.take(8)
    # Z²: off-diagonal (Z²)01 = a (z0 + z1) + b c, …; diagonal (Z²)00 = z0² + a² + b², …
    for zij, s0, s1, f, p0, p1 in ((xy, z0, z1, a, b, c), (xz, z0, z2, b, a, c), (yz, z1, z2, c, a, b)):
        np.add(s0, s1, out=zij)
        zij *= f
        mul(p0, p1, out=t0)
        zij += t0
    mul(a, a, out=t0)
    mul(b, b, out=t1)
    mul(z0, z0, out=xx)
    xx += t0
    xx += t1
    mul(z1, z1, out=yy)
    yy += t0
    mul(z2, z2, out=zz)
    zz += t1
    mul(c, c, out=t0)
    yy += t0
    zz += t0
    for xij, zij in ((xx, z0), (yy, z1), (zz, z2), (xy, a), (xz, b), (yz, c)):
        xij *= g
        mul(zij, alpha, out=t0)
        xij += t0
    xx += E
    yy += E
    zz += E
    free.give(t0, t1)
    return xx, yy, zz, xy, xz, yz


def _rotation_coeffs(w: FloatArray, free: _FreeRows) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """(A, B, C, cos θ) rows for rotation vectors w (3, n): A = sin θ/θ, B = (1 − cos θ)/θ²,
    C = (θ − sin θ)/θ³, by the quarter-angle polynomial, exact libm values for θ > 1.8π. Returns four
    rows of `free`."""
    mul = np.multiply
    w0, w1, w2 = w
    s, zq, A, B, C, cth, sinc_q, tq, t0 = free.take(9)
    # ---- θ-coefficients from s = θ² (quarter angle: x_q = θ/4) --------------------------------
    mul(w0, w0, out=s)
    mul(w1, w1, out=t0)
    s += t0
    mul(w2, w2, out=t0)
    s += t0
    mul(s, 1.0 / 16.0, out=zq)
    _horner(sinc_q, _SINC_COEFFS, zq)  # sin(θ/4)/(θ/4)
    # tq = sin²(θ/4); cos(θ/4) = √(1 − tq), conditioned for θ ≤ 1.8π (beyond: exact fallback)
    mul(sinc_q, sinc_q, out=tq)
    tq *= zq
    sh = sinc_q
    np.subtract(1.0, tq, out=t0)
    # Past θ ≈ 2π the polynomial's tq can exceed 1; those rows are redone exactly below, and the
    # clamp (a no-op on every other row) keeps NaN warnings out of the user's console.
    np.maximum(t0, 0.0, out=t0)
    np.sqrt(t0, out=t0)
    sh *= t0  # sin(θ/2)/(θ/2)
    mul(tq, -2.0, out=t0)
    t0 += 1.0  # cos(θ/2)
    mul(sh, t0, out=A)  # sin θ/θ
    mul(sh, sh, out=B)
    B *= 0.5  # (1 − cos θ)/θ²
    mul(B, s, out=cth)
    np.subtract(1.0, cth, out=cth)  # cos θ
    # C = (θ − sin θ)/θ³ = (1 − A)/θ². It only enters as C (ω·u) ω, of size ≤ C θ² |u|, so the
    # direct formula's error ε/θ² costs ε|u| there; dividing by θ² + c (c = _C_CLAMP_S) instead
    # moves the term by ≤ c|u|/6 < 2e-15 |u| and makes θ = 0 safe, so no series branch is needed.
    np.add(s, _C_CLAMP_S, out=t0)
    np.subtract(1.0, A, out=C)
    C /= t0
    if (s > _POLY_MAX_S).any():
        _exact_rotation_coeffs(s, A, B, C, cth)
    free.give(s, zq, sinc_q, tq, t0)
    return A, B, C, cth


def _rigid(
    w: FloatArray,
    u: FloatArray | None,
    e: FloatArray | tuple[FloatArray, ...] | None,
    theta: tuple[FloatArray, FloatArray, FloatArray, FloatArray],
    O: FloatArray,
    free: _FreeRows,
) -> None:
    """O (3, n) = R(ω) e + V(ω) u = cos θ e + A u + ω × (A e + B u) + (B ω·e + C ω·u) ω, with the
    θ-coefficients (A, B, C, cos θ) of `_rotation_coeffs`; u = None is u = 0 (R e) and e = None is
    the point 0 (V u): their terms are left out. O must not overlap the inputs."""
    A, B, C, cth = theta
    mul = np.multiply
    w0, w1, w2 = w
    k, t0, t1, m0, m1, m2 = free.take(6)
    if e is not None:
        e0, e1, e2 = e
        mul(w0, e0, out=k)
        mul(w1, e1, out=t0)
        k += t0
        mul(w2, e2, out=t0)
        k += t0
        k *= B
    if u is not None:
        u0, u1, u2 = u
        wu = t1 if e is not None else k
        mul(w0, u0, out=wu)
        mul(w1, u1, out=t0)
        wu += t0
        mul(w2, u2, out=t0)
        wu += t0
        wu *= C
        if e is not None:
            k += wu
    ms = (m0, m1, m2)
    for i, mi in enumerate(ms):
        if e is None:
            mul(u[i], B, out=mi)  # type: ignore[index]
            continue
        mul(e[i], A, out=mi)
        if u is not None:
            mul(u[i], B, out=t0)
            mi += t0
    for i, (a_, b_) in enumerate(((1, 2), (2, 0), (0, 1))):  # (ω × m)_i = ω_a m_b − ω_b m_a
        Oi = O[i]
        mul(w[a_], ms[b_], out=Oi)
        mul(w[b_], ms[a_], out=t0)
        Oi -= t0
        if e is not None:
            mul(e[i], cth, out=t0)
            Oi += t0
        if u is not None:
            mul(u[i], A, out=t0)
            Oi += t0
        mul(w[i], k, out=t0)
        Oi += t0
    free.give(k, t0, t1, m0, m1, m2)


def _h2_direct(z: FloatArray, out: FloatArray, tmp: FloatArray) -> None:
    """out = (eᶻ − 1 − z)/z² for z bounded away from 0."""
    np.expm1(z, out=out)
    out -= z
    np.multiply(z, z, out=tmp)
    out /= tmp


def _sym_matvec(
    a00: FloatArray,
    a11: FloatArray,
    a22: FloatArray,
    a01: FloatArray,
    a02: FloatArray,
    a12: FloatArray,
    v0: FloatArray,
    v1: FloatArray,
    v2: FloatArray,
    o0: FloatArray,
    o1: FloatArray,
    o2: FloatArray,
    tmp: FloatArray,
) -> None:
    """(o0, o1, o2) = A v for symmetric A given by its six component rows."""
    for oi, d, oa, va, ob, vb, vi in (
        (o0, a00, a01, v1, a02, v2, v0),
        (o1, a11, a01, v0, a12, v2, v1),
        (o2, a22, a02, v0, a12, v1, v2),
    ):
        np.multiply(d, vi, out=oi)
        np.multiply(oa, va, out=tmp)
        oi += tmp
        np.multiply(ob, vb, out=tmp)
        oi += tmp


def _exact_rotation_coeffs(
    s: FloatArray, A: FloatArray, B: FloatArray, C: FloatArray, cth: FloatArray
) -> None:
    """Recompute the θ-coefficients with np.sin/np.cos where θ² > _POLY_MAX_S (lifted rotations)."""
    big = np.flatnonzero(s > _POLY_MAX_S)
    theta = np.sqrt(s[big])
    sin_t = np.sin(theta)
    half = np.sin(0.5 * theta) / (0.5 * theta)
    A[big] = sin_t / theta
    B[big] = 0.5 * half * half
    C[big] = (theta - sin_t) / (theta * s[big])
    cth[big] = np.cos(theta)


def _dense_weights(idx: IntArray, val: FloatArray, m: int) -> FloatArray:
    """Sparse (N, K) weights as a dense (m, N) matrix."""
    N = idx.shape[0]
    dense = np.zeros((m, N))
    _scatter_weights(dense.reshape(-1), N, np.arange(N, dtype=np.intp), idx, val)
    return dense


def _scatter_weights(flat: FloatArray, stride: int, cols: NDArray[np.intp], idx: IntArray,
                     val: FloatArray) -> None:
    """flat[idx[v, k]·stride + cols[v]] += val[v, k] for every slot k: the sparse (n, K) weights as the
    columns `cols` of a zeroed dense (m, stride) row-major matrix."""
    for k in range(idx.shape[1]):
        pos = idx[:, k].astype(np.intp) * stride
        pos += cols
        if k == 0:
            flat[pos] = val[:, 0]
        else:
            # Each k hits every column once, so `+=` is exact even when a vertex lists a control
            # twice (in different slots).
            flat[pos] += val[:, k]


# ----------------------------------------------------------------------------------------------
# module-level API (docs/DEVELOPING.md)

_local = threading.local()
_pool_lock = threading.Lock()
_pool_instance: ThreadPoolExecutor | None = None

#: Upper bound of the default thread count (a frame handler should not take over a render farm node).
MAX_DEFAULT_THREADS = 8
#: Environment variable that overrides the default thread count.
THREADS_ENV = "AFFINE_DEFORMERS_THREADS"


def default_threads() -> int:
    """Threads a new kernel uses: $AFFINE_DEFORMERS_THREADS, else every core the machine has, at most
    MAX_DEFAULT_THREADS. The frame handler blocks Blender's main thread while the kernel runs, so
    leaving a core idle for Blender gains nothing."""
    env = os.environ.get(THREADS_ENV, "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    return max(1, min(_cpu_count(), MAX_DEFAULT_THREADS))


@functools.lru_cache(maxsize=1)
def _cpu_count() -> int:
    # os.cpu_count() reads /proc or sysfs on every call (µs), and the kernel asks on every update.
    return os.cpu_count() or 1


def _pool() -> ThreadPoolExecutor:
    global _pool_instance
    with _pool_lock:
        if _pool_instance is None:
            _pool_instance = ThreadPoolExecutor(
                max_workers=2 * default_threads(), thread_name_prefix="affine_deformers"
            )
        return _pool_instance


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
