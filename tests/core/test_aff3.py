"""The Aff+(3) maps (core/aff3.py) against scipy.linalg expm/logm/sqrtm/polar and exact ground truth.

Where scipy is itself inaccurate (logm of a rotation by θ → 0 or θ → π loses up to 1e-4 relative
there) the maps are checked against the exact generating parameters and through scipy's expm, which
stays accurate in those regimes.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.linalg as sl
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from affine_deformers import core
from affine_deformers.core import aff3
from tests.core.conftest import ANGLES, AXES, GAPS, STRETCH_FRAME, AffCase, random_affine, rotation

EPS = np.finfo(np.float64).eps


def rel(a: np.ndarray, b: np.ndarray, floor: float = 0.0) -> float:
    """‖a − b‖_F / max(‖b‖_F, floor)."""
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), floor, 1e-300))


def logm_real(M: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns about its own accuracy near π
        return np.real(sl.logm(M))


def block4(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    G = np.eye(4)
    G[:3, :3] = R
    G[:3, 3] = t
    return G


def spd(eigs: tuple[float, float, float], frame: np.ndarray = STRETCH_FRAME) -> np.ndarray:
    S = frame @ np.diag(eigs) @ frame.T
    return 0.5 * (S + S.T)


SPECTRA_Y = [
    (0.0, 0.0, 0.0),
    (0.7, 0.7, 0.7),
    (-6.9, -6.9, -6.9),
    (0.3, 0.3, 2.0),
    (-1.0, 0.5, 0.5),
    (-6.9, 0.0, 6.9),
    (-6.9, -6.9, 6.9),
    (-6.9, 6.9, 6.9),
    *[(0.3, 0.3 + g, 2.0) for g in GAPS],
    *[(-1.0, 0.5, 0.5 + g) for g in GAPS],
    *[(0.7, 0.7 + g, 0.7 + 2 * g) for g in GAPS],
]


# --------------------------------------------------------------------------------------------------
# so(3)


def test_hat_vee() -> None:
    rng = np.random.default_rng(1)
    w, v = rng.normal(size=(2, 50, 3))
    K = aff3.hat(w)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", K, v), np.cross(w, v), rtol=0, atol=1e-14)
    assert np.array_equal(aff3.vee(K), w)
    assert np.array_equal(K, -np.swapaxes(K, -1, -2))


@pytest.mark.parametrize("angle", ANGLES)
@pytest.mark.parametrize("axis", range(len(AXES)))
def test_so3_exp_matches_expm(angle: float, axis: int) -> None:
    w = angle * AXES[axis]
    R = aff3.so3_exp(w)
    assert rel(R, sl.expm(aff3.hat(w))) <= 1e-14
    assert rel(R, rotation(AXES[axis], angle)) <= 1e-14


@pytest.mark.parametrize("angle", ANGLES)
@pytest.mark.parametrize("axis", range(len(AXES)))
def test_so3_log(angle: float, axis: int) -> None:
    w = angle * AXES[axis]
    R = sl.expm(aff3.hat(w))
    got = aff3.so3_log(R)
    # principal branch, and a logarithm according to scipy's (accurate) expm
    assert np.linalg.norm(got) <= np.pi * (1 + 4 * EPS)
    assert rel(sl.expm(aff3.hat(got)), R) <= 1e-14
    if angle < np.pi:
        # relative accuracy even at θ = 1e-12 (series branch) and θ = π − 1e-9 (symmetric-part branch)
        assert rel(got, w) <= 1e-13 if angle > 0 else np.array_equal(got, np.zeros(3))
    else:  # θ = π: both ±π·n are logarithms
        assert min(rel(got, w), rel(got, -w)) <= 1e-14
    if 1e-5 <= angle <= np.pi - 1e-6:  # where scipy's logm is itself accurate
        assert rel(aff3.hat(got), logm_real(R)) <= 1e-9


def test_so3_log_is_batched_and_handles_all_branches_at_once() -> None:
    w = np.stack([a * AXES[i % 4] for i, a in enumerate(ANGLES[:-1])])
    got = aff3.so3_log(aff3.so3_exp(w))
    np.testing.assert_allclose(got, w, rtol=1e-13, atol=0)


def test_left_jacobian_and_inverse() -> None:
    for angle in (*ANGLES[:-1], 0.1999999, 0.2, 0.2000001, 3.0):
        for axis in AXES:
            w = angle * axis
            V = aff3.left_jacobian(w)
            X = np.zeros((4, 4))
            X[:3, :3] = aff3.hat(w)
            # V is the translation block of exp([[ω̂, I], [0, 0]]) column by column
            ref = np.stack(
                [sl.expm(X + np.pad(np.eye(3)[:, [j]], ((0, 1), (3, 0))))[:3, 3] for j in range(3)], 1
            )
            assert rel(V, ref) <= 1e-13
            assert rel(aff3.left_jacobian_inv(w) @ V, np.eye(3)) <= 1e-14


def test_jacobian_inverse_series_is_continuous_at_the_switch() -> None:
    # (1 − (θ/2)cot(θ/2))/θ² from its series (θ < 0.2) and from the closed form (θ ≥ 0.2)
    below = aff3._jacobian_inv_coeff(np.array([0.2 - 1e-12]))
    above = aff3._jacobian_inv_coeff(np.array([0.2]))
    assert abs(below[0] - above[0]) <= 1e-14
    assert aff3._jacobian_inv_coeff(np.array([0.0]))[0] == 1 / 12


# --------------------------------------------------------------------------------------------------
# se(3)


@pytest.mark.parametrize("angle", ANGLES)
def test_se3_exp_log_against_scipy(angle: float) -> None:
    for axis in AXES:
        for t_scale in (0.0, 1e-3, 1.0, 1e3):
            w = angle * axis
            u = t_scale * np.array([0.3, -1.0, 2.0])
            X = np.zeros((4, 4))
            X[:3, :3] = aff3.hat(w)
            X[:3, 3] = u
            R, t = aff3.se3_exp(w, u)
            assert rel(block4(R, t), sl.expm(X)) <= 1e-14
            w2, u2 = aff3.se3_log(R, t)
            X2 = np.zeros((4, 4))
            X2[:3, :3] = aff3.hat(w2)
            X2[:3, 3] = u2
            assert rel(sl.expm(X2), block4(R, t)) <= 1e-14
            if angle < np.pi:
                assert rel(w2, w) <= 1e-13 or angle == 0
                assert rel(u2, u) <= 1e-13 or t_scale == 0
            if 1e-5 <= angle <= np.pi - 1e-6:
                assert rel(X2, logm_real(block4(R, t)), floor=1.0) <= 1e-9


def test_pure_translation_survives_exactly() -> None:
    for t in (np.array([1e3, -2.0, 3e-4]), np.array([0.0, 0.0, 1e-300]), np.array([-7.5, 0.25, 1e3])):
        w, u = aff3.se3_log(np.eye(3), t)
        assert np.array_equal(w, np.zeros(3)) and np.array_equal(u, t)
        R, t2 = aff3.se3_exp(w, u)
        assert np.array_equal(R, np.eye(3)) and np.array_equal(t2, t)
        A = block4(np.eye(3), t)
        X, Y = aff3.psi(A)
        assert np.array_equal(X[:3, 3], t) and not np.any(X[:3, :3]) and not np.any(Y)
        assert np.array_equal(aff3.phi(X, Y), A)


# --------------------------------------------------------------------------------------------------
# sym(3)


@pytest.mark.parametrize("eigs", SPECTRA_Y, ids=str)
def test_sym_exp_against_expm(eigs: tuple[float, float, float]) -> None:
    Y = spd(eigs)
    E = aff3.sym_exp(Y)
    assert rel(E, sl.expm(Y)) <= 1e-12  # scipy's scaling and squaring is off by 3e-13 at e^-6.9 I
    assert rel(E, spd(tuple(np.exp(eigs)))) <= 1e-14
    assert np.array_equal(E, E.T)


def test_sym_exp_of_zero_is_exactly_identity() -> None:
    assert np.array_equal(aff3.sym_exp(np.zeros((3, 3))), np.eye(3))
    assert np.array_equal(aff3.sym_exp(np.zeros((5, 2, 3, 3))), np.broadcast_to(np.eye(3), (5, 2, 3, 3)))


@pytest.mark.parametrize("eigs", SPECTRA_Y, ids=str)
def test_spd_log_and_sqrt_against_scipy(eigs: tuple[float, float, float]) -> None:
    lam = tuple(np.exp(eigs))  # eigenvalues 1e-3 … 1e3 with the same clusters
    S = spd(lam)
    L = aff3.spd_log(S)
    assert rel(L, logm_real(S), floor=1.0) <= 1e-9
    assert rel(L, spd(eigs), floor=1.0) <= 1e-9
    root = aff3.spd_sqrt(S)
    assert rel(root, sl.sqrtm(S).real) <= 1e-9
    assert rel(root, spd(tuple(np.sqrt(lam)))) <= 1e-12
    assert rel(root @ root, S) <= 1e-12


def test_spd_sqrt_of_squared_anisotropic_matrix() -> None:
    # eigenvalues 1e-6 … 1e6 (κ = 1e12): rounding B alone moves √B by ~1e-10 relative, so compare
    # with scipy on the same rounded B and check the square
    B = spd((1e-6, 1.0, 1e6))
    root = aff3.spd_sqrt(B)
    assert rel(root, sl.sqrtm(B).real) <= 1e-9
    assert rel(root @ root, B) <= 1e-12
    assert rel(root, spd((1e-3, 1.0, 1e3))) <= 1e-9


def test_spd_functions_reject_indefinite_input() -> None:
    with pytest.raises(ValueError, match="positive definite"):
        aff3.spd_log(spd((-1.0, 1.0, 2.0)))
    with pytest.raises(ValueError, match="positive definite"):
        aff3.spd_sqrt(-np.eye(3))
    with pytest.raises(ValueError, match="non-finite"):
        aff3.spd_log(np.full((3, 3), np.nan))


def test_sym_eigvals() -> None:
    rng = np.random.default_rng(3)
    Y = rng.normal(size=(200, 3, 3))
    Y = Y + np.swapaxes(Y, -1, -2)
    got = aff3.sym_eigvals(Y)
    ref = np.linalg.eigvalsh(Y)
    scale = np.abs(ref).max(axis=1, keepdims=True)
    assert np.all(np.abs(got - ref) <= 1e-13 * scale)
    assert np.all(np.diff(got, axis=1) >= 0)
    # a tight pair is resolved only to ~√ε·p (the matrix functions do not need more: see aff3)
    pair = aff3.sym_eigvals(spd((0.3, 0.3 + 1e-12, 2.0)))
    np.testing.assert_allclose(pair, [0.3, 0.3, 2.0], rtol=0, atol=1e-7)


def test_sym_compact_layout() -> None:
    y6 = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    Y = aff3.sym_from6(y6)
    assert np.array_equal(Y, [[1, 4, 5], [4, 2, 6], [5, 6, 3]])
    assert np.array_equal(aff3.sym_to6(Y), y6)


# --------------------------------------------------------------------------------------------------
# polar, validation


def test_polar_matches_scipy() -> None:
    rng = np.random.default_rng(5)
    A = random_affine(rng, 50, log_scale=2.0)
    R, S = aff3.polar(A[:, :3, :3])
    for i in range(50):
        Rr, Sr = sl.polar(A[i, :3, :3])
        assert rel(R[i], Rr) <= 1e-12 and rel(S[i], Sr) <= 1e-12
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=1e-14, rtol=0)
    assert np.all(np.linalg.det(R) > 0)
    assert np.array_equal(S, np.swapaxes(S, -1, -2))
    np.testing.assert_allclose(R @ S, A[:, :3, :3], rtol=0, atol=1e-12 * np.abs(A).max())


def _bad_batch(bad: np.ndarray, at: tuple[int, ...], shape: tuple[int, ...] = (2, 3)) -> np.ndarray:
    A = np.broadcast_to(np.eye(4), (*shape, 4, 4)).copy()
    A[at] = bad
    return A


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (np.diag([1.0, 1.0, -1.0, 1.0]), r"transform 4 \(index \(1, 1\)\) has determinant -1"),
        (np.diag([1.0, 0.0, 1.0, 1.0]), r"transform 4 \(index \(1, 1\)\) has determinant 0"),
        (np.where(np.eye(4) > 0, np.nan, 0.0), r"transform 4 \(index \(1, 1\)\) has non-finite"),
        (np.where(np.eye(4) > 0, np.inf, 0.0), r"transform 4 \(index \(1, 1\)\) has non-finite"),
        (
            np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0.5, 0, 1.0]]),
            r"transform 4 .* bottom row",
        ),
        (np.diag([1.0, 1.0, 1.0, 2.0]), r"transform 4 .* bottom row"),
    ],
)
def test_validate_affine_names_the_first_bad_index(bad: np.ndarray, message: str) -> None:
    A = _bad_batch(bad, (1, 1))
    A[1, 2] = np.diag([1.0, -1.0, 1.0, 1.0])  # a later bad one must not be reported first
    with pytest.raises(ValueError, match=message):
        aff3.validate_affine(A)
    with pytest.raises(ValueError, match=message):
        aff3.psi(A)


def test_validate_affine_flat_index_and_shape() -> None:
    A = np.broadcast_to(np.eye(4), (5, 4, 4)).copy()
    A[3, :3, :3] *= -1.0
    with pytest.raises(ValueError, match=r"^transform 3 has determinant"):
        core.psi(A)
    with pytest.raises(ValueError, match="shape"):
        aff3.validate_affine(np.eye(3))
    assert aff3.validate_affine(np.eye(4)).dtype == np.float64


# --------------------------------------------------------------------------------------------------
# psi / phi


def test_phi_of_zero_is_exactly_identity() -> None:
    assert np.array_equal(core.phi(np.zeros((4, 4)), np.zeros((3, 3))), np.eye(4))
    assert np.array_equal(aff3.matrices_from_params(np.zeros((7, 12))), np.broadcast_to(np.eye(4), (7, 4, 4)))
    assert np.array_equal(aff3.params_from_matrices(np.eye(4)), np.zeros(12))


def _roundtrip_errors(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative errors of φ(ψ(A)): linear part vs ‖M‖, translation vs ‖t‖ + ‖M‖."""
    B = core.phi(*core.psi(A))
    M, t = A[..., :3, :3], A[..., :3, 3]
    nM = np.linalg.norm(M, axis=(-2, -1))
    eM = np.linalg.norm(B[..., :3, :3] - M, axis=(-2, -1)) / nM
    et = np.linalg.norm(B[..., :3, 3] - t, axis=-1) / (np.linalg.norm(t, axis=-1) + nM)
    assert np.array_equal(B[..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], B[..., 3, :].shape))
    return eM, et


