"""Cage geometry (core/cage/): corner tetrahedra and face motions, distances, weights, validation."""

from __future__ import annotations

import itertools
import re

import numpy as np
import pytest

import affine_deformers.core.cage as cage_module
import affine_deformers.core.cage.motions as cage_motions
from affine_deformers.core.aff3 import matrices_from_params, so3_exp
from affine_deformers.core.cage import (
    STENCIL_MIN_BETA,
    CageTopology,
    affected_faces,
    apex_stencils,
    check_cage,
    face_motions,
    face_normals,
    point_triangle_distance_sq,
    polygon_distance_sq,
    validate_cage,
)
from affine_deformers.core.cage import cage_weights as _cage_weights
from affine_deformers.core.cage.distances import TOTAL_FACES
from affine_deformers.core.cage.pool import with_pool_nodes
from affine_deformers.core.deform import deform_points, deform_points_params
from affine_deformers.core.weights import POOL_FLOOR

CUBE_POINTS = np.array(list(itertools.product([0, 1], repeat=3)), dtype=float)[:, ::-1] - 0.5
# vertex i has (x, y, z) bits (i & 1, i >> 1 & 1, i >> 2 & 1): 0 (0,0,0) 1 (1,0,0) 2 (0,1,0) 3 (1,1,0) ...
CUBE_FACES = [
    [0, 2, 3, 1],  # bottom, −z
    [4, 5, 7, 6],  # top, +z
    [0, 1, 5, 4],  # front, −y
    [2, 6, 7, 3],  # back, +y
    [0, 4, 6, 2],  # left, −x
    [1, 3, 7, 5],  # right, +x
]
TOP, BOTTOM = 1, 0


def cube() -> tuple[np.ndarray, CageTopology]:
    return CUBE_POINTS.copy(), CageTopology.from_polygons(CUBE_FACES)


def mixed_prism() -> tuple[np.ndarray, CageTopology]:
    """Pentagonal prism: two pentagons, four quads and one side split into two triangles."""
    ang = 2 * np.pi * np.arange(5) / 5
    ring = np.stack([np.cos(ang), np.sin(ang) * 0.8, np.zeros(5)], axis=1)
    points = np.concatenate([ring - np.array([0.0, 0.0, 0.6]), ring + np.array([0.1, 0.0, 0.7])])
    faces = [[4, 3, 2, 1, 0], [5, 6, 7, 8, 9]]
    for i in range(4):
        j = (i + 1) % 5
        faces.append([i, j, j + 5, i + 5])
    faces += [[4, 0, 5], [4, 5, 9]]
    return points, CageTopology.from_polygons(faces)


def box_cage(counts, size) -> tuple[np.ndarray, CageTopology]:  # type: ignore[no-untyped-def]
    """Closed box centred at 0 with `size` (3,), each side a grid of counts (3,) quads: large flat
    regions, so most vertices are coplanar with most faces."""
    grids = [np.linspace(-0.5 * s, 0.5 * s, n + 1) for n, s in zip(counts, size, strict=True)]
    verts: dict[tuple, int] = {}
    faces = []
    for axis, sign in itertools.product(range(3), (-1, 1)):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        for i, j in itertools.product(range(counts[u_ax]), range(counts[v_ax])):
            quad = []
            for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.zeros(3)
                p[axis] = 0.5 * sign * size[axis]
                p[u_ax], p[v_ax] = grids[u_ax][i + di], grids[v_ax][j + dj]
                quad.append(verts.setdefault(tuple(np.round(p, 12)), len(verts)))
            outward = np.cross(np.eye(3)[u_ax], np.eye(3)[v_ax])[axis] * sign > 0
            faces.append(quad if outward else quad[::-1])
    return np.array(list(verts)), CageTopology.from_polygons(faces)


def affine(M, shift) -> np.ndarray:  # type: ignore[no-untyped-def]
    G = np.eye(4)
    G[:3, :3] = M
    G[:3, 3] = shift
    return G


def similarity(angle: float, axis, scale: float, shift) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    G = np.eye(4)
    G[:3, :3] = scale * so3_exp(angle * axis)
    G[:3, 3] = shift
    return G


def apply(G: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ G[:3, :3].T + G[:3, 3]


def cage_weights(*args, **kwargs):  # type: ignore[no-untyped-def]
    """core.cage.cage_weights with its invariants checked: faces' weights strongest first, then (when
    any row pools weight) 8 columns of pooled nodes F + g (core.cage.pool: a cell's corners, sharing
    the pooled weight by trilinear weights); every row sums to 1."""
    indices, values = _cage_weights(*args, **kwargs)
    assert indices.dtype == np.int32 and values.dtype == np.float64
    assert np.all(np.isfinite(values)) and np.all(values >= 0.0)
    np.testing.assert_allclose(values.sum(axis=1), 1.0, atol=1e-12)
    faces = values
    F = args[2].n_faces
    if indices.size and indices.max() >= F:  # the pooled nodes
        assert np.all(indices[:, -8:] >= F) and np.all(indices[:, :-8] < F)
        faces = values[:, :-8]
    assert np.all(np.diff(faces, axis=1) <= 0.0)  # strongest first
    return indices, values


def dense_rows(indices: np.ndarray, values: np.ndarray, n_faces: int) -> np.ndarray:
    """(N, n_faces + 1): column n_faces holds the pooled weight, all pooled nodes' together (0 when
    nothing is pooled)."""
    dense = np.zeros((indices.shape[0], n_faces + 1))
    np.add.at(dense, (np.arange(indices.shape[0])[:, None], np.minimum(indices, n_faces)), values)
    return dense


# --- topology ---------------------------------------------------------------------------------------


def test_corner_triples_fan_and_edges() -> None:
    topo = CageTopology.from_polygons([[0, 1, 2], [3, 4, 5, 6], [7, 8, 9, 10, 11]])
    triples, face, weight = topo.corner_triples()
    assert triples.tolist()[:2] == [[0, 1, 2], [3, 4, 5]]
    assert triples.tolist()[1:5] == [[3, 4, 5], [4, 5, 6], [5, 6, 3], [6, 3, 4]]
    assert face.tolist() == [0] + [1] * 4 + [2] * 5
    np.testing.assert_allclose(weight, [1.0] + [0.25] * 4 + [0.2] * 5)
    fan, fan_face = topo.fan_triangles()
    assert fan.tolist() == [[0, 1, 2], [3, 4, 5], [3, 5, 6], [7, 8, 9], [7, 9, 10], [7, 10, 11]]
    assert fan_face.tolist() == [0, 1, 1, 2, 2, 2]
    assert topo.directed_edges().tolist()[:3] == [[0, 1], [1, 2], [2, 0]]


def test_topology_rejects_malformed_arrays() -> None:
    with pytest.raises(ValueError, match="fewer than 3 corners"):
        CageTopology.from_polygons([[0, 1, 2], [0, 1]])
    with pytest.raises(ValueError, match="refers to vertex 5"):
        CageTopology.from_arrays(np.array([0, 1, 5]), np.array([0]), np.array([3]), n_vertices=4)
    with pytest.raises(ValueError, match="outside loop_vertex_indices"):
        CageTopology.from_arrays(np.array([0, 1, 2]), np.array([1]), np.array([3]))
    with pytest.raises(ValueError, match="integer"):
        CageTopology.from_arrays(np.array([0.0, 1.0, 2.0]), np.array([0]), np.array([3]))
    points, topo = cube()
    with pytest.raises(ValueError, match="has 7 vertices"):
        face_motions(points[:7], points[:7], topo)


def test_loop_start_need_not_follow_face_order() -> None:
    points, topo = mixed_prism()
    sizes = topo.loop_total
    loops = topo.loop_vertex_indices
    # Store the faces' loops back to front while keeping the face order.
    order = np.arange(topo.n_faces)[::-1]
    blocks = [loops[topo.loop_start[f] : topo.loop_start[f] + sizes[f]] for f in order]
    new_start = np.empty_like(topo.loop_start)
    new_start[order] = np.concatenate([[0], np.cumsum([b.size for b in blocks])[:-1]])
    shuffled = CageTopology.from_arrays(np.concatenate(blocks), new_start, sizes.copy())
    np.testing.assert_allclose(face_normals(points, shuffled), face_normals(points, topo), atol=1e-14)
    G = similarity(0.4, [1, 1, 0], 1.2, [0.0, 0.3, 0.0])
    current = apply(G, points) + 0.01 * np.sin(points)
    a, b = face_motions(points, current, shuffled), face_motions(points, current, topo)
    np.testing.assert_allclose(a.params, b.params, atol=1e-13)
    assert check_cage(points, shuffled).ok
    query = np.array([[0.1, 0.2, 0.0], [0.3, -0.2, 0.4]])
    expected = dense_rows(*cage_weights(query, points, topo), 11)
    np.testing.assert_allclose(dense_rows(*cage_weights(query, points, shuffled), 11), expected)


def test_newell_normal_of_a_triangle_is_the_cross_product() -> None:
    points, topo = mixed_prism()
    normals = face_normals(points, topo)
    a, b, c = points[[4, 0, 5]]
    np.testing.assert_allclose(normals[-2], np.cross(b - a, c - a), atol=1e-14)


# --- face motions -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "G",
    [
        similarity(0.7, [1, 2, 3], 1.0, [0.3, -2.0, 1.0]),
        similarity(2.9, [-1, 0.5, 0.2], 2.5, [0.0, 0.0, 0.0]),
        similarity(0.0, [0, 0, 1], 0.01, [5.0, 5.0, 5.0]),
        similarity(np.pi, [1, 0, 0], 1.3, [0.0, 1.0, 0.0]),  # exact half turn: corners must agree
        similarity(np.pi - 1e-9, [0.3, -0.2, 1.0], 0.7, [1.0, 0.0, -1.0]),
    ],
)
def test_similarity_of_the_whole_cage_gives_every_face_exactly_g(G: np.ndarray) -> None:
    for points, topo in (cube(), mixed_prism()):
        motion = face_motions(points, apply(G, points), topo)
        assert motion.valid.all() and motion.messages == ()
        A = matrices_from_params(motion.params)
        np.testing.assert_allclose(A, np.broadcast_to(G, A.shape), atol=1e-9)


