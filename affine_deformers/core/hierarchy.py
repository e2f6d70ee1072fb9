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

#: The band of cumulative weight over which the truncation's pooled point descends one bone
#: (`PoolPoint`, MATH.md §12): a bone on the majority path counts fully once its subtree holds
#: 1/2 + POOL_BAND of the vertex's weight. 1/4 follows a chain curled into a ring of ties (its
#: cumulative weights fall by 1/8 a bone there) closely enough; 1/2 left steps 3.6× the
#: untruncated field's there at 4 influences (docs/field_ties.md).
POOL_BAND = 0.25
#: c in the bones' truncation divisor D = max(S, c·T) (weights.POOL_FLOOR is the probes'): the
#: pooled point is local, so pooling a little more costs little, and at 0.5 the end of a root bone
#: sweeping through the ties of a ring of 8 bones stepped 3.0× the untruncated field's along its
#: axis at 4 influences (0.6: 2.5×; 0.75: 2.1×, but 2.8× on the ring-shaped chain's edges).
BONE_POOL_FLOOR = 0.6

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


def subtree_sums(values: ArrayLike, parents: ArrayLike) -> FloatArray:
    """Σ_{j in the subtree of i} x_j for every control i, over the last axis of `values` (..., m): own
    weights become cumulative weights W (MATH.md §14). A pass per level, deepest first."""
    parents = np.asarray(parents, dtype=np.intp)
    depth = depths(parents)
    out = np.array(values, dtype=np.float64, copy=True)
    for d in range(int(depth.max(initial=0)), 0, -1):  # a pass per level
        level = np.flatnonzero(depth == d)
        np.add.at(out, (..., parents[level]), out[..., level])
    return out


def pool_mix(parents: ArrayLike, scales: ArrayLike, *, leaves: bool = True) -> FloatArray:
    """The pooled nodes of a forest of controls as weights on the controls (m + 1, m) (MATH.md §12):
    row i (< m) is the mean of control i's children μ_i, each child c by its tree share
    A_c / Σ_{c'} A_c' (A = `subtree_sums` of the scale shares a = s / Σ s; uniform when those are 0);
    row m is the mean of the roots μ_⊤ (root r by A_r). A vertex with weight x on μ_i blends exactly
    as with x A_c / Σ A_c' on the children (they share one depth, so their factor gets
    x Σ_c (A_c / Σ A_c') ψ(L_c) either way, and every ancestor x): this matrix converts pooled weights
    to control weights. A leaf's row is the leaf itself (its mean of no children is its own motion)
    or, with leaves=False, zero: then `mix @ ψ(L)` are the pooled nodes' local parameters."""
    parents = np.asarray(parents, dtype=np.intp)
    m = len(parents)
    s = np.asarray(scales, dtype=np.float64).reshape(-1)
    if s.shape != (m,) or not np.all(np.isfinite(s)) or np.any(s < 0.0):
        raise ValueError(f"scales must be {m} finite non-negative numbers")
    share = subtree_sums(s / s.sum() if s.sum() > 0.0 else np.zeros(m), parents)
    owner = np.where(parents >= 0, parents, m)  # the row a control belongs to: its parent's, or μ_⊤
    mix = np.zeros((m + 1, m))
    alike = np.zeros((m + 1, m))
    mix[owner, np.arange(m)] = share
    alike[owner, np.arange(m)] = 1.0
    mix = np.where(mix.sum(axis=1, keepdims=True) > 0.0, mix, alike)  # children that all weigh 0: alike
    count = mix.sum(axis=1, keepdims=True)
    mix /= np.where(count > 0.0, count, 1.0)
    if leaves:
        leaf = np.flatnonzero(count[:m, 0] == 0.0)
        mix[leaf, leaf] = 1.0
    return mix


def pool_parents(parents: ArrayLike) -> NDArray[np.intp]:
    """The forest with its pooled nodes (2m + 1,): control i < m keeps its parent, μ_i = m + i hangs
    below control i, μ_⊤ = 2m is one more root."""
    parents = np.asarray(parents, dtype=np.intp)
    m = len(parents)
    return np.concatenate([parents, np.arange(m), [-1]]).astype(np.intp)


def pool_tables(params: ArrayLike, matrices: ArrayLike, mix: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(local parameters (2m + 1, 12), motions (2m + 1, 4, 4)) of the controls and their pooled nodes
    (`pool_parents` numbering), from ψ(L) (m, 12), the controls' motions A (m, 4, 4) and `pool_mix`
    (m + 1, m): μ_i blends its children's ψ(L_c) (a leaf's row, itself, counts as no children: q = 0)
    and moves by A_i φ(q_i); μ_⊤ blends the roots' ψ(L_r) and moves by φ(q_⊤). A motion shared by
    all controls (L = I below the roots) gives every μ_i its parent's motion and μ_⊤ the common one."""
    from .aff3 import matrices_from_params

    P = np.asarray(params, dtype=np.float64)
    A = np.asarray(matrices, dtype=np.float64)
    m = len(P)
    local = np.array(mix, dtype=np.float64)
    local[np.arange(m), np.arange(m)] = 0.0  # a leaf's own row: its mean of no children
    q = local @ P
    moved = matrices_from_params(q)
    full = np.concatenate([A @ moved[:m], moved[m:]])
    return np.concatenate([P, q]), np.concatenate([A, full])


