"""Harmonic probe weights on the target mesh ('SURFACE' weights): influence that follows the surface.

For a mesh (vertices x_v, triangles) and probes i = 1..m at rest positions c_i, probe i's raw weight
is the discrete harmonic function w_i with

    (L w_i)(v) = Σ_{u ~ v} λ_uv (w_i(v) − w_i(u)) = 0     at every free vertex v,
    w_i = 1 on probe i's constrained set C_i,  w_i = 0 on C_j (j ≠ i),

L the cotangent Laplacian (the P1 finite-element stiffness matrix): λ_uv = ½ (cot α_uv + cot β_uv),
α, β the angles opposite edge uv (only one on a boundary edge). Solved for all probes at once (one
right-hand side per probe). The weights then go through weights.truncate and the normalisation like
distance weights (weights.probe_weights, mode 'SURFACE').

Clamping. A non-Delaunay edge has α + β > π and a negative λ; L is then still positive semidefinite
but no longer an M-matrix, so the maximum principle fails: weights can leave [0, 1] and oscillate,
and a negative weight has no meaning in a blend (weights.sparse_from_blocks refuses it). Every edge weight is
therefore clamped to [EDGE_WEIGHT_FLOOR, EDGE_WEIGHT_CAP] (dimensionless: cotangents do not depend
on the mesh's scale). With all λ > 0 the maximum principle holds, so 0 ≤ w_i ≤ 1 and Σ_i w_i = 1 on
every part that has a probe (the constant 1 is harmonic). A small positive floor rather than 0
keeps every mesh edge in the graph, so the solver's connected parts are the mesh's. A corner of a
zero-area triangle contributes cot = 0; the cap bounds needle triangles.

Constrained sets (cores). One vertex per probe is not enough on fine meshes: a point has zero
capacity in 2-D, so point-constrained harmonic weights flatten towards the same value everywhere as
the mesh is refined (≈ 1/log(1/h)). C_i is a region of fixed geometric size instead, the part of the
surface clearly closest to probe i. With d_i the distance from c_i to its nearest vertex and
e_i(x) = |x − c_i| − d_i the excess distance (0 at that vertex, also for a probe off the surface),
a vertex belongs to the core of its nearest probe i (least e_i) when e_i(x) ≤ CORE_RATIO ·
min_{j≠i} e_j(x): at least twice as close as to any other probe. The rule has no length scale (it
depends on neither the mesh's size nor its resolution), and a band where no probe is twice as
close separates the cores; where the mesh is coarser than that band, the less dominated end of an
edge joining two cores is freed, so cores never share an edge (unless both ends are probes' nearest
vertices) and weights do not jump from one probe to another across a single edge. Of each core
only its surface-connected pieces that reach within 2 d_i of c_i are kept (the piece at the probe
and, for a probe inside a thin part, the far side), so a neighbouring finger that is
Euclidean-close across a gap is not taken. weights.probe_weights then raises the weights to the
deformer's exponent and renormalises them, which localises them further (the share of a probe
where another dominates drops faster).

Parts. A connected part (through triangles) without a constrained vertex has no harmonic solution
(L is singular there): `HarmonicWeights.solved` is False on it and the caller uses distance weights.

Solver (numpy only; no Python loop over vertices): conjugate gradients on the free vertices,
vectorised over the probes (one recurrence per column, all columns per matrix product), with one
V-cycle of smoothed-aggregation algebraic multigrid as the preconditioner: strong couplings
|a_uv| ≥ θ √(a_uu a_vv) (θ = STRENGTH, halved per level; the weak ones lumped into the diagonal);
aggregates = roots at graph distance ≥ 3 (a distance-2 maximal independent set by Luby's rule with
fixed pseudo-random priorities, so the result is reproducible) plus their neighbours; the
prolongator smoothed by one damped-Jacobi step; Galerkin coarse operators; one damped-Jacobi
pre- and post-smoothing step (a symmetric positive definite cycle); a dense inverse on the
coarsest level. The cycle runs in float32, the recurrence in float64 with Polak–Ribière steps
(robust to the slightly inexact cycle). CSR products are one gather and one np.add.reduceat.
Stopping rule: ‖r_i‖₂ ≤ tol · ‖b_i‖₂ for every probe i (b_i: the coupling to the constrained
vertices). The iteration count barely grows with the mesh (8 probes on UV spheres: 13, 16, 18 and
20 iterations at 2k, 8k, 33k and 130k vertices), and at the default tol = 1e-7 the weights are
within ~1e-7 of a direct sparse solve (the error measured against scipy's spsolve is ≈ 1–2 × tol).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

__all__ = [
    "Csr",
    "HarmonicWeights",
    "Multigrid",
    "conjugate_gradient",
    "connected_components",
    "constraint_sets",
    "cotangent_edges",
    "harmonic_weights",
]

#: Bounds of a cotangent edge weight λ_uv (see the module docstring).
EDGE_WEIGHT_FLOOR = 1e-3
EDGE_WEIGHT_CAP = 1e3
#: A vertex is in its nearest probe's core when its excess distance to that probe is at most this
#: fraction of its excess distance to the next nearest (see the module docstring).
CORE_RATIO = 0.5
#: Default relative residual per probe at which conjugate gradients stop, and the iteration limit.
TOLERANCE = 1e-7
MAX_ITERATIONS = 500
#: Multigrid: levels of at most this many unknowns are solved densely.
COARSE_SIZE = 400
#: Damping ω of every Jacobi step (prolongator smoothing and the cycle's smoothing): ω ρ(D⁻¹A) ≤ 4/3
#: since ρ(D⁻¹A) ≤ 2 for a diagonally dominant matrix (Gershgorin).
JACOBI_DAMPING = 2.0 / 3.0
#: Strength-of-connection threshold θ of the finest level (halved on each coarser level).
STRENGTH = 0.08
#: The V-cycle's precision (half the memory traffic of float64; it only preconditions).
CYCLE_DTYPE = np.float32
#: Probes solved together (memory: a few (free vertices × this) float64 arrays).
COLUMN_BATCH = 16


# ------------------------------------------------------------------------------------ sparse matrices


@dataclass(frozen=True)
class Csr:
    """A sparse matrix in compressed-row form: row r holds data[indptr[r]:indptr[r+1]] at columns
    indices[...] (sorted, no duplicates). Rows may be empty."""

    indptr: IndexArray
    indices: IndexArray
    data: NDArray
    shape: tuple[int, int]

    @classmethod
    def from_coo(cls, rows: ArrayLike, cols: ArrayLike, vals: ArrayLike, shape: tuple[int, int]) -> Csr:
        """Sum duplicate (row, col) entries; entries are kept even when they sum to zero."""
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        vals = np.asarray(vals, dtype=np.float64)
        key = rows * shape[1] + cols
        order = np.argsort(key, kind="stable")
        key = key[order]
        first = np.ones(key.size, dtype=bool)
        first[1:] = key[1:] != key[:-1]
        starts = np.flatnonzero(first)
        data = np.add.reduceat(vals[order], starts) if key.size else np.zeros(0)
        unique = key[starts]
        indptr = np.searchsorted(unique // shape[1], np.arange(shape[0] + 1)).astype(np.int64)
        return cls(indptr, unique % shape[1], data, shape)

    @property
    def rows(self) -> IndexArray:
        """Row index of every stored entry."""
        return np.repeat(np.arange(self.shape[0], dtype=np.int64), np.diff(self.indptr))

    def transpose(self) -> Csr:
        return Csr.from_coo(self.indices, self.rows, self.data, (self.shape[1], self.shape[0]))

    def diagonal(self) -> FloatArray:
        rows = self.rows
        on = rows == self.indices
        out = np.zeros(min(self.shape), dtype=np.float64)
        out[rows[on]] = self.data[on]
        return out

    def astype(self, dtype: type) -> Csr:
        return Csr(self.indptr, self.indices, self.data.astype(dtype), self.shape)

    def matmul(self, X: NDArray) -> NDArray:
        """self @ X for X (n_cols, k) -> (n_rows, k) in the dtype of `data`: per row, the sum of its
        entries times the rows X[col] (one gather and one np.add.reduceat)."""
        if not self.data.size:
            return np.zeros((self.shape[0], X.shape[1]), dtype=self.data.dtype)
        gathered = np.take(X.astype(self.data.dtype, copy=False), self.indices, axis=0)
        gathered *= self.data[:, None]
        starts = self.indptr[:-1]
        nonempty = starts < self.indptr[1:]
        if nonempty.all():
            return np.add.reduceat(gathered, starts, axis=0)
        # reduceat from each non-empty row's start: the segments between them are exactly those rows
        out = np.zeros((self.shape[0], X.shape[1]), dtype=self.data.dtype)
        out[nonempty] = np.add.reduceat(gathered, starts[nonempty], axis=0)
        return out

    def product(self, other: Csr) -> Csr:
        """self @ other (sparse): every entry (i, k) of self times every entry (k, j) of other's row k."""
        lengths = np.diff(other.indptr)[self.indices]
        total = int(lengths.sum())
        first = np.repeat(other.indptr[self.indices], lengths)
        pos = first + np.arange(total) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        return Csr.from_coo(np.repeat(self.rows, lengths), other.indices[pos],
                            np.repeat(self.data, lengths) * other.data[pos], (self.shape[0], other.shape[1]))

    def to_dense(self) -> FloatArray:
        out = np.zeros(self.shape)
        np.add.at(out, (self.rows, self.indices), self.data)
        return out


