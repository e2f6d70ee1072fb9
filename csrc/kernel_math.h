/* The per-vertex map's scalar pieces, inlined into the vectorised loops of kernel_vertex.c and
 * kernel_chain.c and used one row at a time by kernel_controls.c (see affine_kernel.h for the
 * conventions and affine_deformers/accel/native.py for the Python side). Same mathematics as
 * core/deform.py, parameters P = (omega, u, Y6) with Y6 = (xx, yy, zz, xy, xz, yz):
 *
 *     v' = R(w) exp(Y) v + V(w) u,
 *     exp(Y) = e^{e1} (I + alpha Z + g Z^2),  Z = Y - e1 I,  e0 <= e1 <= e2 the eigenvalues of Y,
 *     x = e0 - e1 <= 0 <= y = e2 - e1,  g = (y h2(y) - x h2(x))/(y - x),  alpha = 1 + x (h2(x) - g),
 *     h2(z) = (e^z - 1 - z)/z^2,
 *     R w + V u = cos(t) w + A u + w x (A w + B u) + (B w.w + C w.u) w,
 *     A = sin t/t, B = (1 - cos t)/t^2, C = (t - sin t)/t^3, t = |w|.
 *
 * Bit-identity. The Blender layer recomputes only the rows a changed control influences and keeps
 * the others, so a row's result must not depend on the call, the chunk, its position in it or the
 * thread. The kernel gets that from IEEE semantics alone: every file is compiled without -ffast-math
 * and with -ffp-contract=off (no FMA formation), so a vectorised loop computes every lane with exactly the
 * operations of the scalar code, and no sum is reordered. The vectorisable loops run over all CHUNK
 * columns anyway (unused columns zeroed), and the rare libm fix-ups are scalar.
 *
 * Vectorisation. The map runs on a structure-of-arrays scratch (one row of STRIDE doubles per
 * quantity) in straight-line loops without calls or branches (selects only), which clang vectorises
 * across vertices. libm does not vectorise, so the transcendentals there are polynomials:
 *  - acos(r): pi/2 - asin(r) for |r| <= 1/2, else 2 asin(sqrt((1 - |r|)/2)) (reflected for r < 0);
 *    asin(s) = s F(s^2), F the Taylor series sum C(2k,k)/(4^k (2k+1)) z^k to degree 24 on z <= 1/4.
 *  - exp(z) = 2^n e^rho: n = round(z/ln 2) by adding 1.5*2^52, rho = (z - n ln2_hi) - n ln2_lo
 *    (Cody-Waite: ln2_hi has its low 11 bits cleared), e^rho Taylor degree 13; 2^n from the integer
 *    bits of the rounded sum; z clamped to +-709.
 *  - h2(z): Taylor to degree 17 for |z| <= 1, the direct formula beyond.
 *  - sin x/x: Taylor in x^2 to degree 9 for the quarter angle x = t/4 (t <= 1.8 pi), degree 8 for the
 *    eigen-angle a <= pi/3; cosines as sqrt(1 - sin^2) and double-angle formulas. For t > 1.8 pi
 *    (lifted rotations) a scalar pass redoes the column with libm sin/cos (`ak_fixup_*`).
 *  - C = (1 - A)/(t^2 + 1e-14): makes t = 0 safe without a branch.
 *  - exp(Y) of a small Y (every |Y_ij| <= SMALL_Y: rigid controls, whose Y is float32 noise): the
 *    cubic Taylor polynomial; such columns skip the spectrum, each form in a loop of its own.
 *
 * Memory safety: indices into tables are clamped (one min per slot), so wrong but vouched-for
 * inputs can give wrong values, never an out-of-bounds read.
 *
 * Everything here is static inline: each file that includes it gets the same code. */
#ifndef KERNEL_MATH_H
#define KERNEL_MATH_H

#include <math.h>
#include <stdint.h>
#include <string.h>

#pragma STDC FP_CONTRACT OFF

/* The map's pieces must inline into the vectorised loops: a call in a loop body stops vectorisation. */
#define AK_INLINE static inline __attribute__((always_inline))

