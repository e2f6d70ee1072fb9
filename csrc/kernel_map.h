/* The per-vertex map on a chunk, shared by the point and motion entries (kernel_vertex.c, which
 * defines the map) and the products of passes (kernel_chain.c): the scratch layout, the blend of a
 * column's parameters, and the map, fix-up and store of a whole chunk.
 *
 * Scratch: one row of STRIDE doubles per quantity, CHUNK columns (vertices) each; rows 0-11 the
 * blended parameters (w, u, Y6), then the entry's points or results. The loops run over all CHUNK
 * columns (unused ones zeroed), so a column's bits do not depend on how many rows the chunk holds. */
#ifndef KERNEL_MAP_H
#define KERNEL_MAP_H

#include "affine_internal.h"
#include "kernel_math.h"

#define N_POINT_ROWS 18        /* 12 parameters, 3 point coordinates, 3 results */
#define N_MOTION_ROWS 24       /* 12 parameters, 12 results (M e_x, M e_y, M e_z, t) */
#define N_CHAIN_ROWS 21        /* as points, plus the original point (offsets) */
#define N_CHAIN_MOTION_ROWS 36 /* as motions, plus the product so far */

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

static inline void zero_tail(double *W, int first_row, int n_rows, int64_t n) {
    for (int c = first_row; c < first_row + n_rows; c++)
        memset(ROW(W, c) + n, 0, (size_t)(CHUNK - n) * sizeof(double));
}

static inline int64_t row_of(const int64_t *rows, int32_t use_rows, int64_t a, int64_t j) {
    return use_rows ? rows[a + j] : a + j;
}

/* Whether every row of a work list indexes [0, n): checked before anything is written (a row out of
 * range would be written to). One compare per row, against numpy's two reductions. */
static inline int rows_in_range(const int64_t *rows, int64_t n_rows, int64_t n) {
    int bad = 0;
    for (int64_t i = 0; i < n_rows; i++) bad |= (rows[i] < 0) | (rows[i] >= n);
    return !bad;
}

#define ROWS_OUT_OF_RANGE (-2)

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

/* Rows 15-17 = phi(rows 0-11) rows 12-14 for every column; returns the columns with t > 1.8 pi. */
int64_t ak_map_points(double *restrict W);
/* Redo the columns j < n with t > 1.8 pi with libm t-coefficients (rare: lifted rotations). */
void ak_fixup_points(double *W, int64_t n);
/* Rows 12-23 = phi(rows 0-11) as the columns of M = R(w) exp(Y) and t = V(w) u; returns the columns
 * with t > 1.8 pi. */
int64_t ak_map_motions(double *restrict W);
void ak_fixup_motions(double *W, int64_t n);
/* out[:, r] (or out32) = the 12 rows from first_row of column j, for the chunk's rows r. */
void ak_store_motion_columns(const double *W, int first_row, const int64_t *rows, int32_t use_rows, int64_t a,
                             int64_t n, int64_t N, double *out, float *out32, int32_t use32);

#endif
