/* Per-control steps in scalar code (a handful of rows per update): psi of the controls that moved
 * (ak_psi_rows: the polar split by one-sided Jacobi SVD, so3 log, V^-1), the polar split alone
 * (ak_polar_log) and the cage nodes' pivot (ak_node_pivot). ak_jacobi3 and ak_psi_row are shared with
 * affine_solve.c and kernel_cage.c (affine_internal.h). */
#include "affine_kernel.h"
#include "affine_internal.h"
#include "kernel_math.h"

#define JACOBI_TOL (4.0 * 2.220446049250313e-16)
#define JACOBI_SWEEPS 16

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
int ak_psi_row(double *row) {
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
        if (!ak_psi_row(rows + 12 * t) && bad < 0) bad = t;
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
void ak_face_term(const double *p, double b[9]) {
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
void ak_node_finish(double w0, double w1, double w2, const double u[3], const double y[6], const double Bx[3],
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
            ak_node_finish(a[0], a[1], a[2], a + 3, a + 6, Bx, p, out + 12 * i);
        } else {
            ak_face_term(a, out + 9 * i);
        }
    }
    return n;
}
