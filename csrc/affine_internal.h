/* What the kernel's files share and do not export (built with -fvisibility=hidden: only the AK_EXPORT
 * symbols of affine_kernel.h leave the library). The files, one concern each:
 *
 *  - kernel_math.h: the per-vertex map's scalar pieces (static inline);
 *  - kernel_threads.c: the library's own entries (ABI version, chunk size, spin-wait), the scratch
 *    pool and the chunk runner every multi-threaded entry uses (`ak_run_chunks`, below);
 *  - kernel_vertex.c: the map on a chunk and the point and motion entries (kernel_map.h shares the
 *    chunk layout and the map with kernel_chain.c), the incremental update's passes;
 *  - kernel_chain.c: products of blends per vertex (bones);
 *  - kernel_controls.c: psi of a few controls, the polar split, the cage nodes' pivot (scalar code);
 *  - kernel_cage.c: a cage's faces and nodes per update;
 *  - affine_solve.c: the shape-preserving pass. */
#ifndef AFFINE_INTERNAL_H
#define AFFINE_INTERNAL_H

#include <stdint.h>

#define CHUNK 2048
/* Rows a multiple of 4 KiB apart alias in the L1 cache; the map touches ~20 rows at once. */
#define STRIDE (CHUNK + 8)

/* One chunk of an entry's work list, rows [a, a + len): `args` the entry's arguments, W its scratch
 * rows (STRIDE doubles each), Q CHUNK offsets when the entry asked for them (NULL otherwise). */
typedef void (*chunk_fn)(const void *args, double *W, uint64_t *Q, int64_t a, int64_t len);

/* The work list's chunks on the calling thread: claim the next chunk from the shared counter until
 * none is left, running `chunk` on a scratch of `n_scratch_rows` rows (and, with `with_q`, CHUNK
 * offsets). Returns the chunks done, -1 when no scratch could be had. Defined in kernel_threads.c. */
int64_t ak_run_chunks(const void *args, chunk_fn chunk, int64_t n, int n_scratch_rows, int with_q,
                      int64_t *counter);

/* One-sided Jacobi SVD of a 3x3 row-major A: on return A holds A V = U diag(s) (orthogonal columns) and
 * V the right singular vectors (det V = 1). Defined in kernel_controls.c. */
void ak_jacobi3(double A[9], double V[9]);

/* row (M row-major, then t) <- psi in the 12-number layout (w, u, Y6); 1 if finite. Defined in
 * kernel_controls.c (kernel_cage.c takes each corner's psi with it). */
int ak_psi_row(double *row);

/* The cage nodes' pivot in two steps (kernel_controls.c; ak_node_pivot, and ak_cage_nodes in
 * kernel_cage.c): b = V(w)^-1 (M - I) row-major for face parameters p (M the linear part of phi(p)),
 * then out = (w, u + Bx + V(w)^-1 (x - M x), Y) for a node at point x from its blended (w, u, Y) and
 * Bx = (blended B) x. */
void ak_face_term(const double *p, double b[9]);
void ak_node_finish(double w0, double w1, double w2, const double u[3], const double y[6], const double Bx[3],
                    const double *p, double *out);

#endif
