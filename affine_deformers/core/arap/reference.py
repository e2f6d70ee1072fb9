"""Dense reference of the shape-preserving pass (MATH.md §15), for tests on small meshes: the energy
minimised as one weighted least-squares problem, built from the element gradients directly, with no
normal equations, no sparse matrix and no displacement form.

Per coordinate r, the unknowns x_r (N,) satisfy in the least-squares sense

    √w_t Σ_c g_c[s] x_r[c] = √w_t (T_t P_t)[r, s]    (every element t, s = 0, 1, 2),
    √α_v x_r[v] = √α_v y_r[v]                          (every vertex v),

solved by numpy's lstsq (an orthogonal factorisation). Memory O((3E + N) · N): a few thousand vertices
at most.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .elements import Elements
from .system import linear_maps, stretch_parts, swapped_targets

FloatArray = NDArray[np.float64]

__all__ = ["REFERENCE_MAX_VERTICES", "reference_positions"]

#: Larger meshes are refused (the dense design matrix would not fit comfortably).
REFERENCE_MAX_VERTICES = 4000


def _solve(elements: Elements, anchors: FloatArray, targets: FloatArray, y: FloatArray) -> FloatArray:
    n, E = elements.n_vertices, elements.count
    K = elements.corners.shape[1]
    sw = np.sqrt(elements.weights)
    design = np.zeros((3 * E + n, n))
    rows = 3 * np.arange(E)[:, None, None] + np.arange(3)[None, None, :]  # (E, 1, 3): rows of element t
    cols = np.broadcast_to(elements.corners[:, :, None], (E, K, 3))
    np.add.at(design, (np.broadcast_to(rows, (E, K, 3)), cols),
              sw[:, None, None] * elements.gradients)
    sa = np.sqrt(anchors)
    design[3 * E + np.arange(n), np.arange(n)] = sa
    projector = np.eye(3) - np.einsum("ti,tj->tij", elements.normals, elements.normals)
    goal = np.einsum("trs,tsk->trk", targets, projector) * sw[:, None, None]  # (E, r, s)
    rhs = np.concatenate([np.swapaxes(goal, 1, 2).reshape(3 * E, 3), sa[:, None] * y])
    return np.linalg.lstsq(design, rhs, rcond=None)[0]


def reference_positions(elements: Elements, anchors: ArrayLike, motions: ArrayLike, field: ArrayLike,
                        iterations: int = 1) -> FloatArray:
    """The pass's positions x (N, 3) for final anchor weights α (N,) (`ArapSystem.anchors`: every part
    anchored), the blended maps (`motions`, as `system.linear_maps` reads them) and the per-vertex
    field's positions y (N, 3); each further iteration swaps in the solved rotations
    (`system.swapped_targets`)."""
    if elements.n_vertices > REFERENCE_MAX_VERTICES:
        raise ValueError(f"the dense reference is for meshes of at most {REFERENCE_MAX_VERTICES} vertices")
    alpha = np.asarray(anchors, dtype=np.float64)
    y = np.asarray(field, dtype=np.float64)
    targets = linear_maps(motions, elements.count)
    x = _solve(elements, alpha, targets, y)
    if iterations > 1:
        stretch = stretch_parts(targets)
        for _ in range(iterations - 1):
            targets = swapped_targets(elements, x, targets, stretch)
            x = _solve(elements, alpha, targets, y)
    return x