def test_normal_apex_is_exact_in_plane_but_follows_the_normal_under_shear() -> None:
    """MATH.md §9's normal apex ('NORMAL') is similarity-covariant only: under a shear every corner maps
    its own face exactly, and the normal direction goes to cof(M)·N/√|cof(M)·N|, not to M·N."""
    points, topo = mixed_prism()
    G = affine([[1.0, 0.6, 0.0], [0.0, 1.2, 0.3], [0.2, 0.0, 0.8]], [0.5, -0.1, 0.2])
    current = apply(G, points)
    motion = face_motions(points, current, topo, apex="NORMAL")
    assert motion.valid.all()
    A = matrices_from_params(motion.params)
    normals = face_normals(points, topo)
    M = G[:3, :3]
    cof = np.linalg.det(M) * np.linalg.inv(M).T
    for f in range(topo.n_faces):
        verts = topo.loop_vertex_indices[topo.loop_start[f] : topo.loop_start[f] + topo.loop_total[f]]
        np.testing.assert_allclose(apply(A[f], points[verts]), current[verts], atol=1e-9)
        n_hat = normals[f] / np.linalg.norm(normals[f])
        expected = cof @ n_hat / np.sqrt(np.linalg.norm(cof @ n_hat))
        np.testing.assert_allclose(A[f, :3, :3] @ n_hat, expected, atol=1e-9)
    assert np.abs(A - G).max() > 0.1  # so a common shear is NOT reproduced by blending faces


COMMON_MOTIONS = {
    "shear": affine([[1.0, 0.6, 0.0], [0.0, 1.2, 0.3], [0.2, 0.0, 0.8]], [0.5, -0.1, 0.2]),
    "non-uniform scale": affine(np.diag([2.0, 0.5, 1.5]), [0.0, 0.0, 0.0]),
    "squash": affine(np.diag([1.0 / np.sqrt(0.2), 1.0 / np.sqrt(0.2), 0.2]), [0.0, 1.0, 0.0]),
    "rotation + translation": similarity(2.5, [1, -2, 0.5], 1.0, [3.0, -1.0, 2.0]),
    "rotated shear": affine(so3_exp(np.array([0.4, 1.9, -0.7])) @ [[1.3, 0.0, 0.9], [0.0, 0.6, 0.0],
                                                                   [-0.4, 0.0, 1.1]], [1.0, 2.0, -3.0]),
}


def interior_points(points: np.ndarray, topo: CageTopology, n: int, seed: int) -> np.ndarray:
    """Random points inside a convex cage, at least 5% of its size from every face plane."""
    rng = np.random.default_rng(seed)
    lo, hi = points.min(axis=0), points.max(axis=0)
    normals = face_normals(points, topo)
    unit = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    centroid = np.array([points[topo.loop_vertex_indices[s : s + k]].mean(axis=0)
                         for s, k in zip(topo.loop_start, topo.loop_total, strict=True)])
    q = rng.uniform(lo, hi, size=(20 * n, 3))
    depth = np.einsum("fi,nfi->nf", unit, centroid[None] - q[:, None, :]).min(axis=1)
    q = q[depth > 0.05 * np.ptp(points, axis=0).max()][:n]
    assert len(q) == n
    return q


@pytest.mark.parametrize("name", list(COMMON_MOTIONS))
def test_any_common_affine_motion_gives_every_face_exactly_g(name: str) -> None:
    """The 'NEIGHBOURS' apex (default): shear and non-uniform scale of the whole cage are exact too,
    so blending the faces reproduces G·v inside the cage."""
    G = COMMON_MOTIONS[name]
    for points, topo in (mixed_prism(), box_cage((3, 2, 4), (1.5, 1.0, 2.0)), cube()):
        motion = face_motions(points, apply(G, points), topo)
        assert motion.valid.all() and motion.messages == ()
        A = matrices_from_params(motion.params)
        np.testing.assert_allclose(A, np.broadcast_to(G, A.shape), atol=1e-9)
        q = interior_points(points, topo, 40, seed=topo.n_faces)
        idx, val = cage_weights(q, points, topo)
        params = with_pool_nodes(motion.params, points, topo)  # indices F + g: the pooled nodes
        np.testing.assert_allclose(deform_points_params(q, params, idx, val), apply(G, q), atol=1e-9)
        dense = np.zeros((len(q), len(params)))
        np.add.at(dense, (np.arange(len(q))[:, None], idx), val)
        np.testing.assert_allclose(deform_points(q, matrices_from_params(params), dense), apply(G, q),
                                   atol=1e-9)