def test_roundtrip_adversarial(adversarial: list[AffCase]) -> None:
    A = np.stack([c.matrix for c in adversarial])
    eM, et = _roundtrip_errors(A)
    assert eM.max() <= 1e-12, adversarial[int(eM.argmax())].name
    assert et.max() <= 1e-12, adversarial[int(et.argmax())].name


def test_roundtrip_random_1000(random_1000: np.ndarray) -> None:
    eM, et = _roundtrip_errors(random_1000)
    assert eM.max() <= 1e-12 and et.max() <= 1e-12
    eM, et = _roundtrip_errors(random_affine(np.random.default_rng(9), 200, log_scale=3.0, t_scale=1e3))
    assert eM.max() <= 1e-12 and et.max() <= 1e-12


def _scipy_psi(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, S = sl.polar(A[:3, :3])
    return logm_real(block4(R, A[:3, 3])), logm_real(S)


def test_psi_against_scipy_adversarial(adversarial: list[AffCase]) -> None:
    A = np.stack([c.matrix for c in adversarial])
    X, Y = core.psi(A)
    for i, case in enumerate(adversarial):
        assert rel(Y[i], _scipy_psi(A[i])[1], floor=1.0) <= 1e-9, case.name
        # X is a logarithm of [[R, t], [0, 1]] (checked with scipy's expm, accurate everywhere), R the
        # rotation of the polar split: without shear the generating rotation itself, exact, to the
        # split's conditioning 4εκ(M) (two LAPACK builds' polar splits of one matrix differ by that
        # much, so neither is the reference at κ = 1e6); with shear scipy's polar split.
        sigma = np.linalg.svd(A[i, :3, :3], compute_uv=False)
        if case.shear:
            R, bound = sl.polar(A[i, :3, :3])[0], 1e-12
        else:
            R, bound = rotation(case.axis, case.angle), max(1e-12, 4 * EPS * sigma[0] / sigma[-1])
        assert rel(sl.expm(X[i]), block4(R, A[i, :3, 3])) <= bound, case.name
        assert np.linalg.norm(aff3.vee(X[i, :3, :3])) <= np.pi * (1 + 4 * EPS)
        # ... and equals scipy's logm where scipy is accurate (it is not within 1e-6 of π)
        if case.angle <= np.pi - 1e-6:
            assert rel(X[i], _scipy_psi(A[i])[0], floor=1.0) <= 1e-9, case.name


def test_psi_against_ground_truth(adversarial: list[AffCase]) -> None:
    """Against the generating factors, to within the conditioning of the polar split (≈ ε·κ(M))."""
    cases = [c for c in adversarial if c.shear == 0.0]
    P = aff3.params_from_matrices(np.stack([c.matrix for c in cases]))
    for p, c in zip(P, cases, strict=True):
        kappa = max(c.sigma) / min(c.sigma)
        tol = 50 * EPS * kappa
        candidates = [c.angle * c.axis] + ([-np.pi * c.axis] if c.angle == np.pi else [])
        w = min(candidates, key=lambda w: np.linalg.norm(p[:3] - w))
        assert np.linalg.norm(p[:3] - w) <= tol, c.name
        assert np.linalg.norm(p[3:6] - aff3.left_jacobian_inv(w) @ c.t) <= tol * (np.linalg.norm(c.t) + 1), (
            c.name
        )
        Y = STRETCH_FRAME @ np.diag(np.log(c.sigma)) @ STRETCH_FRAME.T
        assert np.linalg.norm(aff3.sym_from6(p[6:]) - Y) <= tol, c.name


def test_psi_against_scipy_random(random_1000: np.ndarray) -> None:
    X, Y = core.psi(random_1000)
    for i in range(0, 1000, 5):  # scipy's logm costs ~1 ms; every fifth matrix keeps the run short
        Xr, Yr = _scipy_psi(random_1000[i])
        assert rel(X[i], Xr, floor=1.0) <= 1e-9 and rel(Y[i], Yr, floor=1.0) <= 1e-9


def test_phi_against_scipy(random_1000: np.ndarray) -> None:
    X, Y = core.psi(random_1000[:200])
    A = core.phi(X, Y)
    for i in range(200):
        ref = sl.expm(X[i]) @ sl.block_diag(sl.expm(Y[i]), 1.0)
        assert rel(A[i], ref) <= 1e-12


def test_params_layout_roundtrip(random_1000: np.ndarray) -> None:
    P = aff3.params_from_matrices(random_1000[:50])
    X, Y = aff3.xy_from_params(P)
    assert np.array_equal(aff3.params_from_xy(X, Y), P)
    assert np.array_equal(P[:, 0:3], aff3.vee(core.psi(random_1000[:50])[0][:, :3, :3]))
    np.testing.assert_allclose(
        aff3.matrices_from_params(P), random_1000[:50], rtol=0, atol=1e-12 * np.abs(random_1000[:50]).max()
    )


def test_rigid_inputs_give_rigid_blends() -> None:
    rng = np.random.default_rng(11)
    w = rng.normal(size=(6, 3))
    w *= (rng.uniform(0, np.pi, 6) / np.linalg.norm(w, axis=1))[:, None]
    A = np.stack([block4(aff3.so3_exp(wi), rng.normal(size=3) * 5) for wi in w])
    P = aff3.params_from_matrices(A)
    assert np.abs(P[:, 6:]).max() <= 4 * EPS  # Y = log S = 0 up to the rounding of S = I
    weights = rng.dirichlet(np.ones(6), size=100)
    B = aff3.matrices_from_params(weights @ P)
    M = B[:, :3, :3]
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", M, M), np.broadcast_to(np.eye(3), M.shape), atol=1e-14
    )
    np.testing.assert_allclose(np.linalg.det(M), 1.0, rtol=0, atol=1e-14)


