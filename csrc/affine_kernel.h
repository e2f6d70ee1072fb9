/* The compiled kernel of Affine Deformers: the per-vertex map v -> phi(sum_k w_k P_idx(k)) v and
 * the per-control and per-cage-face steps around it, in portable C11 (no C++ runtime, no OpenMP,
 * nothing beyond the C library). Loaded with ctypes by affine_deformers/accel/native.py, which
 * holds the argument conventions; the mathematics is docs/MATH.md's and kernel_math.h's.
 *
 * Conventions: every array is C-contiguous; float64 = double, float32 = float, int32 indices,
 * int64 for numpy's intp on every supported 64-bit platform, bool = uint8_t (numpy's bool_).
 * Entries that run on several threads take a shared chunk counter (int64, 0 at the start of a call)
 * and return how many chunks the calling thread did (-1: out of memory; -2: a row of the work list out
 * of range, checked before anything is written). */
#ifndef AFFINE_KERNEL_H
#define AFFINE_KERNEL_H

#include <stdint.h>

#if defined(_WIN32)
#define AK_EXPORT __declspec(dllexport)
#else
#define AK_EXPORT __attribute__((visibility("default")))
#endif

/* Raised when an entry's arguments change meaning; the loader refuses another version. */
#define AK_ABI_VERSION 1

AK_EXPORT int32_t ak_abi_version(void);
AK_EXPORT int64_t ak_chunk(void);

AK_EXPORT int64_t ak_deform_points(const double *points, int64_t n_points, const double *table, int64_t m,
                                   const int32_t *idx, const double *val, int64_t K, const int64_t *rows,
                                   int64_t n_rows, int32_t use_rows, int32_t offsets, double *out, float *out32,
                                   int32_t use32, int64_t *counter);
AK_EXPORT int64_t ak_motion_params(const double *table, int64_t m, const int32_t *idx, const double *val,
                                   int64_t N, int64_t K, const int64_t *rows, int64_t n_rows, int32_t use_rows,
                                   double *out, float *out32, int32_t use32, int64_t *counter);
AK_EXPORT int64_t ak_chain_points(const double *points, int64_t N, const double *table, int64_t m,
                                  const int32_t *idx, const double *val, int64_t n_pass, int64_t K,
                                  const int32_t *prefix, const double *mats, int64_t n_mats, const int64_t *rows,
                                  int64_t n_rows, int32_t use_rows, int32_t offsets, double *out, float *out32,
                                  int32_t use32, int64_t *counter);
AK_EXPORT int64_t ak_chain_motion(const double *table, int64_t m, const int32_t *idx, const double *val,
                                  int64_t n_pass, int64_t N, int64_t K, const int32_t *prefix, const double *mats,
                                  int64_t n_mats, const int64_t *rows, int64_t n_rows, int32_t use_rows,
                                  double *out, float *out32, int32_t use32, int64_t *counter);

AK_EXPORT int64_t ak_polar_log(const double *M, int64_t n, double *R, double *Yh);
AK_EXPORT int64_t ak_psi_rows(double *rows, int64_t n);
AK_EXPORT int64_t ak_node_pivot(int32_t finish, const double *A, int64_t n, int64_t a_cols, const double *x,
                                double *out);
AK_EXPORT double ak_cage_faces(const double *cur, const double *rest, int64_t n_vertices, const int64_t *triples,
                               int64_t n_corners, const int64_t *first, int64_t n_faces, const uint8_t *usable,
                               const double *weight, const uint8_t *rest_ok, const double *centres,
                               const double *inverses, const int64_t *sv, const double *sg, int64_t n_stencil,
                               const double *smom, const double *sspread, const uint8_t *sactive,
                               const int64_t *fan, int64_t n_fan, uint8_t *moved, double *params,
                               double *corner_params, int64_t *flags);
AK_EXPORT int64_t ak_cage_nodes(const double *Wt, int64_t F, int64_t G, const int64_t *reached, int64_t n_reached,
                                const int64_t *faces, int64_t n, const double *face_params, const double *keep,
                                double *totals, int32_t fill_totals, const double *x, double *terms, double *blend,
                                double *out, uint8_t *touched);

/* The shape-preserving pass (affine_solve.c): a sparse SPD factorisation kept behind an opaque handle
 * (ak_spd_factor writes it to *handle; ak_spd_free releases it), its solve, and a frame of the pass. */
AK_EXPORT int64_t ak_spd_factor(int64_t n, const int64_t *indptr, const int64_t *indices, const double *data,
                                int32_t ordering, const int64_t *perm_in, int64_t *perm_out, int64_t *info,
                                void **handle);
AK_EXPORT int64_t ak_spd_solve(void *handle, double *b, int64_t k);
AK_EXPORT int64_t ak_spd_free(void *handle);
AK_EXPORT int64_t ak_spd_bytes(void *handle);
AK_EXPORT int64_t ak_arap_frame(void *handle, int64_t n, int64_t n_elem, int64_t k, const int64_t *corners,
                                const double *grads, const double *weights, const double *normals,
                                const double *motions, const double *field, int64_t iterations, double *out);

AK_EXPORT int64_t ak_rows_reading(const uint8_t *hit, int64_t m, const int32_t *idx, const double *val, int64_t N,
                                  int64_t K, int64_t *out);
AK_EXPORT int32_t ak_same_words(const uint32_t *a, const uint32_t *b, int64_t n);
AK_EXPORT int32_t ak_spin_wait(const int64_t *flag, int64_t seen, int64_t n);

#endif