def test_random_affine_motions_of_the_cage_are_exact() -> None:
    rng = np.random.default_rng(44)
    points, topo = box_cage((2, 3, 2), (1.0, 1.0, 1.0))
    points = points + rng.normal(scale=0.02, size=points.shape)  # no face exactly flat any more
    assert check_cage(points, topo).ok
    for _ in range(10):
        Q1, Q2 = (np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(2))
        M = (Q1 * np.sign(np.linalg.det(Q1))) @ np.diag(np.exp(rng.normal(scale=0.5, size=3))) @ Q2
        G = affine(M * np.sign(np.linalg.det(M)), rng.normal(size=3))
        motion = face_motions(points, apply(G, points), topo)
        assert motion.valid.all()
        A = matrices_from_params(motion.params)
        np.testing.assert_allclose(A, np.broadcast_to(G, A.shape), atol=1e-9)


def test_stencil_fit_reaches_round_flat_sides_and_is_balanced() -> None:
    points, topo = box_cage((4, 3, 2), (2.0, 1.5, 1.0))
    stencil = apex_stencils(points, topo)
    triples, _, _ = topo.corner_triples()
    assert stencil.active.all()  # even a corner in the middle of a flat side has a stencil
    used = stencil.gamma != 0.0
    assert np.all(used.sum(axis=1) == 16)
    assert np.all(np.abs(stencil.beta[used]) >= STENCIL_MIN_BETA)
    # The stencil's rest coordinates are exact: p_j − c = E (α, β).
    E, c, _ = cage_module._corner_frames(points, triples)
    rebuilt = c[:, None, :] + np.einsum("tik,tsk->tsi", E[:, :, :2], stencil.alpha)
    rebuilt += E[:, None, :, 2] * stencil.beta[..., None]
    np.testing.assert_allclose(np.where(used[..., None], rebuilt, 0.0),
                               np.where(used[..., None], points[stencil.vertices], 0.0), atol=1e-12)
    # Σ γβ = 1 makes any common affine motion exact; the fit keeps the in-plane moments Σ γα small.
    np.testing.assert_allclose((stencil.gamma * stencil.beta).sum(axis=1), 1.0, atol=1e-12)
    assert np.abs(stencil.moments[:, 1:]).max() < 0.05
    assert np.all(stencil.spread >= 1.0 - 1e-12)


def test_stencil_matches_its_definition_corner_by_corner() -> None:
    """Reference: for each corner, score every vertex by ω β² (|β| ≥ STENCIL_MIN_BETA), keep the 16
    heaviest, and take γ = ω zᵀ (W + ρ diag(1, 1, 0))⁻¹ e₃ literally."""
    rng = np.random.default_rng(12)
    points, topo = box_cage((3, 2, 2), (1.5, 1.0, 1.0))
    points += rng.normal(scale=0.01, size=points.shape)  # nearly flat sides: small but usable β
    stencil = apex_stencils(points, topo)
    triples, _, _ = topo.corner_triples()
    E, c, _ = cage_module._corner_frames(points, triples)
    for t in range(triples.shape[0]):
        z = np.linalg.solve(E[t], (points - c[t]).T).T
        d_rel_sq = ((points - c[t]) ** 2).sum(axis=1) / (E[t, :, 2] @ E[t, :, 2])
        score = np.where(np.abs(z[:, 2]) >= STENCIL_MIN_BETA, z[:, 2] ** 2 / d_rel_sq**2, 0.0)
        best = np.argsort(-score, kind="stable")[:16]
        assert set(best.tolist()) == set(stencil.vertices[t].tolist())
        w = 1.0 / d_rel_sq[best] ** 2
        W = np.einsum("s,si,sj->ij", w, z[best], z[best])
        W[[0, 1], [0, 1]] += cage_module.STENCIL_RIDGE * 0.5 * (W[0, 0] + W[1, 1])
        gamma = w * (z[best] @ np.linalg.solve(W, [0.0, 0.0, 1.0]))
        order = [int(np.flatnonzero(best == v)[0]) for v in stencil.vertices[t]]
        np.testing.assert_allclose(stencil.gamma[t], gamma[order], rtol=1e-9, atol=1e-12)


def test_stencils_are_cached_by_content() -> None:
    points, topo = box_cage((2, 2, 2), (1.0, 1.0, 1.0))
    first = apex_stencils(points, topo)
    again = CageTopology.from_arrays(topo.loop_vertex_indices.copy(), topo.loop_start.copy(),
                                     topo.loop_total.copy())
    assert apex_stencils(points.copy(), again) is first  # the Blender layer rebuilds topology per frame
    moved = points.copy()
    moved[0, 0] += 1e-3
    assert apex_stencils(moved, topo) is not first
    with pytest.raises(ValueError, match="apex must be one of"):
        face_motions(points, points, topo, apex="NORMALS")


def test_rest_corners_are_cached_by_content_and_change_no_bit() -> None:
    """face_motions takes the rest side of its corners (usability, weights, frames, E_rest⁻¹) from a
    content-keyed cache (`rest_corners`) and the moved corners' stencils by `ApexStencil.take`: the
    same object for the same rest cage and a rebuilt topology, a new one for another rest shape;
    corner_matrices with those gives the same bits as computing them, for all corners and for a
    subset (a few moved faces)."""
    points, topo = mixed_prism()
    first = cage_module.rest_corners(points, topo)
    again = CageTopology.from_arrays(topo.loop_vertex_indices.copy(), topo.loop_start.copy(),
                                     topo.loop_total.copy())
    assert cage_module.rest_corners(points.copy(), again) is first
    moved = points.copy()
    moved[0, 0] += 1e-3
    assert cage_module.rest_corners(moved, topo) is not first
    usable, weight = cage_module._usable_rest_triples(points, topo)
    assert np.array_equal(first.usable, usable) and np.array_equal(first.weight, weight)
    rng = np.random.default_rng(17)
    triples, _, _ = topo.corner_triples()
    stencil = apex_stencils(points, topo)
    for _ in range(5):
        current = points + rng.normal(scale=0.1, size=points.shape)
        for rows in (np.ones(len(triples), dtype=bool), rng.random(len(triples)) < 0.4):
            sub = cage_module.ApexStencil(stencil.vertices[rows], stencil.alpha[rows], stencil.beta[rows],
                                          stencil.gamma[rows])
            taken = stencil.take(rows)  # what face_motions uses: the full stencil's derived rows
            for name in ("vertices", "alpha", "beta", "gamma", "active", "rows", "moments", "spread"):
                np.testing.assert_allclose(getattr(taken, name), getattr(sub, name), rtol=1e-15, atol=0)
            want = cage_module.corner_matrices(points, current, triples[rows], stencil=sub)
            got = cage_module.corner_matrices(points, current, triples[rows], stencil=taken,
                                              rest_frames=first.take(rows))
            assert np.array_equal(want[0], got[0]) and np.array_equal(want[1], got[1])


