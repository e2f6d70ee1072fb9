"""core.cage.harmonic: harmonic cage weights on a grid and the pivoted node blend, against
independent references (an analytic inside test, the series solution of a cube's face harmonic
measure, a sparse direct solve of the same system, the blend of explicitly conjugated matrices)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg

from affine_deformers.core.aff3 import matrices_from_params, params_from_matrices
from affine_deformers.core.cage import (
    CageTopology,
    check_cage,
    face_motions,
    nearest_faces,
    polygon_distance_sq,
)
from affine_deformers.core.cage import harmonic as ch
from affine_deformers.core.deform import deform_points_params


def box_cage(counts, lo, hi) -> tuple[np.ndarray, CageTopology]:  # type: ignore[no-untyped-def]
    """Closed axis-aligned box [lo, hi], counts (3,) quads along each axis, normals out."""
    counts, lo, hi = np.asarray(counts), np.asarray(lo, float), np.asarray(hi, float)
    verts: dict[tuple, int] = {}
    faces = []
    for axis, side in itertools.product(range(3), (0, 1)):
        u, v = [a for a in range(3) if a != axis]
        for i, j in itertools.product(range(counts[u]), range(counts[v])):
            quad = []
            for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.empty(3)
                p[axis] = hi[axis] if side else lo[axis]
                p[u] = lo[u] + (hi[u] - lo[u]) * (i + di) / counts[u]
                p[v] = lo[v] + (hi[v] - lo[v]) * (j + dj) / counts[v]
                quad.append(verts.setdefault(tuple(np.round(p, 12)), len(verts)))
            outward = (np.cross(np.eye(3)[u], np.eye(3)[v])[axis] > 0) == bool(side)
            faces.append(quad if outward else quad[::-1])
    return np.array(list(verts)), CageTopology.from_polygons(faces)


ARM, REACH, HEIGHT = 0.6, 1.2, 3.4


def plus_cage() -> tuple[np.ndarray, CageTopology]:
    """The non-convex 'plus' prism of tests/blender/cage_field.py (6 segments, 82 quads)."""
    a, b = ARM, REACH
    outline = np.array([(a, -a), (b, -a), (b, a), (a, a), (a, b), (-a, b), (-a, a), (-b, a), (-b, -a),
                        (-a, -a), (-a, -b), (a, -b)])
    n, segments = len(outline), 6
    z = np.linspace(-HEIGHT / 2, HEIGHT / 2, segments + 1)
    points = np.array([(x, y, zz) for zz in z for x, y in outline])
    faces = [[s * n + j, s * n + (j + 1) % n, (s + 1) * n + (j + 1) % n, (s + 1) * n + j]
             for s in range(segments) for j in range(n)]
    squares = [[0, 3, 6, 9], [0, 1, 2, 3], [3, 4, 5, 6], [6, 7, 8, 9], [9, 10, 11, 0]]
    faces += [[segments * n + i for i in q] for q in squares] + [q[::-1] for q in squares]
    return points, CageTopology.from_polygons(faces)


def inside_plus(p: np.ndarray) -> np.ndarray:
    x, y, z = np.abs(p).T
    return (z < HEIGHT / 2) & (((x < ARM) & (y < REACH)) | ((x < REACH) & (y < ARM)))


def random_affine(rng: np.random.Generator, n: int, size: float = 0.3) -> np.ndarray:
    A = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    A[:, :3, :3] += size * rng.normal(size=(n, 3, 3))
    A[:, :3, 3] = rng.normal(size=(n, 3))
    assert np.all(np.linalg.det(A[:, :3, :3]) > 0.0)
    return A


# ---------------------------------------------------------------------------------------------- grid


def test_inside_nodes_match_the_analytic_inside_of_a_non_convex_cage() -> None:
    cage, topo = plus_cage()
    assert check_cage(cage, topo).ok
    grid = ch.cage_grid(cage, nodes=20000)
    fan, fan_face = topo.fan_triangles()
    inside = ch.inside_nodes(grid, ch.axis_hits(grid, cage, fan, fan_face, 2)[0])
    points = grid.points(np.arange(grid.size))
    expected = inside_plus(points)
    # nodes on the cage surface may go either way
    on_surface = np.sqrt(polygon_distance_sq(points, cage, topo).min(axis=1)) < 1e-9
    got = inside.ravel()
    assert expected.sum() > 1000
    assert np.array_equal(got[~on_surface], expected[~on_surface])


def test_trilinear_weights_reproduce_linear_functions_and_clamp_outside() -> None:
    cage, _ = box_cage((2, 2, 2), (-1, -1, -1), (1, 2, 1))
    grid = ch.cage_grid(cage, nodes=500)
    rng = np.random.default_rng(1)
    inside = rng.uniform(-1, 1, size=(200, 3)) * [1, 1.5, 1] + [0, 0.5, 0]
    flat, lam = ch.trilinear(grid, inside)
    assert np.all(lam >= 0.0) and np.allclose(lam.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.einsum("nk,nki->ni", lam, grid.points(flat)), inside, atol=1e-12)
    far = np.array([[50.0, 0.2, 0.1]])
    box_hi = grid.origin + grid.spacing * (np.array(grid.shape) - 1)
    clamped = np.array([[box_hi[0], 0.2, 0.1]])
    assert np.array_equal(ch.trilinear(grid, far)[1], ch.trilinear(grid, clamped)[1])


def test_nearest_faces_list_exactly_the_faces_within_width_of_the_nearest() -> None:
    cage, topo = plus_cage()
    rng = np.random.default_rng(2)
    points = rng.uniform(-1.6, 1.6, size=(300, 3)) * [1, 1, 1.4]
    width = 0.35
    point, face, dist = nearest_faces(points, cage, topo, width)
    d = np.sqrt(polygon_distance_sq(points, cage, topo))
    expected = d <= d.min(axis=1, keepdims=True) + width
    got = np.zeros_like(expected)
    got[point, face] = True
    margin = np.abs(d - (d.min(axis=1, keepdims=True) + width)) < 1e-9  # on the boundary of the test
    assert np.array_equal(got[~margin], expected[~margin])
    np.testing.assert_allclose(dist, d[point, face], rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------------------------------------- solve


def cube_face_series(p: np.ndarray, terms: int = 41) -> np.ndarray:
    """Harmonic function in the unit cube [0, 1]³ equal to 1 on z = 1 and 0 on the other faces."""
    x, y, z = p.T
    u = np.zeros(len(p))
    for m, n in itertools.product(range(1, terms + 1, 2), repeat=2):
        k = np.pi * np.hypot(m, n)
        # sinh(k z)/sinh(k) without overflow
        ratio = np.exp(k * (z - 1.0)) * (1.0 - np.exp(-2.0 * k * z)) / (1.0 - np.exp(-2.0 * k))
        u += 16.0 / (np.pi**2 * m * n) * np.sin(m * np.pi * x) * np.sin(n * np.pi * y) * ratio
    return u


def test_one_hot_face_weights_converge_to_the_harmonic_measure_of_a_cube_face(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With hard (one-hot) boundary data the discrete field is the harmonic measure of the face: the
    cut-edge discretisation is first order, so refining the grid brings it to the series solution."""
    monkeypatch.setattr(ch, "FACE_BLUR", 0.0)
    monkeypatch.setattr(ch, "BOUNDARY_WIDTH", 1e-6)
    monkeypatch.setattr(ch, "FINE_TOL", 1e-6)
    cage, topo = box_cage((2, 2, 2), (0, 0, 0), (1, 1, 1))
    corners = cage[topo.loop_vertex_indices].reshape(-1, 4, 3)
    top = np.flatnonzero(np.isclose(corners[:, :, 2], 1.0).all(axis=1))
    assert top.size == 4
    rng = np.random.default_rng(3)
    samples = rng.uniform(0.15, 0.85, size=(400, 3))
    exact = cube_face_series(samples)
    errors = []
    for nodes in (2000, 16000):
        hw = ch.harmonic_weights(samples, cage, topo, nodes=nodes)
        W = hw.node_weights.astype(np.float64)
        got = np.einsum("nk,nk->n", hw.values, W[hw.indices][:, :, top].sum(axis=2))
        errors.append(np.abs(got - exact).max())
    assert errors[1] < 0.006 and errors[1] < 0.6 * errors[0], errors


