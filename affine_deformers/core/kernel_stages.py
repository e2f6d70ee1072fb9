"""The stages of the per-vertex map, on (n,) rows with in-place ufuncs: core/kernel.py runs them on
each chunk's scratch rows (the compiled kernel's pieces have the same names, in the same order).

Both maps run the same stages (module-level functions on rows, named as the compiled kernel's
pieces): `_exp_sym_coeffs` (spectrum of Y → E, α', g', Z), then `_exp_sym_apply` (exp(Y) v) or
`_exp_sym_matrix` (exp(Y) = E I + α' Z + g' Z²), `_rotation_coeffs` (A, B, C, cos θ, with the exact
fallback past 1.8π) and `_rigid` (R e + V u; the motion map calls it with u = 0 on the columns of
exp(Y) and with e = 0 for t). Scratch rows go from stage to stage through `_FreeRows`.

Per row:

* exp(Y) v = e^{e₁} (v + α Z v + g Z² v), Z = Y − e₁ I, from the closed-form spectrum of Y
  (trigonometric cubic on the traceless part) and the divided differences of aff3, written with
  e₁ the middle eigenvalue, x = e₀ − e₁ ≤ 0 ≤ y = e₂ − e₁, g = (y h2(y) − x h2(x))/(y − x),
  α = 1 + x (h2(x) − g), h2(z) = (eᶻ − 1 − z)/z²;
* R w + V u = cos θ w + A u + ω × (A w + B u) + (B ω·w + C ω·u) ω with A = sin θ/θ,
  B = (1 − cos θ)/θ², C = (θ − sin θ)/θ³ (R = cos θ I + A ω̂ + B ωωᵀ, V = A I + B ω̂ + C ωωᵀ).

numpy's float64 sin/cos are scalar code, ~50× slower per element than a multiply; the kernel uses a
Taylor polynomial for sin(θ/4)/(θ/4) in θ²/16 (θ ≤ 1.8π; beyond, a np.sin fallback on those rows),
cos(θ/4) = √(1 − sin²(θ/4)) and double-angle formulas; the eigen-angle a = arccos(r)/3 ≤ π/3 gets
sin a from the same polynomial and cos a = √(1 − sin² a). Branches near 0 are replaced by clamps
whose error is bounded where they are applied, so there is no masked work.

Accuracy: ≤ 2e-15 relative to ‖M‖‖v‖ + ‖t‖ against aff3.phi on an adversarial parameter set (tests).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32]

# The quarter-angle polynomials are used for θ ≤ 1.8π, where cos(θ/4) = √(1 − sin²(θ/4)) ≥ 0.15 is
# well conditioned; larger θ (lifted rotations past ±324°) take the np.sin/np.cos fallback.
_POLY_MAX_S = (1.8 * math.pi) ** 2
#: Rows whose blended Y has every |entry| ≤ SMALL_Y (rigid controls: Y is float32 rounding noise,
#: ~1e-8) take exp(Y) from its cubic Taylor polynomial, whose truncation Y⁴/24 is ≤ (3 SMALL_Y)⁴/24
#: < 1e-17 relative: as accurate as the closed form, without the spectrum (`_small_y`).
SMALL_Y = 4e-5
_TINY = np.finfo(np.float64).tiny
_SQRT3 = math.sqrt(3.0)

# Taylor coefficients in z = x² of sin(x)/x = Σ (−z)^k/(2k+1)!. Degree 9 keeps the truncation below
# 2e-17 for x ≤ 0.45π (z ≤ 2, the quarter angle of θ ≤ 1.8π); degree 8 does for the eigen-angle
# a ≤ π/3 (z ≤ 1.1). (Chebyshev-economised coefficients would save one degree but carry ~1e-15 of
# rounding from the change of basis.)
_SINC_COEFFS = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(10))
_SINC_EIG_COEFFS = _SINC_COEFFS[:9]
# Clamps that replace series branches (see the error bounds where they are used).
_C_CLAMP_S = 1e-14
_H2_CLAMP = 1e-5


def _horner(out: FloatArray, coeffs: tuple[float, ...], z: FloatArray) -> FloatArray:
    """out = Σ coeffs[k] z^k (in place; out must not alias z)."""
    np.multiply(z, coeffs[-1], out=out)
    for c in coeffs[-2:0:-1]:
        out += c
        out *= z
    out += coeffs[0]
    return out


class _FreeRows:
    """Scratch rows of one chunk not in use: a stage takes the rows it needs and gives back those it
    does not return (last given, first taken: the rows most recently written are the warm ones)."""

    def __init__(self, rows: FloatArray) -> None:
        self._rows = list(rows)

    def take(self, count: int) -> list[FloatArray]:
        if count > len(self._rows):
            raise RuntimeError("kernel scratch exhausted")  # a programming error, not an input error
        taken = self._rows[len(self._rows) - count :]
        del self._rows[len(self._rows) - count :]
        return taken

    def give(self, *rows: FloatArray) -> None:
        self._rows.extend(rows)


# ----------------------------------------------------------------------------------------------
# stages of the map, on (n,) rows with in-place ufuncs (the compiled kernel's `_exp_sym_coeffs`,
# `_stretch`, `_exp_sym_matrix`, `_rotation_coeffs_poly`, `_rigid`, in the same order)


def _eigen_gaps(ang: FloatArray, p: FloatArray, x: FloatArray, y: FloatArray, t1: FloatArray) -> None:
    """The eigenvalue gaps of a symmetric 3×3 from its spread p and angle a = arccos(r)/3, into x
    and y: x = e0 − e1 = −2√3 p sin a ≤ 0, y = e2 − e1 = 2√3 p sin(π/3 − a) ≥ 0. sin a comes from
    its polynomial; cos a = √(1 − sin² a) ≥ ½ (a ≤ π/3) is well conditioned, and
    sin(π/3 − a) = (√3/2) cos a − ½ sin a. Overwrites p (with 2√3 p) and t1."""
    mul = np.multiply
    mul(ang, ang, out=t1)
    _horner(x, _SINC_EIG_COEFFS, t1)
    x *= ang
    mul(x, x, out=t1)
    np.subtract(1.0, t1, out=t1)
    np.sqrt(t1, out=t1)
    mul(t1, 0.5 * _SQRT3, out=y)
    mul(x, 0.5, out=t1)
    y -= t1
    p *= -2.0 * _SQRT3
    x *= p
    np.negative(p, out=p)
    y *= p


_TAYLOR_SCRATCH = 13  # rows the larger Taylor form needs (`_exp_sym_small_matrix`)


def _by_form(
    Y: FloatArray,
    extra: tuple[FloatArray, ...],
    free: _FreeRows,
    small_form: Callable[..., tuple[FloatArray, ...]],
    closed_form: Callable[..., tuple[FloatArray, ...]],
) -> tuple[FloatArray, ...]:
    """form(Y, *extra, free) per row: `small_form` (Taylor) where `_small_y`, `closed_form` elsewhere.

    A chunk of one kind runs one form. A mixed chunk runs the closed form on all its rows, in place,
    and the Taylor form on its small rows, gathered. Each row's value then comes from its own form
    and does not depend on its neighbours: the Taylor form is products and sums only, exact in any
    layout, while the closed form is always computed in the kernel's own padded rows. numpy's
    arccos, exp and expm1 have SIMD loops (AVX-512) that round differently from the scalar code it
    falls back to when an input row and the output row touch in memory, as adjacent rows of an
    unpadded buffer do: there ~25 % of the values differed in the last bit (measured), so a closed
    form on gathered rows would give rows other bits than in place."""
    small = _small_y(Y, free)
    count = int(np.count_nonzero(small))
    if count == small.size:
        return small_form(Y, *extra, free)
    out = closed_form(Y, *extra, free)
    if count:
        sel = np.flatnonzero(small)
        # take() gathers ~3× faster than fancy indexing
        gathered = (a.take(sel, axis=1) for a in (Y, *extra))
        part = small_form(*gathered, _FreeRows(np.empty((_TAYLOR_SCRATCH, sel.size))))
        for row, row_part in zip(out, part, strict=True):
            row[sel] = row_part
    return out


def _exp_sym_closed_apply(Y: FloatArray, V: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) v by the spectrum (`_exp_sym_coeffs`, `_exp_sym_apply`). Returns three rows of `free`."""
    coeffs = _exp_sym_coeffs(Y, free)
    ew = _exp_sym_apply(Y[3:6], coeffs, V, free)
    free.give(*coeffs)
    return ew