def test_face_motions_with_a_polar_split_given() -> None:
    """`polar` (the compiled kernel's polar split in the Blender layer) only replaces numpy's SVD in
    ψ: with numpy's own split passed in, the motions are bit for bit the default ones; with a
    different but exact split (transposed twice), equal to rounding."""
    points, topo = mixed_prism()
    rng = np.random.default_rng(19)
    current = points + rng.normal(scale=0.1, size=points.shape)

    def numpy_split(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        U, sigma, Vh = np.linalg.svd(M)
        return U @ Vh, Vh.transpose(0, 2, 1) @ (np.log(sigma)[:, :, None] * Vh)

    def via_transpose(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Mᵀ = U′ Σ V′ᵀ, so M = V′ Σ U′ᵀ: R = V′ U′ᵀ = (U′ V′ᵀ)ᵀ and Ŷ = U′ diag(log σ) U′ᵀ.
        U, sigma, Vh = np.linalg.svd(M.transpose(0, 2, 1))
        return (U @ Vh).transpose(0, 2, 1), U @ (np.log(sigma)[:, :, None] * U.transpose(0, 2, 1))

    want = face_motions(points, current, topo)
    assert np.array_equal(face_motions(points, current, topo, polar=numpy_split).params, want.params)
    assert np.array_equal(face_motions(points, current, topo, polar=lambda M: None).params, want.params)
    got = face_motions(points, current, topo, polar=via_transpose)
    assert np.abs(got.params - want.params).max() < 1e-12
    assert np.array_equal(got.valid, want.valid)


def test_flat_open_cage_keeps_the_normal_apex() -> None:
    """No vertex off a face's plane: no stencil, so 'NEIGHBOURS' falls back to the normal apex."""
    g = np.linspace(0.0, 1.0, 4)
    points = np.array([[x, y, 0.0] for y in g for x in g])
    quads = [[4 * j + i, 4 * j + i + 1, 4 * j + i + 5, 4 * j + i + 4] for j in range(3) for i in range(3)]
    topo = CageTopology.from_polygons(quads)
    assert not apex_stencils(points, topo).active.any()
    current = apply(COMMON_MOTIONS["rotated shear"], points)
    current[5, 2] += 0.2
    a = face_motions(points, current, topo)
    b = face_motions(points, current, topo, apex="NORMAL")
    assert np.array_equal(a.params, b.params) and a.valid.all()


def long_box_with_rigid_half() -> tuple[np.ndarray, np.ndarray, CageTopology, np.ndarray, np.ndarray]:
    """(rest, current, topology, moved (V,) bool, G): the x > 0 half of a 6 × 1 × 1 box moved by a
    rigid G, the rest in place; faces at the junction are stretched."""
    points, topo = box_cage((12, 2, 2), (6.0, 1.0, 1.0))
    G = similarity(0.6, [0.3, -0.4, 0.5], 1.0, [0.3, 0.2, -0.5])
    moved = points[:, 0] > 0.01
    current = points.copy()
    current[moved] = apply(G, points[moved])
    return points, current, topo, moved, G


def faces_depending_only_on(mask: np.ndarray, points: np.ndarray, topo: CageTopology) -> np.ndarray:
    """Faces whose corner vertices and apex stencil vertices all lie in `mask`."""
    stencil = apex_stencils(points, topo)
    triples, face, _ = topo.corner_triples()
    inside = mask[triples].all(axis=1) & np.where(stencil.gamma != 0.0, mask[stencil.vertices], True).all(1)
    out = np.ones(topo.n_faces, dtype=bool)
    np.logical_and.at(out, face, inside)
    return out


def test_rigidly_moved_half_of_a_long_cage_moves_rigidly() -> None:
    """Faces of the turned half move exactly by G. Deep in it (16 faces about equally far: with 8
    influences up to 0.81 of a vertex's weight is pooled, MATH.md §12) the kept faces are all rigid
    ones and the pooled nodes mix the faces near them (core.cage.pool), a few of which, at the
    stretched junction, do not move rigidly: the region moves by G within 1e-3 of the box's width
    (strain within 1 %), and the other half stays within 2e-4 of rest."""
    points, current, topo, moved, G = long_box_with_rigid_half()
    motion = face_motions(points, current, topo)
    assert motion.valid.all()
    A = matrices_from_params(motion.params)
    rigid = faces_depending_only_on(moved, points, topo)
    still = faces_depending_only_on(~moved, points, topo)
    assert rigid.sum() >= 30 and still.sum() >= 30
    np.testing.assert_allclose(A[rigid], np.broadcast_to(G, A[rigid].shape), atol=1e-9)
    np.testing.assert_allclose(A[still], np.broadcast_to(np.eye(4), A[still].shape), atol=1e-9)
    np.testing.assert_array_equal(affected_faces(points, current, topo), ~still)

    rng = np.random.default_rng(5)
    q = np.column_stack([rng.uniform(1.5, 2.5, 40), rng.uniform(-0.35, 0.35, (40, 2))])
    idx, val = cage_weights(q, points, topo)
    F = topo.n_faces
    assert rigid[idx[(val > 0.0) & (idx < F)]].all()  # deep in the moved half: the kept faces are rigid
    params = with_pool_nodes(motion.params, points, topo)

    def deform(x: np.ndarray) -> np.ndarray:
        return deform_points_params(x, params, *cage_weights(x, points, topo))

    np.testing.assert_allclose(deform(q), apply(G, q), atol=1e-3)
    step = 1e-5
    J = np.stack([(deform(q + step * e) - deform(q - step * e)) / (2 * step) for e in np.eye(3)], axis=2)
    np.testing.assert_allclose(np.einsum("nki,nkj->nij", J, J), np.broadcast_to(np.eye(3), J.shape),
                               atol=1e-2)
    far = q * [-1.0, 1.0, 1.0]
    np.testing.assert_allclose(deform(far), far, atol=2e-4)


def test_fold_guard_keeps_faces_valid_when_a_vertex_crosses_the_cage(monkeypatch: pytest.MonkeyPatch) -> None:
    """A cube corner pushed down through the bottom face: without the guard the fitted apex of the
    corners next to it falls through their plane (det ≤ 0, faces dropped, parameters jump)."""
    points, topo = cube()
    path = np.linspace(0.0, 1.2, 121)  # to 0.2 below the bottom face

    def sweep() -> tuple[np.ndarray, float, float]:
        invalid = np.zeros(topo.n_faces, dtype=int)
        jump, det = 0.0, np.inf
        previous = None
        for t in path:
            current = points.copy()
            current[7] += [-0.2, -0.1, -t]
            motion = face_motions(points, current, topo)
            invalid += ~motion.valid
            A = matrices_from_params(motion.params[motion.valid])
            det = min(det, float(np.linalg.det(A[:, :3, :3]).min()))
            if previous is not None:
                jump = max(jump, float(np.abs(motion.params - previous).max()))
            previous = motion.params
        return invalid, jump, det

    invalid, jump, det = sweep()
    assert not invalid.any() and jump < 0.2 and det > 0.05
    monkeypatch.setattr(cage_motions, "FOLD_KAPPA", 0.0)
    invalid, jump, _ = sweep()
    assert invalid.sum() > 30 and jump > 1.0


def test_face_of_loop_follows_the_storage_order() -> None:
    points, topo = mixed_prism()
    order = np.arange(topo.n_faces)[::-1]
    blocks = [topo.loop_vertex_indices[topo.loop_start[f] : topo.loop_start[f] + topo.loop_total[f]]
              for f in order]
    start = np.empty_like(topo.loop_start)
    start[order] = np.concatenate([[0], np.cumsum([b.size for b in blocks])[:-1]])
    shuffled = CageTopology.from_arrays(np.concatenate(blocks), start, topo.loop_total.copy())
    x = np.arange(points.shape[0], dtype=float) ** 2
    for t in (topo, shuffled):
        per_face = np.bincount(t.face_of_loop(), x[t.loop_vertex_indices], t.n_faces)
        expected = [x[t.loop_vertex_indices[s : s + k]].sum() for s, k in zip(t.loop_start, t.loop_total,
                                                                                strict=True)]
        np.testing.assert_allclose(per_face, expected)


@pytest.mark.parametrize("concave", [False, True])
def test_quad_equals_its_two_triangles_under_an_affine_motion(concave: bool) -> None:
    quad = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 1.5, 0.0], [0.0, 1.0, 0.0]])
    if concave:
        quad[3] = [1.6, 0.4, 0.0]  # corner 3 becomes reflex
    R = so3_exp(np.array([0.2, 0.5, -0.3]))
    quad = quad @ R.T + [0.3, 0.1, -0.4]  # a quad in a general plane
    G = np.eye(4)
    G[:3, :3] = [[1.3, 0.4, -0.2], [0.1, 0.7, 0.5], [-0.3, 0.2, 1.1]]
    G[:3, 3] = [1.0, 2.0, -0.5]
    current = apply(G, quad)
    as_quad = face_motions(quad, current, CageTopology.from_polygons([[0, 1, 2, 3]]))
    as_tris = face_motions(quad, current, CageTopology.from_polygons([[0, 1, 2], [0, 2, 3]]))
    np.testing.assert_allclose(as_tris.params[0], as_tris.params[1], atol=1e-10)
    np.testing.assert_allclose(as_quad.params[0], as_tris.params[0], atol=1e-10)
    assert np.abs(as_quad.params[0]).max() > 0.1


