/* The per-vertex map on the structure-of-arrays scratch (kernel_map.h): v' = phi(sum_k w_k P_idx(k)) v
 * for points (ak_deform_points) and the map phi(p_v) itself as the columns of M and t
 * (ak_motion_params), chunk by chunk on the calling thread (kernel_threads.c); and two passes of the
 * incremental update without numerics (ak_rows_reading, ak_same_words). The mathematics and the
 * bit-identity rules are kernel_math.h's. */
#include "affine_kernel.h"
#include "kernel_map.h"

#define SAME_BLOCK 4096

/* ------------------------------------------------------------------------------------------------
 * one chunk: blend (kernel_map.h), map, fix-up, store */

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
int64_t ak_map_points(double *restrict W) {
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
void ak_fixup_points(double *W, int64_t n) {
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

int64_t ak_map_motions(double *restrict W) {
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

void ak_fixup_motions(double *W, int64_t n) {
#pragma clang loop vectorize(disable)
    for (int64_t j = 0; j < n; j++) {
        double s = theta_sq(W, j);
        if (s > POLY_MAX_S) motion_store(W, j, rotation_coeffs_libm(s), y_small(W, j), 0);
    }
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
    if (ak_map_points(W) > 0) ak_fixup_points(W, n);
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

void ak_store_motion_columns(const double *W, int first_row, const int64_t *rows, int32_t use_rows, int64_t a,
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
    if (ak_map_motions(W) > 0) ak_fixup_motions(W, n);
    ak_store_motion_columns(W, 12, rows, use_rows, a, n, N, out, out32, use32);
}

/* ------------------------------------------------------------------------------------------------
 * entries of the point and motion maps */

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
    return ak_run_chunks(&e, points_chunk, use_rows ? n_rows : n_points, N_POINT_ROWS, 0, counter);
}

int64_t ak_motion_params(const double *table, int64_t m, const int32_t *idx, const double *val, int64_t N, int64_t K,
                         const int64_t *rows, int64_t n_rows, int32_t use_rows, double *out, float *out32,
                         int32_t use32, int64_t *counter) {
    if (use_rows && !rows_in_range(rows, n_rows, N)) return ROWS_OUT_OF_RANGE;
    entry_args e = {.table = table, .val = val, .idx = idx, .rows = rows, .N = N, .K = K, .last = (uint64_t)(m - 1),
                    .use_rows = use_rows, .use32 = use32, .out = out, .out32 = out32};
    return ak_run_chunks(&e, motions_chunk, use_rows ? n_rows : N, N_MOTION_ROWS, 0, counter);
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