# ---------------------------------------------------------------------------------------- mesh graph


def cotangent_edges(points: ArrayLike, triangles: ArrayLike) -> tuple[IndexArray, FloatArray]:
    """Unique undirected edges (E, 2) (u < v, sorted) of the triangles and their clamped cotangent
    weights λ_uv = clip(½ Σ cot(angles opposite uv), EDGE_WEIGHT_FLOOR, EDGE_WEIGHT_CAP).

    cot at corner p of triangle (p, q, r) is (q − p)·(r − p) / |(q − p) × (r − p)|; a corner of a
    triangle of zero area (or with a repeated vertex) counts 0.
    """
    P = np.asarray(points, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = P.shape[0]
    if T.size and (T.min() < 0 or T.max() >= n):
        raise ValueError("triangle vertex indices out of range")
    cots = np.empty((T.shape[0], 3))
    for corner in range(3):  # three corners, each vectorised over all triangles
        p, q, r = (P[T[:, (corner + s) % 3]] for s in range(3))
        u, v = q - p, r - p
        cross = np.linalg.norm(np.cross(u, v), axis=1)
        dot = np.einsum("ij,ij->i", u, v)
        scale = np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1)
        ok = cross > 1e-12 * scale
        cots[:, corner] = np.where(ok, dot / np.where(ok, cross, 1.0), 0.0)
    a = T[:, [1, 2, 0]].ravel()  # the edge opposite corner k joins corners k+1 and k+2
    b = T[:, [2, 0, 1]].ravel()
    keep = a != b
    lo, hi = np.minimum(a, b)[keep], np.maximum(a, b)[keep]
    key, inverse = np.unique(lo * n + hi, return_inverse=True)
    lam = np.bincount(inverse.ravel(), weights=0.5 * cots.ravel()[keep], minlength=key.size)
    edges = np.stack([key // n, key % n], axis=1)
    return edges, np.clip(lam, EDGE_WEIGHT_FLOOR, EDGE_WEIGHT_CAP)


def connected_components(n: int, edges: ArrayLike) -> IndexArray:
    """Label (n,) of every vertex's connected part under the undirected `edges` (E, 2): the lowest
    vertex index in the part (an isolated vertex is its own part).

    Min-label hooking with pointer jumping: every round hooks each root to the lowest root it shares
    an edge with, then compresses all labels to roots; a few rounds for mesh-like graphs.
    """
    E = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    label = np.arange(n, dtype=np.int64)
    i, j = E[:, 0], E[:, 1]
    while True:
        li, lj = label[i], label[j]
        lo, hi = np.minimum(li, lj), np.maximum(li, lj)
        moving = lo < hi
        if not moving.any():
            return label
        np.minimum.at(label, hi[moving], lo[moving])
        while True:  # pointer jumping: every label becomes a root
            up = label[label]
            if np.array_equal(up, label):
                break
            label = up
        keep = label[i] != label[j]  # edges inside one part never matter again
        i, j = i[keep], j[keep]


def constraint_sets(points: ArrayLike, edges: ArrayLike, centers: ArrayLike,
                    ratio: float = CORE_RATIO) -> IndexArray:
    """owner (N,): the probe whose core C_i holds each vertex, −1 for free vertices (the rule is in
    the module docstring; only vertices on an edge count, so a loose vertex never anchors a probe).
    One pass over the probes keeps each vertex's two smallest excess distances, each step vectorised
    over the mesh; one connected-components pass splits all cores into their pieces at once."""
    P = np.asarray(points, dtype=np.float64)
    C = np.asarray(centers, dtype=np.float64)
    E = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    n, m = P.shape[0], C.shape[0]
    owner = np.full(n, -1, dtype=np.int64)
    on_surface = np.zeros(n, dtype=bool)
    on_surface[E.ravel()] = True
    if m == 0 or not on_surface.any():
        return owner
    first = np.full(n, np.inf)  # smallest excess |x − c_i| − d_i over the probes, and its probe
    second = np.full(n, np.inf)
    arg = np.zeros(n, dtype=np.int64)
    nearest = np.zeros(m)
    for i in range(m):
        dist = np.where(on_surface, np.sqrt(((P - C[i]) ** 2).sum(-1)), np.inf)
        nearest[i] = dist.min()
        excess = dist - nearest[i]
        better = excess < first  # ties keep the lower index
        second = np.where(better, first, np.minimum(second, excess))
        first = np.where(better, excess, first)
        arg = np.where(better, i, arg)
    core = on_surface & (first <= ratio * second)
    with np.errstate(invalid="ignore", divide="ignore"):
        dominance = np.where(second > 0.0, first / second, 0.0)  # 0: fully inside a core
    anchor = first == 0.0  # a probe's nearest vertex stays in its core
    while True:  # cores never share an edge: free the less dominated end of each edge joining two
        u, v = E[:, 0], E[:, 1]
        touching = core[u] & core[v] & (arg[u] != arg[v]) & ~(anchor[u] & anchor[v])
        if not touching.any():
            break
        u, v = u[touching], v[touching]
        core[np.where(anchor[v] | (~anchor[u] & (dominance[u] >= dominance[v])), u, v)] = False
    same = core[E[:, 0]] & core[E[:, 1]] & (arg[E[:, 0]] == arg[E[:, 1]])
    label = connected_components(n, E[same])
    seed = core & (first <= nearest[arg])  # within twice the probe's nearest distance
    keep = core & np.isin(label, label[seed])
    owner[keep] = arg[keep]
    return owner


# ------------------------------------------------------------------------------------------ multigrid


def _neighbour_max(graph: Csr, x: FloatArray) -> FloatArray:
    """max of x over each row's columns (every row holds its diagonal, so none is empty)."""
    return np.maximum.reduceat(x[graph.indices], graph.indptr[:-1])


def _aggregates(graph: Csr) -> IndexArray:
    """Aggregate id (n,) per node: roots pairwise at graph distance ≥ 3 (a distance-2 maximal
    independent set by Luby's rule: an undecided node whose priority is the largest among the
    undecided within distance 2 becomes a root, and everything within distance 2 of it is decided),
    each other node joining the highest-priority root next to it, else a neighbour's aggregate."""
    n = graph.shape[0]
    # odd multiplier mod 2³²: a bijection, so the priorities are distinct and fixed (reproducible)
    prio = ((np.arange(n, dtype=np.uint64) * np.uint64(2654435761)) % np.uint64(1 << 32)).astype(np.float64)
    undecided = np.ones(n, dtype=bool)
    root = np.zeros(n, dtype=bool)
    while undecided.any():
        val = np.where(undecided, prio, -1.0)
        new = undecided & (val == _neighbour_max(graph, _neighbour_max(graph, val)))
        root |= new
        undecided &= _neighbour_max(graph, _neighbour_max(graph, new.astype(np.float64))) == 0.0
    by_prio = np.argsort(prio)  # priority -> node, to turn a winning priority back into its node
    sorted_prio = prio[by_prio]
    agg = np.full(n, -1, dtype=np.int64)
    agg[root] = np.arange(int(root.sum()))
    for _ in range(2):  # distance 1 (next to a root), then distance 2 (next to an aggregated node)
        best = _neighbour_max(graph, np.where(agg >= 0, prio, -1.0))
        join = (agg < 0) & (best >= 0.0)
        agg[join] = agg[by_prio[np.searchsorted(sorted_prio, best[join])]]
    return agg


@dataclass
class _Level:
    A: Csr
    smoother: NDArray  # ω D⁻¹ (n,)
    P: Csr | None = None
    R: Csr | None = None


@dataclass
class Multigrid:
    """The smoothed-aggregation V-cycle of the module docstring for a symmetric positive definite,
    diagonally dominant A; `apply(b)` ≈ A⁻¹ b for b (n, k), a symmetric positive definite map."""

    levels: list[_Level] = field(default_factory=list)
    coarse_inverse: NDArray = field(default_factory=lambda: np.zeros((0, 0), dtype=CYCLE_DTYPE))

    @classmethod
    def build(cls, A: Csr, strength: float = STRENGTH) -> Multigrid:
        mg = cls()
        omega = JACOBI_DAMPING
        while A.shape[0] > COARSE_SIZE:
            n = A.shape[0]
            diag = A.diagonal()
            rows = A.rows
            on = rows == A.indices
            strong = on | (np.abs(A.data) >= strength * np.sqrt(diag[rows] * diag[A.indices]))
            # the filtered matrix: strong entries, weak ones lumped into the diagonal (row sums kept)
            weak_sum = np.bincount(rows[~strong], A.data[~strong], n)
            kept = np.where(on[strong], A.data[strong] + weak_sum[rows[strong]], A.data[strong])
            graph = Csr(np.searchsorted(rows[strong], np.arange(n + 1)), A.indices[strong], kept, A.shape)
            agg = _aggregates(graph)
            n_coarse = int(agg.max()) + 1
            if n_coarse >= n:
                break
            # P = (I − ω D_F⁻¹ A_F) P_tent with P_tent[v, agg(v)] = 1; a node without strong couplings
            # has a zero filtered row, and its row of P stays tentative
            fdiag = graph.diagonal()
            ok = fdiag > 1e-12 * diag
            inv_fdiag = np.where(ok, 1.0 / np.where(ok, fdiag, 1.0), 0.0)
            AP = Csr.from_coo(graph.rows, agg[graph.indices], graph.data, (n, n_coarse))
            P = Csr.from_coo(np.concatenate([np.arange(n), AP.rows]), np.concatenate([agg, AP.indices]),
                             np.concatenate([np.ones(n), -omega * inv_fdiag[AP.rows] * AP.data]),
                             (n, n_coarse))
            R = P.transpose()
            coarse = R.product(A.product(P))
            mg.levels.append(_Level(A.astype(CYCLE_DTYPE), (omega / diag).astype(CYCLE_DTYPE),
                                    P.astype(CYCLE_DTYPE), R.astype(CYCLE_DTYPE)))
            A = coarse
            strength *= 0.5
        mg.levels.append(_Level(A.astype(CYCLE_DTYPE), np.zeros(0, dtype=CYCLE_DTYPE)))
        dense = A.to_dense()
        inverse = np.linalg.inv(0.5 * (dense + dense.T)) if A.shape[0] else np.zeros((0, 0))
        mg.coarse_inverse = inverse.astype(CYCLE_DTYPE)
        return mg

    def apply(self, b: FloatArray) -> FloatArray:
        """One V-cycle from x = 0 for b (n, k) float64, computed in CYCLE_DTYPE, returned as float64."""
        return self._cycle(np.asarray(b, dtype=CYCLE_DTYPE), 0).astype(np.float64)

    def _cycle(self, b: NDArray, level: int) -> NDArray:
        if level == len(self.levels) - 1:
            return self.coarse_inverse @ b
        lv = self.levels[level]
        w = lv.smoother[:, None]
        x = w * b  # pre-smoothing from x = 0
        x += lv.P.matmul(self._cycle(lv.R.matmul(b - lv.A.matmul(x)), level + 1))
        x += w * (b - lv.A.matmul(x))  # post-smoothing: the same Jacobi step, so the cycle is symmetric
        return x


def conjugate_gradient(A: Csr, B: FloatArray, precondition: Callable[[FloatArray], FloatArray],
                       tol: float = TOLERANCE,
                       max_iterations: int = MAX_ITERATIONS) -> tuple[FloatArray, int, float]:
    """Solve A X = B (A symmetric positive definite, B (n, k)) by preconditioned conjugate gradients,
    one recurrence per column, all columns per product. Polak–Ribière steps
    β = z_new·(r_new − r_old) / z_old·r_old (= Fletcher–Reeves for an exact symmetric preconditioner,
    robust to a slightly inexact one). Stops when ‖b − A x‖ ≤ tol ‖b‖ in every column. Returns
    (X, iterations, worst relative residual over the columns)."""
    X = np.zeros_like(B)
    R = B.copy()
    bnorm = np.linalg.norm(B, axis=0)
    if not np.any(bnorm > 0.0):
        return X, 0, 0.0
    target = tol * bnorm
    Z = precondition(R)
    D = Z.copy()
    rz = np.einsum("ij,ij->j", R, Z)
    rnorm = bnorm.copy()
    iterations = 0
    while iterations < max_iterations:
        AD = A.matmul(D)
        dad = np.einsum("ij,ij->j", D, AD)
        alpha = np.where(dad > 0.0, rz / np.where(dad > 0.0, dad, 1.0), 0.0)
        X += alpha * D
        R -= alpha * AD
        iterations += 1
        rnorm = np.linalg.norm(R, axis=0)
        if np.all(rnorm <= target):
            break
        Z = precondition(R)
        rz_new = np.einsum("ij,ij->j", R, Z)
        change = -alpha * np.einsum("ij,ij->j", Z, AD)  # z_new · (r_new − r_old)
        beta = np.where(rz > 0.0, np.maximum(change, 0.0) / np.where(rz > 0.0, rz, 1.0), 0.0)
        rz = rz_new
        D = Z + beta * D
    worst = float(np.max(np.where(bnorm > 0.0, rnorm / np.where(bnorm > 0.0, bnorm, 1.0), 0.0)))
    return X, iterations, worst


# ------------------------------------------------------------------------------------------- weights


@dataclass
class HarmonicWeights:
    """Result of `harmonic_weights`.

    weights (N, m): w_i(v) in [0, 1], rows summing to 1 (to the solver's tolerance) where solved,
    0 elsewhere; solved (N,): the vertex lies in a connected part holding a constrained vertex;
    owner (N,): the probe whose constrained set holds the vertex, −1 if free;
    loose_parts / loose_vertices: parts without a probe, and their vertices (not solved);
    unanchored: probes that own no vertex (their nearest vertex went to a nearer probe);
    iterations: conjugate-gradient iterations (summed over column batches); residual: the worst
    relative residual reached.
    """

    weights: FloatArray
    solved: NDArray[np.bool_]
    owner: IndexArray
    loose_parts: int
    loose_vertices: int
    unanchored: list[int]
    iterations: int
    residual: float


def harmonic_weights(points: ArrayLike, triangles: ArrayLike, centers: ArrayLike, *,
                     tol: float = TOLERANCE, max_iterations: int = MAX_ITERATIONS,
                     ratio: float = CORE_RATIO) -> HarmonicWeights:
    """Harmonic weights (module docstring) of probes at `centers` (m, 3) on the mesh of `points`
    (N, 3) and `triangles` (T, 3) (vertex indices; any triangulation of the faces)."""
    P = np.asarray(points, dtype=np.float64)
    C = np.asarray(centers, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {P.shape}")
    if C.ndim != 2 or C.shape[1] != 3 or C.shape[0] < 1:
        raise ValueError(f"centers must have shape (m, 3) with m ≥ 1, got {C.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(C))):
        raise ValueError("points or probe positions contain non-finite coordinates")
    n, m = P.shape[0], C.shape[0]
    edges, lam = cotangent_edges(P, triangles)
    part = connected_components(n, edges)
    owner = constraint_sets(P, edges, C, ratio)
    fixed = owner >= 0
    solved = np.isin(part, part[fixed])
    W = np.zeros((n, m))
    W[np.flatnonzero(fixed), owner[fixed]] = 1.0
    free = solved & ~fixed
    iterations, residual = 0, 0.0
    if free.any():
        nf = int(free.sum())
        index = np.full(n, -1, dtype=np.int64)
        index[free] = np.arange(nf)
        u, v = edges[:, 0], edges[:, 1]
        diag = np.bincount(u, lam, n) + np.bincount(v, lam, n)
        both = free[u] & free[v]
        A = Csr.from_coo(np.concatenate([index[u[both]], index[v[both]], np.arange(nf)]),
                         np.concatenate([index[v[both]], index[u[both]], np.arange(nf)]),
                         np.concatenate([-lam[both], -lam[both], diag[free]]), (nf, nf))
        # b_i(v) = Σ λ_uv over the neighbours u of v in C_i (the boundary values are one-hot)
        uv, vu = free[u] & fixed[v], free[v] & fixed[u]
        B = np.zeros((nf, m))
        rows = np.concatenate([index[u[uv]], index[v[vu]]])
        np.add.at(B, (rows, np.concatenate([owner[v[uv]], owner[u[vu]]])), np.concatenate([lam[uv], lam[vu]]))
        mg = Multigrid.build(A)
        X = np.zeros((nf, m))
        for lo in range(0, m, COLUMN_BATCH):
            hi = min(lo + COLUMN_BATCH, m)
            X[:, lo:hi], its, res = conjugate_gradient(A, B[:, lo:hi], mg.apply, tol, max_iterations)
            iterations += its
            residual = max(residual, res)
        W[free] = np.clip(X, 0.0, 1.0)  # the maximum principle holds up to the solver's tolerance
    loose = np.unique(part[~solved])
    unanchored = [i for i in range(m) if not np.any(owner == i)]
    return HarmonicWeights(W, solved, owner, int(loose.size), int((~solved).sum()), unanchored,
                           iterations, residual)