def test_closed_cage_quad_and_its_triangulation_agree() -> None:
    """With the 'NEIGHBOURS' apex the isolated-quad statement above holds in a closed cage too: under
    an affine motion every face (quad or triangle) is exactly G; under any motion a triangle and the
    quad corner on the same three vertices have the same stencil (the fourth vertex is coplanar, so
    not in it) and hence the same tetrahedron motion."""
    points, _ = cube()
    as_quad = CageTopology.from_polygons(CUBE_FACES)
    as_tris = CageTopology.from_polygons([*CUBE_FACES[:TOP], [4, 5, 7], [4, 7, 6], *CUBE_FACES[TOP + 1 :]])
    G = COMMON_MOTIONS["rotated shear"]
    for topo in (as_quad, as_tris):
        A = matrices_from_params(face_motions(points, apply(G, points), topo).params)
        np.testing.assert_allclose(A, np.broadcast_to(G, A.shape), atol=1e-9)
    current = apply(G, points) + 0.05 * np.sin(3.0 * points[:, ::-1])
    corners = {}
    for topo in (as_quad, as_tris):
        triples, _, _ = topo.corner_triples()
        A, ok = cage_module.corner_matrices(points, current, triples, stencil=apex_stencils(points, topo))
        assert ok.all()
        corners[topo] = {tuple(t): a for t, a in zip(triples.tolist(), A, strict=True)}
    np.testing.assert_allclose(corners[as_tris][(4, 5, 7)], corners[as_quad][(4, 5, 7)], atol=1e-12)


def test_collapsed_face_is_reported_and_zeroed_never_nan() -> None:
    # Octahedron; moving +z onto the midpoint of +x and +y makes exactly one triangle collinear.
    points = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float)
    faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    topo = CageTopology.from_polygons(faces)
    assert check_cage(points, topo).ok
    current = points.copy()
    current[4] = [0.5, 0.5, 0.0]
    motion = face_motions(points, current, topo)
    assert motion.valid.tolist() == [False] + [True] * 7
    assert np.array_equal(motion.params[0], np.zeros(12))
    assert np.all(np.isfinite(motion.params))
    assert len(motion.messages) == 1 and "collapsed" in motion.messages[0] and ": 0" in motion.messages[0]

    current[4] = [np.nan, 0.0, 1.0]
    motion = face_motions(points, current, topo)
    assert motion.valid.tolist() == [False] * 4 + [True] * 4
    assert np.all(np.isfinite(motion.params))

    rest = points.copy()
    rest[4] = [0.5, 0.5, 0.0]
    motion = face_motions(rest, points, topo)
    assert not motion.valid[0] and motion.valid[1:].all()
    assert "rest pose" in motion.messages[0] and "degenerate" in motion.messages[0]


def test_corner_rejected_by_psi_invalidates_only_its_face(monkeypatch: pytest.MonkeyPatch) -> None:
    real = cage_motions.params_from_matrices

    def picky(A: np.ndarray) -> np.ndarray:  # rejects batches and every non-identity matrix
        if A.ndim == 3 or not np.allclose(A, np.eye(4)):
            raise ValueError("transform is too degenerate to take its logarithm")
        return real(A)

    monkeypatch.setattr(cage_motions, "params_from_matrices", picky)
    points, topo = box_cage((8, 1, 1), (8.0, 1.0, 1.0))
    current = points.copy()
    end = int(np.argmax(points @ [1.0, 1.0, 1.0]))  # a corner vertex at the +x end
    current[end] += [0.1, 0.2, 0.3]
    # Moving faces: those using the vertex as a corner or in an apex stencil; the others stay valid.
    moving = affected_faces(points, current, topo)
    assert 0 < moving.sum() < topo.n_faces // 2
    motion = face_motions(points, current, topo)
    np.testing.assert_array_equal(motion.valid, ~moving)
    assert np.array_equal(motion.params, np.zeros((topo.n_faces, 12)))
    assert f"{moving.sum()} cage face(s) collapsed" in motion.messages[0]
    normal = face_motions(points, current, topo, apex="NORMAL")
    np.testing.assert_array_equal(normal.valid, ~affected_faces(points, current, topo, apex="NORMAL"))


def test_straight_rest_corner_of_an_ngon_is_skipped() -> None:
    points, _ = cube()
    points = np.vstack([points, [0.0, -0.5, 0.5]])  # vertex 8 on the top-front edge (4, 5)
    faces = [list(f) for f in CUBE_FACES]
    faces[TOP] = [4, 8, 5, 7, 6]
    faces[2] = [0, 1, 5, 8, 4]
    topo = CageTopology.from_polygons(faces)
    assert check_cage(points, topo).ok
    G = similarity(1.1, [0.2, 1.0, -0.4], 1.7, [0.0, 2.0, 1.0])
    motion = face_motions(points, apply(G, points), topo)
    assert motion.valid.all()
    A = matrices_from_params(motion.params)
    np.testing.assert_allclose(A, np.broadcast_to(G, A.shape), atol=1e-9)
    # Bending at the T-junction still gives finite, valid parameters.
    bent = points.copy()
    bent[8, 2] += 0.05
    motion = face_motions(points, bent, topo)
    assert motion.valid.all() and np.all(np.isfinite(motion.params))


