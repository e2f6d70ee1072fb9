"""Elements of the shape-preserving pass (MATH.md §15): a triangle, or a tetrahedron, with its gradient
operator, its energy weight and the per-element control weights.

A triangle (p0, p1, p2) becomes a tetrahedron as a cage face does (MATH.md §9): its rest edge matrix is
E = [e1, e2, h], e1 = p1 − p0, e2 = p2 − p0, h along the normal n = e1 × e2. The fourth point is not a
mesh vertex: in the pass it is a free unknown of its element alone, and minimising the element's term
over it in closed form leaves the tangent-plane gradient (MATH.md §15), so the offset's length drops
out and only the first two rows of E⁻¹ are kept:

    r1 = (e2 × n̂)/|n|,   r2 = (n̂ × e1)/|n|    (r_a · e_b = δ_ab, r_a · n̂ = 0),

and the gradient of positions x on the element is F(x) = Σ_c x_c g_cᵀ with g_1 = r1, g_2 = r2,
g_0 = −r1 − r2 (Σ_c g_c = 0: a translation has no gradient). A tetrahedron (p0 … p3) of a volume mesh
uses all three rows of E⁻¹ = [p1 − p0, p2 − p0, p3 − p0]⁻¹ the same way and no normal.

Energy weight: the rest area (the pass integrates ‖F − A‖² over the surface; a weight growing like a
tetrahedron's volume, area^{3/2}, would not converge as the mesh is refined), or the rest volume.

Degenerate elements are refused at bind (`DegenerateElementsError`, a ValueError): a triangle whose
height is below DEGENERATE_RATIO times its longest edge has no tangent plane to speak of, and its
gradient rows grow like 1/height (the system's conditioning with them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..surface import FloatArray, IndexArray, connected_components

__all__ = [
    "DEGENERATE_RATIO",
    "DegenerateElementsError",
    "Elements",
    "element_gradients",
    "element_weights",
    "mesh_components",
    "tetrahedron_elements",
    "triangle_elements",
    "vertex_areas",
]

#: A triangle (tetrahedron) counts as degenerate when 2·area / (longest edge)² (6·volume / (longest
#: edge)³) is at most this: its height is a millionth of its size.
DEGENERATE_RATIO = 1e-6

#: What the refusal tells the artist to do (Blender's menu names).
DEGENERATE_FIX = ("merge vertices by distance (Mesh ▸ Clean Up ▸ Merge by Distance) or dissolve degenerate "
                  "faces (Mesh ▸ Clean Up ▸ Degenerate Dissolve), then bind again")


class DegenerateElementsError(ValueError):
    """Some elements have (almost) zero area or volume; the message names the first and the fix."""


@dataclass(frozen=True)
class Elements:
    """The pass's elements over a mesh of `n_vertices` vertices.

    corners (E, K) int64, K = 3 (triangles) or 4 (tetrahedra); gradients (E, K, 3): g_c, so that the
    gradient of positions x is F(x)_t = Σ_c x[corners[t, c]] g[t, c]ᵀ; weights (E,): the rest area or
    volume; normals (E, 3): unit rest normals of triangles (zeros for tetrahedra: F is then complete);
    centroids (E, 3): rest centroids (where the caller evaluates an element's control weights)."""

    corners: IndexArray
    gradients: FloatArray
    weights: FloatArray
    normals: FloatArray
    centroids: FloatArray
    n_vertices: int

    @property
    def count(self) -> int:
        return int(self.corners.shape[0])

    @property
    def kind(self) -> str:
        return "TRIANGLES" if self.corners.shape[1] == 3 else "TETRAHEDRA"


def _mesh_inputs(points: ArrayLike, cells: ArrayLike, k: int, what: str) -> tuple[FloatArray, IndexArray]:
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError("points contain non-finite values")
    C = np.asarray(cells)
    if C.size == 0:
        C = C.reshape(0, k)
    if C.ndim != 2 or C.shape[1] != k or not np.issubdtype(C.dtype, np.integer):
        raise ValueError(f"{what} must be an integer array of shape (E, {k}), got {C.dtype} {C.shape}")
    C = C.astype(np.int64)
    if C.size and (int(C.min()) < 0 or int(C.max()) >= P.shape[0]):
        raise ValueError(f"{what} vertex indices must be in [0, {P.shape[0]})")
    return P, C


def _refuse_degenerate(bad: NDArray[np.bool_], cells: IndexArray, what: str, one: str, measure: str) -> None:
    if not bad.any():
        return
    first = int(np.flatnonzero(bad)[0])
    verts = ", ".join(str(int(v)) for v in cells[first])
    raise DegenerateElementsError(
        f"{int(bad.sum())} of the mesh's {cells.shape[0]} {what} have zero {measure} (the first: {one} "
        f"{first}, vertices {verts}); the shape-preserving pass needs a {measure} for every one: "
        f"{DEGENERATE_FIX}")


def triangle_elements(points: ArrayLike, triangles: ArrayLike) -> Elements:
    """The elements of a triangle mesh: points (N, 3) at rest, triangles (F, 3) vertex indices (the
    caller triangulates polygons; Blender's loop triangles). DegenerateElementsError (a ValueError)
    naming the first bad triangle and the fix when some have (almost) zero area."""
    P, T = _mesh_inputs(points, triangles, 3, "triangles")
    p0, p1, p2 = P[T[:, 0]], P[T[:, 1]], P[T[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    n = np.cross(e1, e2)
    area2 = np.sqrt(np.einsum("ij,ij->i", n, n))
    longest = np.max(np.stack([np.einsum("ij,ij->i", e, e) for e in (e1, e2, p2 - p1)]), axis=0)
    _refuse_degenerate(~(area2 > DEGENERATE_RATIO * longest), T, "triangles", "triangle", "area")
    unit = n / area2[:, None]
    grads = np.empty((T.shape[0], 3, 3))
    grads[:, 1] = np.cross(e2, unit) / area2[:, None]
    grads[:, 2] = np.cross(unit, e1) / area2[:, None]
    grads[:, 0] = -(grads[:, 1] + grads[:, 2])
    return Elements(T, grads, 0.5 * area2, unit, (p0 + p1 + p2) / 3.0, P.shape[0])


def tetrahedron_elements(points: ArrayLike, tetrahedra: ArrayLike) -> Elements:
    """The elements of a tetrahedral mesh: points (N, 3), tetrahedra (T, 4) vertex indices (either
    orientation). DegenerateElementsError when some have (almost) zero volume."""
    P, T = _mesh_inputs(points, tetrahedra, 4, "tetrahedra")
    corners = P[T]  # (T, 4, 3)
    E = np.swapaxes(corners[:, 1:] - corners[:, :1], 1, 2)  # columns p_c − p_0
    det = np.linalg.det(E)
    edges = corners[:, [1, 2, 3, 2, 3, 3]] - corners[:, [0, 0, 0, 1, 1, 2]]
    longest = np.sqrt(np.max(np.einsum("tij,tij->ti", edges, edges), axis=1))
    _refuse_degenerate(~(np.abs(det) > DEGENERATE_RATIO * longest**3), T, "tetrahedra", "tetrahedron",
                       "volume")
    rows = np.linalg.inv(E)  # row a of E⁻¹: the gradient of the barycentric coordinate of corner a + 1
    grads = np.concatenate([-rows.sum(axis=1, keepdims=True), rows], axis=1)
    return Elements(T, grads, np.abs(det) / 6.0, np.zeros((T.shape[0], 3)), corners.mean(axis=1), P.shape[0])


def element_gradients(elements: Elements, x: ArrayLike) -> FloatArray:
    """F(x)_t = Σ_c x[corners[t, c]] g[t, c]ᵀ (E, 3, 3) for positions x (N, 3): the gradient of the
    piecewise linear map rest ↦ x on each element (on a triangle's plane: F n̂ = 0)."""
    X = np.asarray(x, dtype=np.float64)
    return np.einsum("tkr,tks->trs", X[elements.corners], elements.gradients)


def vertex_areas(elements: Elements) -> FloatArray:
    """Lumped vertex areas (volumes) m_v = Σ_{t ∋ v} w_t / K (N,): what a vertex stands for."""
    K = elements.corners.shape[1]
    return np.bincount(elements.corners.ravel(), np.repeat(elements.weights / K, K),
                       minlength=elements.n_vertices)


def mesh_components(elements: Elements) -> IndexArray:
    """Each vertex's connected part through the elements (the lowest vertex index in it; a vertex in
    no element is a part of its own): the constant positions of a part are the pass's null space."""
    C = elements.corners
    K = C.shape[1]
    if not C.size:
        return connected_components(elements.n_vertices, np.zeros((0, 2), np.int64))
    edges = np.concatenate([C[:, [a, (a + 1) % K]] for a in range(K)])
    return connected_components(elements.n_vertices, edges)


def element_weights(elements: Elements, indices: ArrayLike,
                    values: ArrayLike) -> tuple[NDArray[np.int32], FloatArray]:
    """Per-element control weights: the mean of the corners' sparse rows (indices, values (N, K) as
    the deformer's weights; pooled columns included), i.e. the weights at the centroid of the linear
    interpolation. Rows keep their sum, so weights summing to 1 still give a shared motion exactly.
    Returns (indices (E, K') int32, values (E, K')) with K' ≤ corners·K (unused slots: index 0,
    value 0), the entries of a row sorted by control index."""
    idx = np.asarray(indices)
    val = np.asarray(values, dtype=np.float64)
    if idx.ndim != 2 or idx.shape != val.shape or idx.shape[0] != elements.n_vertices:
        raise ValueError(f"indices and values must have shape ({elements.n_vertices}, K), "
                         f"got {idx.shape} and {val.shape}")
    E, Kc = elements.corners.shape
    if E == 0 or idx.shape[1] == 0:
        return np.zeros((E, 1), np.int32), np.zeros((E, 1))
    cand_i = idx[elements.corners].reshape(E, -1).astype(np.int64)
    cand_v = val[elements.corners].reshape(E, -1) / Kc
    order = np.argsort(cand_i, axis=1, kind="stable")
    cand_i = np.take_along_axis(cand_i, order, axis=1).ravel()
    cand_v = np.take_along_axis(cand_v, order, axis=1).ravel()
    row = np.repeat(np.arange(E, dtype=np.int64), order.shape[1])
    first = np.ones(cand_i.size, dtype=bool)
    first[1:] = (cand_i[1:] != cand_i[:-1]) | (row[1:] != row[:-1])
    starts = np.flatnonzero(first)
    sums = np.add.reduceat(cand_v, starts)
    keep = sums != 0.0
    r, c, s = row[starts][keep], cand_i[starts][keep], sums[keep]
    counts = np.bincount(r, minlength=E)
    width = max(1, int(counts.max()) if counts.size else 1)
    slot = np.arange(r.size) - np.repeat(np.cumsum(counts) - counts, counts)
    out_i = np.zeros((E, width), np.int32)
    out_v = np.zeros((E, width))
    out_i[r, slot] = c
    out_v[r, slot] = s
    return out_i, out_v