def test_equal_motions_blend_to_themselves(random_1000: np.ndarray) -> None:
    rng = np.random.default_rng(12)
    P = aff3.params_from_matrices(random_1000[:20])
    for i in range(20):
        weights = rng.dirichlet(np.ones(5))
        B = aff3.matrices_from_params(weights @ np.broadcast_to(P[i], (5, 12)))
        assert rel(B, random_1000[i]) <= 1e-13


def test_contract_names_exported() -> None:
    for name in ("phi", "psi", "deform_points"):
        assert callable(getattr(core, name))


# --------------------------------------------------------------------------------------------------
# properties

finite = st.floats(-1.0, 1.0, allow_nan=False, width=64)


@st.composite
def params(draw: st.DrawFn) -> np.ndarray:
    """Parameters of a motion: |ω| < π (principal branch), moderate stretch, translations to 1e3."""
    axis = draw(hnp.arrays(np.float64, 3, elements=finite))
    axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 0.1 else np.array([0.0, 0.0, 1.0])
    w = draw(st.floats(0.0, np.pi * 0.999999)) * axis
    u = draw(hnp.arrays(np.float64, 3, elements=finite)) * draw(st.sampled_from([0.0, 1e-3, 1.0, 1e3]))
    y = draw(hnp.arrays(np.float64, 6, elements=finite)) * draw(st.sampled_from([0.0, 1e-8, 0.1, 2.0]))
    return np.concatenate([w, u, y])


