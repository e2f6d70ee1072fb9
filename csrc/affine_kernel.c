/* The compiled kernel (see affine_kernel.h for the conventions and affine_deformers/accel/native.py
 * for the Python side). Same mathematics as core/deform.py, parameters P = (omega, u, Y6) with Y6 =
 * (xx, yy, zz, xy, xz, yz):
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
 * thread. This file gets that from IEEE semantics alone: it is compiled without -ffast-math and with
 * -ffp-contract=off (no FMA formation), so a vectorised loop computes every lane with exactly the
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
 *    (lifted rotations) a scalar pass redoes the column with libm sin/cos (`fixup_*`).
 *  - C = (1 - A)/(t^2 + 1e-14): makes t = 0 safe without a branch.
 *  - exp(Y) of a small Y (every |Y_ij| <= SMALL_Y: rigid controls, whose Y is float32 noise): the
 *    cubic Taylor polynomial; such columns skip the spectrum, each form in a loop of its own.
 *
 * Memory safety: indices into tables are clamped (one min per slot), so wrong but vouched-for
 * inputs can give wrong values, never an out-of-bounds read. */
#include "affine_kernel.h"
#include "affine_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#if defined(__x86_64__) || defined(_M_X64)
#include <immintrin.h>
#define CPU_RELAX() _mm_pause()
#else
#define CPU_RELAX() ((void)0)
#endif

#pragma STDC FP_CONTRACT OFF

/* The map's pieces must inline into the vectorised loops: a call in a loop body stops vectorisation. */
#define AK_INLINE static inline __attribute__((always_inline))

#define CHUNK 2048
/* Rows a multiple of 4 KiB apart alias in the L1 cache; the map touches ~20 rows at once. */
#define STRIDE (CHUNK + 8)
#define N_POINT_ROWS 18        /* 12 parameters, 3 point coordinates, 3 results */
#define N_MOTION_ROWS 24       /* 12 parameters, 12 results (M e_x, M e_y, M e_z, t) */
#define N_CHAIN_ROWS 21        /* as points, plus the original point (offsets) */
#define N_CHAIN_MOTION_ROWS 36 /* as motions, plus the product so far */

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

/* core.cage's constants (tests/core/test_accel_cage.py compares them through native.py). */
#define COLLAPSED_SIN 1e-10
#define FOLD_KAPPA 0.5
#define NO_LIFT_DIST_SQ 9.0
#define NO_LIFT_NORM_SQ 1e12
#define FACE_REACHED 1
#define FACE_HAS_CORNER 2
#define FACE_VALID 4
#define FACE_NEEDS_LIFT 8

#define JACOBI_TOL (4.0 * 2.220446049250313e-16)
#define JACOBI_SWEEPS 16
#define SAME_BLOCK 4096

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

/* ------------------------------------------------------------------------------------------------
 * scratch: a few reusable buffers (a fresh large allocation per call would fault its pages in
 * every time); a call that finds none free allocates its own */

#define POOL 8
static void *pool_buf[POOL];
static size_t pool_size[POOL];
static int pool_busy[POOL];

static void *scratch_get(size_t bytes, int *slot) {
    for (int i = 0; i < POOL; i++) {
        if (__atomic_exchange_n(&pool_busy[i], 1, __ATOMIC_ACQUIRE) == 0) {
            if (pool_size[i] < bytes) {
                free(pool_buf[i]);
                pool_buf[i] = malloc(bytes);
                pool_size[i] = pool_buf[i] ? bytes : 0;
            }
            if (pool_buf[i]) {
                *slot = i;
                return pool_buf[i];
            }
            __atomic_store_n(&pool_busy[i], 0, __ATOMIC_RELEASE);
            break;
        }
    }
    *slot = -1;
    return malloc(bytes);
}

static void scratch_put(void *buf, int slot) {
    if (slot >= 0)
        __atomic_store_n(&pool_busy[slot], 0, __ATOMIC_RELEASE);
    else
        free(buf);
}

static inline int64_t claim(int64_t *counter) { return __atomic_fetch_add(counter, 1, __ATOMIC_RELAXED); }

/* Whether every row of a work list indexes [0, n): checked before anything is written (a row out of
 * range would be written to). One compare per row, against numpy's two reductions. */
static int rows_in_range(const int64_t *rows, int64_t n_rows, int64_t n) {
    int bad = 0;
    for (int64_t i = 0; i < n_rows; i++) bad |= (rows[i] < 0) | (rows[i] >= n);
    return !bad;
}

#define ROWS_OUT_OF_RANGE (-2)

/* ------------------------------------------------------------------------------------------------
 * one chunk: blend, map, fix-up, store */

#define ROW(W, k) ((W) + (size_t)(k) * STRIDE)

/* Scratch rows 0-11 of column j = sum_k V[r, k] T[I[r, k]] (slot order). A zero weight adds exactly
 * +-0 to a sum that is never -0 (it starts at +0, and x + y = 0 rounds to +0), so skipping it gives
 * the same bits; sparse weights leave most slots empty. Indices clamped to the table (a negative one
 * becomes huge as unsigned). */
/* Four doubles as one value (clang/GCC vector extension; elementwise IEEE operations, so the same
 * bits as four scalar ones). Written out because the SLP vectoriser, left to twelve scalar sums,
 * shuffles them in every iteration. */
typedef double d4 __attribute__((vector_size(32)));

AK_INLINE d4 load4(const double *p) { d4 v; memcpy(&v, p, sizeof v); return v; }

AK_INLINE void blend_params(const double *T, const int32_t *I, const double *V, int64_t K, uint64_t last,
                            double *W, int64_t j, int64_t r) {
    d4 a = {0.0, 0.0, 0.0, 0.0}, b = a, c = a;
    const int32_t *Ir = I + r * K;
    const double *Vr = V + r * K;
    for (int64_t k = 0; k < K; k++) {
        double wv = Vr[k];
        if (wv == 0.0) continue;
        uint64_t q = (uint64_t)(int64_t)Ir[k];
        const double *t = T + (q < last ? q : last) * 12u;
        d4 w = {wv, wv, wv, wv};
        a += w * load4(t);
        b += w * load4(t + 4);
        c += w * load4(t + 8);
    }
    for (int q = 0; q < 4; q++) {
        ROW(W, q)[j] = a[q];
        ROW(W, 4 + q)[j] = b[q];
        ROW(W, 8 + q)[j] = c[q];
    }
}

AK_INLINE int y_small(const double *W, int64_t j) {
    return (fabs(ROW(W, 6)[j]) <= SMALL_Y) & (fabs(ROW(W, 7)[j]) <= SMALL_Y) & (fabs(ROW(W, 8)[j]) <= SMALL_Y)
           & (fabs(ROW(W, 9)[j]) <= SMALL_Y) & (fabs(ROW(W, 10)[j]) <= SMALL_Y) & (fabs(ROW(W, 11)[j]) <= SMALL_Y);
}

AK_INLINE double theta_sq(const double *W, int64_t j) {
    double a = ROW(W, 0)[j], b = ROW(W, 1)[j], c = ROW(W, 2)[j];
    return a * a + b * b + c * c;
}

AK_INLINE sym6 y_at(const double *W, int64_t j) {
    sym6 y = {ROW(W, 6)[j], ROW(W, 7)[j], ROW(W, 8)[j], ROW(W, 9)[j], ROW(W, 10)[j], ROW(W, 11)[j]};
    return y;
}

