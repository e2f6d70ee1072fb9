"""`DeformKernel`: the per-vertex kernel behind core/deform.py's functions — chunks, scratch rows,
the weights and row-set caches, and the shared thread pool (`default_threads`).

No 3×3 matrix is formed per vertex. Vertices are processed in chunks, as structure-of-arrays rows
(12, n) in preallocated scratch rows, with in-place ufuncs only:

* blend: the sparse bind weights become a dense (m, N) matrix (cached while the same weights come
  back, see `DeformKernel._sparse_weights`) and one BLAS product per chunk gives p_v; with many
  controls the parameter rows are gathered instead;
* the map: the stages of core/kernel_stages.py on the chunk's rows.

Throughput, where the time goes and why (memory traffic between scratch rows, not arithmetic): the
'Kernel performance' section of docs/DEVELOPING.md (measurements belong there, not in code).
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Hashable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import (
    check_given_out,
    check_indices,
    check_motion_indices,
    check_motion_out,
    check_out,
    check_points,
    check_rows,
    check_table,
    check_weights_shape,
    identity_motions,
    unchanged,
)
from .kernel_stages import (
    FloatArray,
    IntArray,
    _by_form,
    _exp_sym_closed_apply,
    _exp_sym_closed_matrix,
    _exp_sym_small_apply,
    _exp_sym_small_matrix,
    _FreeRows,
    _rigid,
    _rotation_coeffs,
)

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
        """Sparse hot path: core.deform.deform_points_params (the contract)."""
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
        """Only the listed rows: core.deform.deform_points_params_rows (the contract)."""
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
        """The per-vertex affine maps: core.deform.vertex_motions (the contract)."""
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
            blend_product(table_t, rs.weights[:, a:b], P)
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
            blend_product(table_t, W[a:b].T, P)
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
        """'LINEAR' comparison mode: core.deform.blend_linear_sparse (the contract)."""
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
        check_weights_shape(idx, n_points)
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
            blend_product(table_t, dense[:, a:b], P)
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
            blend_product(table_t, dense, P)
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


#: Multiply-adds per BLAS call of the blend, at most: OpenBLAS runs a product of up to 65536 × 4
#: (its default GEMM_MULTITHREAD_THRESHOLD) multiply-adds on the calling thread alone.
BLAS_SINGLE_THREAD_MNK = 65536 * 4


def blend_product(table_t: FloatArray, weights: FloatArray, out: FloatArray) -> None:
    """out (c, n) = table_t (c, m) · weights (m, n) in column blocks small enough for one BLAS thread.

    A row's bits must not depend on the call (the Blender layer recomputes only the rows a moved
    control influences). A multi-threaded BLAS product splits the columns among its threads, and
    with AVX-512 kernels (OpenBLAS SkylakeX) a column then gets other bits near a split than in a
    product of another width (measured: ~1 % of rows differed between a full call and a subset).
    On one thread each column is accumulated alike wherever it sits."""
    c, m = table_t.shape
    block = max(8, BLAS_SINGLE_THREAD_MNK // max(1, c * m) // 8 * 8)
    n = weights.shape[1]
    for a in range(0, n, block):
        b = min(a + block, n)
        np.matmul(table_t, weights[:, a:b], out=out[:, a:b])


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
# threads

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