def test_every_cut_gets_the_boundary_data_of_its_point_from_both_ends() -> None:
    """A level's right-hand side entries are, row by row of the cut edges (each listed from both
    ends), the soft nearest-face data of the cut's point over θ: the same as taking `boundary_data`
    at every row's point, bit for bit and in the same order (the level takes it once per cut)."""
    for cage, topo in (plus_cage(), box_cage((3, 2, 4), np.zeros(3), np.array([1.0, 0.7, 1.3]))):
        grid = ch.cage_grid(cage, nodes=2000)
        level = ch._level(grid, cage, topo)
        fan, fan_face = topo.fan_triangles()
        hits = [ch.axis_hits(grid, cage, fan, fan_face, axis)[0] for axis in range(3)]
        inside = ch.inside_nodes(grid, hits[2])
        crossings = [ch._crossings(grid, inside, hits[axis], axis) for axis in range(3)]
        node = np.concatenate([c.node for c in crossings])
        theta = np.concatenate([c.theta for c in crossings])
        points = np.concatenate([c.point for c in crossings])
        row, face, g = ch.boundary_data(points, cage, topo, grid.spacing)
        assert row.size > 100 and np.unique(face).size > 10
        np.testing.assert_array_equal(level.rhs_node, node[row])
        np.testing.assert_array_equal(level.rhs_face, face)
        np.testing.assert_array_equal(level.rhs_value, g / theta[row])


