"""The maps of the Aff+(3) parametrisation (Kaji & Ochiai; course notes section 8), batched.

Every function takes arrays with any leading shape ``(...)`` and works in float64.

Notation: ω ∈ R³ is a rotation vector, θ = |ω|, ω̂ = hat(ω) its skew matrix; u ∈ R³ the translation
part of X = [[ω̂, u], [0, 0]] ∈ se(3); Y ∈ sym(3). The two maps are

    φ(X, Y) = exp(X) · ι(exp(Y)),      ψ(A) = (log(A · ι(S)⁻¹), log S),  S = √(MᵀM),

where M is the 3×3 part of A ∈ Aff+(3) and ι(B) = [[B, 0], [0, 1]].

Closed forms used (θ-coefficients have series near θ = 0, see `_so3_coeffs`):

    exp(ω̂)  = I + (sin θ/θ) ω̂ + ((1 − cos θ)/θ²) ω̂²                                (Rodrigues)
    V(ω)     = I + ((1 − cos θ)/θ²) ω̂ + ((θ − sin θ)/θ³) ω̂²       exp(X) = [[exp(ω̂), V u], [0, 1]]
    V(ω)⁻¹   = I − ½ ω̂ + (1/θ²)(1 − θ sin θ / (2(1 − cos θ))) ω̂²

Functions of a symmetric 3×3 matrix (exp, log, √; eigenvector-free closed forms, MATH.md §2–4) are
core/sym3.py's, re-exported here.

Accuracy (tests/core/test_aff3.py):

* φ(ψ(A)) = A to ≤ 1.1e-14 relative (linear part vs ‖M‖, translation vs ‖t‖ + ‖M‖) on the adversarial
  set (θ ∈ {0, 1e-12, …, π − 1e-9, π}, repeated and clustered stretches down to gaps of 1e-12,
  anisotropy 1e3 : 1e-3, shears, translations to 1e3) and on random matrices. This needs ψ to be
  backward stable: the polar split and log S come from the SVD of M (log S = V log Σ Vᵀ). Forming
  MᵀM, or log S from the closed form on S, loses accuracy in proportion to κ(M) (≈ 1e-10 at
  κ = 1e6), so those routes cannot reach 1e-12; the closed forms are used where they are exact
  enough: exp (any Y) and the kernel.
* ψ(A) matches the exact generating factors to ≈ 4ε·κ(M), which is the conditioning of the polar
  split itself, and scipy's logm to ≤ 1e-9 wherever scipy is accurate (it is off by up to 1e-4
  relative for θ → 0 and by 1e-7 at θ = π − 1e-9, where the tests use the exact factors instead).
* sym_exp, spd_log, spd_sqrt: see core/sym3.py.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .sym3 import (
    _det3,
    _float_array,
    _horner,
    spd_log,
    spd_sqrt,
    sym_eigvals,
    sym_exp,
    sym_from6,
    sym_to6,
)

FloatArray = NDArray[np.float64]

__all__ = [
    "hat",
    "inverse3",
    "left_jacobian",
    "left_jacobian_inv",
    "matrices_from_params",
    "params_from_matrices",
    "params_from_xy",
    "phi",
    "polar",
    "psi",
    "se3_exp",
    "se3_log",
    "so3_exp",
    "so3_log",
    "spd_log",
    "spd_sqrt",
    "sym_eigvals",
    "sym_exp",
    "sym_from6",
    "sym_to6",
    "validate_affine",
    "vee",
    "xy_from_params",
]

#: Largest deviation of a transform's bottom row from (0, 0, 0, 1) that `validate_affine` accepts.
#: Products with a numerically inverted 4×4 can leave ~1e-17 there; anything visible is a real error.
BOTTOM_ROW_TOL = 1e-9

# Up to this many rows, branch and validity checks run on Python floats (a few hundred ns per row)
# instead of numpy reductions (a fixed µs or two of per-call cost each). Checks only: values are
# always computed by the same numpy operations, so results do not depend on the batch size.
_FEW_ROWS = 8


# --------------------------------------------------------------------------------------------------
# Cross products and 3×3 inverses


# Index triples for gathering the last axis with `ndarray.take`: on the few-row batches of the update
# path numpy's per-call cost dominates, and one take replaces three views plus a stack.
_NEXT = np.array([1, 2, 0])
_PREV = np.array([2, 0, 1])


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a × b over the last axis: (a₁b₂ − a₂b₁, a₂b₀ − a₀b₂, a₀b₁ − a₁b₀), each entry rounded as written."""
    return a.take(_NEXT, axis=-1) * b.take(_PREV, axis=-1) - a.take(_PREV, axis=-1) * b.take(_NEXT, axis=-1)