@settings(max_examples=150, deadline=None)
@given(params())
def test_property_psi_inverts_phi(p: np.ndarray) -> None:
    A = aff3.matrices_from_params(p)
    eM, et = _roundtrip_errors(A)
    assert eM <= 1e-12 and et <= 1e-12
    q = aff3.params_from_matrices(A)
    # the parameters themselves come back (ψ is the inverse of φ on the principal branch)
    np.testing.assert_allclose(q, p, rtol=0, atol=1e-9 * (1 + np.abs(p).max()))


@settings(max_examples=100, deadline=None)
@given(st.lists(params(), min_size=2, max_size=5), st.data())
def test_property_rigid_and_common_motion_blends(ps: list[np.ndarray], data: st.DataObject) -> None:
    P = np.stack(ps)
    raw = np.array(data.draw(st.lists(st.floats(0.01, 1.0), min_size=len(ps), max_size=len(ps))))
    w = raw / raw.sum()
    rigid = P.copy()
    rigid[:, 6:] = 0.0
    M = aff3.matrices_from_params(w @ rigid)[:3, :3]
    np.testing.assert_allclose(M.T @ M, np.eye(3), rtol=0, atol=1e-13)
    assert abs(np.linalg.det(M) - 1.0) <= 1e-13
    common = aff3.matrices_from_params(w @ np.broadcast_to(P[0], P.shape))
    A0 = aff3.matrices_from_params(P[0])
    assert rel(common, A0) <= 1e-13