def test_face_motions_of_chosen_faces_equal_the_full_computation_bitwise() -> None:
    """`faces=` only skips work: the chosen faces' motions are the same bits, the others are at rest."""
    rng = np.random.default_rng(31)
    points, topo = box_cage((4, 3, 2), (2.0, 1.5, 1.0))
    moved = points.copy()
    moved[7] += (0.2, -0.1, 0.15)
    moved[3] = np.nan  # a broken vertex: faces using it are reported wherever they are computed
    moved[11] += rng.normal(scale=0.05, size=3)
    full = face_motions(points, moved, topo)
    chosen = affected_faces(points, moved, topo)
    assert 0 < chosen.sum() < topo.n_faces
    part = face_motions(points, moved, topo, faces=chosen)
    assert np.array_equal(part.params[chosen], full.params[chosen])
    assert np.array_equal(part.valid[chosen], full.valid[chosen])
    assert np.all(part.params[~chosen] == 0.0) and np.all(part.valid[~chosen])
    assert part.messages == full.messages


def test_reference_rotation_lifts_every_face() -> None:
    points, topo = cube()
    angle = np.radians(400.0)
    G = similarity(angle, [0, 0, 1], 1.0, [0.0, 0.0, 0.0])
    motion = face_motions(points, apply(G, points), topo, w_ref=np.array([0.0, 0.0, angle]))
    np.testing.assert_allclose(motion.params[:, 0:3], np.tile([0.0, 0.0, angle], (6, 1)), atol=1e-9)
    A = matrices_from_params(motion.params)
    np.testing.assert_allclose(A, np.broadcast_to(G, A.shape), atol=1e-9)
    principal = face_motions(points, apply(G, points), topo)
    np.testing.assert_allclose(principal.params[:, 2], angle - 2 * np.pi, atol=1e-9)


# --- distances --------------------------------------------------------------------------------------


def reference_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[float, str]:
    """Literal definition: the plane distance if the projection lies in the triangle, else the
    nearest of the three segments. Also names the closest feature."""

    def segment(p, x, y, names):  # type: ignore[no-untyped-def]
        e = y - x
        t = float(np.clip(np.dot(p - x, e) / np.dot(e, e), 0.0, 1.0))
        name = names[0] if t == 0.0 else names[1] if t == 1.0 else names[0] + names[1]
        return float(np.linalg.norm(p - (x + t * e))), name

    n = np.cross(b - a, c - a)
    ab, ac, ap = b - a, c - a, p - a
    gram = np.array([[ab @ ab, ab @ ac], [ab @ ac, ac @ ac]])
    v, w = np.linalg.solve(gram, [ap @ ab, ap @ ac])
    if v >= 0 and w >= 0 and v + w <= 1:
        return abs(np.dot(p - a, n)) / np.linalg.norm(n), "face"
    return min(segment(p, a, b, "AB"), segment(p, b, c, "BC"), segment(p, c, a, "CA"))


def test_point_triangle_distance_matches_brute_force_in_every_region() -> None:
    rng = np.random.default_rng(8)
    tris = rng.normal(size=(6, 3, 3))
    tris[0] = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    tris[1] = [[0, 0, 0], [10, 0, 0], [0, 0.01, 0]]  # a sliver
    regions: set[str] = set()
    for a, b, c in tris:
        ab, ac, n = b - a, c - a, np.cross(b - a, c - a)
        coef = rng.uniform(-1.0, 2.0, size=(400, 2))
        points = a + coef[:, :1] * ab + coef[:, 1:] * ac + rng.uniform(-1, 1, size=(400, 1)) * n
        got = point_triangle_distance_sq(points, a[None], b[None], c[None])[:, 0]
        for p, d2 in zip(points, got, strict=True):
            d, region = reference_distance(p, a, b, c)
            regions.add(region)
            assert np.sqrt(d2) == pytest.approx(d, abs=1e-9 * max(1.0, np.linalg.norm(p - a)))
    assert regions == {"face", "AB", "BC", "CA", "A", "B", "C"}


def test_degenerate_triangles_reduce_to_segments_and_points() -> None:
    points = np.array([[0.5, 1.0, 0.0], [3.0, 0.0, 0.0], [-1.0, -1.0, 2.0]])
    line = [np.zeros(3)], [np.array([1.0, 0.0, 0.0])], [np.array([2.0, 0.0, 0.0])]
    got = point_triangle_distance_sq(points, *line)[:, 0]
    np.testing.assert_allclose(got, [1.0, 1.0, 1.0 + 1.0 + 4.0], atol=1e-12)
    dot = [np.ones(3)], [np.ones(3)], [np.ones(3)]
    got = point_triangle_distance_sq(points, *dot)[:, 0]
    np.testing.assert_allclose(got, ((points - 1.0) ** 2).sum(axis=1), atol=1e-12)


def test_polygon_distance_is_the_minimum_over_fan_triangles() -> None:
    points, topo = mixed_prism()
    rng = np.random.default_rng(9)
    query = rng.normal(size=(50, 3))
    d2 = polygon_distance_sq(query, points, topo)
    fan, fan_face = topo.fan_triangles()
    per_tri = point_triangle_distance_sq(query, *(points[fan[:, k]] for k in range(3)))
    for f in range(topo.n_faces):
        np.testing.assert_allclose(d2[:, f], per_tri[:, fan_face == f].min(axis=1), atol=1e-12)
    below_pentagon = points[[0, 1, 2, 3, 4]].mean(axis=0) - np.array([0.0, 0.0, 0.25])
    assert polygon_distance_sq(below_pentagon[None], points, topo)[0, 0] == pytest.approx(0.0625)


# --- weights ----------------------------------------------------------------------------------------


def test_inverse_distance_weights_inside_a_cube() -> None:
    points, topo = cube()
    v = np.array([[0.1, -0.2, 0.3]])
    idx, val = cage_weights(v, points, topo, k=6, exponent=2.0)
    dist = {BOTTOM: 0.8, TOP: 0.2, 2: 0.3, 3: 0.7, 4: 0.6, 5: 0.4}
    expected = np.array([dist[f] ** -2.0 for f in range(6)])
    expected /= expected.sum()
    np.testing.assert_allclose(val[0], expected[idx[0]], rtol=1e-12)
    assert idx[0, 0] == TOP
    idx3, val3 = cage_weights(v, points, topo, k=6, exponent=3.0)
    w3 = np.array([dist[f] ** -3.0 for f in range(6)])
    np.testing.assert_allclose(val3[0], (w3 / w3.sum())[idx3[0]], rtol=1e-12)