def inverse3(M: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(M⁻¹, det M) for matrices (..., 3, 3): the adjugate over the determinant, adj(M)/det M, whose
    columns are cross products of M's rows (M⁻¹ = [r₁×r₂, r₂×r₀, r₀×r₁]/det, det = r₀·(r₁×r₂)).
    Rows with det M = 0 give non-finite inverses (callers mask them). Vectorised, no LAPACK: batched
    np.linalg.solve costs microseconds per matrix and waits for cores other threads hold."""
    M = np.asarray(M, dtype=np.float64)
    r0, r1, r2 = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    adjugate = np.stack([_cross(r1, r2), _cross(r2, r0), _cross(r0, r1)], axis=-1)
    det = np.einsum("...i,...i->...", r0, adjugate[..., :, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        return adjugate / det[..., None, None], det


# --------------------------------------------------------------------------------------------------
# so(3)


def hat(w: ArrayLike) -> FloatArray:
    """The skew matrix ω̂ with ω̂ v = ω × v; (..., 3) -> (..., 3, 3)."""
    w = _float_array(w, (3,), "w")
    K = np.zeros((*w.shape[:-1], 3, 3))
    K[..., 0, 1] = -w[..., 2]
    K[..., 0, 2] = w[..., 1]
    K[..., 1, 0] = w[..., 2]
    K[..., 1, 2] = -w[..., 0]
    K[..., 2, 0] = -w[..., 1]
    K[..., 2, 1] = w[..., 0]
    return K


# Flat (row-major 3×3) positions of K₂₁, K₀₂, K₁₀ and of K₁₂, K₂₀, K₀₁.
_VEE_PLUS = np.array([7, 2, 3])
_VEE_MINUS = np.array([5, 6, 1])


def vee(K: ArrayLike) -> FloatArray:
    """Inverse of `hat`, applied to the skew part ½(K − Kᵀ); (..., 3, 3) -> (..., 3). vee(hat(ω)) == ω.

    vee(K) = ½ (K₂₁ − K₁₂, K₀₂ − K₂₀, K₁₀ − K₀₁).
    """
    K = _float_array(K, (3, 3), "K")
    flat = K.reshape(*K.shape[:-2], 9)
    return 0.5 * (flat.take(_VEE_PLUS, axis=-1) - flat.take(_VEE_MINUS, axis=-1))


# Below this angle the θ-coefficients switch to their Taylor series (truncation error < 1e-18).
_SERIES_THETA = 0.2
# A bound below 2π (where sin(θ/2) first vanishes again) for skipping the divide-by-zero guard.
_TWO_PI_BELOW = 6.0


def _so3_coeffs(theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(sin θ/θ, (1 − cos θ)/θ², (θ − sin θ)/θ³), each accurate to a few ulps for every θ ≥ 0.

    (1 − cos θ)/θ² = ½ (sin(θ/2)/(θ/2))² has no cancellation; θ − sin θ does, so the third uses its
    series 1/6 − θ²/120 + θ⁴/5040 − θ⁶/362880 + θ⁸/39916800 for θ < 0.2.
    """
    small = theta < _SERIES_THETA
    safe = np.where(theta > 0.0, theta, 1.0)
    a = np.where(theta > 0.0, np.sin(safe) / safe, 1.0)
    half = 0.5 * safe
    sinc_half = np.where(theta > 0.0, np.sin(half) / half, 1.0)
    b = 0.5 * sinc_half * sinc_half
    t2 = theta * theta
    c_series = _horner((1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800), t2)
    big = np.where(small, 1.0, theta)
    c_direct = (big - np.sin(big)) / (big * big * big)
    c = np.where(small, c_series, c_direct)
    return a, b, c


def _all_within(x: FloatArray, low: float, high: float) -> bool:
    """low ≤ min(x) and max(x) < high, for choosing a branch; NaN entries may go either way (callers
    only use it where a NaN row gives the same NaN on both branches). Empty x gives False."""
    if x.size == 0:
        return False
    if x.size <= _FEW_ROWS:  # Python's min/max on a short list cost less than two numpy reductions
        values = x.ravel().tolist()
        return low <= min(values) and max(values) < high
    return bool(low <= x.min() and x.max() < high)


def _jacobian_inv_coeff(theta: FloatArray) -> FloatArray:
    """(1/θ²)(1 − θ sin θ / (2(1 − cos θ))) = (1 − (θ/2) cot(θ/2))/θ², the ω̂² coefficient of V⁻¹.

    Series 1/12 + θ²/720 + θ⁴/30240 + θ⁶/1209600 + θ⁸/47900160 below θ = 0.2. Infinite at θ = 2π,
    where V is singular (only reachable with a lifted rotation vector).
    """
    if _all_within(theta, _SERIES_THETA, _TWO_PI_BELOW):
        # Every row takes the closed form (the usual case on the update path): skipping the series and
        # the select gives the same bits, and below 2π sin(θ/2) > 0 needs no error-state guard.
        half = 0.5 * theta
        return (1.0 - half * np.cos(half) / np.sin(half)) / (theta * theta)
    small = theta < _SERIES_THETA
    safe = np.where(small, 1.0, theta)
    half = 0.5 * safe
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = (1.0 - half * np.cos(half) / np.sin(half)) / (safe * safe)
    series = _horner((1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160), theta * theta)
    return np.where(small, series, direct)


def _norm3(w: FloatArray) -> FloatArray:
    return np.sqrt(np.einsum("...i,...i->...", w, w))


def so3_exp(w: ArrayLike) -> FloatArray:
    """R = exp(ω̂) = I + (sin θ/θ) ω̂ + ((1 − cos θ)/θ²) ω̂² (Rodrigues); (..., 3) -> (..., 3, 3)."""
    w = _float_array(w, (3,), "w")
    a, b, _ = _so3_coeffs(_norm3(w))
    K = hat(w)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_log(R: ArrayLike) -> FloatArray:
    """Principal rotation vector ω (|ω| ≤ π) with exp(ω̂) = R; (..., 3, 3) -> (..., 3).

    θ = atan2(|s|, (tr R − 1)/2) with s = vee(R) = sin θ · n, accurate over [0, π]. For θ ≤ π/2,
    ω = (θ / sin θ) s (ratio → 1 at θ = 0). For θ > π/2 the skew part vanishes as θ → π, so the axis
    is read from the symmetric part (R + Rᵀ)/2 − cos θ I = (1 − cos θ) n nᵀ (its largest column) and
    its sign from s (MATH.md §6). At θ = π exactly both signs are valid; the one returned is arbitrary.
    """
    R = _float_array(R, (3, 3), "R")
    flat = R.reshape(*R.shape[:-2], 9)
    s = 0.5 * (flat.take(_VEE_PLUS, axis=-1) - flat.take(_VEE_MINUS, axis=-1))  # vee(R)
    sin_t = _norm3(s)
    # minimum/maximum instead of np.clip: the same numbers (NaN included) at a third of the call cost
    cos_t = np.minimum(np.maximum(0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0), -1.0), 1.0)
    theta = np.arctan2(sin_t, cos_t)

    if sin_t.size == 0:
        return np.zeros(s.shape)
    # The branch tests use min(): it is NaN when any row is, and NaN selects the general path.
    if sin_t.min() > 0.0:  # no select needed (the usual case): the same bits as the guarded ratio
        w_skew = (theta / sin_t)[..., None] * s
    else:
        positive = sin_t > 0.0
        ratio = np.where(positive, theta / np.where(positive, sin_t, 1.0), 1.0)
        w_skew = ratio[..., None] * s
    if cos_t.min() >= 0.0:  # no rotation past π/2: the axis branch would not be selected
        return w_skew

    sym = 0.5 * (R + np.swapaxes(R, -1, -2)) - cos_t[..., None, None] * np.eye(3)
    k = np.argmax(np.diagonal(sym, axis1=-2, axis2=-1), axis=-1)
    col = np.take_along_axis(sym, k[..., None, None], axis=-1)[..., 0]
    col_norm = _norm3(col)
    axis = col / np.where(col_norm > 0.0, col_norm, 1.0)[..., None]
    sign = np.where(np.einsum("...i,...i->...", axis, s) < 0.0, -1.0, 1.0)
    w_sym = (sign * theta)[..., None] * axis

    return np.where((cos_t < 0.0)[..., None], w_sym, w_skew)


