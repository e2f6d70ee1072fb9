"""sym(3), the symmetric 3×3 matrices: the compact 6-form (`sym_from6`, `sym_to6`), the closed-form
spectrum (`sym_eigvals`) and the matrix functions exp, log and √ (`sym_exp`, `spd_log`, `spd_sqrt`),
batched over leading axes `(...)` in float64 (aff3 re-exports them; the notation is aff3's).

They are evaluated without eigenvectors: the eigenvalues come from the trigonometric solution of the
characteristic cubic, and f(Y) is the quadratic that interpolates f at them, written in Newton form
centred on the middle eigenvalue e₁ (MATH.md §2–4):

    f(Y) = f(e₁) I + (f[e₁, e₀] − x f[e₁, e₀, e₂]) Z + f[e₁, e₀, e₂] Z²,   Z = Y − e₁ I,

with x = e₀ − e₁ ≤ 0 ≤ y = e₂ − e₁. The second divided difference is a weighted *mean* of two
expm1-type helpers (no cancellation, exact for repeated eigenvalues), and errors of the computed
eigenvalues inside a cluster cancel: the interpolant only sees products of node errors.

Accuracy (tests/core/test_aff3.py): sym_exp matches the exact exponential to ≤ 1e-14 relative for
every spectrum tested (scipy's expm is off by 3e-13 at e^{−6.9} I); spd_log / spd_sqrt are accurate
to ≈ ε·κ(S) normwise.

The array helpers `_float_array`, `_horner` and `_det3` live here, the lowest of the two modules;
aff3 uses them too.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

__all__ = ["spd_log", "spd_sqrt", "sym_eigvals", "sym_exp", "sym_from6", "sym_to6"]

_SQRT3 = float(np.sqrt(3.0))
_EPS = float(np.finfo(np.float64).eps)


# --------------------------------------------------------------------------------------------------
# Array helpers (also aff3's)


def _float_array(a: ArrayLike, tail: tuple[int, ...], name: str) -> FloatArray:
    """`a` as a float64 array whose trailing shape is `tail`; ValueError naming `name` otherwise."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim < len(tail) or arr.shape[arr.ndim - len(tail) :] != tail:
        raise ValueError(f"{name} must have shape (..., {', '.join(map(str, tail))}), got {arr.shape}")
    return arr


def _horner(coeffs: tuple[float, ...], z: FloatArray) -> FloatArray:
    """Σ coeffs[k] z^k."""
    acc = np.full_like(z, coeffs[-1])
    for c in coeffs[-2::-1]:
        acc = acc * z + c
    return acc


def _det3(M: FloatArray) -> FloatArray:
    """det M of (..., 3, 3) by cofactors along the first row (aff3's fast validity check repeats
    this order of operations)."""
    return (
        M[..., 0, 0] * (M[..., 1, 1] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 1])
        - M[..., 0, 1] * (M[..., 1, 0] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 0])
        + M[..., 0, 2] * (M[..., 1, 0] * M[..., 2, 1] - M[..., 1, 1] * M[..., 2, 0])
    )


# --------------------------------------------------------------------------------------------------
# Compact form, spectrum, matrix functions



def sym_from6(y6: ArrayLike) -> FloatArray:
    """(Yxx, Yyy, Yzz, Yxy, Yxz, Yyz) -> symmetric (..., 3, 3)."""
    y6 = _float_array(y6, (6,), "y6")
    xx, yy, zz, xy, xz, yz = np.moveaxis(y6, -1, 0)
    return np.stack(
        [np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], axis=-2
    )


def sym_to6(Y: ArrayLike) -> FloatArray:
    """Symmetric (..., 3, 3) -> (Yxx, Yyy, Yzz, Yxy, Yxz, Yyz); off-diagonals are averaged."""
    Y = _float_array(Y, (3, 3), "Y")
    return np.stack(
        [
            Y[..., 0, 0],
            Y[..., 1, 1],
            Y[..., 2, 2],
            0.5 * (Y[..., 0, 1] + Y[..., 1, 0]),
            0.5 * (Y[..., 0, 2] + Y[..., 2, 0]),
            0.5 * (Y[..., 1, 2] + Y[..., 2, 1]),
        ],
        axis=-1,
    )


# Rows of the 20 3×3 minors of a 6×3 matrix (Cauchy–Binet sum for the discriminant).
_MINOR_ROWS = np.array(list(itertools.combinations(range(6), 3)))