def test_cascade_converges_to_the_direct_solution_of_its_system(monkeypatch: pytest.MonkeyPatch) -> None:
    """The cascadic CG on a level equals scipy's sparse direct solve of the same equations, assembled
    here from their definition: deg_i w_i − Σ_uncut w_j = Σ_cut g/θ (deg counts cut edges as 1/θ)."""
    cage, topo = plus_cage()
    grid = ch.cage_grid(cage, nodes=3000)
    level = ch._level(grid, cage, topo)
    N = grid.size
    rows, cols = [], []
    for axis in range(3):
        stride = int(np.prod(grid.shape[axis + 1:]))
        ijk = np.stack(np.unravel_index(np.arange(N), grid.shape), axis=1)
        has = ijk[:, axis] < grid.shape[axis] - 1
        a = np.flatnonzero(has)
        rows += [a, a + stride]
        cols += [a + stride, a]
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    cut = set()
    for node, across in level.cuts:
        cut.update(zip(node.tolist(), across.tolist(), strict=True))
    keep = np.array([(r, c) not in cut for r, c in zip(rows.tolist(), cols.tolist(), strict=True)])
    A = scipy.sparse.diags(level.diagonal.ravel().astype(np.float64)) - scipy.sparse.coo_matrix(
        (np.ones(keep.sum()), (rows[keep], cols[keep])), shape=(N, N))
    faces = np.array([0, 7, 40, 81])
    b = np.zeros((N, faces.size))
    for k, f in enumerate(faces):
        sel = level.rhs_face == f
        np.add.at(b[:, k], level.rhs_node[sel], level.rhs_value[sel])
    direct = scipy.sparse.linalg.spsolve(A.tocsc(), b)
    monkeypatch.setattr(ch, "FINE_TOL", 1e-7)
    monkeypatch.setattr(ch, "COARSE_TOL", 1e-7)
    levels = ch._levels(grid, cage, topo, ch.LEVELS)
    got, _ = ch._solve_batch(levels, faces, topo.n_faces, np.arange(N))
    assert np.abs(got - direct).max() < 1e-5 and np.abs(direct).max() > 0.1