@dataclass(frozen=True)
class PoolPoint:
    """Where the truncation's pooled weight λ of a vertex goes on a forest of controls (MATH.md §12):
    a point on the tree of the vertex's untruncated cumulative weights, `width` = 4 columns.

    With W_i = Σ_{j in the subtree of i} w_j / Σ w (continuous in the weights, no order statistic),
    the controls with W_i > 1/2 form a path from a root down (two siblings cannot both hold more than
    half), below a top node ⊤. Each bone on it counts g_i = clamp((W_i − 1/2)/`band`, 0, 1), and the
    point lies at depth ρ = Σ g_i along the path: between its nodes n_k (k = ⌊ρ⌋, position 0 being
    ⊤) and n_(k+1), a fraction f = ρ − k of the way. Each of the two takes its share ((1 − f), f),
    split between the node itself, 1 − σ, and the mean of its children μ_n, σ: σ_n = 1 − w_n / (Σ w ·
    W_n), the share of the node's cumulative weight its children hold (σ_⊤ = 1: μ_⊤, the mean of the
    roots; 0 for a leaf). Returned: node indices (n, 4) in the `pool_parents` numbering and shares
    (n, 4) summing to 1 (0 for an all-zero row).

    Continuous: W is; a bone joins or leaves the path at its end with g = 0, so ρ is continuous and the
    point passes a node with all its share on it. Slope: |∇ρ| ≤ Σ |∇W_i| / band, the untruncated
    cumulative weights' own slope over the band. Local: the point is an ancestor of most of the
    vertex's weight, or the mean of the children of one, never a far control's motion."""

    parents: NDArray[np.intp]
    band: float = POOL_BAND
    width: int = 4

    def __call__(self, weights: ArrayLike) -> tuple[NDArray[np.int32], FloatArray]:
        W = np.asarray(weights, dtype=np.float64)
        parents = np.asarray(self.parents, dtype=np.intp)
        m = len(parents)
        if W.ndim != 2 or W.shape[1] != m:
            raise ValueError(f"weights must have shape (n, {m}), got {W.shape}")
        n = len(W)
        total = W.sum(axis=1)
        ok = total > 0.0
        own = W / np.where(ok, total, 1.0)[:, None]
        cum = subtree_sums(own, parents)
        depth = depths(parents)
        levels = int(depth.max(initial=0)) + 1
        rows = np.arange(n)
        path = np.full((n, levels + 1), 2 * m, dtype=np.intp)  # position 0: ⊤ (its mean, μ_⊤)
        rho = np.zeros(n)
        length = np.zeros(n, dtype=np.intp)
        for d in range(levels):  # a pass per level: the bone of that depth holding more than half
            level = np.flatnonzero(depth == d)
            best = level[np.argmax(cum[:, level], axis=1)]
            c = cum[rows, best]
            on = c > 0.5
            path[:, d + 1] = np.where(on, best, path[:, d])
            rho += np.where(on, np.clip((c - 0.5) / self.band, 0.0, 1.0), 0.0)
            length += on
        k = np.minimum(np.floor(rho).astype(np.intp), length)
        f = np.where(k < length, rho - k, 0.0)
        first, second = path[rows, k], path[rows, np.minimum(k + 1, levels)]
        has_children = np.zeros(m + 1, dtype=bool)
        has_children[parents[parents >= 0]] = True

        def split(node: NDArray[np.intp]) -> tuple[NDArray[np.intp], NDArray[np.intp], FloatArray]:
            """(the node, its children's mean, σ): σ_⊤ = 1; a bone on the path has W > 1/2."""
            bone = node < m
            b = np.where(bone, node, 0)
            held = 1.0 - own[rows, b] / np.maximum(cum[rows, b], 0.5)  # by the children
            sigma = np.where(bone, np.where(has_children[b], np.clip(held, 0.0, 1.0), 0.0), 1.0)
            return np.where(bone, node, 2 * m), np.where(bone, node + m, 2 * m), sigma

        a, mu_a, sa = split(first)
        b, mu_b, sb = split(second)
        idx = np.stack([a, mu_a, b, mu_b], axis=1).astype(np.int32)
        shares = np.stack([(1.0 - f) * (1.0 - sa), (1.0 - f) * sa, f * (1.0 - sb), f * sb], axis=1)
        return idx, np.where(ok[:, None], shares, 0.0)


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
