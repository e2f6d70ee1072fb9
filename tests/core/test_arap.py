"""The shape-preserving pass's numpy core (affine_deformers/core/arap, MATH.md §15): the elements'
gradient operator, the refusal of degenerate elements, the assembly against scipy and against the
cotangent formula, anchors and the null space, the dense reference against scipy's sparse solve, the
numpy solver against the reference, exactness (shared affine and rigid motions, the rest pose) and
the quality the pass is for."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from affine_deformers.core import aff3, arap, deform
from tests.core.arap_rigs import bend_rig, box_bar, quality, rig_weights, twist_rig
from tests.core.conftest import random_affine

# ------------------------------------------------------------------------------------------- helpers


def _scipy_matrix(elements: arap.Elements, anchors: np.ndarray) -> sp.csr_matrix:
    """L = Σ_t w_t g gᵀ + diag α, assembled independently with scipy (duplicates summed by COO)."""
    C, G, w = elements.corners, elements.gradients, elements.weights
    K = C.shape[1]
    rows, cols, vals = [], [], []
    for a in range(K):
        for b in range(K):
            rows.append(C[:, a])
            cols.append(C[:, b])
            vals.append(w * np.einsum("ts,ts->t", G[:, a], G[:, b]))
    n = elements.n_vertices
    L = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return (L + sp.diags(anchors)).tocsr()


def _as_scipy(system: arap.ArapSystem) -> sp.csr_matrix:
    A = system.matrix
    return sp.csr_matrix((A.data, A.indices, A.indptr), shape=A.shape)


def _rig_case(n_side: int, rig, strength: float = arap.ANCHOR_STRENGTH) -> SimpleNamespace:
    """A box bar bound to a rig: P, T, el, system, field, motions and the weights idx, val (vertices),
    eidx, evals (elements, at their centroids)."""
    P, T = box_bar(n_side)
    el = arap.triangle_elements(P, T)
    idx, val = rig_weights(P, rig)
    eidx, evals = rig_weights(el.centroids, rig)
    system = arap.bind_system(el, arap.anchor_weights(el, idx, val, strength=strength))
    field = deform.deform_points_params(P, rig.params, idx, val)
    motions = deform.vertex_motions(rig.params, eidx, evals)
    return SimpleNamespace(P=P, T=T, el=el, system=system, field=field, motions=motions, idx=idx, val=val,
                           eidx=eidx, evals=evals)


def _shared(rig_params: np.ndarray, G: np.ndarray) -> np.ndarray:
    return np.repeat(aff3.params_from_matrices(G)[None], rig_params.shape[0], axis=0)


# ------------------------------------------------------------------------------------------ elements


def test_triangle_gradients_reproduce_affine_maps_on_the_plane() -> None:
    rng = np.random.default_rng(1)
    P, T = box_bar(3)
    P = P + rng.normal(scale=0.02, size=P.shape)  # no two triangles alike
    el = arap.triangle_elements(P, T)
    assert np.abs(el.gradients.sum(axis=1)).max() < 1e-13  # Σ g = 0: translations have no gradient
    p = P[T]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.allclose(el.weights, 0.5 * np.linalg.norm(n, axis=1))
    assert np.allclose(el.normals, n / np.linalg.norm(n, axis=1, keepdims=True))
    assert np.abs(np.einsum("tks,ts->tk", el.gradients, el.normals)).max() < 1e-12  # in-plane
    M = random_affine(rng, 1)[0]
    F = arap.element_gradients(el, P @ M[:3, :3].T + M[:3, 3])
    proj = np.eye(3) - np.einsum("ti,tj->tij", el.normals, el.normals)
    assert np.abs(F - M[:3, :3] @ proj).max() < 1e-11 * np.abs(M[:3, :3]).max()
    assert np.allclose(el.centroids, p.mean(axis=1))


def _cube_tets() -> tuple[np.ndarray, np.ndarray]:
    P = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    # the unit cube as six tetrahedra around its diagonal 0–7
    T = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    return P, T


def test_tetrahedron_gradients_are_complete() -> None:
    P, T = _cube_tets()
    el = arap.tetrahedron_elements(P, T)
    assert el.kind == "TETRAHEDRA" and abs(el.weights.sum() - 1.0) < 1e-14
    M = random_affine(np.random.default_rng(2), 1)[0]
    F = arap.element_gradients(el, P @ M[:3, :3].T + M[:3, 3])
    assert np.abs(F - M[:3, :3]).max() < 1e-12 * np.abs(M).max()
    assert not el.normals.any()


@pytest.mark.parametrize("case", ["collinear", "repeated", "sliver"])
def test_degenerate_triangles_are_refused_with_the_fix(case: str) -> None:
    P, T = box_bar(2)
    T = T.copy()
    if case == "repeated":
        T[5, 2] = T[5, 0]
    elif case == "collinear":
        P = np.vstack([P, [[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [2.0, 0.0, 5.0]]])
        T = np.vstack([T[:5], [[len(P) - 3, len(P) - 2, len(P) - 1]], T[5:]])
    else:
        P = np.vstack([P, [[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.5, 1e-9, 5.0]]])
        T = np.vstack([T[:5], [[len(P) - 3, len(P) - 2, len(P) - 1]], T[5:]])
    fix = r"triangle 5, .*Merge by Distance.*Degenerate Dissolve"
    with pytest.raises(arap.DegenerateElementsError, match=fix):
        arap.triangle_elements(P, T)
    assert issubclass(arap.DegenerateElementsError, ValueError)


def test_degenerate_tetrahedra_and_bad_inputs_are_refused() -> None:
    P, T = _cube_tets()
    flat = np.vstack([T, [[0, 1, 2, 3]]])  # four coplanar corners of a face
    with pytest.raises(arap.DegenerateElementsError, match=r"zero volume .*tetrahedron 6, vertices 0, 1, 2"):
        arap.tetrahedron_elements(P, flat)
    with pytest.raises(ValueError, match=r"in \[0, 8\)"):
        arap.tetrahedron_elements(P, T + 1)
    with pytest.raises(ValueError, match="non-finite"):
        arap.triangle_elements(np.full((3, 3), np.nan), [[0, 1, 2]])
    with pytest.raises(ValueError, match=r"shape \(E, 3\)"):
        arap.triangle_elements(np.eye(3), [[0.0, 1.0, 2.0]])


# ---------------------------------------------------------------------------------------- assembly


def test_assembly_matches_scipy_and_the_cotangent_laplacian() -> None:
    rng = np.random.default_rng(3)
    P, T = box_bar(4)
    P = P + rng.normal(scale=0.05, size=P.shape)
    el = arap.triangle_elements(P, T)
    alpha = rng.random(P.shape[0])
    system = arap.bind_system(el, alpha)
    L = _as_scipy(system)
    assert abs(L - _scipy_matrix(el, alpha)).max() < 1e-12
    assert abs(L - L.T).max() < 1e-13
    assert np.allclose(L @ np.ones(P.shape[0]), alpha)  # constants: only the anchors see them
    # the element part is the P1 stiffness matrix: L_ij = −½ (cot α_ij + cot β_ij)
    stiff = (L - sp.diags(alpha)).tocoo()
    expected = {}
    for tri in T:
        for c in range(3):
            o, i, j = tri[c], tri[(c + 1) % 3], tri[(c + 2) % 3]
            u, v = P[i] - P[o], P[j] - P[o]
            cot = u @ v / np.linalg.norm(np.cross(u, v))
            for a, b in ((i, j), (j, i)):
                expected[(a, b)] = expected.get((a, b), 0.0) - 0.5 * cot
    off = stiff.row != stiff.col
    pairs = zip(stiff.row[off].tolist(), stiff.col[off].tolist(), strict=True)
    got = dict(zip(pairs, stiff.data[off], strict=True))
    assert got.keys() == expected.keys()
    assert max(abs(got[k] - expected[k]) for k in got) < 1e-12


def test_every_part_is_anchored_and_the_matrix_positive_definite() -> None:
    P, T = box_bar(2)
    pts = np.vstack([P, P + np.array([10.0, 0.0, 0.0]), [[50.0, 0.0, 0.0]]])  # two bars and a loose vertex
    tris = np.vstack([T, T + len(P)])
    el = arap.triangle_elements(pts, tris)
    alpha = np.zeros(len(pts))
    alpha[:3] = 1.0  # only the first bar is anchored
    system = arap.bind_system(el, alpha)
    assert system.loose_parts == 1
    assert np.all(system.anchors[len(P):2 * len(P)] > 0.0) and system.anchors[-1] == 1.0
    assert np.array_equal(system.anchors[:len(P)], alpha[:len(P)])
    assert np.linalg.eigvalsh(_as_scipy(system).toarray()).min() > 0.0
    with pytest.raises(ValueError, match="finite and ≥ 0"):
        arap.bind_system(el, -alpha)


def test_anchor_weights_follow_the_controls_and_not_the_scale() -> None:
    rig = bend_rig(4.0, np.pi / 2)
    P, T = box_bar(6)
    el = arap.triangle_elements(P, T)
    idx, val = rig_weights(P, rig)
    alpha = arap.anchor_weights(el, idx, val, strength=10.0)
    near = np.linalg.norm(P[:, None, :] - rig.centers[None], axis=2).min(axis=1)
    areas = arap.vertex_areas(el)
    kappa = alpha / (10.0 * areas / areas.sum())  # α = s κ m / A
    assert kappa.max() <= 1.0 + 1e-12 and kappa[near < 0.4].min() > 0.95
    assert kappa[near > 0.7].mean() < 0.5 * kappa[near < 0.55].mean()
    strict = arap.anchor_weights(el, idx, val, strength=10.0, level=0.9)  # only next to the probes
    assert strict[near < 0.4].min() > 0.0 and strict[near > 0.6].max() == 0.0
    assert 0.0 < alpha.sum() <= 10.0
    assert not arap.anchor_weights(el, idx, val, strength=0.0).any()
    # dimensionless: scaling the mesh changes nothing; refining it keeps the total
    big = arap.triangle_elements(P * 7.0, T)
    assert np.allclose(arap.anchor_weights(big, idx, val, strength=10.0), alpha)
    P2, T2 = box_bar(12)
    el2 = arap.triangle_elements(P2, T2)
    alpha2 = arap.anchor_weights(el2, *rig_weights(P2, rig), strength=10.0)
    assert abs(alpha2.sum() / alpha.sum() - 1.0) < 0.15
    # a pooled column (index ≥ controls) anchors nothing
    pooled = np.full_like(idx, rig.centers.shape[0])
    assert not arap.anchor_weights(el, pooled, val, controls=rig.centers.shape[0]).any()


def test_element_weights_average_the_corners() -> None:
    rng = np.random.default_rng(4)
    P, T = box_bar(3)
    el = arap.triangle_elements(P, T)
    dense = rng.random((len(P), 7)) ** 4
    dense /= dense.sum(axis=1, keepdims=True)
    order = np.argsort(-dense, axis=1)[:, :3]
    idx = order.astype(np.int32)
    val = np.take_along_axis(dense, order, axis=1)
    eidx, evals = arap.element_weights(el, idx, val)
    sparse_dense = np.zeros_like(dense)
    np.put_along_axis(sparse_dense, order, val, axis=1)
    expect = sparse_dense[T].mean(axis=1)
    got = np.zeros_like(expect)
    np.add.at(got, (np.repeat(np.arange(len(T)), eidx.shape[1]), eidx.ravel()), evals.ravel())
    assert np.abs(got - expect).max() < 1e-15
    assert eidx.dtype == np.int32 and np.all(np.diff(np.where(evals > 0, eidx, 99), axis=1)[:, :1] != 0)


# ------------------------------------------------------------------------------------------- solving


def test_the_reference_and_scipy_agree() -> None:
    c = _rig_case(4, bend_rig(4.0, np.pi / 2))
    el, system, field, motions = c.el, c.system, c.field, c.motions
    targets = arap.linear_maps(motions)
    ref = arap.reference_positions(el, system.anchors, motions, field)
    r = arap.right_hand_side(el, targets, field)
    x = field + spl.spsolve(_as_scipy(system).tocsc(), r)
    assert np.abs(x - ref).max() < 1e-10 * np.abs(ref).max()
    # the normal equations' right-hand side Σ w T g + α y, solved for x directly, is the same
    b = np.einsum("t,trs,tks->tkr", el.weights, targets, el.gradients)
    rhs = np.stack([np.bincount(el.corners.ravel(), b[..., r].ravel(), minlength=el.n_vertices)
                    for r in range(3)], axis=1)
    direct = spl.spsolve(_as_scipy(system).tocsc(), rhs + system.anchors[:, None] * field)
    assert np.abs(direct - ref).max() < 1e-9 * np.abs(ref).max()


@pytest.mark.parametrize("iterations", [1, 2, 3])
def test_the_numpy_solver_matches_the_reference(iterations: int) -> None:
    c = _rig_case(4, twist_rig(4.0, 1.5 * np.pi))
    solver = arap.NumpyArapSolver(c.system)
    x = solver.frame(c.motions, c.field, iterations)
    ref = arap.reference_positions(c.el, c.system.anchors, c.motions, c.field, iterations)
    assert np.abs(x - ref).max() < 1e-8 * np.abs(ref).max()
    out = np.empty_like(x)
    assert solver.frame(c.motions, c.field, iterations, out=out) is out and np.allclose(out, x)


@pytest.mark.parametrize("motion", ["affine", "rigid", "rest", "far"])
def test_a_motion_shared_by_every_control_is_exact(motion: str) -> None:
    rng = np.random.default_rng(5)
    rig = bend_rig(4.0, np.pi / 2)
    c = _rig_case(6, rig)
    P, T = c.P, c.T
    G = np.eye(4)
    if motion == "affine":
        G = random_affine(rng, 1, log_scale=0.5, t_scale=10.0)[0]
    elif motion in ("rigid", "far"):
        G[:3, :3] = aff3.so3_exp(rng.normal(size=3))
        G[:3, 3] = rng.normal(size=3) * (1e3 if motion == "far" else 1.0)
    params = _shared(rig.params, G)
    field = deform.deform_points_params(P, params, c.idx, c.val)
    motions = deform.vertex_motions(params, c.eidx, c.evals)
    expect = P @ G[:3, :3].T + G[:3, 3]
    solver = arap.NumpyArapSolver(c.system)
    for iterations in (1, 2, 3):
        x = solver.frame(motions, field, iterations)
        assert np.abs(x - expect).max() <= 1e-12 * np.abs(expect).max(), iterations
    if motion in ("rigid", "far"):  # a rigid result: every distance kept
        d0 = np.linalg.norm(P[T[:, 0]] - P[T[:, 1]], axis=1)
        d1 = np.linalg.norm(x[T[:, 0]] - x[T[:, 1]], axis=1)
        assert np.abs(d1 - d0).max() < 1e-12 * max(1.0, np.abs(expect).max())


def test_a_shared_motion_is_exact_on_tetrahedra() -> None:
    P, T = _cube_tets()
    el = arap.tetrahedron_elements(P, T)
    system = arap.bind_system(el, np.r_[1.0, np.zeros(7)])
    G = random_affine(np.random.default_rng(6), 1)[0]
    motions = np.repeat(G[None], len(T), axis=0)
    expect = P @ G[:3, :3].T + G[:3, 3]
    for iterations in (1, 2):
        x = arap.reference_positions(el, system.anchors, motions, expect, iterations)
        assert np.abs(x - expect).max() < 1e-12 * np.abs(expect).max()
        x = arap.NumpyArapSolver(system).frame(motions, expect, iterations)
        assert np.abs(x - expect).max() < 1e-12 * np.abs(expect).max()


def test_the_pass_keeps_edge_lengths_better_than_the_field() -> None:
    """What the pass is for: on the 90° elbow the field compresses the inner side and stretches the
    outer one; the pass spreads the bend (edge-length distortion and roughness well below the field's)."""
    c = _rig_case(8, bend_rig(4.0, np.pi / 2))
    before = quality(c.P, c.field, c.T)
    after = quality(c.P, arap.NumpyArapSolver(c.system).frame(c.motions, c.field), c.T)
    assert after.edge_max < 0.8 * before.edge_max and after.edge_p99 < 0.8 * before.edge_p99
    assert after.roughness < 0.7 * before.roughness
    assert after.volume_ratio > 0.85


# ------------------------------------------------------------------------------- the extra iteration


def test_nearest_rotations_and_stretch() -> None:
    rng = np.random.default_rng(7)
    A = random_affine(rng, 50)[:, :3, :3]
    R, S = aff3.polar(A)
    assert np.allclose(arap.stretch_parts(A), S, atol=1e-12)
    assert np.allclose(arap.closest_rotations(A), R, atol=1e-12)
    flipped = A * np.array([1.0, 1.0, -1.0])  # det < 0: still a rotation
    Q = arap.closest_rotations(flipped)
    assert np.allclose(np.linalg.det(Q), 1.0) and np.allclose(Q @ np.swapaxes(Q, 1, 2), np.eye(3), atol=1e-12)


def test_swapped_targets_keep_the_blended_stretch() -> None:
    """Where the solved gradient already is R S (in the plane), the swap returns R S; in general its
    stretch is the blended one: (R S)ᵀ(R S) = S²."""
    rng = np.random.default_rng(8)
    P, T = box_bar(2)
    el = arap.triangle_elements(P, T)
    M = random_affine(rng, 1)[0]
    x = P @ M[:3, :3].T
    targets = np.repeat(M[None, :3, :3], len(T), axis=0)
    S = arap.stretch_parts(targets)
    assert np.abs(arap.swapped_targets(el, x, targets, S) - targets).max() < 1e-12 * np.abs(M).max()
    other = arap.swapped_targets(el, x + rng.normal(scale=0.1, size=x.shape), targets, S)
    assert np.allclose(np.swapaxes(other, 1, 2) @ other, S @ S, atol=1e-12)


def test_arguments_are_checked() -> None:
    c = _rig_case(2, bend_rig(4.0, 0.3))
    el, field, motions = c.el, c.field, c.motions
    with pytest.raises(ValueError, match="iterations"):
        arap.solve_frame(el, lambda b: b, motions, field, 0)
    with pytest.raises(ValueError, match="field must have shape"):
        arap.solve_frame(el, lambda b: b, motions, field[:-1])
    with pytest.raises(ValueError, match="motions must be"):
        arap.linear_maps(motions[:, :-1], el.count)
    assert np.array_equal(arap.linear_maps(motions), arap.linear_maps(arap.linear_maps(motions)))
    big = arap.Elements(el.corners, el.gradients, el.weights, el.normals, el.centroids, 10**6)
    with pytest.raises(ValueError, match="at most"):
        arap.reference_positions(big, np.zeros(10**6), motions, np.zeros((10**6, 3)))


def test_bind_triangles_is_the_steps_and_stays_exact_with_averaged_weights() -> None:
    """The one-call bind equals its steps; with element weights averaged from the corners (what a
    painted or surface weight mode gives) a shared motion is still exact."""
    rig = twist_rig(4.0, np.pi)
    P, T = box_bar(4)
    idx, val = rig_weights(P, rig)
    bound = arap.bind_triangles(P, T, idx, val, strength=30.0)
    el = arap.triangle_elements(P, T)
    steps = arap.bind_system(el, arap.anchor_weights(el, idx, val, strength=30.0))
    assert np.array_equal(bound.system.matrix.data, steps.matrix.data)
    e_idx, e_val = arap.element_weights(el, idx, val)
    assert np.array_equal(bound.indices, e_idx) and np.array_equal(bound.values, e_val)
    G = random_affine(np.random.default_rng(9), 1, log_scale=0.3)[0]
    params = _shared(rig.params, G)
    x = arap.NumpyArapSolver(bound.system).frame(deform.vertex_motions(params, bound.indices, bound.values),
                                                 deform.deform_points_params(P, params, idx, val), 2)
    expect = P @ G[:3, :3].T + G[:3, 3]
    assert np.abs(x - expect).max() < 1e-12 * np.abs(expect).max()
    given = rig_weights(el.centroids, rig)
    assert np.array_equal(arap.bind_triangles(P, T, idx, val, at_elements=given).values, given[1])
    with pytest.raises(ValueError, match="element weights must have shape"):
        arap.bind_triangles(P, T, idx, val, at_elements=(given[0][:-1], given[1][:-1]))
    painted = arap.bind_triangles(P, T, idx, val, anchors=np.full(len(P), 0.5))
    assert np.all(painted.system.anchors == 0.5)