def _exp_sym_closed_matrix(Y: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) by the spectrum (`_exp_sym_coeffs`, `_exp_sym_matrix`). Returns six rows of `free`."""
    coeffs = _exp_sym_coeffs(Y, free)
    e = _exp_sym_matrix(Y[3:6], coeffs, free)
    free.give(*coeffs)
    return e


def _small_y(Y: FloatArray, free: _FreeRows) -> NDArray[np.bool_]:
    """Rows whose Y (6, n) has every |entry| ≤ SMALL_Y (NaN: not small): a plain comparison, nothing
    rounded, so any chunking decides a row alike."""
    m, t = free.take(2)
    np.abs(Y[0], out=m)
    for y in Y[1:]:
        np.abs(y, out=t)
        np.maximum(m, t, out=m)  # propagates NaN
    small = m <= SMALL_Y
    free.give(m, t)
    return small


def _exp_sym_small_apply(Y: FloatArray, V: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) v ≈ v + Y(v + Y(½v + Y(v/6))) for points V (3, n) and small Y (6, n) (SMALL_Y: the
    first term left out is < 1e-17 relative). Returns three rows taken from `free`."""
    a = free.take(3)
    b = free.take(3)
    (t,) = free.take(1)
    for ai, vi in zip(a, V, strict=True):
        np.multiply(vi, 1.0 / 6.0, out=ai)
    for step in (0.5, 1.0, 1.0):  # a ← step v + Y a
        _sym_matvec(*Y, *a, *b, t)
        for ai, bi, vi in zip(a, b, V, strict=True):
            np.multiply(vi, step, out=ai)
            ai += bi
    free.give(*b, t)
    return a[0], a[1], a[2]


