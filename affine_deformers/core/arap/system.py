"""The shape-preserving pass's linear system (MATH.md §15): anchors, assembly, right-hand side and the
extra iteration's targets, in numpy.

Energy over positions x (N, 3), for per-element targets T_t (3×3: the blended maps' linear parts) and
the per-vertex field's positions y (N, 3):

    E(x) = Σ_t w_t ‖(F_t(x) − T_t) P_t‖² + Σ_v α_v |x_v − y_v|²,

F_t(x) = Σ_c x_c g_cᵀ (elements.py), P_t the projector onto a triangle's plane (I for a tetrahedron;
F_t P_t = F_t). Its normal equations, one 3-column system with one matrix:

    L x = Σ_t w_t T_t g_c + α ∘ y,   L_cd = Σ_t w_t g_c·g_d + δ_cd α_c.

Null space: Σ_c g_c = 0, so the Σ_t term is blind to a translation of every vertex of a connected
part; only the anchors α see it, and L is positive definite exactly when every part holds an anchor.
`bind_system` gives every part without one a weak floor (UNANCHORED_FLOOR) and a vertex in no
element α = 1, so L is always positive definite and such a part follows the field on average.

The solve is written for the displacement from the field, d = x − y:

    L d = r,   r_c = Σ_t w_t (T_t − F_t(y)) g_c   (the anchor term vanishes: x_v − y_v = d_v).

Same solution, but what it solves is the field's mismatch only: a motion G shared by every control
gives T_t = G's linear part and y = G v, so r is rounding noise and x = y to float noise, whatever
the conditioning of L and however far G translates (MATH.md §15).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..surface import Csr, FloatArray, Multigrid, conjugate_gradient
from .elements import (
    Elements,
    element_gradients,
    element_weights,
    mesh_components,
    triangle_elements,
    vertex_areas,
)

__all__ = [
    "ANCHOR_LEVEL",
    "ANCHOR_STRENGTH",
    "ArapBind",
    "ArapSystem",
    "NumpyArapSolver",
    "anchor_weights",
    "bind_system",
    "bind_triangles",
    "closest_rotations",
    "linear_maps",
    "right_hand_side",
    "solve_frame",
    "stretch_parts",
    "swapped_targets",
]

#: Default constraint strength s: α_v = s · κ_v · m_v / A (A the total rest area, m_v the vertex's
#: lumped area, κ_v ∈ [0, 1] its nearness to a control), so the anchors' pull is the same fraction of
#: the mesh's stiffness at every resolution and scale (docs/MATH.md §15; bench/arap_core.py).
ANCHOR_STRENGTH = 100.0
#: A vertex is an anchor where its weight on a control reaches this fraction of that control's largest
#: weight over the mesh (κ rises smoothly from 0 there to 1 at the control's strongest vertices).
ANCHOR_LEVEL = 0.5
#: A connected part without any anchor gets α_v = UNANCHORED_FLOOR · m_v / A on every vertex.
UNANCHORED_FLOOR = 1e-2
#: The numpy solver's conjugate gradients stop at ‖r − L d‖ ≤ CG_TOLERANCE ‖r‖ per coordinate.
CG_TOLERANCE = 1e-10
CG_MAX_ITERATIONS = 2000


# ------------------------------------------------------------------------------------------- anchors


def anchor_weights(elements: Elements, indices: ArrayLike, values: ArrayLike, *,
                   strength: float = ANCHOR_STRENGTH, level: float = ANCHOR_LEVEL,
                   controls: int | None = None) -> FloatArray:
    """Per-vertex anchor weights α (N,) near the controls, from the deformer's sparse weights
    (indices, values (N, K)): with W_i the largest weight of control i over the mesh and
    s(z) = z²(3 − 2z) on [0, 1],

        κ_v = max_k s((values[v, k]/W_idx − level)/(1 − level)),   α_v = strength · κ_v · m_v / A.

    Relative to each control's own largest weight, so probes inside the mesh (whose weights never
    reach 1 on the surface) anchor the vertices nearest them. `controls`: indices ≥ this (a pooled
    column, MATH.md §12) are not controls and anchor nothing."""
    idx = np.asarray(indices, dtype=np.int64)
    val = np.asarray(values, dtype=np.float64)
    n = elements.n_vertices
    if idx.shape != val.shape or idx.ndim != 2 or idx.shape[0] != n:
        raise ValueError(f"indices and values must have shape ({n}, K), got {idx.shape} and {val.shape}")
    if not (strength >= 0.0 and np.isfinite(strength)) or not 0.0 <= level < 1.0:
        raise ValueError(f"strength must be ≥ 0 and level in [0, 1), got {strength} and {level}")
    m = int(idx.max()) + 1 if idx.size else 0
    use = val > 0.0
    if controls is not None:
        use &= idx < controls
    top = np.zeros(max(m, 1))
    np.maximum.at(top, idx[use], val[use])
    rel = np.where(use, val / np.where(use, top[idx], 1.0), 0.0)
    z = np.clip((rel - level) / (1.0 - level), 0.0, 1.0)
    kappa = (z * z * (3.0 - 2.0 * z)).max(axis=1, initial=0.0)
    areas = vertex_areas(elements)
    total = float(areas.sum())
    return strength * kappa * areas / (total if total > 0.0 else 1.0)


# ------------------------------------------------------------------------------------------- system


@dataclass(frozen=True)
class ArapSystem:
    """What a bind assembles (numpy; the factor lives with the solver): the elements, the final anchor
    weights α (N,) (floors included), L as a CSR matrix (N × N, both triangles, sorted columns), and
    how many connected parts had no anchor (`loose_parts`, given the floor)."""

    elements: Elements
    anchors: FloatArray
    matrix: Csr
    loose_parts: int

    @property
    def n(self) -> int:
        return self.elements.n_vertices


def bind_system(elements: Elements, anchors: ArrayLike) -> ArapSystem:
    """Assemble L = Σ_t w_t G_tᵀ G_t + diag(α) for the anchors α (N,) (≥ 0, finite), first giving every
    connected part without an anchor a floor (see the module docstring)."""
    n = elements.n_vertices
    alpha = np.array(anchors, dtype=np.float64, copy=True).reshape(-1)
    if alpha.shape != (n,):
        raise ValueError(f"anchors must have shape ({n},), got {np.shape(anchors)}")
    if not np.all(np.isfinite(alpha)) or np.any(alpha < 0.0):
        raise ValueError("anchor weights must be finite and ≥ 0")
    areas = vertex_areas(elements)
    total = float(areas.sum()) or 1.0
    parts = mesh_components(elements)
    held = np.bincount(parts, alpha, minlength=n) > 0.0
    loose = ~held[parts]
    alpha[loose] = UNANCHORED_FLOOR * areas[loose] / total
    alpha[areas == 0.0] = np.maximum(alpha[areas == 0.0], 1.0)  # in no element: d = 0
    n_loose = int(np.unique(parts[loose & (areas > 0.0)]).size)
    C, G = elements.corners, elements.gradients
    K = C.shape[1]
    gg = np.einsum("tas,tbs->tab", G, G) * elements.weights[:, None, None]
    rows = np.concatenate([np.repeat(C, K, axis=1).ravel(), np.arange(n)])
    cols = np.concatenate([np.tile(C, (1, K)).ravel(), np.arange(n)])
    matrix = Csr.from_coo(rows, cols, np.concatenate([gg.ravel(), alpha]), (n, n))
    return ArapSystem(elements, alpha, matrix, n_loose)


@dataclass(frozen=True)
class ArapBind:
    """Everything a deformer keeps per bind and topology (with the solver `accel.arap_bind(system)`
    makes of `system`): the system, and the elements' control weights (indices (E, K') int32, values)
    for `vertex_motions` / `chain_motions` every frame."""

    system: ArapSystem
    indices: NDArray[np.int32]
    values: FloatArray


def bind_triangles(points: ArrayLike, triangles: ArrayLike, indices: ArrayLike, values: ArrayLike, *,
                   strength: float = ANCHOR_STRENGTH, level: float = ANCHOR_LEVEL,
                   controls: int | None = None, anchors: ArrayLike | None = None,
                   at_elements: tuple[ArrayLike, ArrayLike] | None = None) -> ArapBind:
    """One call for a triangle mesh bound with per-vertex sparse weights (indices, values (N, K), the
    deformer's): the elements (`triangle_elements`: DegenerateElementsError on zero-area triangles),
    their control weights (the corners' mean, or `at_elements` = (indices, values) evaluated by
    the weight mode at the centroids), the anchors (`anchor_weights` with strength, level, controls,
    or the given per-vertex `anchors`) and the assembled system."""
    elements = triangle_elements(points, triangles)
    if at_elements is None:
        e_idx, e_val = element_weights(elements, indices, values)
    else:
        e_idx = np.ascontiguousarray(at_elements[0], dtype=np.int32)
        e_val = np.ascontiguousarray(at_elements[1], dtype=np.float64)
        if e_idx.shape != e_val.shape or e_idx.ndim != 2 or e_idx.shape[0] != elements.count:
            raise ValueError(f"element weights must have shape ({elements.count}, K)")
    alpha = anchor_weights(elements, indices, values, strength=strength, level=level,
                           controls=controls) if anchors is None else anchors
    return ArapBind(bind_system(elements, alpha), e_idx, e_val)


# ------------------------------------------------------------------------------- right-hand side


def linear_maps(motions: ArrayLike, count: int | None = None) -> FloatArray:
    """The elements' linear parts (E, 3, 3) from `vertex_motions`' planar columns (4 or 3, E, 3):
    A[t][:, c] = motions[c, t]; (E, 3, 3) and (E, 4, 4) matrices pass through (their 3×3 part)."""
    M = np.asarray(motions, dtype=np.float64)
    if M.ndim == 3 and M.shape[0] in (3, 4) and M.shape[2] == 3 and (count is None or M.shape[1] == count):
        return np.stack([M[0], M[1], M[2]], axis=-1)
    if M.ndim == 3 and M.shape[1:] in ((3, 3), (4, 4)) and (count is None or M.shape[0] == count):
        return np.ascontiguousarray(M[:, :3, :3])
    raise ValueError(f"motions must be planar columns (4, {count}, 3) or matrices ({count}, 3, 3), "
                     f"got {M.shape}")


def right_hand_side(elements: Elements, targets: ArrayLike, field: ArrayLike) -> FloatArray:
    """r (N, 3), r_c = Σ_t w_t (T_t − F_t(y)) g_c: the displacement form's right-hand side for targets
    T (E, 3, 3) and the field's positions y (N, 3)."""
    y = np.asarray(field, dtype=np.float64)
    mismatch = (np.asarray(targets, dtype=np.float64) - element_gradients(elements, y))
    mismatch *= elements.weights[:, None, None]
    per_corner = np.einsum("trs,tks->tkr", mismatch, elements.gradients)
    flat = elements.corners.ravel()
    n = elements.n_vertices
    return np.stack([np.bincount(flat, per_corner[..., r].ravel(), minlength=n) for r in range(3)], axis=1)


# --------------------------------------------------------------------------- the extra iteration


def stretch_parts(A: ArrayLike) -> FloatArray:
    """S = (AᵀA)^{1/2} = V diag(σ) Vᵀ (…, 3, 3) from the SVD A = U diag(σ) Vᵀ: the blended map's
    stretch exp(Y) (A = R(ω) exp(Y) is A's polar split)."""
    _, s, Vt = np.linalg.svd(np.asarray(A, dtype=np.float64))
    return np.einsum("...ji,...j,...jk->...ik", Vt, s, Vt)


def closest_rotations(X: ArrayLike) -> FloatArray:
    """The rotation nearest each X (…, 3, 3) in the Frobenius norm: U diag(1, 1, det(U Vᵀ)) Vᵀ for the
    SVD X = U diag(σ) Vᵀ (σ descending: the smallest direction flips when det X ≤ 0)."""
    U, _, Vt = np.linalg.svd(np.asarray(X, dtype=np.float64))
    U[..., :, 2] *= np.where(np.linalg.det(U @ Vt) < 0.0, -1.0, 1.0)[..., None]
    return U @ Vt


def swapped_targets(elements: Elements, x: ArrayLike, targets: ArrayLike, stretch: ArrayLike) -> FloatArray:
    """The extra iteration's targets R_t S_t: S_t the blended stretch (`stretch_parts` of the blended
    map), R_t = argmin_R ‖F̃_t − R S_t‖ = the rotation nearest F̃_t S_t, F̃_t = F_t(x) + T_t n̂ n̂ᵀ the
    solved gradient completed off the triangle's plane by the current target (the eliminated fourth
    point's optimum; F̃ = F for a tetrahedron)."""
    T = np.asarray(targets, dtype=np.float64)
    S = np.asarray(stretch, dtype=np.float64)
    nrm = elements.normals
    F = element_gradients(elements, x) + np.einsum("trs,ts,tk->trk", T, nrm, nrm)
    return closest_rotations(F @ S) @ S


# --------------------------------------------------------------------------- solving (numpy path)


def solve_frame(elements: Elements, solve: Callable[[FloatArray], FloatArray], motions: ArrayLike,
                field: ArrayLike, iterations: int = 1) -> FloatArray:
    """Positions x (N, 3) of one frame: d = solve(r) for the blended maps' linear parts (`motions`, see
    `linear_maps`) and the field's positions y, x = y + d; each further iteration swaps the solved
    rotations into the targets (`swapped_targets`) and solves again with the same solver."""
    if iterations < 1:
        raise ValueError(f"iterations must be ≥ 1, got {iterations}")
    y = np.asarray(field, dtype=np.float64)
    if y.shape != (elements.n_vertices, 3):
        raise ValueError(f"field must have shape ({elements.n_vertices}, 3), got {y.shape}")
    targets = linear_maps(motions, elements.count)
    x = y + solve(right_hand_side(elements, targets, y))
    if iterations > 1:
        stretch = stretch_parts(targets)
        for _ in range(iterations - 1):
            targets = swapped_targets(elements, x, targets, stretch)
            x = y + solve(right_hand_side(elements, targets, y))
    return x


@dataclass
class NumpyArapSolver:
    """The pass without the compiled kernel: conjugate gradients on L with the smoothed-aggregation
    V-cycle of core.surface as the preconditioner, from d = 0 every frame (so a frame's result does not
    depend on the frames before it), to CG_TOLERANCE. Slower than the compiled factor by one to two
    orders of magnitude (bench/arap_core.py) but needs nothing beyond numpy. `frame` and `stats` as
    the compiled solver's; `close` does nothing."""

    system: ArapSystem
    tolerance: float = CG_TOLERANCE
    stats: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._multigrid = Multigrid.build(self.system.matrix)
        self.stats.update(backend="numpy", n=self.system.n, nnz_matrix=int(self.system.matrix.data.size),
                          cg_iterations=0)

    def solve(self, rhs: FloatArray) -> FloatArray:
        """L⁻¹ rhs for rhs (N, 3) by preconditioned conjugate gradients."""
        x, iterations, _worst = conjugate_gradient(self.system.matrix, np.asarray(rhs, dtype=np.float64),
                                                   self._multigrid.apply, self.tolerance, CG_MAX_ITERATIONS)
        self.stats["cg_iterations"] = iterations
        return x

    def frame(self, motions: ArrayLike, field: ArrayLike, iterations: int = 1,
              out: FloatArray | None = None) -> FloatArray:
        x = solve_frame(self.system.elements, self.solve, motions, field, iterations)
        if out is None:
            return x
        out[...] = x
        return out

    def close(self) -> None:
        """Nothing to free (the compiled solver frees its factor here)."""