/* (columns with a small Y, columns with t > 1.8 pi) over all CHUNK columns. */
AK_INLINE void count_columns(const double *W, int64_t *n_small, int64_t *n_big) {
    int64_t s = 0, b = 0;
    for (int64_t j = 0; j < CHUNK; j++) {
        s += y_small(W, j);
        b += theta_sq(W, j) > POLY_MAX_S;
    }
    *n_small = s;
    *n_big = b;
}

/* Rows 15-17 of column j = R(w) e + V(w) u unless keep. */
AK_INLINE void point_store(double *W, int64_t j, v3 e, rot_coeffs k, int keep) {
    v3 o = rigid(ROW(W, 0)[j], ROW(W, 1)[j], ROW(W, 2)[j], ROW(W, 3)[j], ROW(W, 4)[j], ROW(W, 5)[j], e.x, e.y, e.z, k);
    double *r15 = ROW(W, 15), *r16 = ROW(W, 16), *r17 = ROW(W, 17);
    r15[j] = keep ? r15[j] : o.x;
    r16[j] = keep ? r16[j] : o.y;
    r17[j] = keep ? r17[j] : o.z;
}

/* Rows 15-17 = phi(rows 0-11) rows 12-14 for every column; returns the columns with t > 1.8 pi. Each
 * form of exp(Y) v has its own loop (the Taylor loop stores every column, then the closed form the
 * columns that are not small), so neither form is computed where it is not needed. */
static int64_t map_points(double *restrict W) {
    int64_t n_small, n_big;
    count_columns(W, &n_small, &n_big);
    if (n_small > 0) {
        for (int64_t j = 0; j < CHUNK; j++) {
            v3 e = stretch_small(y_at(W, j), ROW(W, 12)[j], ROW(W, 13)[j], ROW(W, 14)[j]);
            point_store(W, j, e, rotation_coeffs_poly(theta_sq(W, j)), 0);
        }
    }
    if (n_small < CHUNK) {
#pragma clang loop vectorize(enable)
        for (int64_t j = 0; j < CHUNK; j++) {
            v3 e = stretch(y_at(W, j), ROW(W, 12)[j], ROW(W, 13)[j], ROW(W, 14)[j]);
            point_store(W, j, e, rotation_coeffs_poly(theta_sq(W, j)), y_small(W, j));
        }
    }
    return n_big;
}

/* Redo the columns j < n with t > 1.8 pi with libm t-coefficients (rare: lifted rotations). */
static void fixup_points(double *W, int64_t n) {
#pragma clang loop vectorize(disable)
    for (int64_t j = 0; j < n; j++) {
        double s = theta_sq(W, j);
        if (s > POLY_MAX_S) {
            double v0 = ROW(W, 12)[j], v1 = ROW(W, 13)[j], v2 = ROW(W, 14)[j];
            v3 e = y_small(W, j) ? stretch_small(y_at(W, j), v0, v1, v2) : stretch(y_at(W, j), v0, v1, v2);
            point_store(W, j, e, rotation_coeffs_libm(s), 0);
        }
    }
}

/* Rows 12-23 of column j = phi(rows 0-11) as the columns of M = R(w) exp(Y) and t = V(w) u, unless keep. */
AK_INLINE void motion_store(double *W, int64_t j, rot_coeffs k, int small_form, int keep) {
    double w0 = ROW(W, 0)[j], w1 = ROW(W, 1)[j], w2 = ROW(W, 2)[j];
    sym6 y = y_at(W, j);
    sym6 m = small_form ? exp_sym_matrix_small(y) : exp_sym_matrix(y);
    v3 c0 = rigid(w0, w1, w2, 0.0, 0.0, 0.0, m.xx, m.xy, m.xz, k);
    v3 c1 = rigid(w0, w1, w2, 0.0, 0.0, 0.0, m.xy, m.yy, m.yz, k);
    v3 c2 = rigid(w0, w1, w2, 0.0, 0.0, 0.0, m.xz, m.yz, m.zz, k);
    v3 t = rigid(w0, w1, w2, ROW(W, 3)[j], ROW(W, 4)[j], ROW(W, 5)[j], 0.0, 0.0, 0.0, k);
    double vals[12] = {c0.x, c0.y, c0.z, c1.x, c1.y, c1.z, c2.x, c2.y, c2.z, t.x, t.y, t.z};
    for (int q = 0; q < 12; q++) {
        double *row = ROW(W, 12 + q);
        row[j] = keep ? row[j] : vals[q];
    }
}

static int64_t map_motions(double *restrict W) {
    int64_t n_small, n_big;
    count_columns(W, &n_small, &n_big);
    if (n_small > 0) {
        for (int64_t j = 0; j < CHUNK; j++)
            motion_store(W, j, rotation_coeffs_poly(theta_sq(W, j)), 1, 0);
    }
    if (n_small < CHUNK) {
#pragma clang loop vectorize(enable)
        for (int64_t j = 0; j < CHUNK; j++)
            motion_store(W, j, rotation_coeffs_poly(theta_sq(W, j)), 0, y_small(W, j));
    }
    return n_big;
}

static void fixup_motions(double *W, int64_t n) {
#pragma clang loop vectorize(disable)
    for (int64_t j = 0; j < n; j++) {
        double s = theta_sq(W, j);
        if (s > POLY_MAX_S) motion_store(W, j, rotation_coeffs_libm(s), y_small(W, j), 0);
    }
}

static inline void zero_tail(double *W, int first_row, int n_rows, int64_t n) {
    for (int c = first_row; c < first_row + n_rows; c++)
        memset(ROW(W, c) + n, 0, (size_t)(CHUNK - n) * sizeof(double));
}

static inline int64_t row_of(const int64_t *rows, int32_t use_rows, int64_t a, int64_t j) {
    return use_rows ? rows[a + j] : a + j;
}

static void chunk_points(double *restrict W, const double *P, const double *T, uint64_t last, const int32_t *I,
                         const double *V, int64_t K, const int64_t *rows, int64_t a, int64_t n, int32_t use_rows,
                         int32_t offsets, double *out, float *out32, int32_t use32) {
    for (int64_t j = 0; j < n; j++) {
        int64_t r = row_of(rows, use_rows, a, j);
        blend_params(T, I, V, K, last, W, j, r);
        ROW(W, 12)[j] = P[3 * r];
        ROW(W, 13)[j] = P[3 * r + 1];
        ROW(W, 14)[j] = P[3 * r + 2];
    }
    zero_tail(W, 0, 15, n); /* phi(0) 0 = 0 in the unused columns */
    if (map_points(W) > 0) fixup_points(W, n);
    for (int64_t j = 0; j < n; j++) {
        int64_t r = row_of(rows, use_rows, a, j);
        for (int t = 0; t < 3; t++) {
            double res = ROW(W, 15 + t)[j];
            if (offsets) res = res - ROW(W, 12 + t)[j];
            out[3 * r + t] = res;
            if (use32) out32[3 * r + t] = (float)res;
        }
    }
}

