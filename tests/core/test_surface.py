"""Surface (harmonic) probe weights, core/surface.py: the cotangent Laplacian, connected parts,
probe cores, the multigrid-preconditioned CG solve, against independent references (a per-triangle
finite-element stiffness matrix, scipy's connected components and its direct sparse solver)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spl

from affine_deformers.core import surface as sf
from affine_deformers.core import weights as wt

# ------------------------------------------------------------------------------------------- meshes


def grid(nx: int, ny: int, size=(1.0, 1.0), jitter: float = 0.0, seed: int = 0, offset=(0.0, 0.0, 0.0)):
    """A triangulated nx × ny vertex grid in the z = 0 plane (diagonals alternating), optionally
    jittered in-plane by `jitter` cell sizes."""
    x, y = np.meshgrid(np.linspace(0, size[0], nx), np.linspace(0, size[1], ny), indexing="ij")
    P = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    if jitter:
        h = min(size[0] / (nx - 1), size[1] / (ny - 1))
        inner = ((x > 0) & (x < size[0]) & (y > 0) & (y < size[1])).ravel()
        P[inner, :2] += np.random.default_rng(seed).uniform(-jitter, jitter, (inner.sum(), 2)) * h
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    flip = ((np.arange(nx - 1)[:, None] + np.arange(ny - 1)[None, :]) % 2).astype(bool)
    t1 = np.where(flip[..., None], np.stack([a, b, d], -1), np.stack([a, b, c], -1)).reshape(-1, 3)
    t2 = np.where(flip[..., None], np.stack([b, c, d], -1), np.stack([a, c, d], -1)).reshape(-1, 3)
    return P + np.asarray(offset), np.concatenate([t1, t2])


def uv_sphere(segments: int, rings: int):
    """A closed UV sphere (quads split into triangles, fans at the poles: many obtuse triangles)."""
    theta = np.pi * np.arange(1, rings) / rings
    phi = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                     np.broadcast_to(np.cos(theta)[:, None], (rings - 1, segments))], -1).reshape(-1, 3)
    P = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]])
    s, j = segments, np.arange(segments)
    jn = (j + 1) % s
    start = 1 + s * np.arange(rings - 2)[:, None]
    a, b, c, d = start + j, start + s + j, start + s + jn, start + jn
    last, bottom = 1 + s * (rings - 2), len(P) - 1
    T = np.concatenate([np.stack([np.zeros(s, int), 1 + j, 1 + jn], 1),
                        np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3),
                        np.stack([np.full(s, bottom), last + jn, last + j], 1)])
    return P, T


def fibonacci_sites(m: int) -> np.ndarray:
    k = np.arange(m) + 0.5
    z = 1 - 2 * k / m
    angle = np.pi * (3 - np.sqrt(5)) * k
    return np.stack([np.sqrt(1 - z * z) * np.cos(angle), np.sqrt(1 - z * z) * np.sin(angle), z], axis=1)


def stiffness_reference(P: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The P1 finite-element stiffness matrix K_uv = Σ_t area_t ∇φ_u·∇φ_v, assembled triangle by
    triangle from barycentric gradients (an independent route to the cotangent Laplacian)."""
    K = np.zeros((len(P), len(P)))
    for tri in T:
        x = P[tri]
        e = np.array([x[2] - x[1], x[0] - x[2], x[1] - x[0]])  # edge opposite each corner
        normal = np.cross(x[1] - x[0], x[2] - x[0])
        area2 = np.linalg.norm(normal)
        n = normal / area2
        grads = np.cross(n, e) / area2  # ∇φ_k = n × e_k / (2 area)
        K[np.ix_(tri, tri)] += 0.5 * area2 * grads @ grads.T
    return K


