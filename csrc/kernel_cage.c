/* A cage's per-update path: the motions of the faces a shape change reaches (ak_cage_faces: corner
 * frames, stencil apex, fold guard, psi of each corner, the mean over a face's corners) and the
 * harmonic nodes they reach (ak_cage_nodes), as core.cage.face_motions and
 * core.cage.harmonic.node_params compute them. */
#include "affine_kernel.h"
#include "affine_internal.h"

#include <math.h>
#include <string.h>

#pragma STDC FP_CONTRACT OFF

/* core.cage's constants (tests/core/test_accel_cage.py compares them through native.py). */
#define COLLAPSED_SIN 1e-10
#define FOLD_KAPPA 0.5
#define NO_LIFT_DIST_SQ 9.0
#define NO_LIFT_NORM_SQ 1e12
#define FACE_REACHED 1
#define FACE_HAS_CORNER 2
#define FACE_VALID 4
#define FACE_NEEDS_LIFT 8

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
            if (c->usable[t] && !ak_psi_row(corner_params + 12 * t)) valid = 0;
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
        ak_face_term(p, t + 12);
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
        ak_node_finish(blend[c] * s, blend[(size_t)G + c] * s, blend[(size_t)2 * G + c] * s, u, y, Bx, p, o);
    }
    return count;
}