static void store_motion_columns(const double *W, int first_row, const int64_t *rows, int32_t use_rows, int64_t a,
                                 int64_t n, int64_t N, double *out, float *out32, int32_t use32) {
    for (int64_t j = 0; j < n; j++) {
        int64_t r = row_of(rows, use_rows, a, j);
        for (int c = 0; c < 4; c++)
            for (int t = 0; t < 3; t++) {
                double res = ROW(W, first_row + 3 * c + t)[j];
                size_t o = ((size_t)c * (size_t)N + (size_t)r) * 3 + (size_t)t;
                if (use32)
                    out32[o] = (float)res;
                else
                    out[o] = res;
            }
    }
}

static void chunk_motions(double *restrict W, const double *T, uint64_t last, const int32_t *I, const double *V,
                          int64_t K, const int64_t *rows, int64_t a, int64_t n, int32_t use_rows, int64_t N,
                          double *out, float *out32, int32_t use32) {
    for (int64_t j = 0; j < n; j++) blend_params(T, I, V, K, last, W, j, row_of(rows, use_rows, a, j));
    zero_tail(W, 0, 12, n);
    if (map_motions(W) > 0) fixup_motions(W, n);
    store_motion_columns(W, 12, rows, use_rows, a, n, N, out, out32, use32);
}

/* ------------------------------------------------------------------------------------------------
 * entries of the point and motion maps */

int32_t ak_abi_version(void) { return AK_ABI_VERSION; }

int64_t ak_chunk(void) { return CHUNK; }

/* The work list's chunks on the calling thread: claim the next chunk from the shared counter until
 * none is left, running `chunk` on a scratch of `rows` rows (and, with `with_q`, CHUNK offsets).
 * Returns the chunks done, -1 when no scratch could be had. */
typedef void (*chunk_fn)(const void *args, double *W, uint64_t *Q, int64_t a, int64_t len);

static int64_t run_chunks(const void *args, chunk_fn chunk, int64_t n, int n_scratch_rows, int with_q,
                          int64_t *counter) {
    int64_t n_chunks = (n + CHUNK - 1) / CHUNK;
    size_t wbytes = sizeof(double) * (size_t)n_scratch_rows * STRIDE;
    int slot;
    char *buf = scratch_get(wbytes + (with_q ? sizeof(uint64_t) * CHUNK : 0), &slot);
    if (!buf) return -1;
    int64_t done = 0;
    for (;;) {
        int64_t c = claim(counter);
        if (c >= n_chunks) break;
        int64_t a = c * CHUNK;
        chunk(args, (double *)buf, with_q ? (uint64_t *)(buf + wbytes) : NULL, a, n - a < CHUNK ? n - a : CHUNK);
        done++;
    }
    scratch_put(buf, slot);
    return done;
}

/* One entry's arguments, as the chunk functions read them. */
typedef struct {
    const double *points, *table, *val, *mats;
    const int32_t *idx, *prefix;
    const int64_t *rows;
    int64_t N, K, n_pass;
    uint64_t last, last_mat;
    int32_t use_rows, offsets, use32;
    double *out;
    float *out32;
} entry_args;

static void points_chunk(const void *p, double *W, uint64_t *Q, int64_t a, int64_t len) {
    const entry_args *e = p;
    (void)Q;
    chunk_points(W, e->points, e->table, e->last, e->idx, e->val, e->K, e->rows, a, len, e->use_rows, e->offsets,
                 e->out, e->out32, e->use32);
}

static void motions_chunk(const void *p, double *W, uint64_t *Q, int64_t a, int64_t len) {
    const entry_args *e = p;
    (void)Q;
    chunk_motions(W, e->table, e->last, e->idx, e->val, e->K, e->rows, a, len, e->use_rows, e->N, e->out, e->out32,
                  e->use32);
}

int64_t ak_deform_points(const double *points, int64_t n_points, const double *table, int64_t m, const int32_t *idx,
                         const double *val, int64_t K, const int64_t *rows, int64_t n_rows, int32_t use_rows,
                         int32_t offsets, double *out, float *out32, int32_t use32, int64_t *counter) {
    if (use_rows && !rows_in_range(rows, n_rows, n_points)) return ROWS_OUT_OF_RANGE;
    entry_args e = {.points = points, .table = table, .val = val, .idx = idx, .rows = rows, .N = n_points, .K = K,
                    .last = (uint64_t)(m - 1), .use_rows = use_rows, .offsets = offsets, .use32 = use32,
                    .out = out, .out32 = out32};
    return run_chunks(&e, points_chunk, use_rows ? n_rows : n_points, N_POINT_ROWS, 0, counter);
}

int64_t ak_motion_params(const double *table, int64_t m, const int32_t *idx, const double *val, int64_t N, int64_t K,
                         const int64_t *rows, int64_t n_rows, int32_t use_rows, double *out, float *out32,
                         int32_t use32, int64_t *counter) {
    if (use_rows && !rows_in_range(rows, n_rows, N)) return ROWS_OUT_OF_RANGE;
    entry_args e = {.table = table, .val = val, .idx = idx, .rows = rows, .N = N, .K = K, .last = (uint64_t)(m - 1),
                    .use_rows = use_rows, .use32 = use32, .out = out, .out32 = out32};
    return run_chunks(&e, motions_chunk, use_rows ? n_rows : N, N_MOTION_ROWS, 0, counter);
}

/* ------------------------------------------------------------------------------------------------
 * a product of blends per vertex (core.hierarchy: bones blending down their hierarchy) */

/* Q[j] = 12 x the prefix row of column j (the last row of mats, the identity, in unused columns). */
static void prefix_offsets(const int32_t *prefix, uint64_t last, const int64_t *rows, int32_t use_rows, int64_t a,
                           int64_t n, uint64_t *Q) {
    for (int64_t j = 0; j < n; j++) {
        uint64_t p = (uint64_t)(int64_t)prefix[row_of(rows, use_rows, a, j)];
        Q[j] = (p < last ? p : last) * 12u;
    }
    for (int64_t j = n; j < CHUNK; j++) Q[j] = last * 12u;
}

static void chain_points_chunk(double *restrict W, uint64_t *Q, const double *P, const double *T, uint64_t last,
                               const int32_t *I, const double *V, int64_t n_pass, int64_t N, int64_t K,
                               const int32_t *prefix, const double *mats, uint64_t last_mat, const int64_t *rows,
                               int64_t a, int64_t n, int32_t use_rows, int32_t offsets, double *out, float *out32,
                               int32_t use32) {
    for (int64_t j = 0; j < n; j++) {
        int64_t r = row_of(rows, use_rows, a, j);
        for (int t = 0; t < 3; t++) {
            ROW(W, 12 + t)[j] = P[3 * r + t];
            ROW(W, 18 + t)[j] = P[3 * r + t];
        }
    }
    zero_tail(W, 12, 3, n);
    size_t stride = (size_t)N * (size_t)K;
    for (int64_t p = 0; p < n_pass; p++) {
        const int32_t *Ip = I + (size_t)p * stride;
        const double *Vp = V + (size_t)p * stride;
        for (int64_t j = 0; j < n; j++) blend_params(T, Ip, Vp, K, last, W, j, row_of(rows, use_rows, a, j));
        zero_tail(W, 0, 12, n);
        if (map_points(W) > 0) fixup_points(W, n);
        /* the result is the next pass's point (all columns: see map_points) */
        for (int t = 0; t < 3; t++) memcpy(ROW(W, 12 + t), ROW(W, 15 + t), CHUNK * sizeof(double));
    }
    prefix_offsets(prefix, last_mat, rows, use_rows, a, n, Q);
    double *r12 = ROW(W, 12), *r13 = ROW(W, 13), *r14 = ROW(W, 14);
    double *r15 = ROW(W, 15), *r16 = ROW(W, 16), *r17 = ROW(W, 17);
    for (int64_t j = 0; j < CHUNK; j++) {
        const double *M = mats + Q[j];
        double x0 = r12[j], x1 = r13[j], x2 = r14[j];
        r15[j] = M[0] * x0 + M[1] * x1 + M[2] * x2 + M[9];
        r16[j] = M[3] * x0 + M[4] * x1 + M[5] * x2 + M[10];
        r17[j] = M[6] * x0 + M[7] * x1 + M[8] * x2 + M[11];
    }
    for (int64_t j = 0; j < n; j++) {
        int64_t r = row_of(rows, use_rows, a, j);
        for (int t = 0; t < 3; t++) {
            double res = ROW(W, 15 + t)[j];
            if (offsets) res = res - ROW(W, 18 + t)[j];
            out[3 * r + t] = res;
            if (use32) out32[3 * r + t] = (float)res;
        }
    }
}