def test_inverse3_matches_numpy_and_flags_singular_matrices():
    from affine_deformers.core.aff3 import inverse3

    rng = np.random.default_rng(3)
    M = rng.normal(size=(500, 3, 3))
    M[0] = np.diag([1e3, 1.0, 1e-3])  # anisotropic
    M[1, 2] = M[1, 0] + M[1, 1]  # singular
    inv, det = inverse3(M)
    np.testing.assert_allclose(det, np.linalg.det(M), rtol=1e-10, atol=1e-12)
    good = np.abs(det) > 1e-9
    np.testing.assert_allclose(inv[good] @ M[good], np.broadcast_to(np.eye(3), (good.sum(), 3, 3)),
                               atol=1e-9)
    assert abs(det[1]) < 1e-12 and not good[1]


# ------------------------------------------------------------------------- degenerate controls


_DIRECTION = hnp.arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)).filter(
    lambda a: np.linalg.norm(a) > 0.1)


@settings(max_examples=60, deadline=None)
@given(axis=_DIRECTION, angle=st.floats(-3.0, 3.0), other=_DIRECTION, other_angle=st.floats(-3.0, 3.0),
       scales=hnp.arrays(np.float64, 3, elements=st.floats(0.05, 4.0)), zeros=st.integers(1, 3),
       pivot=hnp.arrays(np.float64, 3, elements=st.floats(-5.0, 5.0)),
       shift=hnp.arrays(np.float64, 3, elements=st.floats(-5.0, 5.0)))