def _exp_sym_small_matrix(Y: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """exp(Y) ≈ I + Y(I + Y(½I + Y/6)) as six rows (xx, yy, zz, xy, xz, yz), for small Y (6, n)
    (the truncation of `_exp_sym_small_apply`). Returns six rows taken from `free`."""
    S = free.take(6)
    T = free.take(6)
    (t,) = free.take(1)
    for si, yi in zip(S, Y, strict=True):
        np.multiply(yi, 1.0 / 6.0, out=si)
    for d in S[:3]:
        d += 0.5
    for _ in range(2):  # S ← I + Y S
        _sym_product(Y, S, T, t)
        S, T = T, S
        for d in S[:3]:
            d += 1.0
    free.give(*T, t)
    return tuple(S)


def _sym_product(Y: FloatArray, S: list[FloatArray], out: list[FloatArray], tmp: FloatArray) -> None:
    """out = Y S as six rows (xx, yy, zz, xy, xz, yz) for symmetric Y, S (6, n) that commute (S a
    polynomial in Y): Y S is then symmetric, and its upper triangle is all of it."""
    # (i, j) of Y S = Σ_k Y_ik S_kj, with the six-row slot of each symmetric entry:
    slot = ((0, 3, 4), (3, 1, 5), (4, 5, 2))
    for o, (i, j) in zip(out, ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)), strict=True):
        np.multiply(Y[slot[i][0]], S[slot[0][j]], out=o)
        for k in (1, 2):
            np.multiply(Y[slot[i][k]], S[slot[k][j]], out=tmp)
            o += tmp