/* Rows 24-35 (the product so far: M e_x, M e_y, M e_z, t) <- product o rows 12-23 (the factor just mapped). */
static void compose_store(double *restrict W) {
    for (int64_t j = 0; j < CHUNK; j++) {
        double g[12];
        for (int q = 0; q < 12; q++) g[q] = ROW(W, 24 + q)[j];
        for (int c = 0; c < 4; c++) {
            double h0 = ROW(W, 12 + 3 * c)[j], h1 = ROW(W, 13 + 3 * c)[j], h2v = ROW(W, 14 + 3 * c)[j];
            double o0 = g[0] * h0 + g[3] * h1 + g[6] * h2v;
            double o1 = g[1] * h0 + g[4] * h1 + g[7] * h2v;
            double o2 = g[2] * h0 + g[5] * h1 + g[8] * h2v;
            if (c == 3) {
                o0 = o0 + g[9];
                o1 = o1 + g[10];
                o2 = o2 + g[11];
            }
            ROW(W, 24 + 3 * c)[j] = o0;
            ROW(W, 25 + 3 * c)[j] = o1;
            ROW(W, 26 + 3 * c)[j] = o2;
        }
    }
}

static void chain_motion_chunk(double *restrict W, uint64_t *Q, const double *T, uint64_t last, const int32_t *I,
                               const double *V, int64_t n_pass, int64_t N, int64_t K, const int32_t *prefix,
                               const double *mats, uint64_t last_mat, const int64_t *rows, int64_t a, int64_t n,
                               int32_t use_rows, double *out, float *out32, int32_t use32) {
    prefix_offsets(prefix, last_mat, rows, use_rows, a, n, Q);
    for (int64_t j = 0; j < CHUNK; j++) { /* the prefix's columns M e_x, M e_y, M e_z, then t */
        const double *M = mats + Q[j];
        ROW(W, 24)[j] = M[0]; ROW(W, 25)[j] = M[3]; ROW(W, 26)[j] = M[6];
        ROW(W, 27)[j] = M[1]; ROW(W, 28)[j] = M[4]; ROW(W, 29)[j] = M[7];
        ROW(W, 30)[j] = M[2]; ROW(W, 31)[j] = M[5]; ROW(W, 32)[j] = M[8];
        ROW(W, 33)[j] = M[9]; ROW(W, 34)[j] = M[10]; ROW(W, 35)[j] = M[11];
    }
    size_t stride = (size_t)N * (size_t)K;
    for (int64_t step = 0; step < n_pass; step++) {
        int64_t p = n_pass - 1 - step;
        const int32_t *Ip = I + (size_t)p * stride;
        const double *Vp = V + (size_t)p * stride;
        for (int64_t j = 0; j < n; j++) blend_params(T, Ip, Vp, K, last, W, j, row_of(rows, use_rows, a, j));
        zero_tail(W, 0, 12, n);
        if (map_motions(W) > 0) fixup_motions(W, n);
        compose_store(W);
    }
    store_motion_columns(W, 24, rows, use_rows, a, n, N, out, out32, use32);
}

static void chain_points_run(const void *p, double *W, uint64_t *Q, int64_t a, int64_t len) {
    const entry_args *e = p;
    chain_points_chunk(W, Q, e->points, e->table, e->last, e->idx, e->val, e->n_pass, e->N, e->K, e->prefix, e->mats,
                       e->last_mat, e->rows, a, len, e->use_rows, e->offsets, e->out, e->out32, e->use32);
}

static void chain_motion_run(const void *p, double *W, uint64_t *Q, int64_t a, int64_t len) {
    const entry_args *e = p;
    chain_motion_chunk(W, Q, e->table, e->last, e->idx, e->val, e->n_pass, e->N, e->K, e->prefix, e->mats,
                       e->last_mat, e->rows, a, len, e->use_rows, e->out, e->out32, e->use32);
}

int64_t ak_chain_points(const double *points, int64_t N, const double *table, int64_t m, const int32_t *idx,
                        const double *val, int64_t n_pass, int64_t K, const int32_t *prefix, const double *mats,
                        int64_t n_mats, const int64_t *rows, int64_t n_rows, int32_t use_rows, int32_t offsets,
                        double *out, float *out32, int32_t use32, int64_t *counter) {
    if (use_rows && !rows_in_range(rows, n_rows, N)) return ROWS_OUT_OF_RANGE;
    entry_args e = {.points = points, .table = table, .val = val, .mats = mats, .idx = idx, .prefix = prefix,
                    .rows = rows, .N = N, .K = K, .n_pass = n_pass, .last = (uint64_t)(m - 1),
                    .last_mat = (uint64_t)(n_mats - 1), .use_rows = use_rows, .offsets = offsets, .use32 = use32,
                    .out = out, .out32 = out32};
    return run_chunks(&e, chain_points_run, use_rows ? n_rows : N, N_CHAIN_ROWS, 1, counter);
}

int64_t ak_chain_motion(const double *table, int64_t m, const int32_t *idx, const double *val, int64_t n_pass,
                        int64_t N, int64_t K, const int32_t *prefix, const double *mats, int64_t n_mats,
                        const int64_t *rows, int64_t n_rows, int32_t use_rows, double *out, float *out32,
                        int32_t use32, int64_t *counter) {
    if (use_rows && !rows_in_range(rows, n_rows, N)) return ROWS_OUT_OF_RANGE;
    entry_args e = {.table = table, .val = val, .mats = mats, .idx = idx, .prefix = prefix, .rows = rows, .N = N,
                    .K = K, .n_pass = n_pass, .last = (uint64_t)(m - 1), .last_mat = (uint64_t)(n_mats - 1),
                    .use_rows = use_rows, .use32 = use32, .out = out, .out32 = out32};
    return run_chunks(&e, chain_motion_run, use_rows ? n_rows : N, N_CHAIN_MOTION_ROWS, 1, counter);
}

/* ------------------------------------------------------------------------------------------------
 * psi: the polar split and the logs (scalar code, a handful of rows per update) */