def left_jacobian(w: ArrayLike) -> FloatArray:
    """V(ω) = I + ((1 − cos θ)/θ²) ω̂ + ((θ − sin θ)/θ³) ω̂²; (..., 3) -> (..., 3, 3)."""
    w = _float_array(w, (3,), "w")
    _, b, c = _so3_coeffs(_norm3(w))
    K = hat(w)
    return np.eye(3) + b[..., None, None] * K + c[..., None, None] * (K @ K)


def left_jacobian_inv(w: ArrayLike) -> FloatArray:
    """V(ω)⁻¹ = I − ½ ω̂ + (1/θ²)(1 − θ sin θ/(2(1 − cos θ))) ω̂²; (..., 3) -> (..., 3, 3).

    Valid for θ < 2π (V is singular at θ = 2π).
    """
    w = _float_array(w, (3,), "w")
    d = _jacobian_inv_coeff(_norm3(w))
    K = hat(w)
    return np.eye(3) - 0.5 * K + d[..., None, None] * (K @ K)


# --------------------------------------------------------------------------------------------------
# se(3)


def se3_exp(w: ArrayLike, u: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """exp([[ω̂, u], [0, 0]]) = [[R, t], [0, 1]] with R = exp(ω̂), t = V(ω) u (MATH.md §5).

    t = u + ((1 − cos θ)/θ²) ω × u + ((θ − sin θ)/θ³) ω × (ω × u), so ω = 0 gives t = u exactly.
    """
    w = _float_array(w, (3,), "w")
    u = _float_array(u, (3,), "u")
    a, b, c = _so3_coeffs(_norm3(w))
    K = hat(w)
    R = np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)
    wu = _cross(w, u)
    t = u + b[..., None] * wu + c[..., None] * _cross(w, wu)
    return R, t