def _exp_sym_coeffs(Y: FloatArray, free: _FreeRows) -> tuple[FloatArray, ...]:
    """The spectral coefficients of exp(Y) for Y (6, n) = (Yxx, Yyy, Yzz, Yxy, Yxz, Yyz) rows:
    (E, α', g', z0, z1, z2) with exp(Y) = E I + α' Z + g' Z², Z = Y − e₁ I (z0 … z2 its diagonal,
    its off-diagonal is Y's), E = e^{e₁}, α' = E α, g' = E g (module doc). Takes 13 rows of `free`,
    returns six of them and gives the other seven back."""
    mul, add, sub = np.multiply, np.add, np.subtract
    yxx, yyy, yzz, yxy, yxz, yyz = Y
    q, b0, b1, b2, p2, p, det, t0, t1, x, y, h2x, h2y = free.take(13)

    # ---- spectrum of Y: q = tr/3, B = Y − qI, p = √(tr B²/6), cos 3a = det B/(2p³) ---------------
    add(yxx, yyy, out=q)
    q += yzz
    q *= 1.0 / 3.0
    sub(yxx, q, out=b0)
    sub(yyy, q, out=b1)
    sub(yzz, q, out=b2)
    # det B = b0 b1 b2 + 2 xy xz yz − b0 yz² − b1 xz² − b2 xy²;  6 p² = Σ b² + 2 Σ off²
    mul(b0, b1, out=det)
    det *= b2
    mul(yxy, yxz, out=t0)
    t0 *= yyz
    t0 += t0
    det += t0
    mul(b0, b0, out=p2)
    for bi, oi in ((b0, yyz), (b1, yxz), (b2, yxy)):
        mul(oi, oi, out=t0)
        mul(bi, t0, out=t1)
        det -= t1
        t0 += t0
        p2 += t0
    mul(b1, b1, out=t0)
    p2 += t0
    mul(b2, b2, out=t0)
    p2 += t0
    p2 *= 1.0 / 6.0
    np.sqrt(p2, out=p)
    # r = det B/(2p³); a zero spread gives det = 0 and r = 0 (adding TINY only avoids 0/0).
    mul(p2, p, out=t1)
    t1 += t1
    t1 += _TINY
    r = t0
    np.divide(det, t1, out=r)
    np.minimum(r, 1.0, out=r)
    np.maximum(r, -1.0, out=r)
    ang = det
    np.arccos(r, out=ang)
    ang *= 1.0 / 3.0
    _eigen_gaps(ang, p, x, y, t1)
    e1 = q
    add(x, y, out=t1)
    t1 *= 1.0 / 3.0
    e1 -= t1

    # ---- exp(Y) = E (I + α Z + g Z²), Z = Y − e1 I ---------------------------------------------
    # g = (y h2(y) − x h2(x))/(y − x) ≥ 0 is a weighted mean of h2 values (no cancellation);
    # α = h1(x) − x g = 1 + x (h2(x) − g). h2 = (eᶻ − 1 − z)/z² is evaluated at z clamped away
    # from 0 (x ≤ −c, y ≥ c, c = _H2_CLAMP): the interpolant then still matches e^y at y and 1
    # at 0 exactly, and misses eˣ by x²·|h2(−c) − h2(x)| ≤ c³/3 ≈ 3e-16. Unclamped, the
    # direct formula's relative error ε/|z| is harmless for the same reason (it is multiplied
    # by z²), so no series branch is needed.
    np.minimum(x, -_H2_CLAMP, out=t0)
    _h2_direct(t0, h2x, t1)
    np.maximum(y, _H2_CLAMP, out=t0)
    _h2_direct(t0, h2y, t1)
    g = p2
    mul(y, h2y, out=g)
    mul(x, h2x, out=t0)
    g -= t0
    sub(y, x, out=t0)
    t0 += _TINY  # y − x ≥ 0; only x = y = 0 (then g multiplies Z = 0) needs the guard
    g /= t0
    alpha = h2x
    alpha -= g
    alpha *= x
    alpha += 1.0
    E = p
    np.exp(e1, out=E)
    alpha *= E
    g *= E
    z0, z1, z2 = b0, b1, b2
    sub(yxx, e1, out=z0)
    sub(yyy, e1, out=z1)
    sub(yzz, e1, out=z2)
    free.give(e1, ang, t0, t1, x, y, h2y)
    return E, alpha, g, z0, z1, z2