/* One-sided Jacobi (Hestenes) sweeps on A (3x3 row-major): plane rotations of column pairs (p, q) of
 * A V, zeta = (|a_q|^2 - |a_p|^2)/(2 a_p.a_q), t = sign(zeta)/(|zeta| + sqrt(1 + zeta^2)),
 * c = 1/sqrt(1 + t^2), s = c t, until no pair exceeds JACOBI_TOL. Backward stable (no A^T A). On return
 * A holds A V (orthogonal columns: U diag(s)) and V the right singular vectors, a product of plane
 * rotations (det V = 1). Shared with affine_solve.c (affine_internal.h). */
void ak_jacobi3(double A[9], double V[9]) {
    static const double eye[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    memcpy(V, eye, sizeof eye);
    for (int sweep = 0; sweep < JACOBI_SWEEPS; sweep++) {
        int rotated = 0;
        for (int p = 0; p < 2; p++) {
            for (int q = p + 1; q < 3; q++) {
                double alpha = A[p] * A[p] + A[3 + p] * A[3 + p] + A[6 + p] * A[6 + p];
                double beta = A[q] * A[q] + A[3 + q] * A[3 + q] + A[6 + q] * A[6 + q];
                double gamma = A[p] * A[q] + A[3 + p] * A[3 + q] + A[6 + p] * A[6 + q];
                if (fabs(gamma) > JACOBI_TOL * sqrt(alpha * beta)) {
                    rotated = 1;
                    double zeta = (beta - alpha) / (2.0 * gamma);
                    double t = copysign(1.0, zeta) / (fabs(zeta) + sqrt(1.0 + zeta * zeta));
                    double cs = 1.0 / sqrt(1.0 + t * t);
                    double sn = cs * t;
                    for (int r = 0; r < 3; r++) {
                        double ap = A[3 * r + p], aq = A[3 * r + q];
                        A[3 * r + p] = cs * ap - sn * aq;
                        A[3 * r + q] = sn * ap + cs * aq;
                        double vp = V[3 * r + p], vq = V[3 * r + q];
                        V[3 * r + p] = cs * vp - sn * vq;
                        V[3 * r + q] = sn * vp + cs * vq;
                    }
                }
            }
        }
        if (!rotated) break;
    }
}

/* R = U V^T and Yh = V diag(log s) V^T for the SVD U diag(s) V^T of A (3x3 row-major, overwritten). */
static void polar_split(double A[9], double R[9], double Yh[9]) {
    double V[9];
    ak_jacobi3(A, V);
    double sig[3], lsig[3];
    for (int c = 0; c < 3; c++) {
        sig[c] = sqrt(A[c] * A[c] + A[3 + c] * A[3 + c] + A[6 + c] * A[6 + c]);
        lsig[c] = log(sig[c]);
    }
    for (int r = 0; r < 3; r++) {
        for (int k = 0; k < 3; k++) {
            double rr = 0.0, yy = 0.0;
            for (int c = 0; c < 3; c++) {
                rr += (A[3 * r + c] / sig[c]) * V[3 * k + c];
                yy += (V[3 * r + c] * lsig[c]) * V[3 * k + c];
            }
            R[3 * r + k] = rr;
            Yh[3 * r + k] = yy;
        }
    }
}

int64_t ak_polar_log(const double *M, int64_t n, double *R, double *Yh) {
    for (int64_t i = 0; i < n; i++) {
        double A[9];
        memcpy(A, M + 9 * i, sizeof A);
        polar_split(A, R + 9 * i, Yh + 9 * i);
    }
    return n;
}

/* The principal rotation vector of R (3x3 row-major), as core.aff3.so3_log: t = atan2(|s|,
 * (tr R - 1)/2) with s = vee(R); w = (t/|s|) s for cos t >= 0, else t times the largest column of
 * (R + R^T)/2 - cos t I normalised, signed by s. */
static v3 so3_log(const double R[9]) {
    double s0 = 0.5 * (R[7] - R[5]);
    double s1 = 0.5 * (R[2] - R[6]);
    double s2 = 0.5 * (R[3] - R[1]);
    double sin_t = sqrt(s0 * s0 + s1 * s1 + s2 * s2);
    double cos_t = 0.5 * (R[0] + R[4] + R[8] - 1.0);
    cos_t = cos_t > 1.0 ? 1.0 : cos_t;
    cos_t = cos_t < -1.0 ? -1.0 : cos_t;
    double theta = atan2(sin_t, cos_t);
    if (cos_t < 0.0) {
        int k = 0;
        double best = R[0] - cos_t;
        for (int j = 1; j < 3; j++) {
            if (R[4 * j] - cos_t > best) {
                best = R[4 * j] - cos_t;
                k = j;
            }
        }
        double c0 = 0.5 * (R[k] + R[3 * k]) - (k == 0 ? cos_t : 0.0);
        double c1 = 0.5 * (R[3 + k] + R[3 * k + 1]) - (k == 1 ? cos_t : 0.0);
        double c2 = 0.5 * (R[6 + k] + R[3 * k + 2]) - (k == 2 ? cos_t : 0.0);
        double norm = sqrt(c0 * c0 + c1 * c1 + c2 * c2);
        if (norm > 0.0) {
            c0 = c0 / norm;
            c1 = c1 / norm;
            c2 = c2 / norm;
        }
        double st = c0 * s0 + c1 * s1 + c2 * s2 < 0.0 ? -theta : theta;
        v3 o = {st * c0, st * c1, st * c2};
        return o;
    }
    double ratio = sin_t > 0.0 ? theta / sin_t : 1.0;
    v3 o = {ratio * s0, ratio * s1, ratio * s2};
    return o;
}

/* V(w)^-1 v = v - w x v / 2 + d(t) w x (w x v), d = (1 - (t/2) cot(t/2))/t^2 (its series below t = 0.2),
 * as core.aff3's left_jacobian_inv. */
static v3 jacobian_inv_apply(double w0, double w1, double w2, double v0, double v1, double v2) {
    double t2 = w0 * w0 + w1 * w1 + w2 * w2;
    double theta = sqrt(t2);
    double d;
    if (theta < 0.2) {
        d = (((t2 * (1.0 / 47900160) + 1.0 / 1209600) * t2 + 1.0 / 30240) * t2 + 1.0 / 720) * t2 + 1.0 / 12;
    } else {
        double half = 0.5 * theta;
        d = (1.0 - half * cos(half) / sin(half)) / t2;
    }
    double a0 = w1 * v2 - w2 * v1, a1 = w2 * v0 - w0 * v2, a2 = w0 * v1 - w1 * v0;
    double b0 = w1 * a2 - w2 * a1, b1 = w2 * a0 - w0 * a2, b2 = w0 * a1 - w1 * a0;
    v3 o = {v0 - 0.5 * a0 + d * b0, v1 - 0.5 * a1 + d * b1, v2 - 0.5 * a2 + d * b2};
    return o;
}

/* row (M row-major, then t) <- psi in the 12-number layout (w, u = V(w)^-1 t, Y6); 1 if finite. */
static int psi_row(double *row) {
    double A[9], R[9], Yh[9];
    memcpy(A, row, sizeof A);
    double t0 = row[9], t1 = row[10], t2 = row[11];
    polar_split(A, R, Yh);
    v3 w = so3_log(R);
    v3 u = jacobian_inv_apply(w.x, w.y, w.z, t0, t1, t2);
    row[0] = w.x; row[1] = w.y; row[2] = w.z;
    row[3] = u.x; row[4] = u.y; row[5] = u.z;
    row[6] = Yh[0]; row[7] = Yh[4]; row[8] = Yh[8];
    row[9] = 0.5 * (Yh[1] + Yh[3]);
    row[10] = 0.5 * (Yh[2] + Yh[6]);
    row[11] = 0.5 * (Yh[5] + Yh[7]);
    int finite = 1;
    for (int k = 0; k < 12; k++) finite = finite && isfinite(row[k]);
    return finite;
}

int64_t ak_psi_rows(double *rows, int64_t n) {
    int64_t bad = -1;
    for (int64_t t = 0; t < n; t++)
        if (!psi_row(rows + 12 * t) && bad < 0) bad = t;
    return bad;
}

/* M = R(w) exp(Y) row-major for Y = y[0..5]: the map of motion_store (polynomial t-coefficients up
 * to 1.8 pi, libm beyond), one row at a time. */
static void linear_columns(double w0, double w1, double w2, const double *y, double c[9]) {
    double s = w0 * w0 + w1 * w1 + w2 * w2;
    rot_coeffs k = s > POLY_MAX_S ? rotation_coeffs_libm(s) : rotation_coeffs_poly(s);
    sym6 ys = {y[0], y[1], y[2], y[3], y[4], y[5]};
    sym6 m = exp_sym_matrix(ys);
    v3 a = rigid(w0, w1, w2, 0.0, 0.0, 0.0, m.xx, m.xy, m.xz, k);
    v3 b = rigid(w0, w1, w2, 0.0, 0.0, 0.0, m.xy, m.yy, m.yz, k);
    v3 d = rigid(w0, w1, w2, 0.0, 0.0, 0.0, m.xz, m.yz, m.zz, k);
    c[0] = a.x; c[1] = b.x; c[2] = d.x;
    c[3] = a.y; c[4] = b.y; c[5] = d.y;
    c[6] = a.z; c[7] = b.z; c[8] = d.z;
}

/* B = V(w)^-1 (M - I) row-major, M the linear part of phi(w, 0, Y). */
static void face_term(const double *p, double b[9]) {
    double c[9];
    linear_columns(p[0], p[1], p[2], p + 6, c);
    v3 x = jacobian_inv_apply(p[0], p[1], p[2], c[0] - 1.0, c[3], c[6]);
    v3 y = jacobian_inv_apply(p[0], p[1], p[2], c[1], c[4] - 1.0, c[7]);
    v3 z = jacobian_inv_apply(p[0], p[1], p[2], c[2], c[5], c[8] - 1.0);
    b[0] = x.x; b[1] = y.x; b[2] = z.x;
    b[3] = x.y; b[4] = y.y; b[5] = z.y;
    b[6] = x.z; b[7] = y.z; b[8] = z.z;
}

/* (w, u', Y) with u' = u + B x + V(w)^-1 (x - M x) from the blended (w, u, Y) and B (given as
 * separate rows: B row-major at b[0..8] scaled by s), for node point p. */
static void node_finish(double w0, double w1, double w2, const double u[3], const double y[6], const double Bx[3],
                        const double *p, double *out) {
    double c[9];
    linear_columns(w0, w1, w2, y, c);
    double p0 = p[0], p1 = p[1], p2 = p[2];
    double v0 = p0 - (c[0] * p0 + c[1] * p1 + c[2] * p2);
    double v1 = p1 - (c[3] * p0 + c[4] * p1 + c[5] * p2);
    double v2 = p2 - (c[6] * p0 + c[7] * p1 + c[8] * p2);
    v3 j = jacobian_inv_apply(w0, w1, w2, v0, v1, v2);
    out[0] = w0; out[1] = w1; out[2] = w2;
    out[3] = (u[0] + Bx[0]) + j.x;
    out[4] = (u[1] + Bx[1]) + j.y;
    out[5] = (u[2] + Bx[2]) + j.z;
    for (int k = 0; k < 6; k++) out[6 + k] = y[k];
}

int64_t ak_node_pivot(int32_t finish, const double *A, int64_t n, int64_t a_cols, const double *x, double *out) {
    for (int64_t i = 0; i < n; i++) {
        const double *a = A + i * a_cols;
        if (finish) {
            const double *p = x + 3 * i;
            double Bx[3] = {a[12] * p[0] + a[13] * p[1] + a[14] * p[2], a[15] * p[0] + a[16] * p[1] + a[17] * p[2],
                            a[18] * p[0] + a[19] * p[1] + a[20] * p[2]};
            node_finish(a[0], a[1], a[2], a + 3, a + 6, Bx, p, out + 12 * i);
        } else {
            face_term(a, out + 9 * i);
        }
    }
    return n;
}

/* ------------------------------------------------------------------------------------------------
 * a cage's faces (core.cage.face_motions for the faces a shape change reaches) */

static inline int finite3(double a, double b, double c) { return isfinite(a) && isfinite(b) && isfinite(c); }

typedef struct {
    const double *cur;
    const uint8_t *moved;
    const int64_t *triples;
    const uint8_t *usable;
    const double *weight;
    const uint8_t *rest_ok;
    const double *centres;
    const double *inverses;
    const int64_t *sv;
    const double *sg;
    int64_t n_stencil;
    const double *smom;
    const double *sspread;
    const uint8_t *sactive;
} cage_tables;

/* core.cage.corner_matrices for corner t: out[0..8] = M = E' E^-1 row-major, out[9..11] = c' - M c,
 * E' = [e1', e2', h'] the current frame with the fitted, fold-guarded stencil apex where the corner
 * has a stencil, an input of it moved bitwise and the fit is finite (the normal apex n'/sqrt|n'|
 * otherwise). Returns ok: uncollapsed, finite and det M > 0. */
static int corner_affine(const cage_tables *c, int64_t t, double *out) {
    const double *cur = c->cur;
    int64_t i0 = c->triples[3 * t], i1 = c->triples[3 * t + 1], i2 = c->triples[3 * t + 2];
    double p00 = cur[3 * i0], p01 = cur[3 * i0 + 1], p02 = cur[3 * i0 + 2];
    double a0 = cur[3 * i1] - p00, a1 = cur[3 * i1 + 1] - p01, a2 = cur[3 * i1 + 2] - p02; /* e1' */
    double b0 = cur[3 * i2] - p00, b1 = cur[3 * i2 + 1] - p01, b2 = cur[3 * i2 + 2] - p02; /* e2' */
    double n0 = a1 * b2 - a2 * b1, n1 = a2 * b0 - a0 * b2, n2 = a0 * b1 - a1 * b0;
    double area2 = sqrt(n0 * n0 + n1 * n1 + n2 * n2);
    double edges = sqrt(a0 * a0 + a1 * a1 + a2 * a2) * sqrt(b0 * b0 + b1 * b1 + b2 * b2);
    double sin_cur = edges > 0.0 ? area2 / edges : 0.0;
    double root = sqrt(area2);
    double h0 = n0 / root, h1 = n1 / root, h2v = n2 / root;
    double c0 = (cur[3 * i0] + cur[3 * i1] + cur[3 * i2]) / 3.0;
    double c1 = (cur[3 * i0 + 1] + cur[3 * i1 + 1] + cur[3 * i2 + 1]) / 3.0;
    double c2 = (cur[3 * i0 + 2] + cur[3 * i1 + 2] + cur[3 * i2 + 2]) / 3.0;
    int64_t S = c->n_stencil;
    if (c->sactive[t]) {
        int reached = c->moved[i0] || c->moved[i1] || c->moved[i2];
        for (int64_t s = 0; s < S; s++)
            if (c->sg[t * S + s] != 0.0 && c->moved[c->sv[t * S + s]]) reached = 1;
        if (reached) {
            double u0 = n0 / area2, u1 = n1 / area2, u2 = n2 / area2;
            double f0 = 0.0, f1 = 0.0, f2 = 0.0, m = 0.0;
            for (int64_t s = 0; s < S; s++) {
                double g = c->sg[t * S + s];
                int64_t v = c->sv[t * S + s];
                double q0 = cur[3 * v] - c0, q1 = cur[3 * v + 1] - c1, q2 = cur[3 * v + 2] - c2;
                f0 += g * q0;
                f1 += g * q1;
                f2 += g * q2;
                m += fabs(g) * fabs(q0 * u0 + q1 * u1 + q2 * u2);
            }
            const double *mom = c->smom + 3 * t;
            f0 -= mom[1] * a0 + mom[2] * b0;
            f1 -= mom[1] * a1 + mom[2] * b1;
            f2 -= mom[1] * a2 + mom[2] * b2;
            double x = f0 * u0 + f1 * u1 + f2 * u2;
            double floor_ = FOLD_KAPPA * m / c->sspread[t];
            if (x < floor_) { /* the fold guard: x -> floor^2/(2 floor - x) below the floor */
                double lift = floor_ * floor_ / (2.0 * floor_ - x) - x;
                f0 += lift * u0;
                f1 += lift * u1;
                f2 += lift * u2;
            }
            if (finite3(f0, f1, f2)) {
                h0 = f0;
                h1 = f1;
                h2v = f2;
            }
        }
    }
    int ok = c->rest_ok[t] && sin_cur > COLLAPSED_SIN;
    ok = ok && finite3(a0, a1, a2) && finite3(b0, b1, b2);
    ok = ok && finite3(h0, h1, h2v) && finite3(c0, c1, c2);
    if (!ok) return 0;
    const double *E = c->inverses + 9 * t; /* E^-1 row-major */
    double m00 = a0 * E[0] + b0 * E[3] + h0 * E[6];
    double m01 = a0 * E[1] + b0 * E[4] + h0 * E[7];
    double m02 = a0 * E[2] + b0 * E[5] + h0 * E[8];
    double m10 = a1 * E[0] + b1 * E[3] + h1 * E[6];
    double m11 = a1 * E[1] + b1 * E[4] + h1 * E[7];
    double m12 = a1 * E[2] + b1 * E[5] + h1 * E[8];
    double m20 = a2 * E[0] + b2 * E[3] + h2v * E[6];
    double m21 = a2 * E[1] + b2 * E[4] + h2v * E[7];
    double m22 = a2 * E[2] + b2 * E[5] + h2v * E[8];
    const double *r = c->centres + 3 * t;
    out[0] = m00; out[1] = m01; out[2] = m02;
    out[3] = m10; out[4] = m11; out[5] = m12;
    out[6] = m20; out[7] = m21; out[8] = m22;
    out[9] = c0 - (m00 * r[0] + m01 * r[1] + m02 * r[2]);
    out[10] = c1 - (m10 * r[0] + m11 * r[1] + m12 * r[2]);
    out[11] = c2 - (m20 * r[0] + m21 * r[1] + m22 * r[2]);
    double det = m00 * (m11 * m22 - m12 * m21) + m01 * (m12 * m20 - m10 * m22) + m02 * (m10 * m21 - m11 * m20);
    int good = det > 0.0;
    for (int k = 0; k < 12; k++) good = good && isfinite(out[k]);
    return good;
}

/* The face owning corners a .. b-1: out (12) its parameters, corner_params its corners' psi; returns its flags. */
static int64_t cage_face(const cage_tables *c, int64_t a, int64_t b, double *out, double *corner_params) {
    int reached = 0, has = 0;
    int64_t S = c->n_stencil;
    for (int64_t t = a; t < b; t++) {
        has = has || c->usable[t];
        if (c->moved[c->triples[3 * t]] || c->moved[c->triples[3 * t + 1]] || c->moved[c->triples[3 * t + 2]])
            reached = 1;
        for (int64_t s = 0; s < S; s++)
            if (c->sg[t * S + s] != 0.0 && c->moved[c->sv[t * S + s]]) reached = 1;
    }
    for (int k = 0; k < 12; k++) out[k] = 0.0;
    int64_t flag = (reached ? FACE_REACHED : 0) | (has ? FACE_HAS_CORNER : 0);
    if (!reached) return flag;
    int valid = has;
    for (int64_t t = a; t < b; t++) {
        int ok = corner_affine(c, t, corner_params + 12 * t);
        if (c->usable[t] && !ok) valid = 0;
    }
    if (valid) {
        for (int64_t t = a; t < b; t++)
            if (c->usable[t] && !psi_row(corner_params + 12 * t)) valid = 0;
    }
    int64_t ref = -1;
    int lift = 0;
    for (int64_t t = a; t < b; t++) {
        double *cp = corner_params + 12 * t;
        if (!(valid && c->usable[t])) {
            for (int k = 0; k < 12; k++) cp[k] = 0.0;
            continue;
        }
        if (ref < 0) ref = t;
        const double *rp = corner_params + 12 * ref;
        double w0 = cp[0], w1 = cp[1], w2 = cp[2];
        double d0 = rp[0] - w0, d1 = rp[1] - w1, d2 = rp[2] - w2;
        int near = d0 * d0 + d1 * d1 + d2 * d2 < NO_LIFT_DIST_SQ;
        if (!(near && w0 * w0 + w1 * w1 + w2 * w2 < NO_LIFT_NORM_SQ)) lift = 1;
    }
    if (!valid) return flag;
    if (lift) return flag | FACE_VALID | FACE_NEEDS_LIFT;
    for (int64_t t = a; t < b; t++)
        if (c->usable[t])
            for (int k = 0; k < 12; k++) out[k] += c->weight[t] * corner_params[12 * t + k];
    return flag | FACE_VALID;
}

/* sum a.(b x c)/6 over the fan triangles, about the mean of cur. */
static double fan_volume(const double *cur, int64_t n_vertices, const int64_t *fan, int64_t n_fan) {
    double o0 = 0.0, o1 = 0.0, o2 = 0.0;
    for (int64_t v = 0; v < n_vertices; v++) {
        o0 += cur[3 * v];
        o1 += cur[3 * v + 1];
        o2 += cur[3 * v + 2];
    }
    o0 = o0 / (double)n_vertices;
    o1 = o1 / (double)n_vertices;
    o2 = o2 / (double)n_vertices;
    double volume = 0.0;
    for (int64_t i = 0; i < n_fan; i++) {
        int64_t j0 = fan[3 * i], j1 = fan[3 * i + 1], j2 = fan[3 * i + 2];
        double x0 = cur[3 * j0] - o0, x1 = cur[3 * j0 + 1] - o1, x2 = cur[3 * j0 + 2] - o2;
        double y0 = cur[3 * j1] - o0, y1 = cur[3 * j1 + 1] - o1, y2 = cur[3 * j1 + 2] - o2;
        double z0 = cur[3 * j2] - o0, z1 = cur[3 * j2 + 1] - o1, z2 = cur[3 * j2 + 2] - o2;
        volume += x0 * (y1 * z2 - y2 * z1) + x1 * (y2 * z0 - y0 * z2) + x2 * (y0 * z1 - y1 * z0);
    }
    return volume / 6.0;
}

double ak_cage_faces(const double *cur, const double *rest, int64_t n_vertices, const int64_t *triples,
                     int64_t n_corners, const int64_t *first, int64_t n_faces, const uint8_t *usable,
                     const double *weight, const uint8_t *rest_ok, const double *centres, const double *inverses,
                     const int64_t *sv, const double *sg, int64_t n_stencil, const double *smom,
                     const double *sspread, const uint8_t *sactive, const int64_t *fan, int64_t n_fan,
                     uint8_t *moved, double *params, double *corner_params, int64_t *flags) {
    (void)n_corners;
    for (int64_t v = 0; v < n_vertices; v++)
        moved[v] = cur[3 * v] != rest[3 * v] || cur[3 * v + 1] != rest[3 * v + 1] || cur[3 * v + 2] != rest[3 * v + 2];
    cage_tables c = {cur, moved, triples, usable, weight, rest_ok, centres, inverses,
                     sv, sg, n_stencil, smom, sspread, sactive};
    for (int64_t f = 0; f < n_faces; f++)
        flags[f] = cage_face(&c, first[f], first[f + 1], params + 12 * f, corner_params);
    return fan_volume(cur, n_vertices, fan, n_fan);
}

/* core.cage.harmonic.node_params for the nodes a moved face reaches; returns how many nodes. The sums
 * run over `faces` in the given order (four at a time, then one at a time), so a node's result depends
 * on its own weights and those faces only. */
int64_t ak_cage_nodes(const double *Wt, int64_t F, int64_t G, const int64_t *reached, int64_t n_reached,
                      const int64_t *faces, int64_t n, const double *face_params, const double *keep, double *totals,
                      int32_t fill_totals, const double *x, double *terms, double *blend, double *out,
                      uint8_t *touched) {
    for (int64_t c = 0; c < G; c++) touched[c] = 0;
    for (int64_t i = 0; i < n_reached; i++) {
        const double *row = Wt + reached[i] * G;
        for (int64_t c = 0; c < G; c++) touched[c] |= row[c] > 0.0; /* a select, so it vectorises */
    }
    for (int64_t i = 0; i < n; i++) {
        const double *p = face_params + 12 * i;
        double *t = terms + 21 * i;
        for (int k = 0; k < 12; k++) t[k] = p[k];
        face_term(p, t + 12);
    }
    if (fill_totals) {
        for (int64_t c = 0; c < G; c++) totals[c] = 0.0;
        for (int64_t f = 0; f < F; f++) {
            double kf = keep[f];
            const double *row = Wt + f * G;
            for (int64_t c = 0; c < G; c++) totals[c] += row[c] * kf;
        }
    }
    memset(blend, 0, sizeof(double) * 21 * (size_t)G);
    /* Four faces per pass over the nodes: a quarter of the loads and stores of `blend`. */
    int64_t i = 0;
    for (; i + 4 <= n; i += 4) {
        const double *r0 = Wt + faces[i] * G, *r1 = Wt + faces[i + 1] * G;
        const double *r2 = Wt + faces[i + 2] * G, *r3 = Wt + faces[i + 3] * G;
        for (int k = 0; k < 21; k++) {
            double t0 = terms[21 * i + k], t1 = terms[21 * (i + 1) + k];
            double t2 = terms[21 * (i + 2) + k], t3 = terms[21 * (i + 3) + k];
            double *b = blend + (size_t)k * G;
            for (int64_t c = 0; c < G; c++) b[c] += (r0[c] * t0 + r1[c] * t1) + (r2[c] * t2 + r3[c] * t3);
        }
    }
    for (; i < n; i++) {
        const double *r0 = Wt + faces[i] * G;
        for (int k = 0; k < 21; k++) {
            double term = terms[21 * i + k];
            double *b = blend + (size_t)k * G;
            for (int64_t c = 0; c < G; c++) b[c] += r0[c] * term;
        }
    }
    int64_t count = 0;
    for (int64_t c = 0; c < G; c++) {
        double *o = out + 12 * c;
        for (int k = 0; k < 12; k++) o[k] = 0.0;
        if (!touched[c]) continue;
        count++;
        double s = totals[c] > 0.0 ? 1.0 / totals[c] : 0.0;
        double y[6], u[3], Bx[3];
        for (int k = 0; k < 6; k++) y[k] = blend[(size_t)(6 + k) * G + c] * s;
        for (int k = 0; k < 3; k++) u[k] = blend[(size_t)(3 + k) * G + c] * s;
        const double *p = x + 3 * c;
        for (int r = 0; r < 3; r++)
            Bx[r] = blend[(size_t)(12 + 3 * r) * G + c] * s * p[0] + blend[(size_t)(13 + 3 * r) * G + c] * s * p[1]
                    + blend[(size_t)(14 + 3 * r) * G + c] * s * p[2];
        node_finish(blend[c] * s, blend[(size_t)G + c] * s, blend[(size_t)2 * G + c] * s, u, y, Bx, p, o);
    }
    return count;
}

/* ------------------------------------------------------------------------------------------------
 * no numerics */

int64_t ak_rows_reading(const uint8_t *hit, int64_t m, const int32_t *idx, const double *val, int64_t N, int64_t K,
                        int64_t *out) {
    int64_t count = 0;
    for (int64_t v = 0; v < N; v++) {
        for (int64_t k = 0; k < K; k++) {
            int32_t j = idx[v * K + k];
            if (val[v * K + k] != 0.0 && 0 <= j && j < m && hit[j]) {
                out[count++] = v;
                break;
            }
        }
    }
    return count;
}

/* Whether a and b hold the same n words: the OR of a[i] ^ b[i] per block, leaving at the first block
 * that differs (a fixed trip count vectorises; a loop that can leave at every word does not). */
int32_t ak_same_words(const uint32_t *a, const uint32_t *b, int64_t n) {
    int64_t blocks = n / SAME_BLOCK;
    for (int64_t block = 0; block < blocks; block++) {
        const uint32_t *pa = a + block * SAME_BLOCK, *pb = b + block * SAME_BLOCK;
        uint32_t diff = 0;
        for (int i = 0; i < SAME_BLOCK; i++) diff |= pa[i] ^ pb[i];
        if (diff != 0) return 0;
    }
    uint32_t tail = 0;
    for (int64_t i = blocks * SAME_BLOCK; i < n; i++) tail |= a[i] ^ b[i];
    return tail == 0;
}

/* Busy-wait until flag[0] != seen (1) or for n iterations (0). */
int32_t ak_spin_wait(const int64_t *flag, int64_t seen, int64_t n) {
    for (int64_t i = 0; i < n; i++) {
        if (__atomic_load_n(flag, __ATOMIC_RELAXED) != seen) return 1;
        CPU_RELAX();
    }
    return 0;
}