def se3_log(R: ArrayLike, t: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """log([[R, t], [0, 1]]) = [[ω̂, u], [0, 0]] with ω = so3_log(R), u = V(ω)⁻¹ t (MATH.md §6).

    u = t − ½ ω × t + d(θ) ω × (ω × t); a pure translation (R = I) gives u = t exactly.
    """
    R = _float_array(R, (3, 3), "R")
    t = _float_array(t, (3,), "t")
    w = so3_log(R)
    d = _jacobian_inv_coeff(_norm3(w))
    # the two cross products ω × t and ω × (ω × t) of `_cross`, sharing the permutations of ω
    w_next, w_prev = w.take(_NEXT, axis=-1), w.take(_PREV, axis=-1)
    wt = w_next * t.take(_PREV, axis=-1) - w_prev * t.take(_NEXT, axis=-1)
    wwt = w_next * wt.take(_PREV, axis=-1) - w_prev * wt.take(_NEXT, axis=-1)
    u = t - 0.5 * wt + d[..., None] * wwt
    return w, u


# --------------------------------------------------------------------------------------------------
# Polar split, validation, phi / psi


def _polar_svd(M: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """(R, Vh, σ, U): M = U diag(σ) Vh, R = U Vh. Backward stable, unlike √(MᵀM) (which squares κ(M))."""
    try:
        U, sigma, Vh = np.linalg.svd(M)
    except np.linalg.LinAlgError as exc:  # only for non-finite or pathological input
        raise ValueError(f"cannot split the linear part into rotation and stretch: {exc}") from None
    return U @ Vh, Vh, sigma, U


def polar(M: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Polar split M = R·S, R orthogonal, S = √(MᵀM) symmetric positive semi-definite.

    Computed from the SVD M = U Σ Vᵀ (R = U Vᵀ, S = V Σ Vᵀ): forming MᵀM would square the condition
    number and lose half the digits of a strongly anisotropic M. R is a rotation when det M > 0.
    """
    M = _float_array(M, (3, 3), "M")
    R, Vh, sigma, _ = _polar_svd(M)
    S = np.swapaxes(Vh, -1, -2) @ (sigma[..., :, None] * Vh)
    return R, 0.5 * (S + np.swapaxes(S, -1, -2))


#: The smallest singular value `nearest_positive` lets a degenerate motion keep (a control scaled to
#: zero acts as one scaled to this: the limit of the nearby valid poses, without log 0 = −∞).
SCALE_FLOOR = 1e-6


def nearest_positive(A: ArrayLike, pivot: ArrayLike, floor: float = SCALE_FLOOR) -> FloatArray:
    """The motion of Aff+(3) that a collapsed motion A (4, 4) stands for: A itself when every singular
    value of its 3×3 part M = U Σ Vᵀ is at least `floor`, else U diag(max(σ, floor)) Vᵀ, with the
    control's `pivot` (its rest origin, (3,)) keeping its image A · pivot. So what a control scaled to
    zero holds collapses onto it, as a bone scaled to zero collapses its vertices in Blender's
    Armature modifier, and scale 0 gives the shape of scale `floor`: the limit of the nearby valid
    poses. ValueError for a mirrored A (det M < 0), which no valid pose approaches."""
    A = np.array(A, dtype=np.float64)
    M = A[:3, :3]
    U, s, Vt = np.linalg.svd(M)
    if s.min() >= floor and np.linalg.det(M) > 0.0:
        return A
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        if s.min() >= floor:
            raise ValueError("the motion is mirrored")
        U = U * np.array([1.0, 1.0, -1.0])  # σ₃ ≈ 0: the sign of its direction is free
    M_new = (U * np.maximum(s, floor)) @ Vt
    p = np.asarray(pivot, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = M_new
    out[:3, 3] = M @ p + A[:3, 3] - M_new @ p
    return out


def _where(flat_index: int, lead: tuple[int, ...]) -> str:
    if len(lead) <= 1:
        return f"{flat_index}"
    return f"{flat_index} (index {tuple(int(i) for i in np.unravel_index(flat_index, lead))})"


# Flat (row-major 4×4) positions for the 2×2 cofactors of the 3×3 part, in `_det3`'s order:
# (m₁₁m₂₂, m₁₀m₂₂, m₁₀m₂₁) − (m₁₂m₂₁, m₁₂m₂₀, m₁₁m₂₀).
_COF_A = np.array([5, 4, 4])
_COF_B = np.array([10, 10, 9])
_COF_C = np.array([6, 6, 5])
_COF_D = np.array([9, 8, 8])
_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])
# The fast check's bounds on |A − [[0, 0], [0, 1]]| entrywise: the 3×4 top below 1e100 (so every
# product in `_det3` stays finite and needs no error state), the bottom row within BOTTOM_ROW_TOL.
_IDENTITY_BOTTOM16 = np.concatenate([np.zeros(12), _BOTTOM])
_ENTRY_BOUND16 = np.concatenate([np.full(12, 1e100), np.full(4, BOTTOM_ROW_TOL)])


def _affine_rows_ok_scalar(rows: list[list[float]]) -> bool:
    """`_affine_rows_ok` on Python floats: the same IEEE operations in the same order as `_det3`.

    A non-finite sum means a non-finite entry or an overflow; either way the full check decides.
    """
    tol = BOTTOM_ROW_TOL
    for r in rows:
        if not math.isfinite(sum(r)):
            return False
        if not (abs(r[12]) <= tol and abs(r[13]) <= tol and abs(r[14]) <= tol and abs(r[15] - 1.0) <= tol):
            return False
        det = (
            r[0] * (r[5] * r[10] - r[6] * r[9])
            - r[1] * (r[4] * r[10] - r[6] * r[8])
            + r[2] * (r[4] * r[9] - r[5] * r[8])
        )
        if not det > 0.0:
            return False
    return True


def _affine_rows_ok(flat: FloatArray) -> bool:
    """True if every 4×4 of flat (m, 16) is certainly accepted by `validate_affine` (a cheap pre-check).

    Finite entries below 1e100 in size, bottom row within BOTTOM_ROW_TOL of (0, 0, 0, 1), and
    det > 0 with det evaluated exactly as `_det3` rounds it. False means "run the full check", so
    the answer of `validate_affine` never depends on which pre-check ran.
    """
    if flat.shape[0] <= _FEW_ROWS:
        return _affine_rows_ok_scalar(flat.tolist())
    if not (np.abs(flat - _IDENTITY_BOTTOM16) <= _ENTRY_BOUND16).all():  # also False for NaN
        return False
    cof = flat.take(_COF_A, axis=1) * flat.take(_COF_B, axis=1) - flat.take(_COF_C, axis=1) * flat.take(
        _COF_D, axis=1
    )
    terms = flat[:, 0:3] * cof
    det = terms[:, 0] - terms[:, 1] + terms[:, 2]
    return bool(det.min() > 0.0)


def validate_affine(A: ArrayLike, name: str = "transform") -> FloatArray:
    """A as float64 (..., 4, 4) if every matrix is in Aff+(3); else ValueError naming the first bad one.

    Rejected: non-finite entries, a bottom row other than (0, 0, 0, 1) (tolerance BOTTOM_ROW_TOL),
    det of the 3×3 part ≤ 0 (mirrored or collapsed). The index is the flat index over the leading
    axes (and the multi-index when there is more than one leading axis).
    """
    A = _float_array(A, (4, 4), name)
    if _affine_rows_ok(A.reshape(-1, 16)):
        return A
    return _validate_affine_full(A, name)


def _validate_affine_full(A: FloatArray, name: str) -> FloatArray:
    """The checks of `validate_affine` on every row, with the message for the first bad one."""
    lead = A.shape[:-2]
    flat = A.reshape(-1, 4, 4)
    finite = np.isfinite(flat).all(axis=(1, 2))
    bottom = np.abs(flat[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        det = _det3(flat[:, :3, :3])
    bad = ~finite | ~(bottom <= BOTTOM_ROW_TOL) | ~(det > 0.0)
    if np.any(bad):
        i = int(np.argmax(bad))
        where = _where(i, lead)
        if not finite[i]:
            raise ValueError(f"{name} {where} has non-finite entries (NaN or inf)")
        if not bottom[i] <= BOTTOM_ROW_TOL:
            raise ValueError(
                f"{name} {where} is not affine: bottom row {flat[i, 3].tolist()} != [0, 0, 0, 1]"
            )
        raise ValueError(
            f"{name} {where} has determinant {det[i]:.6g} <= 0 (mirrored or collapsed); "
            "only orientation-preserving transforms can be blended"
        )
    return A


def psi(A: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """ψ(A) = (X, Y) = (log(A ι(S)⁻¹), log S), S = √(MᵀM); (..., 4, 4) -> ((..., 4, 4), (..., 3, 3)).

    With the SVD M = U Σ Vᵀ: A ι(S)⁻¹ = [[U Vᵀ, t], [0, 1]] and Y = V log(Σ) Vᵀ, which is accurate to
    ε·|log σ| even when M is strongly anisotropic. ω is on the principal branch |ω| ≤ π.
    ValueError (naming the first bad index) unless every A is in Aff+(3).
    """
    A = validate_affine(A)
    M = A[..., :3, :3]
    t = A[..., :3, 3]
    R, Vh, sigma, _ = _polar_svd(M)
    log_sigma = np.log(sigma)
    Y = np.swapaxes(Vh, -1, -2) @ (log_sigma[..., :, None] * Vh)
    Y = 0.5 * (Y + np.swapaxes(Y, -1, -2))
    w, u = se3_log(R, t)
    X = np.zeros(A.shape)
    X[..., :3, :3] = hat(w)
    X[..., :3, 3] = u
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
        bad = ~(np.isfinite(X).all(axis=(-2, -1)) & np.isfinite(Y).all(axis=(-2, -1)))
        i = int(np.argmax(bad.reshape(-1)))
        raise ValueError(f"transform {_where(i, A.shape[:-2])} is too degenerate to take its logarithm")
    return X, Y


def phi(X: ArrayLike, Y: ArrayLike) -> FloatArray:
    """φ(X, Y) = exp(X) ι(exp(Y)) = [[R(ω) exp(Y), V(ω) u], [0, 1]]; φ(0, 0) is exactly I.

    X (..., 4, 4) in se(3) (its skew part and last column are read), Y (..., 3, 3) symmetric.
    """
    X = _float_array(X, (4, 4), "X")
    Y = _float_array(Y, (3, 3), "Y")
    R, t = se3_exp(vee(X[..., :3, :3]), X[..., :3, 3])
    E = sym_exp(Y)
    lead = np.broadcast_shapes(R.shape[:-2], E.shape[:-2])
    A = np.zeros((*lead, 4, 4))
    A[..., :3, :3] = R @ E
    A[..., :3, 3] = t
    A[..., 3, 3] = 1.0
    return A


# --------------------------------------------------------------------------------------------------
# The 12-number layout (docs/DEVELOPING.md): ω (0:3), u (3:6), Y as (xx, yy, zz, xy, xz, yz) (6:12)


def params_from_xy(X: ArrayLike, Y: ArrayLike) -> FloatArray:
    """(X (..., 4, 4), Y (..., 3, 3)) -> P (..., 12)."""
    X = _float_array(X, (4, 4), "X")
    Y = _float_array(Y, (3, 3), "Y")
    w = vee(X[..., :3, :3])
    u = X[..., :3, 3]
    y6 = sym_to6(Y)
    lead = np.broadcast_shapes(w.shape[:-1], y6.shape[:-1])
    return np.concatenate(
        [np.broadcast_to(w, (*lead, 3)), np.broadcast_to(u, (*lead, 3)), np.broadcast_to(y6, (*lead, 6))],
        axis=-1,
    )


def xy_from_params(P: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """P (..., 12) -> (X (..., 4, 4), Y (..., 3, 3))."""
    P = _float_array(P, (12,), "params")
    X = np.zeros((*P.shape[:-1], 4, 4))
    X[..., :3, :3] = hat(P[..., 0:3])
    X[..., :3, 3] = P[..., 3:6]
    return X, sym_from6(P[..., 6:12])


# Flat (row-major 3×3) positions of (xx, yy, zz, xy, xz, yz) and of their transposes.
_SYM6_UPPER = np.array([0, 4, 8, 1, 2, 5])
_SYM6_LOWER = np.array([0, 4, 8, 3, 6, 7])


def params_from_matrices(
    A: ArrayLike, polar: Callable[[FloatArray], tuple[FloatArray, FloatArray] | None] | None = None
) -> FloatArray:
    """ψ in the 12-number layout: A (..., 4, 4) -> P (..., 12). ValueError on invalid A.

    Bit for bit params_from_xy(*psi(A)) (vee(hat(ω)) = ω and the averaged off-diagonals of the
    exactly symmetric Y are exact), without forming X: the Blender layer calls this once per update
    for the one or two controls that moved, where numpy's per-call overhead is the whole cost.

    polar: optional faster evaluation of the polar split, M (n, 3, 3) ↦ (R = U Vᵀ, Ŷ = V diag(log σ)
    Vᵀ) for the SVD M = U diag(σ) Vᵀ, or None to use numpy's SVD here (`accel.polar_log`: the
    compiled kernel's, the same quantities to ~1e-15 relative).
    """
    A = validate_affine(A)
    lead = A.shape[:-2]
    flat = A.reshape(-1, 4, 4)
    split = None if polar is None else polar(flat[:, :3, :3])
    if split is None:
        R, Vh, sigma, _ = _polar_svd(flat[:, :3, :3])
        Yh = (Vh.transpose(0, 2, 1) @ (np.log(sigma)[:, :, None] * Vh)).reshape(-1, 9)
    else:
        R, Yh = split[0], split[1].reshape(-1, 9)
    w, u = se3_log(R, flat[:, :3, 3])
    # Y = ½(Ŷ + Ŷᵀ) read straight into the layout: ½(Ŷᵢᵢ + Ŷᵢᵢ) = Ŷᵢᵢ exactly, off-diagonals averaged.
    y6 = 0.5 * (Yh.take(_SYM6_UPPER, axis=1) + Yh.take(_SYM6_LOWER, axis=1))
    P = np.concatenate([w, u, y6], axis=1)
    # A finite sum of a short batch proves every entry finite; otherwise (or on overflow) numpy decides.
    few_and_finite = P.shape[0] <= _FEW_ROWS and math.isfinite(sum(P.ravel().tolist()))
    if not few_and_finite and not np.isfinite(P).all():
        bad = ~np.isfinite(P).all(axis=-1)
        i = int(np.argmax(bad))
        raise ValueError(f"transform {_where(i, lead)} is too degenerate to take its logarithm")
    return P.reshape(*lead, 12)


def matrices_from_params(P: ArrayLike) -> FloatArray:
    """φ in the 12-number layout: P (..., 12) -> A (..., 4, 4)."""
    return phi(*xy_from_params(P))