def _exp_sym_apply(
    Y_off: FloatArray, coeffs: tuple[FloatArray, ...], V: FloatArray, free: _FreeRows
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """exp(Y) v = (α' Z v + g' Z² v) + E v for points V (3, n), from `_exp_sym_coeffs`; Y_off the
    off-diagonal rows (Yxy, Yxz, Yyz). Returns three rows taken from `free`."""
    E, alpha, g, z0, z1, z2 = coeffs
    yxy, yxz, yyz = Y_off
    v0, v1, v2 = V
    zv0, zv1, zv2, zzv0, zzv1, zzv2, t0 = free.take(7)
    _sym_matvec(z0, z1, z2, yxy, yxz, yyz, v0, v1, v2, zv0, zv1, zv2, t0)
    _sym_matvec(z0, z1, z2, yxy, yxz, yyz, zv0, zv1, zv2, zzv0, zzv1, zzv2, t0)
    ew0, ew1, ew2 = zv0, zv1, zv2  # exp(Y) v, in place of Z v
    for ew, vi, zzvi in ((ew0, v0, zzv0), (ew1, v1, zzv1), (ew2, v2, zzv2)):
        ew *= alpha
        np.multiply(zzvi, g, out=t0)
        ew += t0
        np.multiply(vi, E, out=t0)
        ew += t0
    free.give(zzv0, zzv1, zzv2, t0)
    return ew0, ew1, ew2


def _exp_sym_matrix(
    Y_off: FloatArray, coeffs: tuple[FloatArray, ...], free: _FreeRows
) -> tuple[FloatArray, ...]:
    """exp(Y) = (α' Z + g' Z²) + E I as its six rows (xx, yy, zz, xy, xz, yz), from
    `_exp_sym_coeffs`; Y_off the off-diagonal rows (Yxy, Yxz, Yyz). Returns six rows of `free`."""
    E, alpha, g, z0, z1, z2 = coeffs
    a, b, c = Y_off  # Z = [[z0, a, b], [a, z1, c], [b, c, z2]]
    mul = np.multiply
    xx, yy, zz, xy, xz, yz, t0, t1 = free.take(8)
    # Z²: off-diagonal (Z²)01 = a (z0 + z1) + b c, …; diagonal (Z²)00 = z0² + a² + b², …
    for zij, s0, s1, f, p0, p1 in ((xy, z0, z1, a, b, c), (xz, z0, z2, b, a, c), (yz, z1, z2, c, a, b)):
        np.add(s0, s1, out=zij)
        zij *= f
        mul(p0, p1, out=t0)
        zij += t0
    mul(a, a, out=t0)
    mul(b, b, out=t1)
    mul(z0, z0, out=xx)
    xx += t0
    xx += t1
    mul(z1, z1, out=yy)
    yy += t0
    mul(z2, z2, out=zz)
    zz += t1
    mul(c, c, out=t0)
    yy += t0
    zz += t0
    for xij, zij in ((xx, z0), (yy, z1), (zz, z2), (xy, a), (xz, b), (yz, c)):
        xij *= g
        mul(zij, alpha, out=t0)
        xij += t0
    xx += E
    yy += E
    zz += E
    free.give(t0, t1)
    return xx, yy, zz, xy, xz, yz


def _rotation_coeffs(w: FloatArray, free: _FreeRows) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """(A, B, C, cos θ) rows for rotation vectors w (3, n): A = sin θ/θ, B = (1 − cos θ)/θ²,
    C = (θ − sin θ)/θ³, by the quarter-angle polynomial, exact libm values for θ > 1.8π. Returns four
    rows of `free`."""
    mul = np.multiply
    w0, w1, w2 = w
    s, zq, A, B, C, cth, sinc_q, tq, t0 = free.take(9)
    # ---- θ-coefficients from s = θ² (quarter angle: x_q = θ/4) --------------------------------
    mul(w0, w0, out=s)
    mul(w1, w1, out=t0)
    s += t0
    mul(w2, w2, out=t0)
    s += t0
    mul(s, 1.0 / 16.0, out=zq)
    _horner(sinc_q, _SINC_COEFFS, zq)  # sin(θ/4)/(θ/4)
    # tq = sin²(θ/4); cos(θ/4) = √(1 − tq), conditioned for θ ≤ 1.8π (beyond: exact fallback)
    mul(sinc_q, sinc_q, out=tq)
    tq *= zq
    sh = sinc_q
    np.subtract(1.0, tq, out=t0)
    # Past θ ≈ 2π the polynomial's tq can exceed 1; those rows are redone exactly below, and the
    # clamp (a no-op on every other row) keeps NaN warnings out of the user's console.
    np.maximum(t0, 0.0, out=t0)
    np.sqrt(t0, out=t0)
    sh *= t0  # sin(θ/2)/(θ/2)
    mul(tq, -2.0, out=t0)
    t0 += 1.0  # cos(θ/2)
    mul(sh, t0, out=A)  # sin θ/θ
    mul(sh, sh, out=B)
    B *= 0.5  # (1 − cos θ)/θ²
    mul(B, s, out=cth)
    np.subtract(1.0, cth, out=cth)  # cos θ
    # C = (θ − sin θ)/θ³ = (1 − A)/θ². It only enters as C (ω·u) ω, of size ≤ C θ² |u|, so the
    # direct formula's error ε/θ² costs ε|u| there; dividing by θ² + c (c = _C_CLAMP_S) instead
    # moves the term by ≤ c|u|/6 < 2e-15 |u| and makes θ = 0 safe, so no series branch is needed.
    np.add(s, _C_CLAMP_S, out=t0)
    np.subtract(1.0, A, out=C)
    C /= t0
    if (s > _POLY_MAX_S).any():
        _exact_rotation_coeffs(s, A, B, C, cth)
    free.give(s, zq, sinc_q, tq, t0)
    return A, B, C, cth


def _rigid(
    w: FloatArray,
    u: FloatArray | None,
    e: FloatArray | tuple[FloatArray, ...] | None,
    theta: tuple[FloatArray, FloatArray, FloatArray, FloatArray],
    O: FloatArray,
    free: _FreeRows,
) -> None:
    """O (3, n) = R(ω) e + V(ω) u = cos θ e + A u + ω × (A e + B u) + (B ω·e + C ω·u) ω, with the
    θ-coefficients (A, B, C, cos θ) of `_rotation_coeffs`; u = None is u = 0 (R e) and e = None is
    the point 0 (V u): their terms are left out. O must not overlap the inputs."""
    A, B, C, cth = theta
    mul = np.multiply
    w0, w1, w2 = w
    k, t0, t1, m0, m1, m2 = free.take(6)
    if e is not None:
        e0, e1, e2 = e
        mul(w0, e0, out=k)
        mul(w1, e1, out=t0)
        k += t0
        mul(w2, e2, out=t0)
        k += t0
        k *= B
    if u is not None:
        u0, u1, u2 = u
        wu = t1 if e is not None else k
        mul(w0, u0, out=wu)
        mul(w1, u1, out=t0)
        wu += t0
        mul(w2, u2, out=t0)
        wu += t0
        wu *= C
        if e is not None:
            k += wu
    ms = (m0, m1, m2)
    for i, mi in enumerate(ms):
        if e is None:
            mul(u[i], B, out=mi)  # type: ignore[index]
            continue
        mul(e[i], A, out=mi)
        if u is not None:
            mul(u[i], B, out=t0)
            mi += t0
    for i, (a_, b_) in enumerate(((1, 2), (2, 0), (0, 1))):  # (ω × m)_i = ω_a m_b − ω_b m_a
        Oi = O[i]
        mul(w[a_], ms[b_], out=Oi)
        mul(w[b_], ms[a_], out=t0)
        Oi -= t0
        if e is not None:
            mul(e[i], cth, out=t0)
            Oi += t0
        if u is not None:
            mul(u[i], A, out=t0)
            Oi += t0
        mul(w[i], k, out=t0)
        Oi += t0
    free.give(k, t0, t1, m0, m1, m2)


def _h2_direct(z: FloatArray, out: FloatArray, tmp: FloatArray) -> None:
    """out = (eᶻ − 1 − z)/z² for z bounded away from 0."""
    np.expm1(z, out=out)
    out -= z
    np.multiply(z, z, out=tmp)
    out /= tmp


def _sym_matvec(
    a00: FloatArray,
    a11: FloatArray,
    a22: FloatArray,
    a01: FloatArray,
    a02: FloatArray,
    a12: FloatArray,
    v0: FloatArray,
    v1: FloatArray,
    v2: FloatArray,
    o0: FloatArray,
    o1: FloatArray,
    o2: FloatArray,
    tmp: FloatArray,
) -> None:
    """(o0, o1, o2) = A v for symmetric A given by its six component rows."""
    for oi, d, oa, va, ob, vb, vi in (
        (o0, a00, a01, v1, a02, v2, v0),
        (o1, a11, a01, v0, a12, v2, v1),
        (o2, a22, a02, v0, a12, v1, v2),
    ):
        np.multiply(d, vi, out=oi)
        np.multiply(oa, va, out=tmp)
        oi += tmp
        np.multiply(ob, vb, out=tmp)
        oi += tmp


def _exact_rotation_coeffs(
    s: FloatArray, A: FloatArray, B: FloatArray, C: FloatArray, cth: FloatArray
) -> None:
    """Recompute the θ-coefficients with np.sin/np.cos where θ² > _POLY_MAX_S (lifted rotations)."""
    big = np.flatnonzero(s > _POLY_MAX_S)
    theta = np.sqrt(s[big])
    sin_t = np.sin(theta)
    half = np.sin(0.5 * theta) / (0.5 * theta)
    A[big] = sin_t / theta
    B[big] = 0.5 * half * half
    C[big] = (theta - sin_t) / (theta * s[big])
    cth[big] = np.cos(theta)