def laplacian(n: int, edges: np.ndarray, lam: np.ndarray) -> sp.csr_matrix:
    W = sp.coo_matrix((np.r_[lam, lam], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                      shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W).tocsr()


def direct_solve(P, T, owner, m):
    """Harmonic weights with the given cores by scipy's direct solver (the clamped Laplacian)."""
    edges, lam = sf.cotangent_edges(P, T)
    L = laplacian(len(P), edges, lam)
    fixed = owner >= 0
    free = ~fixed
    Xc = np.zeros((fixed.sum(), m))
    Xc[np.arange(fixed.sum()), owner[fixed]] = 1.0
    W = np.zeros((len(P), m))
    W[fixed] = Xc
    if free.any():
        W[free] = np.asarray(spl.spsolve(L[free][:, free].tocsc(), -(L[free][:, fixed] @ Xc))).reshape(-1, m)
    return W


# -------------------------------------------------------------------------------------------- tests


def test_cotangent_weights_are_the_finite_element_stiffness_matrix() -> None:
    P, T = grid(9, 8, size=(1.0, 0.8), jitter=0.2, seed=3)
    P[:, 2] = 0.3 * np.sin(3 * P[:, 0]) * P[:, 1]  # not flat
    edges, lam = sf.cotangent_edges(P, T)
    K = stiffness_reference(P, T)
    off = -K[edges[:, 0], edges[:, 1]]
    unclamped = (off > sf.EDGE_WEIGHT_FLOOR) & (off < sf.EDGE_WEIGHT_CAP)
    assert unclamped.mean() > 0.8
    np.testing.assert_allclose(lam[unclamped], off[unclamped], rtol=1e-12, atol=1e-14)
    clipped = np.clip(off[~unclamped], sf.EDGE_WEIGHT_FLOOR, sf.EDGE_WEIGHT_CAP)
    np.testing.assert_allclose(lam[~unclamped], clipped)
    # with the clamped entries put back, the Laplacian is the stiffness matrix
    restored = laplacian(len(P), edges, np.where(unclamped, lam, off)).toarray()
    np.testing.assert_allclose(restored, K, atol=1e-12)
    # every mesh edge exactly once, u < v
    assert np.all(edges[:, 0] < edges[:, 1]) and len(np.unique(edges, axis=0)) == len(edges)


def test_negative_cotangent_weights_are_clamped_and_keep_the_maximum_principle() -> None:
    """A free vertex V between a vertex held at 1 across a non-Delaunay edge (opposite angles near
    180°, λ < 0) and vertices held at 0: the true cotangent Laplacian gives V a negative weight (the
    maximum principle fails), the clamped one a small positive weight."""
    P = np.array([[0, 0, 0], [2, 0, 0], [1, 0.2, 0], [1, -0.2, 0], [-2, 0, 0], [-1, 1, 0], [-1, -1, 0.0]])
    V, A, C1, C2, B, D1, D2 = range(7)
    T = np.array([[V, A, C1], [V, C1, D1], [V, D1, B], [V, B, D2], [V, D2, C2], [V, C2, A]])
    K = stiffness_reference(P, T)
    assert K[V, A] > 0.0, "edge VA has a negative cotangent weight"
    value = np.array([0.0, 1.0, 0, 0, 0, 0, 0])  # A held at 1, every other neighbour of V at 0
    unclamped = -(K[V] @ value - K[V, V] * value[V]) / K[V, V]
    assert unclamped < -0.1
    edges, lam = sf.cotangent_edges(P, T)
    at_v = (edges == V).any(axis=1)
    other = edges[at_v].sum(axis=1) - V
    clamped = (lam[at_v] * value[other]).sum() / lam[at_v].sum()
    assert 0.0 < clamped < 0.01
    # a whole mesh with many non-Delaunay edges: every weight stays in [0, 1], rows sum to 1
    P, T = uv_sphere(48, 24)
    P = P * np.array([1.0, 1.0, 3.0])  # stretched: thin quads, obtuse triangles
    edges, lam = sf.cotangent_edges(P, T)
    raw = -stiffness_reference(P, T)[edges[:, 0], edges[:, 1]]
    assert (raw < 0).sum() > 50
    np.testing.assert_allclose(lam, np.clip(raw, sf.EDGE_WEIGHT_FLOOR, sf.EDGE_WEIGHT_CAP), rtol=1e-10,
                               atol=1e-13)
    result = sf.harmonic_weights(P, T, np.array([[0, 0, 3.0], [0, 0, -3.0], [1.0, 0, 0]]))
    assert result.weights.min() >= 0.0 and result.weights.max() <= 1.0
    np.testing.assert_allclose(result.weights.sum(axis=1), 1.0, atol=1e-6)


def test_connected_components_match_scipy() -> None:
    rng = np.random.default_rng(7)
    for n, e in ((1, 0), (50, 0), (200, 150), (1000, 900), (3000, 6000)):
        edges = rng.integers(0, n, (e, 2))
        label = sf.connected_components(n, edges)
        count, ref = csgraph.connected_components(
            sp.coo_matrix((np.ones(e), (edges[:, 0], edges[:, 1])), shape=(n, n)), directed=False)
        assert len(np.unique(label)) == count
        # the same partition: label ↔ ref is a bijection
        pairs = np.unique(np.stack([label, ref], 1), axis=0)
        assert len(pairs) == count
        # labels are the lowest vertex of each part
        assert np.all(label[label] == label) and np.all(label <= np.arange(n))


def test_csr_operations_match_scipy() -> None:
    rng = np.random.default_rng(11)
    rows, cols = rng.integers(0, 40, 300), rng.integers(0, 30, 300)
    vals = rng.normal(size=300)
    A = sf.Csr.from_coo(rows, cols, vals, (45, 30))  # rows 40..44 empty
    ref = sp.coo_matrix((vals, (rows, cols)), shape=(45, 30)).toarray()
    np.testing.assert_allclose(A.to_dense(), ref, atol=1e-14)
    X = rng.normal(size=(30, 5))
    np.testing.assert_allclose(A.matmul(X), ref @ X, atol=1e-13)
    np.testing.assert_allclose(A.transpose().to_dense(), ref.T, atol=1e-14)
    B = sf.Csr.from_coo(rng.integers(0, 30, 200), rng.integers(0, 20, 200), rng.normal(size=200), (30, 20))
    np.testing.assert_allclose(A.product(B).to_dense(), ref @ B.to_dense(), atol=1e-12)
    single = A.astype(np.float32).matmul(X.astype(np.float32))
    assert single.dtype == np.float32
    np.testing.assert_allclose(single, ref @ X, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("case", ["grid", "sphere", "two_parts"])
def test_harmonic_weights_match_a_direct_solve(case: str) -> None:
    """The multigrid-preconditioned CG solution equals scipy's spsolve on the same Laplacian and
    cores to 1e-6 (default tolerance 1e-7 in the relative residual), is a partition of unity in
    [0, 1] where solved, and a part without a probe is reported and left unsolved."""
    if case == "grid":
        P, T = grid(60, 40, size=(3.0, 2.0), jitter=0.25)
        centers = np.array([[0.2, 0.2, 0.1], [2.8, 1.8, 0.0], [1.5, 1.0, -0.3], [2.9, 0.1, 0.0]])
    elif case == "sphere":
        P, T = uv_sphere(96, 48)
        centers = fibonacci_sites(8) * 1.05
    else:  # a probed grid and, beside it, a grid no probe is near
        P1, T1 = grid(40, 40)
        P2, T2 = grid(15, 15, offset=(0.0, 0.0, 0.5))
        P, T = np.concatenate([P1, P2]), np.concatenate([T1, T2 + len(P1)])
        centers = np.array([[0.0, 0.0, -0.2], [1.0, 1.0, -0.2], [1.0, 0.0, -0.2]])
    m = len(centers)
    result = sf.harmonic_weights(P, T, centers)
    assert result.residual <= sf.TOLERANCE and 0 < result.iterations < 40
    if case == "two_parts":
        assert result.loose_parts == 1 and result.loose_vertices == 225
        assert not result.solved[1600:].any() and result.solved[:1600].all()
        assert np.all(result.weights[1600:] == 0.0)
    else:
        assert result.loose_parts == 0 and result.solved.all()
    assert result.unanchored == []
    assert all(np.any(result.owner == i) for i in range(m))
    solved_mesh = (P1, T1) if case == "two_parts" else (P, T)
    ref = direct_solve(*solved_mesh, result.owner[result.solved], m)
    got = result.weights[result.solved]
    assert np.abs(got - ref).max() < 1e-6
    assert got.min() >= 0.0 and got.max() <= 1.0
    np.testing.assert_allclose(got.sum(axis=1), 1.0, atol=1e-6)


def test_cores_are_apart_and_do_not_jump_a_gap() -> None:
    """Two parallel strips joined at one end (a U): a probe at the tip of one strip takes none of the
    other strip although it is near in space; cores of different probes never share an edge."""
    P, T = grid(41, 9, size=(4.0, 0.8))
    keep = ~((P[:, 0] > 0.6) & (P[:, 1] > 0.25) & (P[:, 1] < 0.55))  # cut a slot: two prongs
    index = np.cumsum(keep) - 1
    T = index[T[keep[T].all(axis=1)]]
    P = P[keep]
    edges, _ = sf.cotangent_edges(P, T)
    assert len(np.unique(sf.connected_components(len(P), edges))) == 1, "one connected U"
    centers = np.array([[4.0, 0.1, 0.0], [4.0, 0.7, 0.0], [0.0, 0.4, 0.0]])
    owner = sf.constraint_sets(P, edges, centers)
    lower, upper = P[:, 1] < 0.3, P[:, 1] > 0.5
    assert np.any(owner == 0) and np.all(lower[owner == 0]), "probe 0's core stays on its prong"
    assert np.any(owner == 1) and np.all(upper[owner == 1])
    u, v = owner[edges[:, 0]], owner[edges[:, 1]]
    assert not np.any((u >= 0) & (v >= 0) & (u != v)), "a free band separates every two cores"
    # a coarse mesh, probes two edges apart: the cores still never share an edge, each keeps a vertex
    Pc, Tc = grid(4, 4)
    ec, _ = sf.cotangent_edges(Pc, Tc)
    oc = sf.constraint_sets(Pc, ec, Pc[[0, 2, 15]] + [0.0, 0.0, 0.01])
    assert all(np.any(oc == i) for i in range(3))
    u, v = oc[ec[:, 0]], oc[ec[:, 1]]
    assert not np.any((u >= 0) & (v >= 0) & (u != v))
    result = sf.harmonic_weights(P, T, centers)
    far_tip = lower & (P[:, 0] > 3.0)
    assert result.weights[far_tip, 1].max() < 0.02, "the other prong's probe reaches round the U only"


def test_cores_keep_their_size_under_refinement_while_point_constraints_flatten() -> None:
    """Why cores and not single vertices: a point has no capacity in 2-D, so with one constrained
    vertex per probe the weight at a fixed point between two probes drifts towards ½ as the mesh is
    refined (measured at x = 1.6 between probes at 0.5 and 3.5: 0.585, 0.578, 0.572 for 861, 3321,
    13041 vertices) and is flat at every resolution; with the cores it stays local (0.871, 0.875,
    0.882) and moves by less than 0.01 per refinement."""
    centers = np.array([[0.5, 1.0, 0.0], [3.5, 1.0, 0.0]])
    cores, points = [], []
    for n in (21, 41, 81):
        P, T = grid(2 * n - 1, n, size=(4.0, 2.0))
        query = np.argmin(np.linalg.norm(P - [1.6, 1.0, 0.0], axis=1))
        result = sf.harmonic_weights(P, T, centers)
        assert result.owner[query] == -1, "the query point is free, between the cores"
        cores.append(result.weights[query, 0])
        owner = np.full(len(P), -1)
        owner[np.argmin(np.linalg.norm(P[:, None] - centers[None], axis=2), axis=0)] = [0, 1]
        points.append(direct_solve(P, T, owner, 2)[query, 0])
    assert points[0] > points[1] > points[2] > 0.5, points  # drifting towards ½
    assert np.abs(np.diff(cores)).max() < 0.01, cores
    assert min(c - p for c, p in zip(cores, points, strict=True)) > 0.25, (cores, points)


def test_multigrid_iterations_barely_grow_with_the_mesh() -> None:
    """Measured on UV spheres with 8 probes: the CG iteration count at the default tolerance stays
    small and nearly constant from 2k to 33k vertices (Jacobi-preconditioned CG needs ~20× more)."""
    its = {}
    for inner in (32, 64, 128):
        P, T = uv_sphere(2 * inner, inner + 1)
        its[len(P)] = sf.harmonic_weights(P, T, fibonacci_sites(8)).iterations
    counts = list(its.values())
    assert max(counts) <= 25 and counts[-1] - counts[0] <= 8, its


def test_multigrid_cycle_is_a_symmetric_positive_definite_preconditioner() -> None:
    P, T = uv_sphere(64, 33)
    edges, lam = sf.cotangent_edges(P, T)
    L = laplacian(len(P), edges, lam)
    free = np.ones(len(P), bool)
    free[:40] = False
    A = L[free][:, free].tocoo()
    mg = sf.Multigrid.build(sf.Csr.from_coo(A.row, A.col, A.data, A.shape))
    assert len(mg.levels) >= 2
    n = A.shape[0]
    M = mg.apply(np.eye(n))
    assert np.abs(M - M.T).max() < 1e-5 * np.abs(M).max(), "symmetric (to float32 rounding)"
    assert np.linalg.eigvalsh(0.5 * (M + M.T)).min() > 0.0
    # a good preconditioner: the spectrum of M A is bounded away from 0 and not far above 1
    eig = np.sort(np.real(np.linalg.eigvals(M @ A.toarray())))
    assert eig[0] > 0.1 and eig[-1] < 2.0, (eig[0], eig[-1])


def test_loose_vertices_never_anchor_a_probe_and_results_are_reproducible() -> None:
    P, T = grid(30, 30)
    stray = np.array([[0.02, 0.02, 0.05]])  # a loose vertex (no face) right next to the probe
    P = np.concatenate([P, stray])
    centers = np.array([[0.0, 0.0, 0.05], [1.0, 1.0, 0.0]])
    a = sf.harmonic_weights(P, T, centers)
    assert a.owner[-1] == -1 and not a.solved[-1] and a.loose_parts == 1 and a.loose_vertices == 1
    b = sf.harmonic_weights(P, T, centers)
    assert np.array_equal(a.weights, b.weights) and np.array_equal(a.owner, b.owner)


def test_surface_mode_of_probe_weights() -> None:
    """weights.probe_weights 'SURFACE': harmonic rows sharpened h^p / Σ h^p then truncated like
    distance weights; rows outside the solved parts get the inverse-distance weights."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(-1, 1, (50, 3))
    centers = rng.uniform(-1, 1, (6, 3))
    H = rng.dirichlet(np.ones(6), size=50)
    solved = np.arange(50) < 40
    idx, val = wt.probe_weights(pts, centers, mode="SURFACE", dense=H, solved=solved, exponent=2.0, k=4)
    sharp = H**2 / (H**2).sum(axis=1, keepdims=True)
    kept_idx, kept, pooled = wt.truncate(sharp[:40], 4, total=sharp[:40].sum(axis=1), floor=wt.POOL_FLOOR,
                                         with_pooled=True)
    assert np.array_equal(idx[:40, :4], kept_idx)
    np.testing.assert_allclose(val[:40, :4], kept, rtol=1e-12)
    np.testing.assert_allclose(val[:40, 4], pooled, rtol=1e-12)  # column 4: the pooled control
    assert np.all(idx[:, 4] == 6)
    dist_idx, dist_val = wt.probe_weights(pts[40:], centers, mode="INVERSE_DISTANCE", k=4)
    assert np.array_equal(idx[40:, :dist_idx.shape[1]], dist_idx)
    assert np.array_equal(val[40:, :dist_val.shape[1]], dist_val)
    # exponent 1: the harmonic weights themselves (they are a partition of unity already)
    _, plain = wt.probe_weights(pts, centers, mode="SURFACE", dense=H, solved=solved, exponent=1.0, k=6,
                                normalize="NONE")
    np.testing.assert_allclose(np.sort(plain[:40], axis=1), np.sort(H[:40], axis=1), rtol=1e-12)
    with pytest.raises(ValueError, match="harmonic weights"):
        wt.probe_weights(pts, centers, mode="SURFACE")
    with pytest.raises(ValueError, match="shape"):
        wt.probe_weights(pts, centers, mode="SURFACE", dense=H[:10], solved=solved)
    with pytest.raises(ValueError, match="exponent"):
        wt.probe_weights(pts, centers, mode="SURFACE", dense=H, solved=solved, exponent=0.0)