def test_half_space_rule_on_a_cube() -> None:
    points, topo = cube()
    inside = np.array([[0.0, 0.0, 0.45]])
    _, val = cage_weights(inside, points, topo, k=6)
    assert np.all(val > 0.0)  # inside a convex cage nothing is cut

    above = np.array([[0.1, 0.0, 0.8]])
    weight = dense_rows(*cage_weights(above, points, topo, k=6), 6)[0]
    assert weight[TOP] == 0.0 and np.count_nonzero(weight) == 5
    idx, val = cage_weights(above, points, topo, k=6, half_space=False)
    assert idx[0, 0] == TOP and val[0, 0] > 0.4  # the nearest face dominates again

    corner = np.array([[0.8, 0.9, 0.7]])  # outside right, back and top
    weight = dense_rows(*cage_weights(corner, points, topo, k=6), 6)[0]
    # elevations z/d: right 0.3/√0.29, back 0.4/√0.29 (past the band: 0); top 0.2/√0.29 (ramped)
    d2 = {BOTTOM: 0.3**2 + 0.4**2 + 1.2**2, TOP: 0.29, 2: 0.3**2 + 1.4**2 + 0.2**2, 3: 0.29,
          4: 1.3**2 + 0.4**2 + 0.2**2, 5: 0.29}
    raw = np.array([d2[f] ** -1.0 for f in range(6)])
    raw[[3, 5]] = 0.0
    raw[TOP] *= ramp(0.2 / np.sqrt(0.29))
    assert 0.0 < ramp(0.2 / np.sqrt(0.29)) < 0.5
    np.testing.assert_allclose(weight[:6], raw / raw.sum(), rtol=1e-7)  # HALF_SPACE_TOL shifts the plane

    on_face = np.array([[0.1, 0.2, 0.5]])  # on the top face: it keeps (almost all) the weight
    idx, val = cage_weights(on_face, points, topo, k=6)
    assert idx[0, 0] == TOP and val[0, 0] > 0.999


def plus_prism() -> tuple[np.ndarray, CageTopology]:
    """A non-convex prism with a 'plus' cross-section (12 sides, re-entrant corners at (±0.6, ±0.6),
    arms to ±1.2), z in [−1, 1], caps of 5 quads each."""
    a, b = 0.6, 1.2
    outline = [(a, -a), (b, -a), (b, a), (a, a), (a, b), (-a, b), (-a, a), (-b, a), (-b, -a), (-a, -a),
               (-a, -b), (a, -b)]
    points = np.array([(x, y, z) for z in (-1.0, 1.0) for x, y in outline])
    faces = [[j, (j + 1) % 12, 12 + (j + 1) % 12, 12 + j] for j in range(12)]
    squares = [[0, 3, 6, 9], [0, 1, 2, 3], [3, 4, 5, 6], [6, 7, 8, 9], [9, 10, 11, 0]]
    faces += [[12 + i for i in q] for q in squares] + [q[::-1] for q in squares]
    return points, CageTopology.from_polygons(faces)


@pytest.mark.parametrize("half_space", [True, False])
def test_weights_are_continuous_across_face_planes_and_rank_swaps(half_space: bool) -> None:
    """Inside a non-convex cage the plane of the +x arm's top wall (y = 0.6) cuts through the centre:
    a hard half-space cut, or a hard top-K, jumps there whatever the sampling; the ramp and the
    continuous truncation make the largest step between neighbouring samples shrink with the step."""
    cage, topo = plus_prism()
    assert check_cage(cage, topo).ok

    def largest_step(n: int) -> float:
        t = np.linspace(0.0, 1.0, n)[:, None]
        line = np.array([0.3, 0.45, 0.1]) + t * np.array([0.02, 0.3, 0.05])  # crosses y = 0.6 inside
        dense = dense_rows(*cage_weights(line, cage, topo, k=4, half_space=half_space), topo.n_faces)
        return float(np.abs(np.diff(dense, axis=0)).max())

    coarse, fine = largest_step(2001), largest_step(20001)
    assert fine < 0.2 * coarse and fine < 2e-3, (coarse, fine)
    # the same line, with the rules made hard again (the 0.1 weights), keeps a jump at any step
    t = np.linspace(0.0, 1.0, 20001)[:, None]
    line = np.array([0.3, 0.45, 0.1]) + t * np.array([0.02, 0.3, 0.05])
    d2 = np.maximum(polygon_distance_sq(line, cage, topo), 1e-18)
    w = 1.0 / d2
    if half_space:
        n = face_normals(cage, topo)
        c = np.array([cage[topo.loop_vertex_indices[st : st + k]].mean(axis=0)
                      for st, k in zip(topo.loop_start, topo.loop_total, strict=True)])
        w = np.where(np.einsum("fi,nfi->nf", n, line[:, None] - c) > 1e-9, 0.0, w)
    kept = np.where(w >= -np.sort(-w, axis=1)[:, 3:4], w, 0.0)
    hard = kept / kept.sum(axis=1, keepdims=True)
    assert np.abs(np.diff(hard, axis=0)).max() > 5e-3, np.abs(np.diff(hard, axis=0)).max()