#define LN2_HI 0x1.62e42fefa3800p-1
#define LN2_LO 0x1.ef35793c76730p-45
#define LOG2E 0x1.71547652b82fep+0
#define SQRT3 0x1.bb67ae8584caap+0
#define PI 0x1.921fb54442d18p+1
#define ROUND_MAGIC 6755399441055744.0 /* 1.5 * 2^52 */
#define EXP_MAX 709.0
#define TINY 0x1p-1022
#define POLY_MAX_S 0x1.ffa3ea2fbec10p+4 /* (1.8 pi)^2 */
#define SMALL_Y 4e-5
#define C_CLAMP_S 1e-14

typedef struct { double x, y, z; } v3;
typedef struct { double A, B, C, c; } rot_coeffs;
typedef struct { double xx, yy, zz, xy, xz, yz; } sym6;

/* ------------------------------------------------------------------------------------------------
 * polynomials (Horner, coefficients exact to the double nearest the series' terms) */

AK_INLINE double sinc_quarter(double z) { return (((((((((-0x1.2f49b46814157p-57) * z + 0x1.952c77030ad4ap-49) * z + -0x1.ae7f3e733b81fp-41) * z + 0x1.6124613a86d09p-33) * z + -0x1.ae64567f544e4p-26) * z + 0x1.71de3a556c734p-19) * z + -0x1.a01a01a01a01ap-13) * z + 0x1.1111111111111p-7) * z + -0x1.5555555555555p-3) * z + 0x1.0000000000000p+0; }
AK_INLINE double sinc_eig(double z) { return ((((((((0x1.952c77030ad4ap-49) * z + -0x1.ae7f3e733b81fp-41) * z + 0x1.6124613a86d09p-33) * z + -0x1.ae64567f544e4p-26) * z + 0x1.71de3a556c734p-19) * z + -0x1.a01a01a01a01ap-13) * z + 0x1.1111111111111p-7) * z + -0x1.5555555555555p-3) * z + 0x1.0000000000000p+0; }
AK_INLINE double asin_f(double z) { return ((((((((((((((((((((((((0x1.3275586c5f2f0p-9) * z + 0x1.464c0950f7d47p-9) * z + 0x1.5c5f56efaaaabp-9) * z + 0x1.750de64d7d05fp-9) * z + 0x1.90cb77f60c7cep-9) * z + 0x1.b026f57b13b14p-9) * z + 0x1.d3d2a8e0dd67dp-9) * z + 0x1.fcaf8fb6db6dbp-9) * z + 0x1.15ee9d45d1746p-8) * z + 0x1.31683bdef7bdfp-8) * z + 0x1.51ba308d3dcb1p-8) * z + 0x1.782dda12f684cp-8) * z + 0x1.a6863d70a3d71p-8) * z + 0x1.df3bd37a6f4dfp-8) * z + 0x1.12ef3cf3cf3cfp-7) * z + 0x1.3fde50d79435ep-7) * z + 0x1.7a87878787878p-7) * z + 0x1.c99999999999ap-7) * z + 0x1.1c4ec4ec4ec4fp-6) * z + 0x1.6e8ba2e8ba2e9p-6) * z + 0x1.f1c71c71c71c7p-6) * z + 0x1.6db6db6db6db7p-5) * z + 0x1.3333333333333p-4) * z + 0x1.5555555555555p-3) * z + 0x1.0000000000000p+0; }
AK_INLINE double exp_taylor(double z) { return (((((((((((((0x1.6124613a86d09p-33) * z + 0x1.1eed8eff8d898p-29) * z + 0x1.ae64567f544e4p-26) * z + 0x1.27e4fb7789f5cp-22) * z + 0x1.71de3a556c734p-19) * z + 0x1.a01a01a01a01ap-16) * z + 0x1.a01a01a01a01ap-13) * z + 0x1.6c16c16c16c17p-10) * z + 0x1.1111111111111p-7) * z + 0x1.5555555555555p-5) * z + 0x1.5555555555555p-3) * z + 0x1.0000000000000p-1) * z + 0x1.0000000000000p+0) * z + 0x1.0000000000000p+0; }
AK_INLINE double h2_taylor(double z) { return (((((((((((((((((0x1.2f49b46814157p-57) * z + 0x1.6827863b97d97p-53) * z + 0x1.952c77030ad4ap-49) * z + 0x1.ae7f3e733b81fp-45) * z + 0x1.ae7f3e733b81fp-41) * z + 0x1.93974a8c07c9dp-37) * z + 0x1.6124613a86d09p-33) * z + 0x1.1eed8eff8d898p-29) * z + 0x1.ae64567f544e4p-26) * z + 0x1.27e4fb7789f5cp-22) * z + 0x1.71de3a556c734p-19) * z + 0x1.a01a01a01a01ap-16) * z + 0x1.a01a01a01a01ap-13) * z + 0x1.6c16c16c16c17p-10) * z + 0x1.1111111111111p-7) * z + 0x1.5555555555555p-5) * z + 0x1.5555555555555p-3) * z + 0x1.0000000000000p-1; }

