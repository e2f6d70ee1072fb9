"""The per-vertex kernel v ↦ φ(Σ_k w_k P_idx(k)) v compiled with numba (optional backend), and its
motion twin p ↦ φ(p) itself (`motion_params`: the columns of M = R(ω) exp(Y) and t = V(ω) u).

Same mathematics as `core/deform.py` (parameter layout of docs/DEVELOPING.md, P = (ω, u, Y₆)):

    v' = R(ω) exp(Y) v + V(ω) u,
    exp(Y) = e^{e₁} (I + α Z + g Z²),  Z = Y − e₁ I,  e₀ ≤ e₁ ≤ e₂ the eigenvalues of Y,
    x = e₀ − e₁ ≤ 0 ≤ y = e₂ − e₁,  g = (y h2(y) − x h2(x))/(y − x),  α = 1 + x (h2(x) − g),
    h2(z) = (eᶻ − 1 − z)/z²,
    R w + V u = cos θ w + A u + ω × (A w + B u) + (B ω·w + C ω·u) ω,
    A = sin θ/θ, B = (1 − cos θ)/θ², C = (θ − sin θ)/θ³, θ = |ω|.

The eigenvalues come from the trigonometric cubic on the traceless part (a = arccos(r)/3 ≤ π/3).
The pieces are inlined scalar functions shared by both maps: `_exp_sym_coeffs` (spectrum → E, α', g',
Z), `_stretch` (exp(Y) v) or `_exp_sym_matrix` (exp(Y) itself), `_rotation_coeffs_poly` /
`_rotation_coeffs_libm` (A, B, C, cos θ) and `_rigid` (R e + V u; the motion calls it with u = 0 on
the columns of exp(Y) and with e = 0 for t), as the numpy kernel's stages of the same names.

Layout: vertices go in chunks of CHUNK rows (threads claim whole chunks). Per chunk, `_chunk` blends
the parameters into a structure-of-arrays scratch (12 parameter rows, 3 point rows, 3 result rows)
and then runs the map over it as one straight-line loop without calls or branches (selects only), so
LLVM vectorises it across vertices. libm is not vectorisable, so the transcendentals are polynomials:

* acos(r): π/2 − asin(r) for |r| ≤ ½, else 2 asin(√((1 − |r|)/2)) (reflected for r < 0); 1 − |r| is
  exact (Sterbenz, |r| ∈ [½, 1]). asin(s) = s F(s²), F the Taylor series Σ C(2k,k)/(4ᵏ(2k+1)) zᵏ to
  degree 24 on z ≤ ¼: truncation < 3e-18 relative.
* exp(z) = 2ⁿ e^ρ: n = round(z/ln 2) by adding 1.5·2⁵² (round to nearest in the low mantissa bits),
  ρ = (z − n ln2_hi) − n ln2_lo (Cody–Waite: ln2_hi has its low 11 bits cleared, so n ln2_hi is exact
  for |n| < 2¹¹), e^ρ Taylor degree 13 on |ρ| ≤ ln2/2 (truncation < 1e-17 relative); 2ⁿ is built
  from the integer bits of the rounded sum. z is clamped to ±709 (e^709 is finite).
* h2(z): Taylor Σ zᵏ/(k+2)! to degree 17 for |z| ≤ 1 (truncation < 1e-18), the direct formula beyond
  (≤ 5ε relative there: the numerator is ≥ e⁻¹ against terms of size ≤ eᶻ), so no clamp near z = 0.
* sin x/x: Taylor in x² to degree 9 for the quarter angle x = θ/4 ≤ 0.45π (truncation < 2e-17),
  degree 8 for the eigen-angle a ≤ π/3 (< 2e-17); cosines as √(1 − sin²) (cos(θ/4) ≥ 0.15 and
  cos a ≥ ½ keep that well conditioned) and double-angle formulas. For θ > 1.8π (lifted rotations)
  that is no longer accurate: the map counts those vertices and a scalar pass redoes them with libm
  sin/cos (`_fixup`).
* C = (1 − A)/(θ² + 1e-14): moves C (ω·u) ω by ≤ 1e-14 |u|/6 and makes θ = 0 safe without a branch.
* exp(Y) of a small Y (every |Y_ij| ≤ SMALL_Y = 4e-5: rigid controls, whose Y is float32 rounding
  noise): the cubic Taylor polynomial in Horner form (`_stretch_small`, `_exp_sym_matrix_small`);
  the first term left out is < 1e-17 relative. Such columns skip the spectrum; `_map` runs each form
  in a loop of its own (see there for why).

Accuracy: ≤ 3e-15 relative to ‖M‖‖v‖ + ‖t‖ against aff3 on the adversarial set of the core tests.

Bit-identity: a row's result depends on that row only — not on the call (full or rows, with or
without the float32 copy), the chunk, the position in it, the thread count, and not on whether the
entry was compiled in this session or loaded from numba's on-disk cache: the Blender layer
recomputes only the rows a changed control influences and keeps the others, and a frame must give
the same bits however it was reached. The rules:

* One compiled entry per map, one specialisation each: `deform_points_entry` (full call and rows,
  offsets and float32 copy are runtime flags; unused arrays are passed empty), `motion_params`, and
  `polar_log` (the polar split of ψ for a batch of 3×3 matrices), `node_pivot` (the per-face and
  per-node steps of a harmonic cage's pivoted node blend) and `cage_faces` (a cage's whole face path:
  corner tetrahedra, stencil apex, ψ, the mean over each face's corners, and the signed volume).
* Each entry is one LLVM module: every other jitted function here is inline="always" (numba IR
  inlining), and the entries have no prange. A call between separately compiled numba functions —
  a plain njit callee, or the gufunc numba makes of a prange body — links a copy of the callee's
  optimised module into the caller and optimises it again; in the session that compiled it the call
  still goes to the callee's own code, while the object in the cache holds the re-optimised copy,
  and a second round of optimisation can reorder operands and so change which products LLVM fuses
  into FMAs. Measured on 204k random and adversarial rows before this layout: ~11 % of the point
  rows and ~45 % of the motion rows (float64) differed in the last bit between a cached entry and a
  session-compiled one (the float32 roundings agreed); now none do, and the bits are those of the
  session-compiled entries before.
* Threads come from the caller (`affine_deformers.accel._run_chunks`): the entries release the GIL,
  and every thread running one call claims chunks from a shared counter (`_claim`, an atomic
  increment), so a helper that starts late takes fewer chunks instead of delaying the call; each
  entry returns how many chunks its thread did, so a caller that did them all need not wait for a
  helper that is still asleep (it will claim nothing).
* Every function carries the same fastmath flags (only 'contract': FMA formation; no reassociation,
  so no sum is reordered), and the map always runs a full chunk, so no row is computed by a scalar
  remainder loop whose FMA contraction could differ from the vector body's (see `_map`).
* The fix-up loops (`_fixup`, `_fixup_motion`: variable trip count) start with `_scalar_barrier()`:
  LLVM would vectorise them despite the libm calls, and a θ > 1.8π row would then get other bits in
  the vector body of a full chunk than in the scalar remainder of a short one (seen with cached
  entries: 1400 of 11737 such rows before the barrier).

The float32 copy `deform_points_entry` can store next to a row is one conversion of the stored
float64 (round to nearest even, overflow to ±inf), the same rounding as numpy's astype(np.float32);
`motion_params` writes either float64 `out` or float32 `out32` (the other passed empty), rounded
the same way.

Memory safety: indices are clamped to the table in the blend (one min per slot), so inputs the caller
vouched for (a `key`) but that are wrong can give wrong values but never read out of bounds.

This module imports numba; `affine_deformers.accel` imports it only on first use. Nothing is compiled
at import: the two entries compile on their first call (or load from numba's cache next to this
file; without a usable cache location they are compiled in every session).
"""

from __future__ import annotations

import math
import platform
from collections.abc import Callable
from decimal import Decimal, localcontext
from fractions import Fraction

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["CHUNK", "ENTRIES", "cage_faces", "cage_nodes", "chain_motion_entry", "chain_points_entry",
           "deform_points_entry", "motion_params", "node_pivot", "polar_log", "psi_rows", "rows_reading",
           "same_words", "spin_wait"]

#: The only fastmath flag: FMA contraction. It must be the same on every function (see module doc).
FASTMATH = {"contract"}
#: Vertices per chunk (a thread's unit of work): 18 scratch rows of this length stay in L2.
CHUNK = 2048
# Scratch row stride: rows a multiple of 4 KiB apart alias in the L1 cache (4K aliasing) and the
# vectorised map reads and writes ~20 rows at once.
_STRIDE = CHUNK + 8
_N_SCRATCH = 18  # 12 parameters, 3 point coordinates, 3 results
_N_MOTION_SCRATCH = 24  # 12 parameters, 12 results (M e_x, M e_y, M e_z, t)
_N_CHAIN_SCRATCH = 21  # as _N_SCRATCH, plus the original point (offsets)
_N_CHAIN_MOTION_SCRATCH = 36  # as _N_MOTION_SCRATCH, plus the product so far
#: The compiled kernel entries, one specialisation each (`warm_up` runs exactly these and `spin_wait`).
ENTRIES = ("deform_points_entry", "motion_params", "polar_log", "node_pivot", "chain_points_entry",
           "chain_motion_entry", "cage_faces", "cage_nodes", "psi_rows", "rows_reading", "same_words")

# ---------------------------------------------------------------------------------------------
# constants


def _split_ln2() -> tuple[float, float, float]:
    """(ln2_hi, ln2_lo, 1/ln 2): ln2_hi with its 11 low mantissa bits cleared, ln2_lo the rest."""
    with localcontext() as ctx:
        ctx.prec = 50
        ln2 = Decimal(2).ln()
        bits = np.array([float(ln2)]).view(np.int64)[0] & ~np.int64((1 << 11) - 1)
        hi = float(np.array([bits]).view(np.float64)[0])
        return hi, float(ln2 - Decimal(hi)), float(1 / ln2)


_LN2_HI, _LN2_LO, _LOG2E = _split_ln2()
_ROUND_MAGIC = 6755399441055744.0  # 1.5·2⁵²: (x + M) − M rounds x to the nearest integer, |x| < 2⁵¹
_EXP_MAX = 709.0
_SQRT3 = math.sqrt(3.0)
_TINY = float(np.finfo(np.float64).tiny)
POLY_MAX_S = (1.8 * math.pi) ** 2  # θ² beyond which the libm fix-up takes over
#: Largest |entry| of a blended Y whose exp(Y) comes from the cubic Taylor polynomial (see `_map`);
#: the same value as `core.deform.SMALL_Y`.
SMALL_Y = 4e-5
_C_CLAMP_S = 1e-14

_SINC = [(-1.0) ** k / math.factorial(2 * k + 1) for k in range(10)]
_ASIN_F = [float(Fraction(math.comb(2 * k, k), 4**k * (2 * k + 1))) for k in range(25)]
_EXP_T = [1.0 / math.factorial(k) for k in range(14)]
_H2_T = [1.0 / math.factorial(k + 2) for k in range(18)]


# ---------------------------------------------------------------------------------------------
# bit casts (2ⁿ from the exponent field without a libm call or a branch)