def _centred_spectrum(Y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(e₁, x, y): middle eigenvalue and offsets x = e₀ − e₁ ≤ 0 ≤ y = e₂ − e₁ of symmetric Y.

    Trigonometric solution of the characteristic cubic on the traceless part B = Y − qI, q = tr Y/3,
    scaled to C = B/p, p = √(tr(B²)/6): the eigenvalues of C are 2 cos(φ + 2πk/3) with
    cos 3φ = det(C)/2 and sin 3φ = √(Δ/108), Δ = Π_{i<j}(λᵢ − λⱼ)² the discriminant of C.

    Taking 3φ = arccos(det C/2) alone resolves a tight pair only to ~√ε·p (arccos is singular at
    ±1). Here Δ is computed as a sum of squares (Cauchy–Binet on the Gram matrix of I, C, C²:
    Δ = det[tr C^(i+j)] = Σ over the 20 3×3 minors of [v(I) v(C) v(C²)]², v the trace-inner-product
    coordinates of a symmetric matrix), which is accurate in absolute terms, so 3φ = atan2(sin, cos)
    and every eigenvalue gap come out to ~ε·p. The offsets are formed straight from the angle,
    x = −2√3 p sin φ and y = 2√3 p sin(π/3 − φ), never as a difference of two eigenvalues.
    Exactly repeated eigenvalues give exactly x = 0 or y = 0 whenever the arithmetic is exact.
    """
    y6 = sym_to6(Y)
    q = (y6[..., 0] + y6[..., 1] + y6[..., 2]) / 3.0
    b0, b1, b2 = y6[..., 0] - q, y6[..., 1] - q, y6[..., 2] - q
    o01, o02, o12 = y6[..., 3], y6[..., 4], y6[..., 5]
    p = np.sqrt((b0 * b0 + b1 * b1 + b2 * b2 + 2.0 * (o01 * o01 + o02 * o02 + o12 * o12)) / 6.0)
    inv_p = 1.0 / np.where(p > 0.0, p, 1.0)
    c0, c1, c2 = b0 * inv_p, b1 * inv_p, b2 * inv_p
    d01, d02, d12 = o01 * inv_p, o02 * inv_p, o12 * inv_p
    det = c0 * (c1 * c2 - d12 * d12) - d01 * (d01 * c2 - d12 * d02) + d02 * (d01 * d12 - c1 * d02)
    # C² and the 6×3 matrix W = [v(I), v(C), v(C²)] (off-diagonals weighted by √2)
    s00 = c0 * c0 + d01 * d01 + d02 * d02
    s11 = d01 * d01 + c1 * c1 + d12 * d12
    s22 = d02 * d02 + d12 * d12 + c2 * c2
    s01 = c0 * d01 + d01 * c1 + d02 * d12
    s02 = c0 * d02 + d01 * d12 + d02 * c2
    s12 = d01 * d02 + c1 * d12 + d12 * c2
    one, zero, r2 = np.ones_like(p), np.zeros_like(p), np.sqrt(2.0)
    W = np.stack(
        [
            np.stack([one, c0, s00], -1),
            np.stack([one, c1, s11], -1),
            np.stack([one, c2, s22], -1),
            np.stack([zero, r2 * d01, r2 * s01], -1),
            np.stack([zero, r2 * d02, r2 * s02], -1),
            np.stack([zero, r2 * d12, r2 * s12], -1),
        ],
        axis=-2,
    )
    minors = _det3(W[..., _MINOR_ROWS, :])
    disc = np.einsum("...k,...k->...", minors, minors)
    ang = np.arctan2(np.sqrt(disc / 108.0), 0.5 * det) / 3.0
    x = -2.0 * _SQRT3 * p * np.sin(ang)
    y = 2.0 * _SQRT3 * p * np.sin(np.pi / 3.0 - ang)
    e1 = q - (x + y) / 3.0
    return e1, x, y


def sym_eigvals(Y: ArrayLike) -> FloatArray:
    """Eigenvalues of symmetric Y in ascending order, closed form; (..., 3, 3) -> (..., 3)."""
    Y = _float_array(Y, (3, 3), "Y")
    e1, x, y = _centred_spectrum(Y)
    return np.stack([e1 + x, e1, e1 + y], axis=-1)


def _exp_h1_h2(z: FloatArray) -> tuple[FloatArray, FloatArray]:
    """h1(z) = (eᶻ − 1)/z and h2(z) = (eᶻ − 1 − z)/z², with h2's series Σ zᵏ/(k+2)! for |z| < 0.1."""
    small = np.abs(z) < 0.1
    safe = np.where(small, 1.0, z)
    direct = (np.expm1(safe) - safe) / (safe * safe)
    series = _horner(tuple(1.0 / float(np.prod(np.arange(1, k + 3))) for k in range(11)), z)
    h2 = np.where(small, series, direct)
    return 1.0 + z * h2, h2


def _log_l1_l2(z: FloatArray) -> tuple[FloatArray, FloatArray]:
    """L1(z) = log(1 + z)/z and L2(z) = (log(1 + z) − z)/z², series Σ (−1)^(k+1) zᵏ/(k+2) for |z| < 0.01."""
    small = np.abs(z) < 0.01
    safe = np.where(small, 1.0, z)
    direct = (np.log1p(safe) - safe) / (safe * safe)
    series = _horner(tuple((-1.0) ** (k + 1) / (k + 2) for k in range(9)), z)
    l2 = np.where(small, series, direct)
    return 1.0 + z * l2, l2


def _weighted_second_difference(x: FloatArray, hx: FloatArray, y: FloatArray, hy: FloatArray) -> FloatArray:
    """(y·h(y) − x·h(x))/(y − x) for x ≤ 0 ≤ y: a weighted mean of h(x), h(y), exact when x = y = 0."""
    span = y - x
    safe = np.where(span > 0.0, span, 1.0)
    return np.where(span > 0.0, (y * hy - x * hx) / safe, 0.5 * (hx + hy))


def _quadratic_in(Z: FloatArray, f0: FloatArray, f1: FloatArray, f2: FloatArray) -> FloatArray:
    """f0 I + f1 Z + f2 Z² for symmetric Z, returned exactly symmetric."""
    F = f0[..., None, None] * np.eye(3) + f1[..., None, None] * Z + f2[..., None, None] * (Z @ Z)
    return 0.5 * (F + np.swapaxes(F, -1, -2))


def sym_exp(Y: ArrayLike) -> FloatArray:
    """exp(Y) of symmetric Y, eigenvector-free; (..., 3, 3) -> (..., 3, 3).

    exp(Y) = e^{e₁} (I + (h1(x) − x g) Z + g Z²),  Z = Y − e₁ I,  g = (y h2(y) − x h2(x))/(y − x).
    exp(0) is exactly I.
    """
    Y = _float_array(Y, (3, 3), "Y")
    Ys = 0.5 * (Y + np.swapaxes(Y, -1, -2))
    e1, x, y = _centred_spectrum(Ys)
    h1x, h2x = _exp_h1_h2(x)
    _, h2y = _exp_h1_h2(y)
    g = _weighted_second_difference(x, h2x, y, h2y)
    scale = np.exp(e1)
    Z = Ys - e1[..., None, None] * np.eye(3)
    return _quadratic_in(Z, scale, scale * (h1x - x * g), scale * g)


def _spd_spectrum(S: FloatArray, name: str) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Centred spectrum of SPD S with the smallest eigenvalue kept positive; ValueError if not SPD."""
    e1, x, y = _centred_spectrum(S)
    if not np.all(np.isfinite(e1)):
        raise ValueError(f"{name} has non-finite entries")
    e0 = e1 + x
    scale = np.maximum(np.abs(e1 + y), np.finfo(np.float64).tiny)
    if np.any(e1 <= 0.0) or np.any(e0 <= -8.0 * _EPS * scale):
        raise ValueError(f"{name} is not positive definite")
    # The closed form resolves eigenvalues only to ~ε·‖S‖: a positive one below that may come out
    # as ±0; keep it a positive number of that size so log/√ stay finite.
    floor = _EPS * scale
    x = np.where(e0 < floor, floor - e1, x)
    return e1, x, y


def spd_log(S: ArrayLike) -> FloatArray:
    """log S of a symmetric positive definite S, eigenvector-free; (..., 3, 3) -> (..., 3, 3).

    With ξ = x/e₁, η = y/e₁, Zn = (S − e₁ I)/e₁:
    log S = log e₁ I + (L1(ξ) − ξ G) Zn + G Zn², G = (η L2(η) − ξ L2(ξ))/(η − ξ), where
    L1(z) = log(1 + z)/z and L2(z) = (log(1 + z) − z)/z². Normwise relative accuracy is about
    ε·κ(S) for ill-conditioned S (the quadratic form cancels along the small eigenvectors).
    """
    S = _float_array(S, (3, 3), "S")
    Ss = 0.5 * (S + np.swapaxes(S, -1, -2))
    e1, x, y = _spd_spectrum(Ss, "S")
    xi, eta = x / e1, y / e1
    l1x, l2x = _log_l1_l2(xi)
    _, l2y = _log_l1_l2(eta)
    G = _weighted_second_difference(xi, l2x, eta, l2y)
    Zn = (Ss - e1[..., None, None] * np.eye(3)) / e1[..., None, None]
    return _quadratic_in(Zn, np.log(e1), l1x - xi * G, G)


def spd_sqrt(B: ArrayLike) -> FloatArray:
    """√B of a symmetric positive definite B, eigenvector-free; (..., 3, 3) -> (..., 3, 3).

    With r_i = √λ_i the divided differences of √ have no cancellation at all:
    f[λ₁, λ₀] = 1/(r₀ + r₁),  f[λ₁, λ₀, λ₂] = −1/((r₀ + r₁)(r₁ + r₂)(r₀ + r₂)).
    """
    B = _float_array(B, (3, 3), "B")
    Bs = 0.5 * (B + np.swapaxes(B, -1, -2))
    e1, x, y = _spd_spectrum(Bs, "B")
    r0, r1, r2 = np.sqrt(e1 + x), np.sqrt(e1), np.sqrt(e1 + y)
    d1 = 1.0 / (r0 + r1)
    d2 = -d1 / ((r1 + r2) * (r0 + r2))
    Z = Bs - e1[..., None, None] * np.eye(3)
    return _quadratic_in(Z, r1, d1 - x * d2, d2)