def test_default_weights_are_a_partition_of_unity_and_do_not_depend_on_threads() -> None:
    cage, topo = plus_cage()
    rng = np.random.default_rng(4)
    points = rng.uniform(-1.3, 1.3, size=(3000, 3)) * [1, 1, 1.4]
    one = ch.harmonic_weights(points, cage, topo, threads=1)
    two = ch.harmonic_weights(points, cage, topo, threads=2)
    assert np.array_equal(one.node_weights, two.node_weights) and np.array_equal(one.indices, two.indices)
    W = one.node_weights.astype(np.float64)
    assert W.min() >= 0.0 and np.allclose(W.sum(axis=1), 1.0, atol=1e-6)
    dense = np.einsum("nk,nkf->nf", one.values, W[one.indices])
    assert np.allclose(dense.sum(axis=1), 1.0, atol=1e-6)


def test_a_cage_thinner_than_the_grid_still_weights_every_node() -> None:
    """A flat slab a fraction of a cell thick: no grid node is inside; every used node still gets
    weights (the nearest faces), summing to 1."""
    cage, topo = box_cage((4, 4, 1), (-1, -1, -0.001), (1, 1, 0.001))
    points = np.random.default_rng(5).uniform(-0.9, 0.9, size=(200, 3)) * [1, 1, 0.001]
    hw = ch.harmonic_weights(points, cage, topo, nodes=500)
    assert np.allclose(hw.node_weights.astype(np.float64).sum(axis=1), 1.0, atol=1e-6)


# ---------------------------------------------------------------------------------------------- blend


def conjugated_blend(x: np.ndarray, W: np.ndarray, A: np.ndarray) -> np.ndarray:
    """T(x) φ(Σ_f W_f ψ(T(−x) A_f T(x))) T(−x): the blend about x, built from matrices."""
    T, Ti = np.eye(4), np.eye(4)
    T[:3, 3], Ti[:3, 3] = x, -x
    local = params_from_matrices(Ti @ A @ T)
    return T @ matrices_from_params(W @ local) @ Ti


def test_node_params_are_the_blend_about_the_node() -> None:
    rng = np.random.default_rng(6)
    F, G = 7, 5
    A = random_affine(rng, F)
    P = params_from_matrices(A)
    W = rng.uniform(0.0, 1.0, size=(G, F)) * (rng.uniform(size=(G, F)) > 0.3)
    W /= W.sum(axis=1, keepdims=True)
    x = rng.normal(scale=2.0, size=(G, 3))
    got = matrices_from_params(ch.node_params(x, W, P))
    for c in range(G):
        np.testing.assert_allclose(got[c], conjugated_blend(x[c], W[c], A), atol=1e-10)
    # the pivot matters: blended about the origin the result differs
    assert np.abs(matrices_from_params(W @ P) - got).max() > 1e-2


def test_common_motion_single_face_and_skipped_faces() -> None:
    rng = np.random.default_rng(7)
    F, G = 6, 9
    W = rng.uniform(0.0, 1.0, size=(G, F))
    W /= W.sum(axis=1, keepdims=True)
    x = rng.normal(size=(G, 3))
    G_motion = random_affine(rng, 1, size=0.4)[0]
    common = np.broadcast_to(params_from_matrices(G_motion), (F, 12))
    np.testing.assert_allclose(matrices_from_params(ch.node_params(x, W, common)),
                               np.broadcast_to(G_motion, (G, 4, 4)), atol=1e-12)
    P = params_from_matrices(random_affine(rng, F))
    one_hot = np.eye(F)[rng.integers(0, F, size=G)]
    np.testing.assert_allclose(ch.node_params(x, one_hot, P), P[one_hot.argmax(axis=1)], atol=1e-12)
    valid = np.ones(F, dtype=bool)
    valid[2] = False
    W_without = W.copy()
    W_without[:, 2] = 0.0
    np.testing.assert_allclose(ch.node_params(x, W, P, valid=valid),
                               ch.node_params(x, W_without / W_without.sum(axis=1, keepdims=True), P),
                               atol=1e-12)
    faces = np.array([0, 3])
    sparse = np.zeros_like(P)
    sparse[faces] = P[faces]
    np.testing.assert_allclose(ch.node_params(x, W, sparse, faces=faces), ch.node_params(x, W, sparse),
                               atol=1e-14)
    lin = ch.node_matrices_linear(W, matrices_from_params(P))
    np.testing.assert_allclose(lin, np.einsum("gf,fij->gij", W, matrices_from_params(P)), atol=1e-12)