def test_a_collapsed_motion_is_the_one_of_its_scales_raised_to_the_floor(axis, angle, other, other_angle,
                                                                        scales, zeros, pivot, shift):
    """A = R diag(s) Qᵀ with `zeros` singular values 0 (a control scaled to zero on that many axes),
    built from its exact factors: nearest_positive gives R diag(max(s, floor)) Qᵀ, which keeps the
    pivot's image; the limit of the nearby valid poses (rank 2 determines the rotation; rank ≤ 1
    leaves the null space's rotation free, so only the singular values and the pivot are checked)."""
    R = aff3.so3_exp(axis / np.linalg.norm(axis) * angle)
    Q = aff3.so3_exp(other / np.linalg.norm(other) * other_angle)
    s = scales.copy()
    s[:zeros] = 0.0
    A = np.eye(4)
    A[:3, :3] = R @ np.diag(s) @ Q.T
    A[:3, 3] = shift
    out = aff3.nearest_positive(A, pivot)
    floor = aff3.SCALE_FLOOR
    singular = np.sort(np.linalg.svd(out[:3, :3])[1])
    assert np.allclose(singular, np.sort(np.maximum(s, floor)), rtol=1e-9, atol=1e-12)
    assert np.linalg.det(out[:3, :3]) > 0.0
    assert np.allclose(out[:3, :3] @ pivot + out[:3, 3], A[:3, :3] @ pivot + A[:3, 3], atol=1e-9)
    if zeros == 1:
        assert np.allclose(out[:3, :3], R @ np.diag(np.maximum(s, floor)) @ Q.T, atol=1e-9)


def test_a_motion_in_aff3_is_kept_and_a_mirrored_one_refused():
    A = random_affine(np.random.default_rng(5), 1)[0]
    assert np.array_equal(aff3.nearest_positive(A, np.zeros(3)), A)
    mirrored = A.copy()
    mirrored[:3, 0] *= -1.0
    with pytest.raises(ValueError, match="mirrored"):
        aff3.nearest_positive(mirrored, np.zeros(3))