/* ------------------------------------------------------------------------------------------------
 * branch-free scalar pieces of the map (inlined into the vectorised loops) */

AK_INLINE double bits_to_double(uint64_t b) { double d; memcpy(&d, &b, sizeof d); return d; }
AK_INLINE uint64_t double_to_bits(double d) { uint64_t b; memcpy(&b, &d, sizeof b); return b; }

/* e^z = 2^n e^rho, z clamped to [-709, 709]. The low 12 bits of kn's bit pattern hold n mod 2^12;
 * n + 1023 in [0, 2046] is the biased exponent. */
AK_INLINE double exp_poly(double z) {
    z = z > EXP_MAX ? EXP_MAX : z;
    z = z < -EXP_MAX ? -EXP_MAX : z;
    double kn = z * LOG2E + ROUND_MAGIC;
    double n = kn - ROUND_MAGIC;
    double rho = (z - n * LN2_HI) - n * LN2_LO;
    return exp_taylor(rho) * bits_to_double((double_to_bits(kn) + 1023u) << 52);
}

/* (e^z - 1 - z)/z^2: Taylor for |z| <= 1, direct beyond (both computed, one selected). */
AK_INLINE double h2(double z) {
    double zz = z * z;
    int big = zz > 1.0;
    double direct = (exp_poly(z) - 1.0 - z) / (big ? zz : 1.0);
    return big ? direct : h2_taylor(z);
}

/* arccos(r)/3 for r in [-1, 1] via asin on |argument| <= 1/2. */
AK_INLINE double acos_third(double r) {
    double ar = r >= 0.0 ? r : -r;
    int big = ar > 0.5;
    double zb = 0.5 * (1.0 - ar);
    double s = big ? sqrt(zb) : r;
    double t = s * asin_f(big ? zb : r * r);
    double acos_big = r > 0.0 ? 2.0 * t : PI - 2.0 * t;
    return (big ? acos_big : 0.5 * PI - t) * (1.0 / 3.0);
}

/* exp(Y) = E I + alpha' Z + g' Z^2 with Z = Y - e1 I (its diagonal z0..z2, its off-diagonal Y's),
 * E = e^{e1}, alpha' = E alpha, g' = E g. */
typedef struct { double E, alpha, g, z0, z1, z2; } exp_sym;

