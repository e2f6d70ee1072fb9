/* A product of blends per vertex (core.hierarchy: bones blending down their hierarchy): the map of
 * kernel_vertex.c applied pass after pass on the same chunk, then the vertex's prefix matrix
 * (ak_chain_points), or the maps composed (ak_chain_motion). */
#include "affine_kernel.h"
#include "kernel_map.h"

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
        if (ak_map_points(W) > 0) ak_fixup_points(W, n);
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
        if (ak_map_motions(W) > 0) ak_fixup_motions(W, n);
        compose_store(W);
    }
    ak_store_motion_columns(W, 24, rows, use_rows, a, n, N, out, out32, use32);
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
    return ak_run_chunks(&e, chain_points_run, use_rows ? n_rows : N, N_CHAIN_ROWS, 1, counter);
}

int64_t ak_chain_motion(const double *table, int64_t m, const int32_t *idx, const double *val, int64_t n_pass,
                        int64_t N, int64_t K, const int32_t *prefix, const double *mats, int64_t n_mats,
                        const int64_t *rows, int64_t n_rows, int32_t use_rows, double *out, float *out32,
                        int32_t use32, int64_t *counter) {
    if (use_rows && !rows_in_range(rows, n_rows, N)) return ROWS_OUT_OF_RANGE;
    entry_args e = {.table = table, .val = val, .mats = mats, .idx = idx, .prefix = prefix, .rows = rows, .N = N,
                    .K = K, .n_pass = n_pass, .last = (uint64_t)(m - 1), .last_mat = (uint64_t)(n_mats - 1),
                    .use_rows = use_rows, .use32 = use32, .out = out, .out32 = out32};
    return ak_run_chunks(&e, chain_motion_run, use_rows ? n_rows : N, N_CHAIN_MOTION_ROWS, 1, counter);
}
