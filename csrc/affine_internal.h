/* What the kernel's translation units share and do not export (built with -fvisibility=hidden: only
 * AK_EXPORT symbols of affine_kernel.h leave the library). */
#ifndef AFFINE_INTERNAL_H
#define AFFINE_INTERNAL_H

/* One-sided Jacobi SVD of a 3x3 row-major A: on return A holds A V = U diag(s) (orthogonal columns) and
 * V the right singular vectors (det V = 1). Defined in affine_kernel.c. */
void ak_jacobi3(double A[9], double V[9]);

#endif