AK_INLINE exp_sym exp_sym_coeffs(double yxx, double yyy, double yzz, double yxy, double yxz, double yyz) {
    double q = (yxx + yyy + yzz) * (1.0 / 3.0);
    double b0 = yxx - q, b1 = yyy - q, b2 = yzz - q;
    double det = b0 * b1 * b2 + 2.0 * yxy * yxz * yyz - b0 * yyz * yyz - b1 * yxz * yxz - b2 * yxy * yxy;
    double p2 = (b0 * b0 + b1 * b1 + b2 * b2 + 2.0 * (yxy * yxy + yxz * yxz + yyz * yyz)) * (1.0 / 6.0);
    double p = sqrt(p2);
    /* r = det(B/p)/2 in [-1, 1] up to rounding; TINY only avoids 0/0 for a multiple of I. */
    double r = det / (2.0 * p2 * p + TINY);
    r = r > 1.0 ? 1.0 : r;
    r = r < -1.0 ? -1.0 : r;
    double a = acos_third(r);
    double sa = sinc_eig(a * a) * a;
    double ca = sqrt(1.0 - sa * sa);
    double sb = 0.5 * SQRT3 * ca - 0.5 * sa; /* sin(pi/3 - a) */
    double x = -2.0 * SQRT3 * p * sa;
    double y = 2.0 * SQRT3 * p * sb;
    double e1 = q - (x + y) * (1.0 / 3.0);
    double h2x = h2(x), h2y = h2(y);
    /* y - x >= 0 vanishes only for x = y = 0, where g multiplies Z = 0. */
    double g = (y * h2y - x * h2x) / (y - x + TINY);
    double alpha = 1.0 + x * (h2x - g);
    double E = exp_poly(e1);
    exp_sym out = {E, alpha * E, g * E, yxx - e1, yyy - e1, yzz - e1};
    return out;
}

/* exp(Y) v = (alpha' Z v + g' Z^2 v) + E v. */
AK_INLINE v3 stretch(const sym6 y, double v0, double v1, double v2) {
    exp_sym s = exp_sym_coeffs(y.xx, y.yy, y.zz, y.xy, y.xz, y.yz);
    double zv0 = s.z0 * v0 + y.xy * v1 + y.xz * v2;
    double zv1 = y.xy * v0 + s.z1 * v1 + y.yz * v2;
    double zv2 = y.xz * v0 + y.yz * v1 + s.z2 * v2;
    double zz0 = s.z0 * zv0 + y.xy * zv1 + y.xz * zv2;
    double zz1 = y.xy * zv0 + s.z1 * zv1 + y.yz * zv2;
    double zz2 = y.xz * zv0 + y.yz * zv1 + s.z2 * zv2;
    v3 o = {s.alpha * zv0 + s.g * zz0 + s.E * v0, s.alpha * zv1 + s.g * zz1 + s.E * v1,
            s.alpha * zv2 + s.g * zz2 + s.E * v2};
    return o;
}

/* exp(Y) = (alpha' Z + g' Z^2) + E I. */
AK_INLINE sym6 exp_sym_matrix(const sym6 y) {
    exp_sym s = exp_sym_coeffs(y.xx, y.yy, y.zz, y.xy, y.xz, y.yz);
    double a = y.xy, b = y.xz, c = y.yz;
    double aa = a * a, bb = b * b, cc = c * c;
    sym6 o = {s.alpha * s.z0 + s.g * (s.z0 * s.z0 + aa + bb) + s.E,
              s.alpha * s.z1 + s.g * (s.z1 * s.z1 + aa + cc) + s.E,
              s.alpha * s.z2 + s.g * (s.z2 * s.z2 + bb + cc) + s.E,
              s.alpha * a + s.g * (a * (s.z0 + s.z1) + b * c),
              s.alpha * b + s.g * (b * (s.z0 + s.z2) + a * c),
              s.alpha * c + s.g * (c * (s.z1 + s.z2) + a * b)};
    return o;
}

AK_INLINE v3 sym_apply(const sym6 y, double v0, double v1, double v2) {
    v3 o = {y.xx * v0 + y.xy * v1 + y.xz * v2, y.xy * v0 + y.yy * v1 + y.yz * v2,
            y.xz * v0 + y.yz * v1 + y.zz * v2};
    return o;
}

/* exp(Y) v ~ v + Y(v + Y(v/2 + Y(v/6))) for |Y_ij| <= SMALL_Y: the first term left out, Y^4 v/24,
 * is < 1e-17 relative to v. */