def test_any_common_affine_motion_of_the_cage_is_exact_at_every_vertex() -> None:
    cage, topo = plus_cage()
    rng = np.random.default_rng(8)
    points = rng.uniform(-1.1, 1.1, size=(2000, 3)) * [1, 1, 1.4]
    hw = ch.harmonic_weights(points, cage, topo)
    W = hw.node_weights.astype(np.float64)
    W /= W.sum(axis=1, keepdims=True)
    M = np.array([[1.1, 0.45, 0.0], [0.0, 0.9, 0.3], [0.25, 0.0, 1.2]])
    t = np.array([0.3, -0.2, 0.4])
    motion = face_motions(cage, cage @ M.T + t, topo)
    got = deform_points_params(points, ch.node_params(hw.node_points, W, motion.params), hw.indices,
                               hw.values)
    assert np.abs(got - (points @ M.T + t)).max() < 1e-9


def test_a_rigidly_turned_half_of_a_long_cage_moves_rigidly_and_the_far_half_stays() -> None:
    cage, topo = box_cage((16, 2, 2), (-4, -0.5, -0.5), (4, 0.5, 0.5))
    xs = np.linspace(-3.8, 3.8, 77)
    points = np.stack(np.meshgrid(xs, [-0.3, 0.0, 0.3], [-0.3, 0.0, 0.3], indexing="ij"), -1).reshape(-1, 3)
    hw = ch.harmonic_weights(points, cage, topo)
    W = hw.node_weights.astype(np.float64)
    W /= W.sum(axis=1, keepdims=True)
    angle, axis = 0.9, np.array([0.2, 1.0, 0.4]) / np.linalg.norm([0.2, 1.0, 0.4])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    moved = cage.copy()
    half = cage[:, 0] > 0.25
    moved[half] = cage[half] @ R.T
    motion = face_motions(cage, moved, topo)
    got = deform_points_params(points, ch.node_params(hw.node_points, W, motion.params), hw.indices,
                               hw.values)
    inside = points[:, 0] > 2.4
    assert np.abs(got[inside] - points[inside] @ R.T).max() < 1e-3
    still = points[:, 0] < -2.4
    assert np.abs(got[still] - points[still]).max() < 1e-5
    near_moved = motion.params.any(axis=1)
    far_nodes = hw.node_points[:, 0] < -3.0
    assert not (W[far_nodes][:, near_moved] > 0.0).any(), "far nodes hold no moved face: bitwise at rest"


def test_outside_points_are_those_the_cage_does_not_hold():
    """A box cage, rotated: points clearly outside (beyond a grid cell of the surface) and clearly
    inside are classified exactly (the exact answer: the box's own coordinates); near the surface a
    point may count as inside."""
    from affine_deformers.core.cage.harmonic import outside_points
    from affine_deformers.core.cage.topology import CageTopology

    corners = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-2.0, 2.0) for z in (-0.5, 0.5)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    c, s = np.cos(0.4), np.sin(0.4)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(7)
    local = rng.uniform(-3.0, 3.0, size=(20000, 3))
    out = outside_points(local @ turn.T, corners @ turn.T, CageTopology.from_polygons(quads, 8))
    beyond = np.abs(local) / np.array([1.0, 2.0, 0.5])
    cell = 0.25  # more than the spacing of the classifying grid over this cage
    assert np.all(out[np.any(np.abs(local) > np.array([1.0, 2.0, 0.5]) + cell, axis=1)])
    assert not np.any(out[np.all(beyond < 1.0, axis=1)])