@intrinsic
def _i2f(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


@intrinsic
def _f2i(typingctx, x):
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _scalar_barrier(typingctx):
    """An empty inline asm with a memory clobber: LLVM can neither vectorise a loop containing it nor
    move memory accesses across it, so every iteration of such a loop runs the same scalar code
    (a loop with a variable trip count is otherwise vectorised, and then a row's bits depend on
    whether it fell into the vector body or the scalar remainder)."""

    def codegen(context, builder, signature, args):
        builder.asm(ir.FunctionType(ir.VoidType(), []), "", "~{memory}", [], True)
        return context.get_dummy_value()

    return types.none(), codegen


@intrinsic
def _claim(typingctx, counter):
    """counter[0]++ as one atomic read-modify-write; returns the old value. counter: a 1-D int64
    array shared by the threads that run one call (each claims the next chunk)."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", ary.data, ir.Constant(ir.IntType(64), 1), "monotonic")

    return types.int64(counter), codegen


@intrinsic
def _load_relaxed(typingctx, flag):
    """flag[0] as an atomic load (a spin loop re-reads it every iteration). flag: 1-D int64."""
    if not (isinstance(flag, types.Array) and flag.dtype == types.int64 and flag.ndim == 1):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.load_atomic(ary.data, "monotonic", 8)

    return types.int64(flag), codegen


_PAUSE = platform.machine().lower() in ("x86_64", "amd64")


@intrinsic
def _cpu_relax(typingctx):
    """The x86 PAUSE hint in a spin loop (spares the sibling hyperthread); nothing elsewhere."""

    def codegen(context, builder, signature, args):
        if _PAUSE:
            fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), []),
                                                "llvm.x86.sse2.pause")
            builder.call(fn, [])
        return context.get_dummy_value()

    return types.none(), codegen


# ---------------------------------------------------------------------------------------------
# polynomials: written out as straight-line Horner code. A loop over a coefficient array inside
# the map would be an inner loop, and LLVM only vectorises innermost loops.


def _horner_src(name: str, coeffs: list[float]) -> str:
    expr = repr(coeffs[-1])
    for c in coeffs[-2::-1]:
        expr = f"({expr}) * z + {c!r}"
    return f"@_inline\ndef {name}(z):\n    return {expr}\n"


def _inline(fn: Callable) -> Callable:
    return numba.njit(inline="always", fastmath=FASTMATH, error_model="numpy")(fn)


_POLY_NAMESPACE: dict = {"_inline": _inline}
exec(
    compile(
        "".join(
            _horner_src(name, coeffs)
            for name, coeffs in (
                ("_sinc_quarter", _SINC),
                ("_sinc_eig", _SINC[:9]),
                ("_asin_f", _ASIN_F),
                ("_exp_taylor", _EXP_T),
                ("_h2_taylor", _H2_T),
            )
        ),
        "<affine_deformers.accel.compiled polynomials>",
        "exec",
    ),
    _POLY_NAMESPACE,
)
_sinc_quarter = _POLY_NAMESPACE["_sinc_quarter"]
_sinc_eig = _POLY_NAMESPACE["_sinc_eig"]
_asin_f = _POLY_NAMESPACE["_asin_f"]
_exp_taylor = _POLY_NAMESPACE["_exp_taylor"]
_h2_taylor = _POLY_NAMESPACE["_h2_taylor"]


# ---------------------------------------------------------------------------------------------
# branch-free scalar pieces of the map (inlined into the vectorised loop)


@_inline
def _exp(z: float) -> float:
    """e^z = 2ⁿ e^ρ (Cody–Waite reduction, Taylor e^ρ), z clamped to [−709, 709]."""
    z = _EXP_MAX if z > _EXP_MAX else z
    z = -_EXP_MAX if z < -_EXP_MAX else z
    kn = z * _LOG2E + _ROUND_MAGIC
    n = kn - _ROUND_MAGIC
    rho = (z - n * _LN2_HI) - n * _LN2_LO
    # The low 12 bits of kn's bit pattern hold n mod 2¹²; n + 1023 ∈ [0, 2046] is the biased exponent.
    return _exp_taylor(rho) * _i2f((_f2i(kn) + 1023) << 52)


@_inline
def _h2(z: float) -> float:
    """(eᶻ − 1 − z)/z²: Taylor for |z| ≤ 1, direct beyond (both computed, one selected)."""
    zz = z * z
    big = zz > 1.0
    direct = (_exp(z) - 1.0 - z) / (zz if big else 1.0)
    return direct if big else _h2_taylor(z)


@_inline
def _acos_third(r: float) -> float:
    """arccos(r)/3 for r ∈ [−1, 1] via asin on |argument| ≤ ½."""
    ar = r if r >= 0.0 else -r
    big = ar > 0.5
    zb = 0.5 * (1.0 - ar)
    s = math.sqrt(zb) if big else r
    t = s * _asin_f(zb if big else r * r)
    acos_big = 2.0 * t if r > 0.0 else math.pi - 2.0 * t
    return (acos_big if big else 0.5 * math.pi - t) * (1.0 / 3.0)


@_inline
def _exp_sym_coeffs(
    yxx: float, yyy: float, yzz: float, yxy: float, yxz: float, yyz: float
) -> tuple[float, float, float, float, float, float]:
    """(E, α', g', z0, z1, z2) with exp(Y) = E I + α' Z + g' Z², Z = Y − e₁ I (z0 … z2 its diagonal,
    its off-diagonal is Y's), E = e^{e₁}, α' = E α, g' = E g, for Y = [[yxx, yxy, yxz],
    [yxy, yyy, yyz], [yxz, yyz, yzz]] (see the module doc)."""
    q = (yxx + yyy + yzz) * (1.0 / 3.0)
    b0 = yxx - q
    b1 = yyy - q
    b2 = yzz - q
    det = b0 * b1 * b2 + 2.0 * yxy * yxz * yyz - b0 * yyz * yyz - b1 * yxz * yxz - b2 * yxy * yxy
    p2 = (b0 * b0 + b1 * b1 + b2 * b2 + 2.0 * (yxy * yxy + yxz * yxz + yyz * yyz)) * (1.0 / 6.0)
    p = math.sqrt(p2)
    # r = det(B/p)/2 ∈ [−1, 1] up to rounding; TINY only avoids 0/0 for a multiple of the identity.
    r = det / (2.0 * p2 * p + _TINY)
    r = 1.0 if r > 1.0 else r
    r = -1.0 if r < -1.0 else r
    a = _acos_third(r)
    sa = _sinc_eig(a * a) * a
    ca = math.sqrt(1.0 - sa * sa)
    sb = 0.5 * _SQRT3 * ca - 0.5 * sa  # sin(π/3 − a)
    x = -2.0 * _SQRT3 * p * sa
    y = 2.0 * _SQRT3 * p * sb
    e1 = q - (x + y) * (1.0 / 3.0)
    h2x = _h2(x)
    h2y = _h2(y)
    # y − x ≥ 0 vanishes only for x = y = 0, where g multiplies Z = 0.
    g = (y * h2y - x * h2x) / (y - x + _TINY)
    alpha = 1.0 + x * (h2x - g)
    E = _exp(e1)
    alpha *= E
    g *= E
    return E, alpha, g, yxx - e1, yyy - e1, yzz - e1


@_inline
def _stretch(
    yxx: float, yyy: float, yzz: float, yxy: float, yxz: float, yyz: float, v0: float, v1: float, v2: float
) -> tuple[float, float, float]:
    """exp(Y) v = (α' Z v + g' Z² v) + E v (`_exp_sym_coeffs`)."""
    E, alpha, g, z0, z1, z2 = _exp_sym_coeffs(yxx, yyy, yzz, yxy, yxz, yyz)
    zv0 = z0 * v0 + yxy * v1 + yxz * v2
    zv1 = yxy * v0 + z1 * v1 + yyz * v2
    zv2 = yxz * v0 + yyz * v1 + z2 * v2
    zz0 = z0 * zv0 + yxy * zv1 + yxz * zv2
    zz1 = yxy * zv0 + z1 * zv1 + yyz * zv2
    zz2 = yxz * zv0 + yyz * zv1 + z2 * zv2
    return (alpha * zv0 + g * zz0 + E * v0, alpha * zv1 + g * zz1 + E * v1, alpha * zv2 + g * zz2 + E * v2)


@_inline
def _exp_sym_matrix(
    yxx: float, yyy: float, yzz: float, yxy: float, yxz: float, yyz: float
) -> tuple[float, float, float, float, float, float]:
    """exp(Y) = (α' Z + g' Z²) + E I as (xx, yy, zz, xy, xz, yz) (`_exp_sym_coeffs`)."""
    E, alpha, g, z0, z1, z2 = _exp_sym_coeffs(yxx, yyy, yzz, yxy, yxz, yyz)
    a, b, c = yxy, yxz, yyz  # Z = [[z0, a, b], [a, z1, c], [b, c, z2]]
    aa, bb, cc = a * a, b * b, c * c
    return (
        alpha * z0 + g * (z0 * z0 + aa + bb) + E,
        alpha * z1 + g * (z1 * z1 + aa + cc) + E,
        alpha * z2 + g * (z2 * z2 + bb + cc) + E,
        alpha * a + g * (a * (z0 + z1) + b * c),
        alpha * b + g * (b * (z0 + z2) + a * c),
        alpha * c + g * (c * (z1 + z2) + a * b),
    )


@_inline
def _sym_apply(
    yxx: float, yyy: float, yzz: float, yxy: float, yxz: float, yyz: float, v0: float, v1: float, v2: float
) -> tuple[float, float, float]:
    """Y v for Y = [[yxx, yxy, yxz], [yxy, yyy, yyz], [yxz, yyz, yzz]]."""
    return (yxx * v0 + yxy * v1 + yxz * v2, yxy * v0 + yyy * v1 + yyz * v2, yxz * v0 + yyz * v1 + yzz * v2)


@_inline
def _stretch_small(
    yxx: float, yyy: float, yzz: float, yxy: float, yxz: float, yyz: float, v0: float, v1: float, v2: float
) -> tuple[float, float, float]:
    """exp(Y) v ≈ v + Y(v + Y(½v + Y(v/6))), the cubic Taylor polynomial in Horner form, for
    |Y_ij| ≤ SMALL_Y: the first term left out, Y⁴v/24, is ≤ (3 SMALL_Y)⁴/24 < 1e-17 relative to v.
    The innermost product is Y(v/6), not (Y v)/6: no product here has both operands of one in
    `_stretch` (a scalar fix-up loop holds both forms)."""
    k = 1.0 / 6.0
    s0, s1, s2 = _sym_apply(yxx, yyy, yzz, yxy, yxz, yyz, k * v0, k * v1, k * v2)
    b0, b1, b2 = _sym_apply(yxx, yyy, yzz, yxy, yxz, yyz, 0.5 * v0 + s0, 0.5 * v1 + s1, 0.5 * v2 + s2)
    c0, c1, c2 = _sym_apply(yxx, yyy, yzz, yxy, yxz, yyz, v0 + b0, v1 + b1, v2 + b2)
    return v0 + c0, v1 + c1, v2 + c2


@_inline
def _sym_times(
    yxx: float, yyy: float, yzz: float, yxy: float, yxz: float, yyz: float,
    sxx: float, syy: float, szz: float, sxy: float, sxz: float, syz: float,
) -> tuple[float, float, float, float, float, float]:
    """Y S as (xx, yy, zz, xy, xz, yz) for symmetric Y, S that commute (S a polynomial in Y), so
    that Y S is symmetric and its upper triangle is all of it."""
    return (
        yxx * sxx + yxy * sxy + yxz * sxz,
        yxy * sxy + yyy * syy + yyz * syz,
        yxz * sxz + yyz * syz + yzz * szz,
        yxx * sxy + yxy * syy + yxz * syz,
        yxx * sxz + yxy * syz + yxz * szz,
        yxy * sxz + yyy * syz + yyz * szz,
    )


@_inline
def _exp_sym_matrix_small(
    yxx: float, yyy: float, yzz: float, yxy: float, yxz: float, yyz: float
) -> tuple[float, float, float, float, float, float]:
    """exp(Y) ≈ I + Y(I + Y(½I + Y/6)) as (xx, yy, zz, xy, xz, yz), for |Y_ij| ≤ SMALL_Y (the
    truncation of `_stretch_small`)."""
    k = 1.0 / 6.0
    a = _sym_times(yxx, yyy, yzz, yxy, yxz, yyz, 0.5 + k * yxx, 0.5 + k * yyy, 0.5 + k * yzz,
                   k * yxy, k * yxz, k * yyz)
    b = _sym_times(yxx, yyy, yzz, yxy, yxz, yyz, 1.0 + a[0], 1.0 + a[1], 1.0 + a[2], a[3], a[4], a[5])
    return 1.0 + b[0], 1.0 + b[1], 1.0 + b[2], b[3], b[4], b[5]


@_inline
def _rotation_coeffs_poly(s: float) -> tuple[float, float, float, float]:
    """(A, B, C, cos θ) from s = θ² by the quarter-angle polynomial; accurate for θ ≤ 1.8π."""
    zq = s * (1.0 / 16.0)
    sq = _sinc_quarter(zq)  # sin(θ/4)/(θ/4)
    tq = sq * sq * zq  # sin²(θ/4)
    cq2 = 1.0 - tq
    cq2 = 0.0 if cq2 < 0.0 else cq2  # only reachable for θ > 1.8π, which the fix-up redoes
    sh = sq * math.sqrt(cq2)  # sin(θ/2)/(θ/2)
    A = sh * (1.0 - 2.0 * tq)
    B = 0.5 * sh * sh
    return A, B, (1.0 - A) / (s + _C_CLAMP_S), 1.0 - B * s


@_inline
def _rotation_coeffs_libm(s: float) -> tuple[float, float, float, float]:
    """(A, B, C, cos θ) with libm sin/cos, for θ > 1.8π only (no small-θ care needed)."""
    th = math.sqrt(s)
    st = math.sin(th)
    half = math.sin(0.5 * th) / (0.5 * th)
    return st / th, 0.5 * half * half, (th - st) / (th * s), math.cos(th)


@_inline
def _rigid(
    w0: float, w1: float, w2: float, u0: float, u1: float, u2: float, e0: float, e1: float, e2: float,
    A: float, B: float, C: float, cth: float,
) -> tuple[float, float, float]:
    """R(ω) e + V(ω) u from the θ-coefficients."""
    k = B * (w0 * e0 + w1 * e1 + w2 * e2) + C * (w0 * u0 + w1 * u1 + w2 * u2)
    m0 = A * e0 + B * u0
    m1 = A * e1 + B * u1
    m2 = A * e2 + B * u2
    return (
        w1 * m2 - w2 * m1 + cth * e0 + A * u0 + w0 * k,
        w2 * m0 - w0 * m2 + cth * e1 + A * u1 + w1 * k,
        w0 * m1 - w1 * m0 + cth * e2 + A * u2 + w2 * k,
    )


# ---------------------------------------------------------------------------------------------
# one chunk: blend, map, fix-up, store (`_chunk` for points, `_motion_chunk` for motions), inlined
# into the entries


@_inline
def _blend(T: np.ndarray, I: np.ndarray, V: np.ndarray, P: np.ndarray, K: int, last: np.uint64,
           W: np.ndarray, j: int, r: int) -> None:
    """Column j of the scratch from row r: parameters (`_blend_params`) in scratch rows 0–11, the
    point P[r] (P the flat points) in rows 12–14."""
    _blend_params(T, I, V, K, last, W, j, r)
    S = _STRIDE
    W[12 * S + j] = P[3 * r]
    W[13 * S + j] = P[3 * r + 1]
    W[14 * S + j] = P[3 * r + 2]


@_inline
def _blend_params(T: np.ndarray, I: np.ndarray, V: np.ndarray, K: int, last: np.uint64, W: np.ndarray, j: int,
                  r: int) -> None:
    """Scratch rows 0–11 of column j = Σ_k V[r, k] T[I[r, k]] (slot order, zero weights skipped).
    T, I, V are the flat (row-major) table, indices and values; `last` = m − 1. Indices are clamped
    to the table (no effect on valid input, see the module doc)."""
    # Unsigned offsets: numba adds a negative-index wraparound select to every signed subscript,
    # which here would cost as much as the arithmetic.
    one = np.uint64(1)
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = 0.0
    base = r * K
    for k in range(K):
        wv = V[base + k]
        # A zero weight adds exactly ±0 (the table is finite) to a sum that is never −0 (it starts
        # at +0, and x + y = 0 rounds to +0): skipping the slot gives the same bits, and sparse
        # weights (falloff, vertex groups) leave most of the K slots empty.
        if wv == 0.0:
            continue
        # A negative index becomes huge as unsigned and is clamped like a too-large one.
        c = min(np.uint64(I[base + k]), last) * np.uint64(12)
        a0 += wv * T[c]
        c += one
        a1 += wv * T[c]
        c += one
        a2 += wv * T[c]
        c += one
        a3 += wv * T[c]
        c += one
        a4 += wv * T[c]
        c += one
        a5 += wv * T[c]
        c += one
        a6 += wv * T[c]
        c += one
        a7 += wv * T[c]
        c += one
        a8 += wv * T[c]
        c += one
        a9 += wv * T[c]
        c += one
        a10 += wv * T[c]
        c += one
        a11 += wv * T[c]
    S = _STRIDE
    W[j] = a0
    W[S + j] = a1
    W[2 * S + j] = a2
    W[3 * S + j] = a3
    W[4 * S + j] = a4
    W[5 * S + j] = a5
    W[6 * S + j] = a6
    W[7 * S + j] = a7
    W[8 * S + j] = a8
    W[9 * S + j] = a9
    W[10 * S + j] = a10
    W[11 * S + j] = a11


@_inline
def _stretch_at(W: np.ndarray, j: int, small_form: bool) -> tuple[float, float, float]:
    """exp(Y) v for scratch column j: by the Taylor form when small_form (`_stretch_small`), else by
    the closed form (`_stretch`). The vector loops pass a constant, so each holds one form only."""
    S = _STRIDE
    y0, y1, y2, y3, y4, y5 = (W[6 * S + j], W[7 * S + j], W[8 * S + j], W[9 * S + j], W[10 * S + j],
                              W[11 * S + j])
    v0, v1, v2 = W[12 * S + j], W[13 * S + j], W[14 * S + j]
    if small_form:
        return _stretch_small(y0, y1, y2, y3, y4, y5, v0, v1, v2)
    return _stretch(y0, y1, y2, y3, y4, y5, v0, v1, v2)


@_inline
def _y_small(W: np.ndarray, j: int) -> bool:
    """Every entry of column j's Y (scratch rows 6–11) is at most SMALL_Y in magnitude (NaN: not
    small). One comparison per entry, no rounding: every loop decides a row alike."""
    S = _STRIDE
    return ((abs(W[6 * S + j]) <= SMALL_Y) & (abs(W[7 * S + j]) <= SMALL_Y) & (abs(W[8 * S + j]) <= SMALL_Y)
            & (abs(W[9 * S + j]) <= SMALL_Y) & (abs(W[10 * S + j]) <= SMALL_Y)
            & (abs(W[11 * S + j]) <= SMALL_Y))


@_inline
def _put(W: np.ndarray, i: int, value: float, keep: bool) -> None:
    """W[i] = value unless keep (a select, not a branch: the loop stays vectorised)."""
    W[i] = W[i] if keep else value


@_inline
def _rigid_store(
    W: np.ndarray, j: int, e0: float, e1: float, e2: float, A: float, B: float, C: float, cth: float,
    keep: bool,
) -> None:
    """Scratch rows 15–17 of column j = R(ω) e + V(ω) u, unless keep (then left as they are)."""
    S = _STRIDE
    o0, o1, o2 = _rigid(W[j], W[S + j], W[2 * S + j], W[3 * S + j], W[4 * S + j], W[5 * S + j],
                        e0, e1, e2, A, B, C, cth)
    _put(W, 15 * S + j, o0, keep)
    _put(W, 16 * S + j, o1, keep)
    _put(W, 17 * S + j, o2, keep)


@_inline
def _theta_sq(W: np.ndarray, j: int) -> float:
    S = _STRIDE
    return W[j] * W[j] + W[S + j] * W[S + j] + W[2 * S + j] * W[2 * S + j]


@_inline
def _small_columns(W: np.ndarray) -> tuple[int, int]:
    """(how many columns have a small Y (`_y_small`), how many have θ > 1.8π), over all CHUNK."""
    n_small = 0
    n_big = 0
    for j in range(CHUNK):
        n_small += 1 if _y_small(W, j) else 0
        n_big += 1 if _theta_sq(W, j) > POLY_MAX_S else 0
    return n_small, n_big


@_inline
def _map(W: np.ndarray) -> int:
    """Result rows 15–17 = φ(rows 0–11) · rows 12–14 for every column of the flat scratch (row
    stride _STRIDE), θ-coefficients by polynomial; returns how many columns have θ > 1.8π (to be
    redone by `_fixup`).

    exp(Y) v takes one of two forms, chosen per column by `_y_small`: the Taylor form
    (`_stretch_small`; rigid controls, whose Y is float32 noise) or the closed form (`_stretch`).
    Each form has its own loop over all columns: the Taylor loop (when any column is small) stores
    every column, then the closed-form loop (when any is not small) stores the others. A column's
    bits therefore come from the same loop code whatever the rest of its chunk holds. One loop
    computing both forms and selecting does not give that: LLVM shares the products the two have in
    common there, a product used twice is not fused into an FMA, and a small row then had other
    bits in a mixed chunk than in an all-small one (measured).

    Always all CHUNK columns (unused ones zeroed by the caller): with this constant trip count, a
    multiple of any vector width × unroll, LLVM emits no scalar remainder loop, so every column goes
    through the same vector code. A remainder would compute some rows with scalar code, where FMA
    contraction and SLP operand order may differ from the vector body in the last bit."""
    n_small, n_big = _small_columns(W)
    if n_small > 0:
        for j in range(CHUNK):
            e0, e1, e2 = _stretch_at(W, j, True)
            A, B, C, cth = _rotation_coeffs_poly(_theta_sq(W, j))
            _rigid_store(W, j, e0, e1, e2, A, B, C, cth, False)
    if n_small < CHUNK:
        for j in range(CHUNK):
            e0, e1, e2 = _stretch_at(W, j, False)
            A, B, C, cth = _rotation_coeffs_poly(_theta_sq(W, j))
            _rigid_store(W, j, e0, e1, e2, A, B, C, cth, _y_small(W, j))
    return n_big


@_inline
def _fixup(W: np.ndarray, n: int) -> None:
    """Redo the columns j < n with θ > 1.8π with libm θ-coefficients (rare: lifted rotations). Kept
    scalar by a barrier: without it LLVM can vectorise this loop (variable trip count) in the entry,
    and a row then gets different bits in a full chunk than alone in a short one."""
    for j in range(n):
        _scalar_barrier()
        s = _theta_sq(W, j)
        if s > POLY_MAX_S:
            e0, e1, e2 = _stretch_at(W, j, _y_small(W, j))
            A, B, C, cth = _rotation_coeffs_libm(s)
            _rigid_store(W, j, e0, e1, e2, A, B, C, cth, False)


@_inline
def _motion_store_at(
    W: np.ndarray, j: int, A: float, B: float, C: float, cth: float, small_form: bool, keep: bool
) -> None:
    """Scratch rows 12–23 of column j = φ(rows 0–11) as the columns of M = R(ω) exp(Y) (rows 12–14,
    15–17, 18–20) and t = V(ω) u (rows 21–23): `_rigid` with u = 0 on the columns of exp(Y), and with
    the point 0. exp(Y) by the Taylor form when small_form (`_exp_sym_matrix_small`), else the closed
    form; nothing stored when keep."""
    S = _STRIDE
    w0, w1, w2 = W[j], W[S + j], W[2 * S + j]
    y = (W[6 * S + j], W[7 * S + j], W[8 * S + j], W[9 * S + j], W[10 * S + j], W[11 * S + j])
    if small_form:
        xx, yy, zz, xy, xz, yz = _exp_sym_matrix_small(y[0], y[1], y[2], y[3], y[4], y[5])
    else:
        xx, yy, zz, xy, xz, yz = _exp_sym_matrix(y[0], y[1], y[2], y[3], y[4], y[5])
    o0, o1, o2 = _rigid(w0, w1, w2, 0.0, 0.0, 0.0, xx, xy, xz, A, B, C, cth)
    _put(W, 12 * S + j, o0, keep)
    _put(W, 13 * S + j, o1, keep)
    _put(W, 14 * S + j, o2, keep)
    o0, o1, o2 = _rigid(w0, w1, w2, 0.0, 0.0, 0.0, xy, yy, yz, A, B, C, cth)
    _put(W, 15 * S + j, o0, keep)
    _put(W, 16 * S + j, o1, keep)
    _put(W, 17 * S + j, o2, keep)
    o0, o1, o2 = _rigid(w0, w1, w2, 0.0, 0.0, 0.0, xz, yz, zz, A, B, C, cth)
    _put(W, 18 * S + j, o0, keep)
    _put(W, 19 * S + j, o1, keep)
    _put(W, 20 * S + j, o2, keep)
    o0, o1, o2 = _rigid(w0, w1, w2, W[3 * S + j], W[4 * S + j], W[5 * S + j], 0.0, 0.0, 0.0, A, B, C, cth)
    _put(W, 21 * S + j, o0, keep)
    _put(W, 22 * S + j, o1, keep)
    _put(W, 23 * S + j, o2, keep)


@_inline
def _map_motion(W: np.ndarray) -> int:
    """Rows 12–23 = φ(rows 0–11) as (M e_x, M e_y, M e_z, t) for every column of the flat motion
    scratch (row stride _STRIDE), θ-coefficients by polynomial; returns how many columns have
    θ > 1.8π (to be redone by `_fixup_motion`). Always all CHUNK columns, and one loop per form of
    exp(Y), as `_map`."""
    n_small, n_big = _small_columns(W)
    if n_small > 0:
        for j in range(CHUNK):
            A, B, C, cth = _rotation_coeffs_poly(_theta_sq(W, j))
            _motion_store_at(W, j, A, B, C, cth, True, False)
    if n_small < CHUNK:
        for j in range(CHUNK):
            A, B, C, cth = _rotation_coeffs_poly(_theta_sq(W, j))
            _motion_store_at(W, j, A, B, C, cth, False, _y_small(W, j))
    return n_big


@_inline
def _fixup_motion(W: np.ndarray, n: int) -> None:
    """Redo the columns j < n with θ > 1.8π with libm θ-coefficients. Kept scalar by a barrier:
    without it LLVM vectorises this loop (variable trip count) in the entry point, and a row then
    gets different bits in a full chunk than alone in a short one."""
    for j in range(n):
        _scalar_barrier()
        s = _theta_sq(W, j)
        if s > POLY_MAX_S:
            A, B, C, cth = _rotation_coeffs_libm(s)
            _motion_store_at(W, j, A, B, C, cth, _y_small(W, j), False)


@_inline
def _motion_chunk(
    W: np.ndarray, table: np.ndarray, idx: np.ndarray, val: np.ndarray, rows: np.ndarray, a: int, n: int,
    use_rows: bool, out: np.ndarray, out32: np.ndarray, use32: bool,
) -> None:
    """Rows a … a+n−1 of the work list (0 … N−1, or `rows` when use_rows): blend, motion map, store
    into out[:, r] (float64), or with use32 into out32[:, r] (the float64 value rounded once: IEEE
    round to nearest, as numpy's cast). W: the scratch, _N_MOTION_SCRATCH rows of _STRIDE."""
    T, I, V = table.reshape(-1), idx.reshape(-1), val.reshape(-1)
    K = idx.shape[1]
    last = np.uint64(table.shape[0] - 1)
    for j in range(n):
        _blend_params(T, I, V, K, last, W, j, rows[a + j] if use_rows else a + j)
    for c in range(12):  # φ(0) in the unused columns (see `_map`)
        W[c * _STRIDE + n : c * _STRIDE + CHUNK] = 0.0
    if _map_motion(W) > 0:
        _fixup_motion(W, n)
    for j in range(n):
        r = rows[a + j] if use_rows else a + j
        for c in range(4):
            for t in range(3):
                res = W[(12 + 3 * c + t) * _STRIDE + j]
                if use32:
                    out32[c, r, t] = np.float32(res)
                else:
                    out[c, r, t] = res


@_inline
def _chunk(
    W: np.ndarray, points: np.ndarray, table: np.ndarray, idx: np.ndarray, val: np.ndarray, rows: np.ndarray,
    a: int, n: int, use_rows: bool, offsets: bool, out: np.ndarray, out32: np.ndarray, use32: bool,
) -> None:
    """Rows a … a+n−1 of the work list (0 … N−1, or `rows` when use_rows): blend, map, store (minus
    the point when offsets); with use32 also out32[r] = float32(out[r]) (one rounding of the stored
    value: IEEE round to nearest, as numpy's cast). W: the scratch, _N_SCRATCH rows of _STRIDE."""
    # Flat views once per chunk (a reshape per row would cost more than the blend).
    T, I, V, P = table.reshape(-1), idx.reshape(-1), val.reshape(-1), points.reshape(-1)
    K = idx.shape[1]
    last = np.uint64(table.shape[0] - 1)
    for j in range(n):
        _blend(T, I, V, P, K, last, W, j, rows[a + j] if use_rows else a + j)
    for c in range(15):  # φ(0) 0 = 0 in the unused columns (see `_map`)
        W[c * _STRIDE + n : c * _STRIDE + CHUNK] = 0.0
    if _map(W) > 0:
        _fixup(W, n)
    for j in range(n):
        r = rows[a + j] if use_rows else a + j
        for t in range(3):
            res = W[(15 + t) * _STRIDE + j]
            res = res - W[(12 + t) * _STRIDE + j] if offsets else res
            out[r, t] = res
            if use32:
                out32[r, t] = np.float32(res)


# ---------------------------------------------------------------------------------------------
# entry points (arguments validated by the caller: C-contiguous, float64 / int32 / intp)


def _entry(fn: Callable) -> Callable:
    """njit(nogil) with numba's on-disk cache when it has somewhere to write it. Without a cache
    locator (read-only install, no user cache dir) numba raises RuntimeError at decoration; then the
    kernel is compiled in every session instead.

    No parallel=True: a prange body is compiled as a separate gufunc library, which brings back the
    cached-versus-session difference of the module doc. Threads come from the caller instead: the
    entry releases the GIL, and every thread running one call claims chunks from a shared counter
    until none are left (a helper that starts late takes fewer)."""
    try:
        return numba.njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")(fn)
    except RuntimeError:
        return numba.njit(nogil=True, cache=False, fastmath=FASTMATH, error_model="numpy")(fn)


@_entry
def deform_points_entry(
    points: np.ndarray, table: np.ndarray, idx: np.ndarray, val: np.ndarray, rows: np.ndarray, use_rows: bool,
    offsets: bool, out: np.ndarray, out32: np.ndarray, use32: bool, counter: np.ndarray,
) -> int:
    """The point map on the chunks (CHUNK rows each) of the work list it claims from `counter` (a
    (1,) int64 array, 0 at the start of a call; chunk c is claimed by the thread that increments it
    from c, so a lone call with a fresh counter does every chunk): every row v (use_rows
    False: out[v] = φ(Σ_k val[v, k] table[idx[v, k]]) points[v]) or v = rows[i] (use_rows; other rows
    of out untouched); minus points[v] when offsets; with use32 also out32[v] = float32(out[v]) (the
    value np.astype(np.float32) gives), otherwise out32 is not accessed.

    points (N, 3) f64, table (m ≥ 1, 12) f64, idx (N, K) int32, val (N, K) f64, rows (n,) intp in
    [0, N) (empty when not use_rows; without repeats when out shares memory with points), out (N, 3)
    f64, out32 (N, 3) f32 (an empty (0, 3) one without use32). Full call and rows, float32 copy or
    not, all go through this one specialisation (see the module doc). out may be points itself in a
    full call (a chunk reads its rows before it writes them). Threads: call it on each with the same
    counter; a row's value does not depend on which thread computes its chunk. Returns how many
    chunks this thread did (when that is all of them, the other threads of the call write nothing)."""
    n = rows.shape[0] if use_rows else points.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    W = np.empty(_N_SCRATCH * _STRIDE)
    done = 0
    while True:
        c = _claim(counter)
        if c >= n_chunks:
            break
        a = c * CHUNK
        _chunk(W, points, table, idx, val, rows, a, min(CHUNK, n - a), use_rows, offsets, out, out32, use32)
        done += 1
    return done


@_entry
def motion_params(
    table: np.ndarray, idx: np.ndarray, val: np.ndarray, rows: np.ndarray, use_rows: bool, out: np.ndarray,
    out32: np.ndarray, use32: bool, counter: np.ndarray,
) -> int:
    """The affine map φ(p_v), p_v = Σ_k val[v, k] table[idx[v, k]], on the chunks of the work list it
    claims from `counter` (as `deform_points_entry`): every vertex v (use_rows False) or v = rows[i]
    (use_rows), as out[:, v] = (M e_x, M e_y, M e_z, t) (M = R(ω) exp(Y), t = V(ω) u); other rows
    untouched. table (m ≥ 1, 12) f64, idx (N, K) int32, val (N, K) f64, rows (n,) intp in [0, N)
    (empty when not use_rows), out (4, N, 3) f64; with use32 out32 (4, N, 3) f32 gets the float64
    value rounded once instead and out is not accessed. One specialisation for both output types
    (pass an empty (4, 0, 3) array for the unused one), full call or rows: see the module doc.
    Returns how many chunks this thread did, as `deform_points_entry`."""
    n = rows.shape[0] if use_rows else idx.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    W = np.empty(_N_MOTION_SCRATCH * _STRIDE)
    done = 0
    while True:
        c = _claim(counter)
        if c >= n_chunks:
            break
        a = c * CHUNK
        _motion_chunk(W, table, idx, val, rows, a, min(CHUNK, n - a), use_rows, out, out32, use32)
        done += 1
    return done


#: One-sided Jacobi (`polar_log`): a column pair is rotated while |a_p·a_q| > tol·|a_p||a_q|; at most
#: this many sweeps (3×3 matrices converge quadratically, in 3–5).
_JACOBI_TOL = 4.0 * 2.220446049250313e-16
_JACOBI_SWEEPS = 16


@_inline
def _polar_split(A: np.ndarray, V: np.ndarray, sig: np.ndarray, lsig: np.ndarray, R: np.ndarray,
                 Yh: np.ndarray) -> None:
    """R (3, 3) = U Vᵀ and Yh (3, 3) = V diag(log σ) Vᵀ for the SVD U diag(σ) Vᵀ of the matrix in A
    (3, 3), by the one-sided Jacobi sweeps of `polar_log` (its doc); A, V, sig, lsig are scratch (A
    is overwritten)."""
    for r in range(3):
        for c in range(3):
            V[r, c] = 1.0 if r == c else 0.0
    for _ in range(_JACOBI_SWEEPS):
        rotated = False
        for p in range(2):
            for q in range(p + 1, 3):
                alpha = A[0, p] * A[0, p] + A[1, p] * A[1, p] + A[2, p] * A[2, p]
                beta = A[0, q] * A[0, q] + A[1, q] * A[1, q] + A[2, q] * A[2, q]
                gamma = A[0, p] * A[0, q] + A[1, p] * A[1, q] + A[2, p] * A[2, q]
                if abs(gamma) > _JACOBI_TOL * math.sqrt(alpha * beta):
                    rotated = True
                    zeta = (beta - alpha) / (2.0 * gamma)
                    t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                    cs = 1.0 / math.sqrt(1.0 + t * t)
                    sn = cs * t
                    for r in range(3):
                        ap = A[r, p]
                        aq = A[r, q]
                        A[r, p] = cs * ap - sn * aq
                        A[r, q] = sn * ap + cs * aq
                        vp = V[r, p]
                        vq = V[r, q]
                        V[r, p] = cs * vp - sn * vq
                        V[r, q] = sn * vp + cs * vq
        if not rotated:
            break
    for c in range(3):
        sig[c] = math.sqrt(A[0, c] * A[0, c] + A[1, c] * A[1, c] + A[2, c] * A[2, c])
        lsig[c] = math.log(sig[c])
    for r in range(3):
        for k in range(3):
            rr = 0.0
            yy = 0.0
            for c in range(3):
                rr += (A[r, c] / sig[c]) * V[k, c]
                yy += (V[r, c] * lsig[c]) * V[k, c]
            R[r, k] = rr
            Yh[r, k] = yy


@_entry
def polar_log(M: np.ndarray, R: np.ndarray, Yh: np.ndarray) -> int:
    """The polar split of ψ for each M[i] (n, 3, 3) f64 with det > 0: R[i] = U Vᵀ and
    Yh[i] = V diag(log σ) Vᵀ for the SVD M = U diag(σ) Vᵀ (so M = R exp(Yh), Yh = ½ log(MᵀM)), the
    quantities `core.aff3.params_from_matrices` takes from numpy's SVD; returns n.

    The SVD is one-sided Jacobi (Hestenes): plane rotations of column pairs (p, q) of A = M V,
    ζ = (‖a_q‖² − ‖a_p‖²)/(2 a_p·a_q), t = sign ζ/(|ζ| + √(1 + ζ²)), c = 1/√(1 + t²), s = c t,
    (a_p, a_q) ← (c a_p − s a_q, s a_p + c a_q) (and the same on V), which makes a_p ⊥ a_q; sweeps
    until no pair exceeds _JACOBI_TOL. Then σ_c = ‖a_c‖, u_c = a_c/σ_c, R = Σ_c u_c v_cᵀ and
    Yh = Σ_c log σ_c v_c v_cᵀ (independent of the order and signs of the singular pairs). Backward
    stable like LAPACK's SVD (no MᵀM is formed); R and Yh agree with the numpy path to ~1e-15 relative
    for well-conditioned M. Non-finite input gives non-finite output. Scalar code, one thread."""
    n = M.shape[0]
    A = np.empty((3, 3))
    V = np.empty((3, 3))
    sig = np.empty(3)
    lsig = np.empty(3)
    for i in range(n):
        for r in range(3):
            for c in range(3):
                A[r, c] = M[i, r, c]
        _polar_split(A, V, sig, lsig, R[i], Yh[i])
    return n


@_inline
def _linear_columns(w0: float, w1: float, w2: float, y: np.ndarray, o: int
                    ) -> tuple[float, float, float, float, float, float, float, float, float]:
    """M = R(ω) exp(Y) (the linear part of φ(ω, 0, Y)), row-major, Y = y[o : o + 6] in the layout
    (xx, yy, zz, xy, xz, yz); the map of `_motion_store_at` (polynomial θ-coefficients up to 1.8π,
    libm beyond), one row at a time."""
    s = w0 * w0 + w1 * w1 + w2 * w2
    if s > POLY_MAX_S:
        A, B, C, cth = _rotation_coeffs_libm(s)
    else:
        A, B, C, cth = _rotation_coeffs_poly(s)
    xx, yy, zz, xy, xz, yz = _exp_sym_matrix(y[o], y[o + 1], y[o + 2], y[o + 3], y[o + 4], y[o + 5])
    c00, c10, c20 = _rigid(w0, w1, w2, 0.0, 0.0, 0.0, xx, xy, xz, A, B, C, cth)
    c01, c11, c21 = _rigid(w0, w1, w2, 0.0, 0.0, 0.0, xy, yy, yz, A, B, C, cth)
    c02, c12, c22 = _rigid(w0, w1, w2, 0.0, 0.0, 0.0, xz, yz, zz, A, B, C, cth)
    return c00, c01, c02, c10, c11, c12, c20, c21, c22


@_inline
def _jacobian_inv_apply(w0: float, w1: float, w2: float, v0: float, v1: float, v2: float
                        ) -> tuple[float, float, float]:
    """V(ω)⁻¹ v = v − ½ ω × v + d(θ) ω × (ω × v), d = (1 − (θ/2) cot(θ/2))/θ² (its series
    1/12 + θ²/720 + θ⁴/30240 + θ⁶/1209600 + θ⁸/47900160 below θ = 0.2), as core.aff3's
    left_jacobian_inv."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = math.sqrt(t2)
    if theta < 0.2:
        d = (((t2 * (1.0 / 47900160) + 1.0 / 1209600) * t2 + 1.0 / 30240) * t2 + 1.0 / 720) * t2 + 1.0 / 12
    else:
        half = 0.5 * theta
        d = (1.0 - half * math.cos(half) / math.sin(half)) / t2
    a0 = w1 * v2 - w2 * v1
    a1 = w2 * v0 - w0 * v2
    a2 = w0 * v1 - w1 * v0
    b0 = w1 * a2 - w2 * a1
    b1 = w2 * a0 - w0 * a2
    b2 = w0 * a1 - w1 * a0
    return v0 - 0.5 * a0 + d * b0, v1 - 0.5 * a1 + d * b1, v2 - 0.5 * a2 + d * b2


@_entry
def node_pivot(finish: bool, A: np.ndarray, x: np.ndarray, out: np.ndarray) -> int:
    """The two per-row steps of core.cage_harmonic.node_params (its module doc), one row at a time;
    returns the row count.

    finish False (faces): A (n, 12) face parameters (ω, u, Y) → out (n, 9) B = V(ω)⁻¹ (M − I)
    row-major, M = R(ω) exp(Y) (face_blend_terms' B; x unused, pass an empty (0, 3) array).
    finish True (nodes): A (G, 21) the nodes' blended (ω, u, Y, B), x (G, 3) the node points →
    out (G, 12) = (ω, u′, Y) with u′ = u + B x + V(ω)⁻¹ (x − M x), M the linear part for (ω, 0, Y).
    Scalar code, one thread (a few hundred rows)."""
    n = A.shape[0]
    for i in range(n):
        w0, w1, w2 = A[i, 0], A[i, 1], A[i, 2]
        c00, c01, c02, c10, c11, c12, c20, c21, c22 = _linear_columns(w0, w1, w2, A[i], 6)
        if finish:
            p0, p1, p2 = x[i, 0], x[i, 1], x[i, 2]
            v0 = p0 - (c00 * p0 + c01 * p1 + c02 * p2)
            v1 = p1 - (c10 * p0 + c11 * p1 + c12 * p2)
            v2 = p2 - (c20 * p0 + c21 * p1 + c22 * p2)
            j0, j1, j2 = _jacobian_inv_apply(w0, w1, w2, v0, v1, v2)
            u0 = A[i, 3] + (A[i, 12] * p0 + A[i, 13] * p1 + A[i, 14] * p2)
            u1 = A[i, 4] + (A[i, 15] * p0 + A[i, 16] * p1 + A[i, 17] * p2)
            u2 = A[i, 5] + (A[i, 18] * p0 + A[i, 19] * p1 + A[i, 20] * p2)
            for k in range(3):
                out[i, k] = A[i, k]
            out[i, 3] = u0 + j0
            out[i, 4] = u1 + j1
            out[i, 5] = u2 + j2
            for k in range(6, 12):
                out[i, k] = A[i, k]
        else:
            b00, b10, b20 = _jacobian_inv_apply(w0, w1, w2, c00 - 1.0, c10, c20)
            b01, b11, b21 = _jacobian_inv_apply(w0, w1, w2, c01, c11 - 1.0, c21)
            b02, b12, b22 = _jacobian_inv_apply(w0, w1, w2, c02, c12, c22 - 1.0)
            out[i, 0], out[i, 1], out[i, 2] = b00, b01, b02
            out[i, 3], out[i, 4], out[i, 5] = b10, b11, b12
            out[i, 6], out[i, 7], out[i, 8] = b20, b21, b22
    return n


# ---------------------------------------------------------------------------------------------
# a cage's faces (core.cage.face_motions for the faces a shape change reaches), one call per update

#: core.cage's constants, repeated here because numba's cache is keyed on this file alone (a changed
#: constant in core/cage.py would not recompile a cached entry); tests/core/test_accel_cage.py checks
#: they are equal.
COLLAPSED_SIN = 1e-10
FOLD_KAPPA = 0.5
#: unwrap._no_row_lifts' bounds: |ω_ref − ω|² below the first and |ω|² below the second prove that
#: lifting ω onto ω_ref's branch is a no-op.
NO_LIFT_DIST_SQ = 9.0
NO_LIFT_NORM_SQ = 1e12
#: cage_faces' per-face flags.
FACE_REACHED = 1
FACE_HAS_CORNER = 2
FACE_VALID = 4
FACE_NEEDS_LIFT = 8


@_inline
def _finite3(a: float, b: float, c: float) -> bool:
    return math.isfinite(a) and math.isfinite(b) and math.isfinite(c)


@_inline
def _so3_log(R: np.ndarray) -> tuple[float, float, float]:
    """The principal rotation vector of R (3, 3), as core.aff3.so3_log: θ = atan2(|s|, (tr R − 1)/2)
    with s = vee(R); ω = (θ/|s|) s for cos θ ≥ 0, else θ times the largest column of
    (R + Rᵀ)/2 − cos θ I normalised, signed by s."""
    s0 = 0.5 * (R[2, 1] - R[1, 2])
    s1 = 0.5 * (R[0, 2] - R[2, 0])
    s2 = 0.5 * (R[1, 0] - R[0, 1])
    sin_t = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    cos_t = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    cos_t = 1.0 if cos_t > 1.0 else cos_t
    cos_t = -1.0 if cos_t < -1.0 else cos_t
    theta = math.atan2(sin_t, cos_t)
    if cos_t < 0.0:
        k = 0
        best = R[0, 0] - cos_t
        for j in range(1, 3):
            if R[j, j] - cos_t > best:
                best = R[j, j] - cos_t
                k = j
        c0 = 0.5 * (R[0, k] + R[k, 0]) - (cos_t if k == 0 else 0.0)
        c1 = 0.5 * (R[1, k] + R[k, 1]) - (cos_t if k == 1 else 0.0)
        c2 = 0.5 * (R[2, k] + R[k, 2]) - (cos_t if k == 2 else 0.0)
        norm = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if norm > 0.0:
            c0, c1, c2 = c0 / norm, c1 / norm, c2 / norm
        st = -theta if c0 * s0 + c1 * s1 + c2 * s2 < 0.0 else theta
        return st * c0, st * c1, st * c2
    ratio = theta / sin_t if sin_t > 0.0 else 1.0
    return ratio * s0, ratio * s1, ratio * s2


@_inline
def _corner_affine(
    cur: np.ndarray, moved: np.ndarray, t: int, triples: np.ndarray, rest_ok: np.ndarray, centres: np.ndarray,
    inverses: np.ndarray, sv: np.ndarray, sg: np.ndarray, smom: np.ndarray, sspread: np.ndarray,
    sactive: np.ndarray, out: np.ndarray,
) -> bool:
    """core.cage.corner_matrices for corner t: out[t, 0:9] = M = E′ E⁻¹ row-major and out[t, 9:12] =
    c′ − M c, E′ = [e1′, e2′, h′] the current frame with the fitted, fold-guarded stencil apex where
    the corner has a stencil, an input of it moved bitwise and the fit is finite (the normal apex
    n′/√|n′| otherwise). Returns ok: both corners uncollapsed (sin > COLLAPSED_SIN), everything
    finite and det M > 0 (out is not meaningful otherwise)."""
    i0, i1, i2 = triples[t, 0], triples[t, 1], triples[t, 2]
    p00, p01, p02 = cur[i0, 0], cur[i0, 1], cur[i0, 2]
    a0, a1, a2 = cur[i1, 0] - p00, cur[i1, 1] - p01, cur[i1, 2] - p02  # e1′
    b0, b1, b2 = cur[i2, 0] - p00, cur[i2, 1] - p01, cur[i2, 2] - p02  # e2′
    n0, n1, n2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    area2 = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    edges = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2) * math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    sin_cur = area2 / edges if edges > 0.0 else 0.0
    root = math.sqrt(area2)
    h0, h1, h2 = n0 / root, n1 / root, n2 / root
    c0 = (cur[i0, 0] + cur[i1, 0] + cur[i2, 0]) / 3.0
    c1 = (cur[i0, 1] + cur[i1, 1] + cur[i2, 1]) / 3.0
    c2 = (cur[i0, 2] + cur[i1, 2] + cur[i2, 2]) / 3.0
    if sactive[t]:
        reached = moved[i0] or moved[i1] or moved[i2]
        for s in range(sv.shape[1]):
            if sg[t, s] != 0.0 and moved[sv[t, s]]:
                reached = True
        if reached:
            u0, u1, u2 = n0 / area2, n1 / area2, n2 / area2
            f0 = 0.0
            f1 = 0.0
            f2 = 0.0
            m = 0.0
            for s in range(sv.shape[1]):
                g = sg[t, s]
                v = sv[t, s]
                q0, q1, q2 = cur[v, 0] - c0, cur[v, 1] - c1, cur[v, 2] - c2
                f0 += g * q0
                f1 += g * q1
                f2 += g * q2
                m += abs(g) * abs(q0 * u0 + q1 * u1 + q2 * u2)
            f0 -= smom[t, 1] * a0 + smom[t, 2] * b0
            f1 -= smom[t, 1] * a1 + smom[t, 2] * b1
            f2 -= smom[t, 1] * a2 + smom[t, 2] * b2
            x = f0 * u0 + f1 * u1 + f2 * u2
            floor = FOLD_KAPPA * m / sspread[t]
            if x < floor:  # the fold guard: x ↦ floor²/(2 floor − x) below the floor
                lift = floor * floor / (2.0 * floor - x) - x
                f0 += lift * u0
                f1 += lift * u1
                f2 += lift * u2
            if _finite3(f0, f1, f2):
                h0, h1, h2 = f0, f1, f2
    ok = rest_ok[t] and sin_cur > COLLAPSED_SIN
    ok = ok and _finite3(a0, a1, a2) and _finite3(b0, b1, b2)
    ok = ok and _finite3(h0, h1, h2) and _finite3(c0, c1, c2)
    if not ok:
        return False
    # M = E′ E⁻¹, E′ with columns e1′, e2′, h′: M_ij = e1′_i E⁻¹_0j + e2′_i E⁻¹_1j + h′_i E⁻¹_2j
    m00 = a0 * inverses[t, 0, 0] + b0 * inverses[t, 1, 0] + h0 * inverses[t, 2, 0]
    m01 = a0 * inverses[t, 0, 1] + b0 * inverses[t, 1, 1] + h0 * inverses[t, 2, 1]
    m02 = a0 * inverses[t, 0, 2] + b0 * inverses[t, 1, 2] + h0 * inverses[t, 2, 2]
    m10 = a1 * inverses[t, 0, 0] + b1 * inverses[t, 1, 0] + h1 * inverses[t, 2, 0]
    m11 = a1 * inverses[t, 0, 1] + b1 * inverses[t, 1, 1] + h1 * inverses[t, 2, 1]
    m12 = a1 * inverses[t, 0, 2] + b1 * inverses[t, 1, 2] + h1 * inverses[t, 2, 2]
    m20 = a2 * inverses[t, 0, 0] + b2 * inverses[t, 1, 0] + h2 * inverses[t, 2, 0]
    m21 = a2 * inverses[t, 0, 1] + b2 * inverses[t, 1, 1] + h2 * inverses[t, 2, 1]
    m22 = a2 * inverses[t, 0, 2] + b2 * inverses[t, 1, 2] + h2 * inverses[t, 2, 2]
    r0, r1, r2 = centres[t, 0], centres[t, 1], centres[t, 2]
    out[t, 0], out[t, 1], out[t, 2] = m00, m01, m02
    out[t, 3], out[t, 4], out[t, 5] = m10, m11, m12
    out[t, 6], out[t, 7], out[t, 8] = m20, m21, m22
    out[t, 9] = c0 - (m00 * r0 + m01 * r1 + m02 * r2)
    out[t, 10] = c1 - (m10 * r0 + m11 * r1 + m12 * r2)
    out[t, 11] = c2 - (m20 * r0 + m21 * r1 + m22 * r2)
    det = m00 * (m11 * m22 - m12 * m21) + m01 * (m12 * m20 - m10 * m22) + m02 * (m10 * m21 - m11 * m20)
    good = det > 0.0
    for k in range(12):
        good = good and math.isfinite(out[t, k])
    return good


@_inline
def _psi_row(out: np.ndarray, t: int, A: np.ndarray, Vs: np.ndarray, sig: np.ndarray, lsig: np.ndarray,
             R: np.ndarray, Yh: np.ndarray) -> bool:
    """out[t] (M row-major, then t) ← ψ in the 12-number layout (ω, u = V(ω)⁻¹ t, Y₆), as
    core.aff3.params_from_matrices with the polar split of `polar_log`; returns whether it is finite.
    A, Vs, sig, lsig, R, Yh: scratch."""
    for r in range(3):
        for c in range(3):
            A[r, c] = out[t, 3 * r + c]
    t0, t1, t2 = out[t, 9], out[t, 10], out[t, 11]
    _polar_split(A, Vs, sig, lsig, R, Yh)
    w0, w1, w2 = _so3_log(R)
    u0, u1, u2 = _jacobian_inv_apply(w0, w1, w2, t0, t1, t2)
    out[t, 0], out[t, 1], out[t, 2] = w0, w1, w2
    out[t, 3], out[t, 4], out[t, 5] = u0, u1, u2
    out[t, 6], out[t, 7], out[t, 8] = Yh[0, 0], Yh[1, 1], Yh[2, 2]
    out[t, 9] = 0.5 * (Yh[0, 1] + Yh[1, 0])
    out[t, 10] = 0.5 * (Yh[0, 2] + Yh[2, 0])
    out[t, 11] = 0.5 * (Yh[1, 2] + Yh[2, 1])
    finite = True
    for k in range(12):
        finite = finite and math.isfinite(out[t, k])
    return finite


@_entry
def psi_rows(out: np.ndarray) -> int:
    """ψ of every row of out (n, 12) f64 in place: (M row-major, t) ↦ (ω, u, Y₆), the 12-number
    layout of core.aff3.params_from_matrices (`_psi_row`: the polar split of `polar_log`, ω the
    principal log of R, u = V(ω)⁻¹ t), agreeing with it to ~1e-15; det M > 0 is checked by the
    caller. Returns the first row that is not finite, −1 when every row is. Scalar code, one thread:
    the controls that moved in one update, a handful of rows."""
    A = np.empty((3, 3))
    Vs = np.empty((3, 3))
    sig = np.empty(3)
    lsig = np.empty(3)
    R = np.empty((3, 3))
    Yh = np.empty((3, 3))
    bad = -1
    for t in range(out.shape[0]):
        if not _psi_row(out, t, A, Vs, sig, lsig, R, Yh) and bad < 0:
            bad = t
    return bad


@_inline
def _cage_face(
    cur: np.ndarray, moved: np.ndarray, a: int, b: int, triples: np.ndarray, usable: np.ndarray,
    weight: np.ndarray, rest_ok: np.ndarray, centres: np.ndarray, inverses: np.ndarray, sv: np.ndarray,
    sg: np.ndarray, smom: np.ndarray, sspread: np.ndarray, sactive: np.ndarray, out: np.ndarray,
    corner_params: np.ndarray, scratch: np.ndarray, sig: np.ndarray,
) -> int:
    """`cage_faces` for the face owning corners a … b − 1: out (12,) its parameters, corner_params
    its corners' ψ; returns its flags. scratch (4, 3, 3), sig (2, 3): scratch."""
    reached = False
    has = False
    for t in range(a, b):
        has = has or usable[t]
        if moved[triples[t, 0]] or moved[triples[t, 1]] or moved[triples[t, 2]]:
            reached = True
        for s in range(sv.shape[1]):
            if sg[t, s] != 0.0 and moved[sv[t, s]]:
                reached = True
    for k in range(12):
        out[k] = 0.0
    flag = (FACE_REACHED if reached else 0) | (FACE_HAS_CORNER if has else 0)
    if not reached:
        return flag
    valid = has
    for t in range(a, b):
        ok = _corner_affine(cur, moved, t, triples, rest_ok, centres, inverses, sv, sg, smom, sspread,
                            sactive, corner_params)
        if usable[t] and not ok:
            valid = False
    if valid:
        for t in range(a, b):
            if usable[t] and not _psi_row(corner_params, t, scratch[0], scratch[1], sig[0], sig[1],
                                          scratch[2], scratch[3]):
                valid = False
    ref = -1
    lift = False
    for t in range(a, b):
        if not (valid and usable[t]):
            for k in range(12):
                corner_params[t, k] = 0.0
            continue
        if ref < 0:
            ref = t
        w0, w1, w2 = corner_params[t, 0], corner_params[t, 1], corner_params[t, 2]
        d0, d1, d2 = corner_params[ref, 0] - w0, corner_params[ref, 1] - w1, corner_params[ref, 2] - w2
        near = d0 * d0 + d1 * d1 + d2 * d2 < NO_LIFT_DIST_SQ
        if not (near and w0 * w0 + w1 * w1 + w2 * w2 < NO_LIFT_NORM_SQ):
            lift = True
    if not valid:
        return flag
    if lift:
        return flag | FACE_VALID | FACE_NEEDS_LIFT
    for t in range(a, b):
        if usable[t]:
            for k in range(12):
                out[k] += weight[t] * corner_params[t, k]
    return flag | FACE_VALID


@_inline
def _fan_volume(cur: np.ndarray, fan: np.ndarray) -> float:
    """Σ a·(b × c)/6 over the fan triangles (a, b, c) of `fan` (Tf, 3), about the mean of cur (V, 3)."""
    V = cur.shape[0]
    o0 = 0.0
    o1 = 0.0
    o2 = 0.0
    for v in range(V):
        o0 += cur[v, 0]
        o1 += cur[v, 1]
        o2 += cur[v, 2]
    o0, o1, o2 = o0 / V, o1 / V, o2 / V
    volume = 0.0
    for i in range(fan.shape[0]):
        j0, j1, j2 = fan[i, 0], fan[i, 1], fan[i, 2]
        x0, x1, x2 = cur[j0, 0] - o0, cur[j0, 1] - o1, cur[j0, 2] - o2
        y0, y1, y2 = cur[j1, 0] - o0, cur[j1, 1] - o1, cur[j1, 2] - o2
        z0, z1, z2 = cur[j2, 0] - o0, cur[j2, 1] - o1, cur[j2, 2] - o2
        volume += x0 * (y1 * z2 - y2 * z1) + x1 * (y2 * z0 - y0 * z2) + x2 * (y0 * z1 - y1 * z0)
    return volume / 6.0


@_entry
def cage_faces(
    cur: np.ndarray, rest: np.ndarray, triples: np.ndarray, first: np.ndarray, usable: np.ndarray,
    weight: np.ndarray, rest_ok: np.ndarray, centres: np.ndarray, inverses: np.ndarray, sv: np.ndarray,
    sg: np.ndarray, smom: np.ndarray, sspread: np.ndarray, sactive: np.ndarray, fan: np.ndarray,
    moved: np.ndarray, params: np.ndarray, corner_params: np.ndarray, flags: np.ndarray,
) -> float:
    """core.cage.face_motions (apex 'NEIGHBOURS', no w_ref or pivot) for the faces the shape change
    reaches (core.cage.affected_faces), and the signed volume Σ a·(b × c)/6 over the fan triangles
    `fan` about the mean vertex (core.cage.signed_volume), which it returns.

    cur, rest (V, 3) f64: the current and rest cage; corners t (rows of CageTopology.corner_triples,
    grouped by face: face f owns first[f] … first[f+1] − 1): triples (T, 3) int64, usable (T,) bool
    and weight (T,) f64 (core.cage.RestCorners), rest_ok (T,) bool (rest corner uncollapsed and
    finite), centres (T, 3) and inverses (T, 3, 3) the rest centroids and E⁻¹; the stencils
    (core.cage.ApexStencil): vertices sv (T, S) int64, gamma sg (T, S), moments smom (T, 3), spread
    sspread (T,), active sactive (T,) bool. moved (V,) bool: scratch (a vertex moved bitwise; NaN
    counts as moved).

    Per face f: flags[f] has FACE_REACHED when a corner or stencil vertex of it moved (the others get
    params 0 and nothing else is computed), FACE_HAS_CORNER when it has a usable rest corner,
    FACE_VALID when it is reached, has one, and every usable corner's tetrahedron is uncollapsed with
    det > 0 and a finite ψ. Then corner_params[t] = ψ(A_t) of its usable corners (principal branch)
    and params[f] = Σ_t weight[t] corner_params[t] in corner order — unless lifting the corners onto
    the first one's rotation branch might change one (|ω_ref − ω|² ≥ NO_LIFT_DIST_SQ or |ω|² ≥
    NO_LIFT_NORM_SQ): then FACE_NEEDS_LIFT is set, params[f] is 0 and the caller lifts and sums
    (`affine_deformers.accel.cage_faces`). A face's results depend on its own inputs only (scalar code,
    one thread), so they are the same bits whichever other faces moved."""
    for v in range(cur.shape[0]):
        moved[v] = cur[v, 0] != rest[v, 0] or cur[v, 1] != rest[v, 1] or cur[v, 2] != rest[v, 2]
    scratch = np.empty((4, 3, 3))
    sig = np.empty((2, 3))
    for f in range(first.shape[0] - 1):
        flags[f] = _cage_face(cur, moved, first[f], first[f + 1], triples, usable, weight, rest_ok,
                              centres, inverses, sv, sg, smom, sspread, sactive, params[f], corner_params,
                              scratch, sig)
    return _fan_volume(cur, fan)


@_entry
def cage_nodes(
    Wt: np.ndarray, reached: np.ndarray, faces: np.ndarray, face_params: np.ndarray, keep: np.ndarray,
    totals: np.ndarray, fill_totals: bool, x: np.ndarray, terms: np.ndarray, blend: np.ndarray,
    out: np.ndarray, touched: np.ndarray,
) -> int:
    """core.cage_harmonic.node_params for the nodes a moved face reaches, in one call; returns how
    many nodes that is.

    Wt (F, G) f64: the node weights transposed (face by face; W_cf = Wt[f, c]); reached (n_r,)
    int64: the faces that moved (valid or not); faces (n,) int64 those of them to blend (valid),
    face_params (n, 12) their parameters (ω, u, Y); keep (F,) f64 1 for a valid face, 0 for one left
    out; totals (G,) f64 the sums T_c = Σ_f W_cf keep_f over every face, computed into it when
    fill_totals and read from it otherwise (they are the same on every update with the same weights
    and valid faces: the caller keeps them; scale_c = 1 / T_c, 0 for a node without any valid face);
    x (G, 3) the node points. Scratch: terms (n, 21), blend (21, G).

    touched[c] = W_cf > 0 for some reached face f; out[c] (G, 12) = (ω̄, ū + V(ω̄)⁻¹ (x − M̄ x), Ȳ)
    for those (zeros for the others) with (ω̄, ū, Ȳ, B̄) = scale_c Σ_f W_cf (ω_f, u_f, Y_f, B_f),
    ū ← ū + B̄ x_c, B_f = V(ω_f)⁻¹ (M_f − I) (`node_pivot`'s two steps). The sums run over `faces`
    in the given order (four at a time, then one at a time), so a node's result depends on its own
    weights and those faces only. Scalar
    and loops over all G nodes (LLVM may vectorise the blend across nodes: every node is in the same
    loop whatever the call, so its bits do not depend on which nodes are touched)."""
    G = Wt.shape[1]
    n = faces.shape[0]
    for c in range(G):
        touched[c] = False
    for i in range(reached.shape[0]):
        f = reached[i]
        for c in range(G):
            if Wt[f, c] > 0.0:
                touched[c] = True
    for i in range(n):
        w0, w1, w2 = face_params[i, 0], face_params[i, 1], face_params[i, 2]
        c00, c01, c02, c10, c11, c12, c20, c21, c22 = _linear_columns(w0, w1, w2, face_params[i], 6)
        b00, b10, b20 = _jacobian_inv_apply(w0, w1, w2, c00 - 1.0, c10, c20)
        b01, b11, b21 = _jacobian_inv_apply(w0, w1, w2, c01, c11 - 1.0, c21)
        b02, b12, b22 = _jacobian_inv_apply(w0, w1, w2, c02, c12, c22 - 1.0)
        for k in range(12):
            terms[i, k] = face_params[i, k]
        terms[i, 12], terms[i, 13], terms[i, 14] = b00, b01, b02
        terms[i, 15], terms[i, 16], terms[i, 17] = b10, b11, b12
        terms[i, 18], terms[i, 19], terms[i, 20] = b20, b21, b22
    if fill_totals:
        for c in range(G):
            totals[c] = 0.0
        for f in range(Wt.shape[0]):
            kf = keep[f]
            for c in range(G):
                totals[c] += Wt[f, c] * kf
    for k in range(21):
        for c in range(G):
            blend[k, c] = 0.0
    # Four faces per pass over the nodes: a quarter of the loads and stores of `blend`, which is
    # the bound of this loop (the weights' rows are read once either way).
    i = 0
    while i + 4 <= n:
        f0, f1, f2, f3 = faces[i], faces[i + 1], faces[i + 2], faces[i + 3]
        for k in range(21):
            t0, t1, t2, t3 = terms[i, k], terms[i + 1, k], terms[i + 2, k], terms[i + 3, k]
            for c in range(G):
                blend[k, c] += (Wt[f0, c] * t0 + Wt[f1, c] * t1) + (Wt[f2, c] * t2 + Wt[f3, c] * t3)
        i += 4
    while i < n:
        f = faces[i]
        for k in range(21):
            term = terms[i, k]
            for c in range(G):
                blend[k, c] += Wt[f, c] * term
        i += 1
    count = 0
    y = np.empty(12)
    for c in range(G):
        for k in range(12):
            out[c, k] = 0.0
        if not touched[c]:
            continue
        count += 1
        s = 1.0 / totals[c] if totals[c] > 0.0 else 0.0
        w0, w1, w2 = blend[0, c] * s, blend[1, c] * s, blend[2, c] * s
        for k in range(6, 12):
            y[k] = blend[k, c] * s
        c00, c01, c02, c10, c11, c12, c20, c21, c22 = _linear_columns(w0, w1, w2, y, 6)
        p0, p1, p2 = x[c, 0], x[c, 1], x[c, 2]
        v0 = p0 - (c00 * p0 + c01 * p1 + c02 * p2)
        v1 = p1 - (c10 * p0 + c11 * p1 + c12 * p2)
        v2 = p2 - (c20 * p0 + c21 * p1 + c22 * p2)
        j0, j1, j2 = _jacobian_inv_apply(w0, w1, w2, v0, v1, v2)
        u0 = blend[3, c] * s + (blend[12, c] * s * p0 + blend[13, c] * s * p1 + blend[14, c] * s * p2)
        u1 = blend[4, c] * s + (blend[15, c] * s * p0 + blend[16, c] * s * p1 + blend[17, c] * s * p2)
        u2 = blend[5, c] * s + (blend[18, c] * s * p0 + blend[19, c] * s * p1 + blend[20, c] * s * p2)
        out[c, 0], out[c, 1], out[c, 2] = w0, w1, w2
        out[c, 3], out[c, 4], out[c, 5] = u0 + j0, u1 + j1, u2 + j2
        for k in range(6, 12):
            out[c, k] = y[k]
    return count


# ---------------------------------------------------------------------------------------------
# a product of blends per vertex (core.hierarchy: bones blending down their hierarchy), one chunk at
# a time: the passes run on the scratch in turn, so nothing goes back to memory between them


@_inline
def _prefix_indices(prefix: np.ndarray, mats: np.ndarray, rows: np.ndarray, a: int, n: int, use_rows: bool,
                    Q: np.ndarray) -> None:
    """Q[j] = 12 × the prefix row of column j (the identity row, the last of `mats`, in the unused
    columns), clamped to the table."""
    last = np.uint64(mats.shape[0] - 1)
    for j in range(n):
        r = rows[a + j] if use_rows else a + j
        Q[j] = min(np.uint64(prefix[r]), last) * np.uint64(12)
    Q[n:CHUNK] = last * np.uint64(12)


@_inline
def _prefix_at(Mf: np.ndarray, q: np.uint64) -> tuple[float, ...]:
    """The 12 numbers (row-major M, then t) of the flat prefix table at offset q (unsigned offsets, as
    in `_blend_params`)."""
    one = np.uint64(1)
    m00 = Mf[q]
    q += one
    m01 = Mf[q]
    q += one
    m02 = Mf[q]
    q += one
    m10 = Mf[q]
    q += one
    m11 = Mf[q]
    q += one
    m12 = Mf[q]
    q += one
    m20 = Mf[q]
    q += one
    m21 = Mf[q]
    q += one
    m22 = Mf[q]
    q += one
    t0 = Mf[q]
    q += one
    t1 = Mf[q]
    q += one
    t2 = Mf[q]
    return m00, m01, m02, m10, m11, m12, m20, m21, m22, t0, t1, t2


@_inline
def _chain_chunk(
    W: np.ndarray, Q: np.ndarray, points: np.ndarray, table: np.ndarray, idx: np.ndarray, val: np.ndarray,
    prefix: np.ndarray, mats: np.ndarray, rows: np.ndarray, a: int, n: int, use_rows: bool, offsets: bool,
    out: np.ndarray, out32: np.ndarray, use32: bool,
) -> None:
    """Rows a … a+n−1 of the work list: x = points[r], then for each pass p = 0 … P−1 in turn
    x ← φ(Σ_k val[p, r, k] table[idx[p, r, k]]) x, then x ← M x + t with (M, t) = mats[prefix[r]]
    (row-major M, then t), stored as `_chunk` stores (minus the point when offsets). W:
    _N_CHAIN_SCRATCH rows of _STRIDE (rows 18–20 keep the original point); Q: CHUNK uint64."""
    S = _STRIDE
    T, Pf, Mf = table.reshape(-1), points.reshape(-1), mats.reshape(-1)
    n_pass, K = idx.shape[0], idx.shape[2]
    stride = idx.shape[1] * K
    I, V = idx.reshape(-1), val.reshape(-1)
    last = np.uint64(table.shape[0] - 1)
    for j in range(n):
        r = rows[a + j] if use_rows else a + j
        for t in range(3):
            W[(12 + t) * S + j] = Pf[3 * r + t]
            W[(18 + t) * S + j] = Pf[3 * r + t]
    for c in range(12, 15):  # φ(0) 0 = 0 in the unused columns (see `_map`)
        W[c * S + n : c * S + CHUNK] = 0.0
    for p in range(n_pass):
        Ip, Vp = I[p * stride : (p + 1) * stride], V[p * stride : (p + 1) * stride]
        for j in range(n):
            _blend_params(T, Ip, Vp, K, last, W, j, rows[a + j] if use_rows else a + j)
        for c in range(12):
            W[c * S + n : c * S + CHUNK] = 0.0
        if _map(W) > 0:
            _fixup(W, n)
        for t in range(3):  # the result is the next pass's point (all columns: see `_map`)
            W[(12 + t) * S : (12 + t) * S + CHUNK] = W[(15 + t) * S : (15 + t) * S + CHUNK]
    _prefix_indices(prefix, mats, rows, a, n, use_rows, Q)
    for j in range(CHUNK):  # constant trip count, as `_map`
        m00, m01, m02, m10, m11, m12, m20, m21, m22, t0, t1, t2 = _prefix_at(Mf, Q[j])
        x0, x1, x2 = W[12 * S + j], W[13 * S + j], W[14 * S + j]
        W[15 * S + j] = m00 * x0 + m01 * x1 + m02 * x2 + t0
        W[16 * S + j] = m10 * x0 + m11 * x1 + m12 * x2 + t1
        W[17 * S + j] = m20 * x0 + m21 * x1 + m22 * x2 + t2
    for j in range(n):
        r = rows[a + j] if use_rows else a + j
        for t in range(3):
            res = W[(15 + t) * S + j]
            res = res - W[(18 + t) * S + j] if offsets else res
            out[r, t] = res
            if use32:
                out32[r, t] = np.float32(res)


@_inline
def _compose_store(W: np.ndarray) -> None:
    """Rows 24–35 (the product so far, columns M e_x, M e_y, M e_z, t) ← product ∘ rows 12–23 (the
    factor just mapped), for every column of the scratch (constant trip count, as `_map`)."""
    S = _STRIDE
    for j in range(CHUNK):
        g0, g1, g2 = W[24 * S + j], W[25 * S + j], W[26 * S + j]
        g3, g4, g5 = W[27 * S + j], W[28 * S + j], W[29 * S + j]
        g6, g7, g8 = W[30 * S + j], W[31 * S + j], W[32 * S + j]
        g9, g10, g11 = W[33 * S + j], W[34 * S + j], W[35 * S + j]
        for c in range(4):
            h0, h1, h2 = W[(12 + 3 * c) * S + j], W[(13 + 3 * c) * S + j], W[(14 + 3 * c) * S + j]
            o0 = g0 * h0 + g3 * h1 + g6 * h2
            o1 = g1 * h0 + g4 * h1 + g7 * h2
            o2 = g2 * h0 + g5 * h1 + g8 * h2
            if c == 3:
                o0, o1, o2 = o0 + g9, o1 + g10, o2 + g11
            W[(24 + 3 * c) * S + j] = o0
            W[(25 + 3 * c) * S + j] = o1
            W[(26 + 3 * c) * S + j] = o2


@_inline
def _chain_motion_chunk(
    W: np.ndarray, Q: np.ndarray, table: np.ndarray, idx: np.ndarray, val: np.ndarray, prefix: np.ndarray,
    mats: np.ndarray, rows: np.ndarray, a: int, n: int, use_rows: bool, out: np.ndarray, out32: np.ndarray,
    use32: bool,
) -> None:
    """Rows a … a+n−1 of the work list: the motion (M, t) ∘ F_(P−1) ∘ ⋯ ∘ F_0 with F_p = φ(Σ_k
    val[p, r, k] table[idx[p, r, k]]) and (M, t) = mats[prefix[r]], stored as `_motion_chunk` stores.
    W: _N_CHAIN_MOTION_SCRATCH rows of _STRIDE (rows 24–35 hold the product, built from the prefix
    down); Q: CHUNK uint64."""
    S = _STRIDE
    T, Mf = table.reshape(-1), mats.reshape(-1)
    n_pass, K = idx.shape[0], idx.shape[2]
    stride = idx.shape[1] * K
    I, V = idx.reshape(-1), val.reshape(-1)
    last = np.uint64(table.shape[0] - 1)
    _prefix_indices(prefix, mats, rows, a, n, use_rows, Q)
    for j in range(CHUNK):  # the prefix's columns M e_x, M e_y, M e_z, then t
        m00, m01, m02, m10, m11, m12, m20, m21, m22, t0, t1, t2 = _prefix_at(Mf, Q[j])
        W[24 * S + j], W[25 * S + j], W[26 * S + j] = m00, m10, m20
        W[27 * S + j], W[28 * S + j], W[29 * S + j] = m01, m11, m21
        W[30 * S + j], W[31 * S + j], W[32 * S + j] = m02, m12, m22
        W[33 * S + j], W[34 * S + j], W[35 * S + j] = t0, t1, t2
    for step in range(n_pass):
        p = n_pass - 1 - step
        Ip, Vp = I[p * stride : (p + 1) * stride], V[p * stride : (p + 1) * stride]
        for j in range(n):
            _blend_params(T, Ip, Vp, K, last, W, j, rows[a + j] if use_rows else a + j)
        for c in range(12):
            W[c * S + n : c * S + CHUNK] = 0.0
        if _map_motion(W) > 0:
            _fixup_motion(W, n)
        _compose_store(W)
    for j in range(n):
        r = rows[a + j] if use_rows else a + j
        for c in range(4):
            for t in range(3):
                res = W[(24 + 3 * c + t) * S + j]
                if use32:
                    out32[c, r, t] = np.float32(res)
                else:
                    out[c, r, t] = res


@_entry
def chain_points_entry(
    points: np.ndarray, table: np.ndarray, idx: np.ndarray, val: np.ndarray, prefix: np.ndarray,
    mats: np.ndarray, rows: np.ndarray, use_rows: bool, offsets: bool, out: np.ndarray, out32: np.ndarray,
    use32: bool, counter: np.ndarray,
) -> int:
    """`deform_points_entry` for a product of P blends per vertex and a matrix (core.hierarchy):
    idx (P, N, K) int32 and val (P, N, K) f64 hold pass p's weights of every vertex (a zero row is
    φ(0) = identity; pass 0 acts first), then prefix (N,) int32 picks each vertex's final matrix in
    mats (m' ≥ 1, 12) f64 (row-major M, then t). Other arguments, threads and rows as
    `deform_points_entry`, but out must not share memory with points. Returns the chunks this thread
    did, as `deform_points_entry`."""
    n = rows.shape[0] if use_rows else points.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    W = np.empty(_N_CHAIN_SCRATCH * _STRIDE)
    Q = np.empty(CHUNK, dtype=np.uint64)
    done = 0
    while True:
        c = _claim(counter)
        if c >= n_chunks:
            break
        a = c * CHUNK
        done += 1
        _chain_chunk(W, Q, points, table, idx, val, prefix, mats, rows, a, min(CHUNK, n - a), use_rows,
                     offsets, out, out32, use32)
    return done


@_entry
def chain_motion_entry(
    table: np.ndarray, idx: np.ndarray, val: np.ndarray, prefix: np.ndarray, mats: np.ndarray,
    rows: np.ndarray, use_rows: bool, out: np.ndarray, out32: np.ndarray, use32: bool, counter: np.ndarray,
) -> int:
    """`motion_params` for the product of `chain_points_entry`: the motion (M, t) ∘ F_(P−1) ∘ ⋯ ∘ F_0
    (idx, val, prefix, mats as there); other arguments and the return value as `motion_params`."""
    n = rows.shape[0] if use_rows else prefix.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    W = np.empty(_N_CHAIN_MOTION_SCRATCH * _STRIDE)
    Q = np.empty(CHUNK, dtype=np.uint64)
    done = 0
    while True:
        c = _claim(counter)
        if c >= n_chunks:
            break
        a = c * CHUNK
        done += 1
        _chain_motion_chunk(W, Q, table, idx, val, prefix, mats, rows, a, min(CHUNK, n - a), use_rows, out,
                            out32, use32)
    return done


@_entry
def rows_reading(hit: np.ndarray, idx: np.ndarray, val: np.ndarray, out: np.ndarray) -> int:
    """The vertices v with val[v, k] != 0 and hit[idx[v, k]] for some k, in increasing order, into
    out[:count]; returns count. hit (m,) bool, idx (N, K) int32 (an index outside [0, m) flags
    nothing), val (N, K) f64, out (N,) intp. One pass over the weights, no numerics."""
    m = hit.shape[0]
    count = 0
    for v in range(idx.shape[0]):
        for k in range(idx.shape[1]):
            j = idx[v, k]
            if val[v, k] != 0.0 and 0 <= j < m and hit[j]:
                out[count] = v
                count += 1
                break
    return count


#: Words `same_words` compares between early exits: a fixed trip count LLVM vectorises (a loop that
#: can leave at every word is scalar, 2.5× slower than numpy), 16 KiB per array between checks.
_SAME_BLOCK = 4096


@_entry
def same_words(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the uint32 arrays a and b (n,) (same n, checked by the caller) hold the same words:
    the OR of a[i] XOR b[i] over blocks of _SAME_BLOCK, leaving at the first block that differs.
    No numerics: float data compares bit for bit (−0.0 ≠ 0.0, a NaN equals its own bits)."""
    n = a.shape[0]
    blocks = n // _SAME_BLOCK
    for block in range(blocks):
        base = block * _SAME_BLOCK
        diff = np.uint32(0)
        for i in range(_SAME_BLOCK):
            diff |= a[base + i] ^ b[base + i]
        if diff != 0:
            return False
    tail = np.uint32(0)
    for i in range(blocks * _SAME_BLOCK, n):
        tail |= a[i] ^ b[i]
    return tail == 0


@_entry
def spin_wait(flag: np.ndarray, seen: int, n: int) -> bool:
    """Busy-wait without the GIL until flag[0] != seen (True) or for n iterations (False): keeps an
    idle helper thread of `affine_deformers.accel` awake for a moment after a call, so one that
    follows at once does not wait for the thread (or its virtual CPU) to wake up. No numerics."""
    for _ in range(n):
        if _load_relaxed(flag) != seen:
            return True
        _cpu_relax()
    return False