AK_INLINE v3 stretch_small(const sym6 y, double v0, double v1, double v2) {
    const double k = 1.0 / 6.0;
    v3 s = sym_apply(y, k * v0, k * v1, k * v2);
    v3 b = sym_apply(y, 0.5 * v0 + s.x, 0.5 * v1 + s.y, 0.5 * v2 + s.z);
    v3 c = sym_apply(y, v0 + b.x, v1 + b.y, v2 + b.z);
    v3 o = {v0 + c.x, v1 + c.y, v2 + c.z};
    return o;
}

/* Y S for symmetric Y, S that commute (S a polynomial in Y): symmetric, its upper triangle. */
AK_INLINE sym6 sym_times(const sym6 y, const sym6 s) {
    sym6 o = {y.xx * s.xx + y.xy * s.xy + y.xz * s.xz,
              y.xy * s.xy + y.yy * s.yy + y.yz * s.yz,
              y.xz * s.xz + y.yz * s.yz + y.zz * s.zz,
              y.xx * s.xy + y.xy * s.yy + y.xz * s.yz,
              y.xx * s.xz + y.xy * s.yz + y.xz * s.zz,
              y.xy * s.xz + y.yy * s.yz + y.yz * s.zz};
    return o;
}

/* exp(Y) ~ I + Y(I + Y(I/2 + Y/6)) for |Y_ij| <= SMALL_Y. */
AK_INLINE sym6 exp_sym_matrix_small(const sym6 y) {
    const double k = 1.0 / 6.0;
    sym6 s1 = {0.5 + k * y.xx, 0.5 + k * y.yy, 0.5 + k * y.zz, k * y.xy, k * y.xz, k * y.yz};
    sym6 a = sym_times(y, s1);
    sym6 s2 = {1.0 + a.xx, 1.0 + a.yy, 1.0 + a.zz, a.xy, a.xz, a.yz};
    sym6 b = sym_times(y, s2);
    sym6 o = {1.0 + b.xx, 1.0 + b.yy, 1.0 + b.zz, b.xy, b.xz, b.yz};
    return o;
}

/* (A, B, C, cos t) from s = t^2 by the quarter-angle polynomial; accurate for t <= 1.8 pi. */
AK_INLINE rot_coeffs rotation_coeffs_poly(double s) {
    double zq = s * (1.0 / 16.0);
    double sq = sinc_quarter(zq); /* sin(t/4)/(t/4) */
    double tq = sq * sq * zq;     /* sin^2(t/4) */
    double cq2 = 1.0 - tq;
    cq2 = cq2 < 0.0 ? 0.0 : cq2; /* only reachable for t > 1.8 pi, which the fix-up redoes */
    double sh = sq * sqrt(cq2);  /* sin(t/2)/(t/2) */
    double A = sh * (1.0 - 2.0 * tq);
    double B = 0.5 * sh * sh;
    rot_coeffs o = {A, B, (1.0 - A) / (s + C_CLAMP_S), 1.0 - B * s};
    return o;
}

/* (A, B, C, cos t) with libm sin/cos, for t > 1.8 pi only (no small-t care needed). */
static inline rot_coeffs rotation_coeffs_libm(double s) {
    double th = sqrt(s);
    double st = sin(th);
    double half = sin(0.5 * th) / (0.5 * th);
    rot_coeffs o = {st / th, 0.5 * half * half, (th - st) / (th * s), cos(th)};
    return o;
}

/* R(w) e + V(w) u from the t-coefficients. */
AK_INLINE v3 rigid(double w0, double w1, double w2, double u0, double u1, double u2, double e0, double e1,
                       double e2, rot_coeffs k) {
    double d = k.B * (w0 * e0 + w1 * e1 + w2 * e2) + k.C * (w0 * u0 + w1 * u1 + w2 * u2);
    double m0 = k.A * e0 + k.B * u0;
    double m1 = k.A * e1 + k.B * u1;
    double m2 = k.A * e2 + k.B * u2;
    v3 o = {w1 * m2 - w2 * m1 + k.c * e0 + k.A * u0 + w0 * d,
            w2 * m0 - w0 * m2 + k.c * e1 + k.A * u1 + w1 * d,
            w0 * m1 - w1 * m0 + k.c * e2 + k.A * u2 + w2 * d};
    return o;
}

#endif
