"""Blending down a hierarchy of controls (MATH.md §14): what a bone deformer's vertices blend.

Controls form a forest: parents[i] is the nearest ancestor of control i among the controls (−1 for a
root). With their motions A_i (rest → now, in Aff+(3)) each control has a local motion

    L_i = A_parent(i)⁻¹ A_i   (L_i = A_i for a root),

its motion relative to its parent's. A vertex with weights w_j gets cumulative weights
W_i = Σ_{j in the subtree of i} w_j (the weight of i and all that hangs below it) and goes to

    v' = F_0 F_1 ⋯ F_D v,   F_d = φ(Σ_{depth(i) = d} W_i ψ(L_i)),

the factors in depth order from the roots. A vertex between a bone and its parent (w_p + w_c = 1)
gets A_p φ(w_c ψ(L_c)): the parent's full motion, then part of the child's turn about the joint, so
a twist of the child past 180° under a turned parent stays on the child's axis (blending ψ(A_c), the
screw of the parent's turn and the twist together, leaves it). W is continuous in the weights, so the
field has no seam where a vertex's set of bones changes; a vertex fully weighted to one control gets
exactly its motion (all W on its chain are 1, the rest 0: L_root ⋯ L_i = A_i).

Evaluation: the leading factors whose single W is 1 multiply to the full motion of the deepest of
them (the vertex's `prefix`), so a vertex applies the matrix A_prefix after the factors below it
only — a blend pass per factor. Rows are independent, so a subset of vertices computes bit for bit
what the whole set gives them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .aff3 import inverse3

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: A cumulative weight within this of 1 counts as 1 (stored weights are float32: a vertex's weights
#: sum to 1 within ~1e-7), so its factor is the control's exact local motion and joins the prefix.
FULL_TOL = 1e-5
#: Most roots the truncation's pooled weight is spread over (`pool_to_roots`); a forest with more
#: (a flat rig: every bone a root) leaves the pooled weight at rest instead, since a column per root
#: would cost as much as keeping every bone.
MAX_POOL_ROOTS = 4

PointKernel = Callable[[FloatArray, FloatArray, NDArray[np.int32], FloatArray], FloatArray]
MotionKernel = Callable[[FloatArray, NDArray[np.int32], FloatArray], np.ndarray]


def depths(parents: ArrayLike) -> IntArray:
    """The depth of every control (0 for a root) from `parents` (m,) in [-1, m); ValueError when
    an entry is out of range or the parents form a cycle."""
    parents = np.asarray(parents)
    if parents.ndim != 1 or not np.issubdtype(parents.dtype, np.integer):
        raise ValueError(f"parents must be a 1-D integer array, got shape {parents.shape} {parents.dtype}")
    m = len(parents)
    if m and (parents.min() < -1 or parents.max() >= m):
        raise ValueError("parents must be in [-1, m)")
    depth = np.zeros(m, dtype=np.intp)
    above = parents.astype(np.intp)
    for _ in range(m + 1):  # a pass per level: one more than the deepest chain ends it
        rooted = above < 0
        if rooted.all():
            return depth
        depth += ~rooted
        above = np.where(rooted, -1, parents[np.maximum(above, 0)])
    raise ValueError("parents form a cycle")


def pool_to_roots(indices: ArrayLike, values: ArrayLike, parents: ArrayLike, scales: ArrayLike,
                  max_roots: int = MAX_POOL_ROOTS) -> tuple[NDArray[np.int32], FloatArray]:
    """Truncated weights (indices (N, K + 1), values) whose last column is the pooled control (index
    m = len(parents), weights.sparse_from_blocks) -> the same weights with that column's weight λ
    given to the roots of the forest instead: root r gets λ a_r, a_r = Σ_{i in r's tree} s_i / Σ_i s_i
    (s = `scales`), one column per root (MATH.md §12). The blend down the hierarchy (MATH.md §14)
    then follows the roots fully (W_root = 1 for a single tree), so a motion shared by all bones,
    which is the root's, stays exact wherever weight is pooled, and the pooled share does not follow
    the bones below the root. With more than `max_roots` roots the pooled column is dropped (that
    weight stays at rest). Weights without a pooled column are returned as they are."""
    indices = np.asarray(indices)
    values = np.asarray(values, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.intp)
    m = len(parents)
    if indices.size == 0 or int(indices.max()) != m:
        return indices.astype(np.int32), values
    if not np.all(indices[:, -1] == m) or np.any(indices[:, :-1] == m):
        raise ValueError("the pooled control must be the last column of every row")
    s = np.asarray(scales, dtype=np.float64).reshape(-1)
    if s.shape != (m,) or not np.all(np.isfinite(s)) or np.any(s < 0.0):
        raise ValueError(f"scales must be {m} finite non-negative numbers")
    depths(parents)  # checks the forest (no cycle)
    root = np.arange(m)
    for _ in range(m):  # a pass per level: every control climbs to its root
        up = parents[root]
        if np.all(up < 0):
            break
        root = np.where(up >= 0, up, root)
    share = np.bincount(root, weights=s, minlength=m) if s.sum() > 0.0 else np.bincount(root, minlength=m)
    roots = np.flatnonzero(share > 0.0)
    pooled = values[:, -1]
    if len(roots) > max_roots:
        return indices[:, :-1].astype(np.int32), values[:, :-1].copy()
    share = share[roots] / share[roots].sum()
    new_idx = np.concatenate([indices[:, :-1], np.broadcast_to(roots, (len(indices), len(roots)))], axis=1)
    new_val = np.concatenate([values[:, :-1], pooled[:, None] * share[None, :]], axis=1)
    return new_idx.astype(np.int32), new_val


def local_motions(matrices: ArrayLike, parents: ArrayLike) -> FloatArray:
    """L_i = A_parent(i)⁻¹ A_i (A_i for a root) for motions (m, 4, 4) with bottom rows 0 0 0 1; rows
    with a singular parent are non-finite (callers check)."""
    A = np.asarray(matrices, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.intp)
    out = A.copy()
    child = np.flatnonzero(parents >= 0)
    if len(child):
        P = A[parents[child]]
        with np.errstate(all="ignore"):
            inv, _ = inverse3(P[:, :3, :3])
            out[child, :3, :3] = inv @ A[child, :3, :3]
            out[child, :3, 3] = np.einsum("nij,nj->ni", inv, A[child, :3, 3] - P[:, :3, 3])
    return out


@dataclass(frozen=True)
class ChainLayout:
    """Every vertex's product A_prefix F_(prefix depth + 1) ⋯ F_D in evaluation form: P blend passes
    over the local parameters ψ(L_i), then the prefix matrix.

    indices (P, N, k) int32 and values (P, N, k): pass 0 holds every vertex's deepest factor, pass 1
    the one above it, …; a vertex with fewer factors has zero weights there (φ(0) v = v). `prefix`
    (N,) int32: the control whose full motion a vertex ends with, m for none (the identity row of
    `prefix_table`); per control the vertices that read it (`ptr`, `readers`: CSR, sorted) for
    incremental updates.
    """

    prefix: NDArray[np.int32]
    indices: NDArray[np.int32]
    values: FloatArray
    ptr: IntArray
    readers: IntArray

    def affected_rows(self, controls: ArrayLike) -> IntArray:
        """Sorted vertices whose result reads any of `controls` (as prefix or in a factor)."""
        controls = np.asarray(controls, dtype=np.intp)
        if len(controls) == 1:
            c = int(controls[0])
            return self.readers[self.ptr[c] : self.ptr[c + 1]]
        mask = np.zeros(len(self.prefix), dtype=bool)
        for c in controls:  # a pass per control, not per vertex
            mask[self.readers[self.ptr[c] : self.ptr[c + 1]]] = True
        return np.flatnonzero(mask)


def _closure(indices: np.ndarray, values: np.ndarray, parents: IntArray,
             depth: IntArray) -> tuple[IntArray, IntArray, IntArray, FloatArray]:
    """(vertex, depth, control, W) of every non-zero cumulative weight, sorted by vertex, depth and
    control: each weight added to its control and to every ancestor of it."""
    r, s = np.nonzero(values)
    b = indices[r, s].astype(np.intp)
    w = values[r, s]
    parts_r, parts_b, parts_w = [r], [b], [w]
    up = parents[b]
    while len(up):  # a pass per level of the deepest chain
        keep = up >= 0
        r, up, w = r[keep], up[keep], w[keep]
        parts_r.append(r)
        parts_b.append(up)
        parts_w.append(w)
        up = parents[up]
    R, B, W = np.concatenate(parts_r), np.concatenate(parts_b), np.concatenate(parts_w)
    m = len(parents)
    levels = int(depth.max(initial=0)) + 1
    key = (R.astype(np.int64) * levels + depth[B]) * m + B
    unique, inverse = np.unique(key, return_inverse=True)
    total = np.bincount(inverse.ravel(), weights=W, minlength=len(unique))
    vertex, rest = np.divmod(unique, levels * m)
    d, control = np.divmod(rest, m)
    return vertex.astype(np.intp), d.astype(np.intp), control.astype(np.intp), total


def _starts(first: np.ndarray) -> IntArray:
    """For runs marked by `first` (True at each run's first entry): the index of each entry's run start."""
    return np.maximum.accumulate(np.where(first, np.arange(len(first)), 0))


def _leading(vertex: IntArray, d: IntArray, W: FloatArray, full_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(leading, new_level) over the sorted closure: leading marks each vertex's run of depths 0, 1, …
    each held by one control with W within `full_tol` of 1 (its prefix); new_level the first entry of
    each (vertex, depth)."""
    e = len(vertex)
    new_vertex = np.ones(e, dtype=bool)
    new_vertex[1:] = vertex[1:] != vertex[:-1]
    new_level = new_vertex.copy()
    new_level[1:] |= d[1:] != d[:-1]
    alone = new_level.copy()  # the only control of its (vertex, depth)
    alone[:-1] &= new_level[1:]
    ok = (d == np.arange(e) - _starts(new_vertex)) & alone & (np.abs(W - 1.0) <= full_tol)
    bad = np.cumsum(~ok)
    leading = bad == (bad - ~ok)[_starts(new_vertex)]
    return leading, new_level


def chain_layout(indices: ArrayLike, values: ArrayLike, parents: ArrayLike,
                 full_tol: float = FULL_TOL) -> ChainLayout:
    """The `ChainLayout` of sparse weights (indices (N, K), values (N, K)) over controls with `parents`."""
    indices = np.asarray(indices)
    values = np.asarray(values, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.intp)
    depth = depths(parents)
    n, m = len(indices), len(parents)
    vertex, d, control, W = _closure(indices, values, parents, depth)
    leading, new_level = _leading(vertex, d, W, full_tol)
    last = leading.copy()
    last[:-1] &= ~(leading[1:] & (vertex[1:] == vertex[:-1]))
    prefix = np.full(n, m, dtype=np.int32)
    prefix[vertex[last]] = control[last]
    below = ~leading
    vb, cb, wb = vertex[below], control[below], W[below]
    slot = np.arange(len(vb)) - _starts(new_level[below])
    # Each vertex's factors counted from its deepest (pass 0) up.
    level_start = new_level[below]
    rank = np.cumsum(level_start) - 1  # the (vertex, depth) group number
    groups_per_vertex = np.bincount(vb[level_start], minlength=n)
    first_group = np.concatenate([[0], np.cumsum(groups_per_vertex)[:-1]])
    from_top = rank - first_group[vb]
    pass_of = groups_per_vertex[vb] - 1 - from_top
    has = prefix < m
    n_pass = int(groups_per_vertex.max(initial=0))
    width = int(slot.max(initial=0)) + 1
    idx = np.zeros((n_pass, n, width), dtype=np.int32)
    val = np.zeros((n_pass, n, width))
    idx[pass_of, vb, slot] = cb
    val[pass_of, vb, slot] = wb
    pair_v = np.concatenate([np.flatnonzero(has), vb])
    pair_c = np.concatenate([prefix[has].astype(np.intp), cb])
    order = np.lexsort((pair_v, pair_c))
    ptr = np.zeros(m + 1, dtype=np.intp)
    np.cumsum(np.bincount(pair_c, minlength=m), out=ptr[1:])
    return ChainLayout(prefix, idx, val, ptr, pair_v[order].astype(np.intp))


def prefix_table(matrices: ArrayLike) -> FloatArray:
    """The prefix matrices (m + 1, 12) of motions A (m, 4, 4): each row M (row-major, 9) then t (3),
    x ↦ M x + t; the last row is the identity (vertices without a prefix)."""
    A = np.asarray(matrices, dtype=np.float64)
    out = np.zeros((len(A) + 1, 12))
    out[:-1, :9] = A[:, :3, :3].reshape(-1, 9)
    out[:-1, 9:] = A[:, :3, 3]
    out[-1, [0, 4, 8]] = 1.0
    return out


def _apply_prefix(table: FloatArray, prefix: NDArray[np.int32], x: FloatArray) -> FloatArray:
    """M x + t per row with (M, t) = table[prefix] (`prefix_table` rows), elementwise."""
    T = table[prefix]
    out = np.empty_like(x)
    for i in range(3):
        row = 3 * i
        out[:, i] = T[:, row] * x[:, 0] + T[:, row + 1] * x[:, 1] + T[:, row + 2] * x[:, 2] + T[:, 9 + i]
    return out


def chain_points(points: ArrayLike, params: ArrayLike, prefixes: ArrayLike, layout: ChainLayout,
                 rows: ArrayLike | None = None, kernel: PointKernel | None = None) -> FloatArray:
    """v' = A_prefix F_(prefix depth + 1) ⋯ F_D v for the vertices `rows` (sorted; None: all) of
    `points` (N, 3): params (m, 12) ψ(L_i), prefixes (m + 1, 12) from `prefix_table`. Returns
    (len(rows), 3) float64. `kernel(points, params, indices, values)` is the blend map
    v ↦ φ(Σ w P) v (default: the numpy one)."""
    if kernel is None:
        from .deform import deform_points_params as kernel
    points = np.asarray(points, dtype=np.float64)
    sel = None if rows is None else np.asarray(rows, dtype=np.intp)
    x = points.copy() if sel is None else points[sel]
    table = np.ascontiguousarray(params, dtype=np.float64)
    for idx, val in zip(layout.indices, layout.values, strict=True):  # the deepest factor first
        if sel is not None:
            idx, val = idx[sel], val[sel]
        x = kernel(x, table, idx, val)
    prefix = layout.prefix if sel is None else layout.prefix[sel]
    return _apply_prefix(np.asarray(prefixes, dtype=np.float64), prefix, x)


def _compose(G: np.ndarray, H: np.ndarray) -> FloatArray:
    """G ∘ H for motions in column form (4, n, 3) (M e_x, M e_y, M e_z, t): columns G_M (H e_c) and
    G_M t_H + t_G, elementwise (a row's bits do not depend on the batch)."""
    out = np.empty(np.shape(H), dtype=np.float64)
    for c in range(4):
        out[c] = G[0] * H[c][:, 0:1]
        out[c] += G[1] * H[c][:, 1:2]
        out[c] += G[2] * H[c][:, 2:3]
    out[3] += G[3]
    return out


def identity_motions(n: int) -> FloatArray:
    """n identity motions in column form (4, n, 3)."""
    out = np.zeros((4, n, 3))
    for c in range(3):
        out[c, :, c] = 1.0
    return out


def chain_motions(params: ArrayLike, prefixes: ArrayLike, layout: ChainLayout, rows: ArrayLike | None = None,
                  kernel: MotionKernel | None = None) -> FloatArray:
    """The motions x ↦ A_prefix F_(prefix depth + 1) ⋯ F_D x of the vertices `rows` (sorted; None:
    all) in column form (4, len(rows), 3) float64 (arguments as `chain_points`). `kernel(params,
    indices, values)` gives the columns of φ(Σ w P) per row (default: the numpy one)."""
    if kernel is None:
        from .deform import vertex_motions as kernel
    sel = None if rows is None else np.asarray(rows, dtype=np.intp)
    table = np.ascontiguousarray(params, dtype=np.float64)
    T = np.asarray(prefixes, dtype=np.float64)[layout.prefix if sel is None else layout.prefix[sel]]
    out = np.stack([T[:, [0, 3, 6]], T[:, [1, 4, 7]], T[:, [2, 5, 8]], T[:, 9:]])  # A_prefix's columns
    for idx, val in zip(layout.indices[::-1], layout.values[::-1], strict=True):  # outermost first
        if sel is not None:
            idx, val = idx[sel], val[sel]
        out = _compose(out, np.asarray(kernel(table, idx, val), dtype=np.float64))
    return out