def test_vertex_outside_every_half_space_falls_back_to_plain_weights() -> None:
    points, _ = cube()
    open_cage = CageTopology.from_polygons([CUBE_FACES[TOP], CUBE_FACES[5]])  # two faces, open
    far = np.array([[2.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
    idx, val = cage_weights(far, points, open_cage, k=8)
    assert idx.shape == (2, 2)
    assert np.all(val[0] > 0.0)  # outside both faces: fallback, no zero row
    assert np.all(val[1] > 0.0)


def ramp(s):  # type: ignore[no-untyped-def]
    """The half-space ramp as documented: 1 below the plane, smoothstep down to 0 at s = 0.5."""
    t = np.clip(s / 0.5, 0.0, 1.0)
    return 1.0 - 3.0 * t**2 + 2.0 * t**3


def dense_reference_weights(points, cage, topo, k, exponent=2.0, half_space=True):  # type: ignore[no-untyped-def]
    """(N, F) weights measured against every face: d^-p times the half-space ramp of the elevation
    z/d, the (k+1)-th largest subtracted from the k largest, rows normalised."""
    size = np.ptp(cage, axis=0).max()
    d2 = np.maximum(polygon_distance_sq(points, cage, topo), (1e-6 * size) ** 2)
    w = d2 ** (-exponent / 2)
    if half_space:
        normals = face_normals(cage, topo)
        unit = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        centroid = np.array([cage[topo.loop_vertex_indices[s : s + n]].mean(axis=0)
                             for s, n in zip(topo.loop_start, topo.loop_total, strict=True)])
        height = np.einsum("fi,nfi->nf", unit, points[:, None, :] - centroid[None]) - 1e-9 * size
        ramped = w * ramp(np.maximum(height, 0.0) / np.sqrt(d2))
        w = np.where((height <= 0.0).any(axis=1, keepdims=True), ramped, w)
    ranked = -np.sort(-w, axis=1)
    dropped = ranked[:, k : k + 1] if w.shape[1] > k else np.zeros((len(w), 1))
    cut = np.where(w >= ranked[:, k - 1 : k], np.maximum(w - dropped, 0.0), 0.0)
    # divided by D = max(S, c T), T the weight of the max(TOTAL_FACES, k + 1) nearest faces (MATH.md
    # §12); the rest, near ties only, is pooled (last column). A face tied with the (k+1)-th gets 0
    # whichever is kept, so no row depends on rounding.
    S = cut.sum(axis=1, keepdims=True)
    F = POOL_FLOOR * ranked[:, :max(TOTAL_FACES, k + 1)].sum(axis=1, keepdims=True)
    D = np.maximum(S, F)
    return np.hstack([cut / D, np.where(S < F, 1.0 - S / D, 0.0)])


def test_weights_match_a_dense_reference_for_any_chunking() -> None:
    rng = np.random.default_rng(10)
    # A bumpy closed cage with many faces: a subdivided, perturbed cube surface.
    n = 6
    g = np.linspace(-0.5, 0.5, n + 1)
    verts: dict[tuple, int] = {}
    faces = []

    def vid(p):  # type: ignore[no-untyped-def]
        key = tuple(np.round(p, 9))
        return verts.setdefault(key, len(verts))

    for axis, sign in itertools.product(range(3), (-1, 1)):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        for i, j in itertools.product(range(n), range(n)):
            quad = []
            for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.zeros(3)
                p[axis] = 0.5 * sign
                p[u_ax], p[v_ax] = g[i + di], g[j + dj]
                quad.append(vid(p))
            outward = np.cross(np.eye(3)[u_ax], np.eye(3)[v_ax])[axis] * sign > 0
            faces.append(quad if outward else quad[::-1])
    cage = np.array(list(verts.keys()))
    cage += rng.normal(scale=0.01, size=cage.shape)
    topo = CageTopology.from_polygons(faces)
    assert check_cage(cage, topo).ok
    points = np.concatenate([rng.uniform(-0.45, 0.45, size=(300, 3)), rng.uniform(-0.8, 0.8, size=(100, 3))])
    expected = dense_reference_weights(points, cage, topo, k=8)
    assert not np.isnan(expected).any()
    for chunk in (1, 7, 32, 1000):
        idx, val = cage_weights(points, cage, topo, k=8, chunk_size=chunk)
        np.testing.assert_allclose(dense_rows(idx, val, topo.n_faces), expected, rtol=1e-8, atol=1e-10)


def bumpy_sphere_cage(rng: np.random.Generator, segments: int, rings: int) -> tuple[np.ndarray, CageTopology]:
    """A UV sphere of quads with triangle fans at the poles, one cap merged into an n-gon, vertices
    moved radially at random (non-planar quads, no symmetric ties)."""
    theta = np.pi * np.arange(1, rings) / rings
    phi = 2.0 * np.pi * np.arange(segments) / segments
    ring = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.sin(theta), np.sin(phi)),
                     np.outer(np.cos(theta), np.ones(segments))], axis=-1).reshape(-1, 3)
    points = np.concatenate([[[0.0, 0.0, 1.0]], ring])
    points *= rng.uniform(0.85, 1.15, size=(len(points), 1))
    faces = [[0, 1 + j, 1 + (j + 1) % segments] for j in range(segments)]
    for r in range(rings - 2):
        base = 1 + r * segments
        nxt = (np.arange(segments) + 1) % segments
        faces += [[base + j, base + segments + j, base + segments + n, base + n]
                  for j, n in zip(range(segments), nxt, strict=True)]
    last = 1 + (rings - 2) * segments
    faces.append([last + j for j in range(segments)][::-1])  # the bottom cap as one n-gon
    return points, CageTopology.from_polygons(faces)


@pytest.mark.parametrize(("k", "exponent", "half_space"), [(1, 2.0, True), (4, 2.0, True), (6, 3.0, True),
                                                            (4, 2.0, False)])
def test_pruned_weights_equal_the_dense_computation_on_a_random_cage(
    k: int, exponent: float, half_space: bool
) -> None:
    """cage_weights measures exact distances only where its bounds cannot rule a face out; the result
    must equal measuring every face (the dense reference) to rounding, index sets included."""
    rng = np.random.default_rng(20 + k)
    cage, topo = bumpy_sphere_cage(rng, 14, 9)
    assert check_cage(cage, topo).ok
    direction = rng.normal(size=(3000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = np.concatenate([rng.uniform(0.0, 0.8, 2000),  # inside
                             rng.uniform(0.8, 1.2, 800),  # around the surface: both half-spaces
                             rng.uniform(1.2, 2.0, 200)])  # outside
    points = direction * radius[:, None]
    expected = dense_reference_weights(points, cage, topo, k, exponent, half_space)
    # Rows where the k+1 strongest weights (nearly) tie have no continuous K-sparse value (which side
    # is kept is rounding): compared on the row sums only.
    tie = np.isnan(expected).any(axis=1)
    assert np.count_nonzero(~tie) > 2000
    for chunk in (1, 64):
        idx, val = cage_weights(points, cage, topo, k=k, exponent=exponent, half_space=half_space,
                                chunk_size=chunk)
        got = dense_rows(idx, val, topo.n_faces)
        # The reference expands |p − a|² = |p|² − 2 p·a + |a|², which cancels for vertices near the
        # cage (relative error ~1e-16 |p|²/d²; cage_weights takes p − a first); truncated weights
        # near a rank swap are differences of such distances.
        np.testing.assert_allclose(got[~tie], expected[~tie], rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(got.sum(axis=1), 1.0, rtol=1e-12)


def test_weight_input_errors() -> None:
    points, topo = cube()
    with pytest.raises(ValueError, match="non-finite"):
        _cage_weights(np.array([[np.nan, 0, 0]]), points, topo)
    with pytest.raises(ValueError, match="exponent"):
        _cage_weights(np.zeros((1, 3)), points, topo, exponent=0.0)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        _cage_weights(np.zeros((3,)), points, topo)


# --- validation -------------------------------------------------------------------------------------


def test_closed_outward_cube_validates() -> None:
    points, topo = cube()
    report = validate_cage(points, topo)
    assert report.ok and report.boundary_edges == 0 and report.signed_volume == pytest.approx(1.0)
    assert validate_cage(*mixed_prism()).ok


def test_open_inside_out_inconsistent_nonmanifold_and_zero_area_cages_are_rejected() -> None:
    points, _ = cube()
    cases = {
        "cage is open: 4 boundary edges": CUBE_FACES[:TOP] + CUBE_FACES[TOP + 1 :],
        "cage is inside-out (normals point inward): flip normals": [f[::-1] for f in CUBE_FACES],
        "cage normals are inconsistent: 4 edges": [CUBE_FACES[0][::-1], *CUBE_FACES[1:]],
        "cage is non-manifold: 1 edges": [*CUBE_FACES, [4, 5, 8]],
    }
    pts = np.vstack([points, [0.0, -1.0, 1.0]])
    for message, faces in cases.items():
        report = check_cage(pts, CageTopology.from_polygons(faces))
        assert not report.ok
        assert any(p.startswith(message) for p in report.problems), report.problems
        with pytest.raises(ValueError, match=re.escape(message)):
            validate_cage(pts, CageTopology.from_polygons(faces))
    flat = points.copy()
    flat[[4, 5, 6, 7], 2] = -0.5  # the top collapses onto the bottom
    report = check_cage(flat, CageTopology.from_polygons(CUBE_FACES))
    assert "cage has 4 zero-area face(s): 2, 3, 4, 5" in report.problems
    assert "cage encloses no volume (flat or collapsed)" in report.problems
