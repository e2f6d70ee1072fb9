"""Cage faces → rest/current tetrahedra → per-face motion parameters (`face_motions`), the rest
tables of the compiled face path (`face_tables`) and the faces an edit reaches (`affected_faces`).

Per-face motion (course notes 8.3.2 with MATH.md §9): every consecutive vertex triple (p0, p1, p2) of a
face (n triples for an n-gon, n ≥ 4; one for a triangle) is a corner with the rest frame

    E = [e1, e2, h],   e1 = p1 − p0,  e2 = p2 − p0,  h = n/√|n|,  n = e1 × e2,

centroid c = (p0 + p1 + p2)/3 and apex c + h (offset length √(2·area), so the tetrahedron scales with
the face; det E = |n|^{3/2} > 0). The corner's motion is the affine map taking the rest tetrahedron
onto the current one: linear part M = E′ E⁻¹, translation c′ − M c. The face's parameters are the mean
of ψ_params(A_t) over its corners, so they do not depend on how the polygon would be triangulated.

Current apex. e1′, e2′ and c′ follow any affine motion G of the cage, but the current normal follows
cof(G), not G, so the normal apex c′ + n′/√|n′| ('NORMAL') reproduces only similarities exactly. A
face alone cannot know the out-of-plane part of the motion; its neighbourhood can ('NEIGHBOURS', the
default). At bind every cage vertex is written in each rest corner frame, p_j − c = E z_j with
z_j = (α_j, β_j) (α_j ∈ R² in plane, β_j out of plane), and the current apex column is

    h′ = Σ_j γ_j r_j,   r_j = p′_j − c′ − [e1′ e2′] α_j,   with fixed γ_j such that Σ_j γ_j β_j = 1.

Under a common affine G every r_j = G h β_j, so h′ = G h and A_t = G exactly (shear and non-uniform
scale included) whatever the γ_j; when a corner and its stencil move rigidly, A_t is that rigid
motion. The γ_j are the out-of-plane row of the weighted least-squares fit of a linear map to the
stencil (p_j − c ↦ p′_j − c′):

    γ_j = ω_j z_jᵀ (W + ρ diag(1, 1, 0))⁻¹ e₃,   W = Σ_j ω_j z_j z_jᵀ,   ω_j = (|p_j − c|/|h|)⁻⁴,

ρ = STENCIL_RIDGE · (W₁₁ + W₂₂)/2. Fitting the in-plane columns as well (small ρ) drives Σ γ_j α_j to
0, so the corner's own in-plane distortion is not extrapolated across the stencil; pinning them
(ρ → ∞, γ_j = ω_j β_j / Σ ω β²) amplifies vertex motion into the apex about three times more on
finely tessellated curved cages. The ridge keeps the fit well posed for any stencil. The stencil
holds the STENCIL_SIZE vertices with the largest weight ω_j β_j² among those with |β_j| ≥
STENCIL_MIN_BETA (coplanar vertices carry no out-of-plane information, so on a flat side of a cage
the stencil reaches round the edge to the next sides).

Local edits: h′ is linear in the current cage, so moving one vertex by δ moves the apex of every
corner whose stencil holds it by γ_j δ — continuous and proportional; `affected_faces` lists the
faces reached. A corner without stencil (a flat or open cage) keeps the normal apex, as does one
whose stencil has non-finite current positions.

Fold guard: x = h′·n̂′ = Σ γ_j (p′_j − c′)·n̂′ (in-plane terms drop out), and x ≤ 0 would give
det M ≤ 0. With m = Σ |γ_j| |(p′_j − c′)·n̂′| and μ = Σ |γ_j β_j| ≥ 1 (fixed at bind), every common
affine or rigid motion has m = μ x. x is replaced by f(x) = x for x ≥ τ = κ m/μ and τ²/(2τ − x) below
(κ = FOLD_KAPPA): C¹, increasing and > 0. It acts only once stencil vertices cross the corner's
current plane (the cage folds through itself) and keeps the tetrahedron from flipping or collapsing
there. A cage folded far through itself can still turn a corner more than a half turn from its rest,
where the principal rotation log changes branch, as a face turned over does with either apex.
"""

from __future__ import annotations

import contextlib
import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..aff3 import inverse3, params_from_matrices
from ..unwrap import lift_params
from .topology import CageTopology, _check_points, _list_indices, _norm

# A rest corner (consecutive triple) of an n-gon whose triangle area is below this fraction of the
# face's largest corner triangle is skipped: a straight or nearly straight corner (e.g. a T-junction
# vertex) has a needle tetrahedron that would turn any bending of the face into a huge stretch.
STRAIGHT_CORNER_RATIO = 1e-2

# A corner counts as collapsed when sin(corner angle) = |n|/(|e1||e2|) is below this.
COLLAPSED_SIN = 1e-10

# Elements per (corners × vertices) work array when building apex stencils.
CHUNK_ELEMENTS = 1 << 17

APEX_MODES = ("NEIGHBOURS", "NORMAL")

# Vertices per corner stencil for the 'NEIGHBOURS' apex: enough to average out a local edit, few
# enough to keep the stencil local and the per-frame cost O(corners · STENCIL_SIZE).
STENCIL_SIZE = 16

# Stencil vertices must lie at least this far off the corner plane, in units of the apex length
# √|n| (|β| ≥ this): nearly coplanar vertices (rounding, float32 noise) would amplify their motion
# by 1/|β| into the apex.
STENCIL_MIN_BETA = 1e-3

# Fold guard (module docstring): the apex's normal component is floored smoothly once it drops below
# this fraction of what a common motion of the stencil would give (m/μ). With 1/2 and equal
# per-vertex estimates, the guard acts once over a quarter of the fit's weight has crossed the plane.
FOLD_KAPPA = 0.5

# Ridge on the in-plane block of the stencil fit, relative to its mean diagonal (module docstring):
# small enough to balance the stencil's in-plane moments, large enough to keep the fit well posed
# when the stencil vertices are nearly collinear in the corner frame.
STENCIL_RIDGE = 1e-2

# Rest cages whose stencils are kept (the Blender layer rebuilds CageTopology every frame, so the
# cache is keyed by content, not by object).
_STENCIL_CACHE_ENTRIES = 4

#: M (n, 3, 3) ↦ (R, Ŷ) of the polar split, or None (`aff3.params_from_matrices`' `polar`).
PolarSplit = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray] | None"]


# --- corner frames ------------------------------------------------------------------------------


def _corner_frames(points: np.ndarray, triples: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E (T, 3, 3) columns [e1, e2, n/√|n|], centroid (T, 3), sin of the corner angle (T,))."""
    p0, p1, p2 = (points[triples[:, k]] for k in range(3))
    e1, e2 = p1 - p0, p2 - p0
    n = np.cross(e1, e2)
    area2 = _norm(n)
    edge_product = _norm(e1) * _norm(e2)
    with np.errstate(divide="ignore", invalid="ignore"):
        sin_corner = np.where(edge_product > 0.0, area2 / edge_product, 0.0)
        h = n / np.sqrt(area2)[:, None]
    E = np.stack([e1, e2, h], axis=2)
    return E, (p0 + p1 + p2) / 3.0, sin_corner


def _usable_rest_triples(rest: np.ndarray, topology: CageTopology) -> tuple[np.ndarray, np.ndarray]:
    """(usable (T,) bool, weight (T,)): rest corners kept after dropping collapsed and (for n-gons)
    nearly straight ones; weights renormalised to sum 1 per face over the kept corners."""
    triples, face, _ = topology.corner_triples()
    _, _, sin_corner = _corner_frames(rest, triples)
    p0, p1, p2 = (rest[triples[:, k]] for k in range(3))
    area2 = _norm(np.cross(p1 - p0, p2 - p0))
    largest = np.zeros(topology.n_faces)
    np.maximum.at(largest, face, np.where(np.isfinite(area2), area2, 0.0))
    usable = np.isfinite(sin_corner) & (sin_corner > COLLAPSED_SIN)
    is_ngon = topology.loop_total[face] > 3
    usable &= ~is_ngon | (area2 >= STRAIGHT_CORNER_RATIO * largest[face])
    kept = np.bincount(face, usable.astype(np.float64), topology.n_faces)
    weight = np.where(usable, 1.0 / np.maximum(kept[face], 1.0), 0.0)
    return usable, weight


@dataclass(frozen=True, eq=False)
class RestCorners:
    """What `face_motions` needs of the rest cage alone, per corner t (rows of
    `CageTopology.corner_triples`): `usable` and `weight` (`_usable_rest_triples`), the rest frame
    `frame` (T, 3, 3), centroid `centre` (T, 3) and sin of the corner angle `sin` (T,)
    (`_corner_frames`), and `inverse` (T, 3, 3) = E_rest⁻¹ by the adjugate (`inverse3`; rows that
    are singular or non-finite hold whatever the adjugate gives and are never used). Every entry is
    computed row by row, so a row is bit for bit what the same computation on a subset of the corners
    gives."""

    usable: np.ndarray
    weight: np.ndarray
    frame: np.ndarray
    centre: np.ndarray
    sin: np.ndarray
    inverse: np.ndarray

    def take(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(frame, centre, sin, inverse) of the corners `rows` (a bool mask or indices), the
        `rest_frames` argument of `corner_matrices`."""
        return self.frame[rows], self.centre[rows], self.sin[rows], self.inverse[rows]


_rest_corner_cache: OrderedDict[bytes, RestCorners] = OrderedDict()


def rest_corners(rest_points: np.ndarray, topology: CageTopology) -> RestCorners:
    """The rest cage's corner data (`RestCorners`), cached by content as `apex_stencils` is: a cage
    deformer asks for them on every update with the same rest cage."""
    rest = _check_points(rest_points, topology, "rest_points")
    key = b"corners" + _stencil_key(rest, topology, 0)
    with _stencil_lock:
        found = _rest_corner_cache.get(key)
        if found is not None:
            _rest_corner_cache.move_to_end(key)
            return found
    triples, _, _ = topology.corner_triples()
    usable, weight = _usable_rest_triples(rest, topology)
    E, c, sin_corner = _corner_frames(rest, triples)
    with np.errstate(all="ignore"):
        inverse = inverse3(E)[0]
    corners = RestCorners(usable, weight, E, c, sin_corner, inverse)
    with _stencil_lock:
        _rest_corner_cache[key] = corners
        while len(_rest_corner_cache) > _STENCIL_CACHE_ENTRIES:
            _rest_corner_cache.popitem(last=False)
    return corners


# --- apex stencils -------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ApexStencil:
    """Per corner t (rows of `CageTopology.corner_triples`), the stencil of the 'NEIGHBOURS' apex
    (module docstring): cage vertex indices (T, S), their rest coordinates in the corner frame,
    alpha (T, S, 2) in plane and beta (T, S) out of plane, and the fit coefficients gamma (T, S)
    (Σ_s gamma β = 1), so h′_t = Σ_s gamma r_s. Unused slots have alpha, beta, gamma 0 and repeat
    the row's first vertex; a row without stencil is all zero."""

    vertices: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    gamma: np.ndarray
    active: np.ndarray = field(init=False, repr=False)  # (T,) bool: corners with a stencil
    rows: np.ndarray = field(init=False, repr=False)  # flatnonzero(active)
    moments: np.ndarray = field(init=False, repr=False)  # (T, 3): Σ γ, Σ γ α₁, Σ γ α₂
    spread: np.ndarray = field(init=False, repr=False)  # (T,): Σ |γ β| (≥ 1, as Σ γ β = 1)

    def __post_init__(self) -> None:
        active = np.any(self.gamma != 0.0, axis=1)
        moments = np.concatenate(
            [self.gamma.sum(axis=1, keepdims=True), np.einsum("ts,tsk->tk", self.gamma, self.alpha)],
            axis=1,
        )
        object.__setattr__(self, "active", active)
        object.__setattr__(self, "rows", np.flatnonzero(active))
        object.__setattr__(self, "moments", moments)
        object.__setattr__(self, "spread", np.abs(self.gamma * self.beta).sum(axis=1))

    def take(self, rows: np.ndarray) -> ApexStencil:
        """The stencils of the corners `rows` (a bool mask or indices), the derived rows (`moments`,
        `spread`) taken from this one's rather than recomputed: exactly the rows the full stencil
        uses, so a corner's apex does not depend on which other corners are computed with it."""
        sub = object.__new__(ApexStencil)
        for name in ("vertices", "alpha", "beta", "gamma", "active", "moments", "spread"):
            object.__setattr__(sub, name, getattr(self, name)[rows])
        object.__setattr__(sub, "rows", np.flatnonzero(sub.active))
        return sub


_stencil_cache: OrderedDict[bytes, ApexStencil] = OrderedDict()
_stencil_lock = threading.Lock()


def _stencil_key(rest: np.ndarray, topology: CageTopology, size: int) -> bytes:
    digest = hashlib.blake2b(digest_size=20)
    for arr in (rest, topology.loop_vertex_indices, topology.loop_start, topology.loop_total):
        digest.update(np.ascontiguousarray(arr).tobytes())
        digest.update(str(arr.shape).encode())
    digest.update(f"{topology.n_vertices}:{size}:{STENCIL_RIDGE!r}".encode())
    return digest.digest()


def apex_stencils(
    rest_points: np.ndarray, topology: CageTopology, *, size: int = STENCIL_SIZE
) -> ApexStencil:
    """The 'NEIGHBOURS' apex stencils of the rest cage (module docstring), cached by content.

    For corner t with rest frame E_t, centroid c_t, every vertex used by a face is written as
    p_j − c_t = E_t (α_j, β_j); candidates have |β_j| ≥ STENCIL_MIN_BETA, and the `size` with the
    largest least-squares weight ω_j β_j² (ω_j = (|p_j − c_t|/|h_t|)⁻⁴) are kept — the heaviest terms
    of the fit over the whole cage. Collapsed or non-finite rest corners get no stencil.
    """
    rest = _check_points(rest_points, topology, "rest_points")
    if size < 1:
        raise ValueError(f"stencil size must be at least 1, got {size}")
    key = _stencil_key(rest, topology, size)
    with _stencil_lock:
        found = _stencil_cache.get(key)
        if found is not None:
            _stencil_cache.move_to_end(key)
            return found
    stencil = _build_stencils(rest, topology, size)
    with _stencil_lock:
        _stencil_cache[key] = stencil
        while len(_stencil_cache) > _STENCIL_CACHE_ENTRIES:
            _stencil_cache.popitem(last=False)
    return stencil


def _build_stencils(rest: np.ndarray, topology: CageTopology, size: int) -> ApexStencil:
    triples, _, _ = topology.corner_triples()
    E, c, sin_corner = _corner_frames(rest, triples)
    good = np.isfinite(sin_corner) & (sin_corner > COLLAPSED_SIN)
    good &= np.isfinite(E).all(axis=(1, 2)) & np.isfinite(c).all(axis=1)
    used = np.zeros(rest.shape[0], dtype=bool)
    used[topology.loop_vertex_indices] = True
    candidates = np.flatnonzero(used & np.isfinite(rest).all(axis=1))
    S = min(size, candidates.size)
    T = triples.shape[0]
    vertices = np.zeros((T, S), dtype=np.intp)
    alpha = np.zeros((T, S, 2))
    beta = np.zeros((T, S))
    gamma = np.zeros((T, S))
    rows = np.flatnonzero(good)
    if rows.size == 0 or S == 0:
        return ApexStencil(vertices, alpha, beta, gamma)
    origin = rest[candidates].mean(axis=0)  # keeps the expanded |p − c|² well conditioned
    P = rest[candidates] - origin
    P_sq = np.einsum("vi,vi->v", P, P)
    # Rows of E⁻¹ are the dual basis: (α₁, α₂, β) of p − c are dot products with them.
    dual = np.linalg.inv(E[rows])
    centre = c[rows] - origin
    apex_sq = np.einsum("ti,ti->t", E[rows, :, 2], E[rows, :, 2])  # |h|² = |n|
    step = max(1, CHUNK_ELEMENTS // candidates.size)
    for lo in range(0, rows.size, step):  # chunks of corners bound the (corners × vertices) arrays
        sl = slice(lo, lo + step)
        cb = centre[sl]
        beta_all = dual[sl, 2, :] @ P.T - np.einsum("ti,ti->t", dual[sl, 2, :], cb)[:, None]
        dist_sq = (P_sq[None, :] - 2.0 * (cb @ P.T) + np.einsum("ti,ti->t", cb, cb)[:, None])
        dist_sq /= apex_sq[sl, None]
        np.maximum(dist_sq, beta_all * beta_all, out=dist_sq)  # d ≥ |β|·|h| exactly; undo rounding
        candidate = np.abs(beta_all) >= STENCIL_MIN_BETA
        with np.errstate(divide="ignore", invalid="ignore"):
            score = np.where(candidate, beta_all * beta_all / (dist_sq * dist_sq), 0.0)  # ω β²
        if candidates.size > S:
            pick = np.argpartition(-score, S - 1, axis=1)[:, :S]
        else:
            pick = np.broadcast_to(np.arange(S), score.shape).copy()
        # Heaviest first, so the per-frame sums run in a fixed order.
        pick = np.take_along_axis(pick, np.argsort(-np.take_along_axis(score, pick, 1), 1, "stable"), 1)
        s = np.take_along_axis(score, pick, axis=1)
        b = np.take_along_axis(beta_all, pick, axis=1)
        keep = s > 0.0
        pick = np.where(keep, pick, pick[:, :1])
        r = rows[sl]
        coords = np.einsum("tki,tsi->tsk", dual[sl, :2, :], P[pick] - cb[:, None, :])
        a = np.where(keep[..., None], coords, 0.0)
        b = np.where(keep, b, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(keep, s / np.where(keep, b * b, 1.0), 0.0)  # ω
        g = _stencil_coefficients(w, a, b)
        vertices[r] = candidates[pick]
        alpha[r] = a
        beta[r] = b
        gamma[r] = g
    return ApexStencil(vertices, alpha, beta, gamma)


def _stencil_coefficients(w: np.ndarray, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """γ (C, S) = ω z ᵀ(W + ρ diag(1, 1, 0))⁻¹ e₃ (module docstring), so Σ γ β = 1; rows with no
    stencil (all ω = 0) give 0. w (C, S) the weights ω (0 in unused slots), alpha (C, S, 2), beta (C, S)."""
    z = np.concatenate([alpha, beta[..., None]], axis=2)
    W = np.einsum("ts,tsi,tsj->tij", w, z, z)
    ok = W[:, 2, 2] > 0.0
    ridge = STENCIL_RIDGE * 0.5 * (W[:, 0, 0] + W[:, 1, 1])
    W[:, 0, 0] += ridge
    W[:, 1, 1] += ridge
    sol = np.zeros((w.shape[0], 3))
    rhs = np.zeros((int(ok.sum()), 3, 1))
    rhs[:, 2, 0] = 1.0
    sol[ok] = np.linalg.solve(W[ok], rhs)[..., 0]
    return w * np.einsum("tsi,ti->ts", z, sol)


def _stencil_apex(
    current: np.ndarray, E_cur: np.ndarray, c_cur: np.ndarray, stencil: ApexStencil
) -> np.ndarray:
    """(T, 3) the fitted current apex column h′ of each corner with a stencil, fold-guarded (module
    docstring); NaN rows where there is no stencil or the fit is not finite.

    h′ = Σ γ_s (p′_s − c′) − (Σ γ α₁) e1′ − (Σ γ α₂) e2′, and since e1′, e2′ ⊥ n̂′ the normal
    residuals are r_s·n̂′ = (p′_s − c′)·n̂′. Padding slots (γ = 0) of an active row repeat one of its
    stencil vertices, so they cannot bring in a non-finite value of their own.
    """
    out = np.full((E_cur.shape[0], 3), np.nan)
    rows = stencil.rows
    if rows.size == 0:
        return out
    g = stencil.gamma[rows]
    moments = stencil.moments[rows]
    e1, e2, c = E_cur[rows, :, 0], E_cur[rows, :, 1], c_cur[rows]
    with np.errstate(all="ignore"):
        Q = current[stencil.vertices[rows]] - c[:, None, :]
        h = np.einsum("ts,tsi->ti", g, Q)
        h -= moments[:, 1:2] * e1 + moments[:, 2:3] * e2
        n = np.cross(e1, e2)
        unit = n / _norm(n)[:, None]
        normal = np.einsum("tsi,ti->ts", Q, unit)
        x = np.einsum("ti,ti->t", h, unit)
        m = np.einsum("ts,ts->t", np.abs(g), np.abs(normal))
        floor = FOLD_KAPPA * m / stencil.spread[rows]
        low = x < floor
        if np.any(low):
            guarded = floor[low] ** 2 / (2.0 * floor[low] - x[low])
            h[low] += (guarded - x[low])[:, None] * unit[low]
    out[rows] = np.where(np.isfinite(h).all(axis=1)[:, None], h, np.nan)
    return out


def corner_matrices(
    rest: np.ndarray,
    current: np.ndarray,
    triples: np.ndarray,
    *,
    stencil: ApexStencil | None = None,
    rest_frames: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(A (T, 4, 4), ok (T,)): the affine map taking each rest corner tetrahedron onto the current one.

    rest and current are (V, 3). The current apex is c′ + n′/√|n′| ('NORMAL'), or with `stencil`
    (rows matching `triples`) the fitted c′ + h′ wherever that is available (module docstring) and
    some input of the corner has moved (bitwise), so a corner at rest is exactly the identity. ok is
    False where either tetrahedron is collapsed (sin of the corner angle ≤ COLLAPSED_SIN) or the
    result is non-finite or has det ≤ 0; those rows of A are the identity. rest_frames: the rest
    side (frame, centre, sin, E_rest⁻¹) of these corners computed before (`RestCorners.take`): the
    same values, so the same result bit for bit.
    """
    if rest_frames is None:
        E_rest, c_rest, sin_rest = _corner_frames(rest, triples)
        rest_inverse = None
    else:
        E_rest, c_rest, sin_rest, rest_inverse = rest_frames
    E_cur, c_cur, sin_cur = _corner_frames(current, triples)
    if stencil is not None:
        fitted = _stencil_apex(current, E_cur, c_cur, stencil)
        use = np.isfinite(fitted).all(axis=1)
        # A corner whose inputs are bitwise at rest keeps the normal apex, which then equals the rest
        # apex bitwise, so its motion is exactly the identity rather than rounding noise.
        moved = np.any(current != rest, axis=1)
        use &= moved[triples].any(axis=1) | (moved[stencil.vertices] & (stencil.gamma != 0.0)).any(1)
        E_cur[use, :, 2] = fitted[use]
    ok = (sin_rest > COLLAPSED_SIN) & (sin_cur > COLLAPSED_SIN)
    ok &= np.isfinite(E_rest).all(axis=(1, 2)) & np.isfinite(E_cur).all(axis=(1, 2))
    ok &= np.isfinite(c_rest).all(axis=1) & np.isfinite(c_cur).all(axis=1)
    A = np.broadcast_to(np.eye(4), (triples.shape[0], 4, 4)).copy()
    if np.any(ok):
        # M E_rest = E_cur (the rest frames are well conditioned: sin of the corner > COLLAPSED_SIN)
        M = E_cur[ok] @ (inverse3(E_rest[ok])[0] if rest_inverse is None else rest_inverse[ok])
        A[ok, :3, :3] = M
        A[ok, :3, 3] = c_cur[ok] - np.einsum("tij,tj->ti", M, c_rest[ok])
    good = np.isfinite(A).all(axis=(1, 2)) & (inverse3(A[:, :3, :3])[1] > 0.0)
    ok &= good
    A[~ok] = np.eye(4)
    return A, ok


def _params_or_nan(A: np.ndarray, polar: PolarSplit | None = None) -> np.ndarray:
    """ψ_params of each matrix; a row that ψ rejects comes back as NaN instead of raising. polar: as
    in `params_from_matrices`."""

    def psi(M: np.ndarray) -> np.ndarray:
        return params_from_matrices(M) if polar is None else params_from_matrices(M, polar)

    try:
        return psi(A)
    except ValueError:
        # Rare (a corner too degenerate for the logarithm): redo row by row to isolate it.
        out = np.full((A.shape[0], 12), np.nan)
        for i in range(A.shape[0]):
            with contextlib.suppress(ValueError):
                out[i] = psi(A[i])
        return out


@dataclass(frozen=True)
class FaceMotions:
    """Per-face motion of a cage. params (F, 12) in the docs/DEVELOPING.md layout, zero (the identity)
    for invalid faces; valid (F,) bool; messages: human-readable summary of what was rejected."""

    params: np.ndarray
    valid: np.ndarray
    messages: tuple[str, ...]


def face_motions(
    rest_points: np.ndarray,
    current_points: np.ndarray,
    topology: CageTopology,
    *,
    w_ref: np.ndarray | None = None,
    pivot: np.ndarray | None = None,
    apex: str = "NEIGHBOURS",
    faces: np.ndarray | None = None,
    polar: PolarSplit | None = None,
) -> FaceMotions:
    """P_f = Σ_t (1/n_f) ψ_params(A_t) over the face's corner tetrahedra (see module docstring).

    polar: the polar split of ψ, as in `aff3.params_from_matrices` (the Blender layer passes the
    compiled kernel's `accel.polar_log`; the same motions to ~1e-15).

    faces: optional (F,) bool, the only faces whose motions are computed; the others get params 0
    and count as valid, as if at rest (for callers that know which faces can have moved,
    `affected_faces`: the computed faces' results do not depend on this).

    apex: 'NEIGHBOURS' (default) fits each corner's current apex to its rest-cage stencil
    (`apex_stencils`, cached per rest cage), so any common affine motion of the cage — shear and
    non-uniform scale included — gives every face exactly that motion; 'NORMAL' uses the current
    normal (MATH.md §9), exact for similarities only. A face's motion then depends on its own vertices
    and on its corners' stencil vertices (`affected_faces`).

    Corners are weighted 1/n, except that collapsed or nearly straight rest corners of n-gons are
    skipped (weight shared among the others). A face is invalid — params 0, reported — when it has
    no usable rest corner, or when a used corner is collapsed / non-finite in the current pose.

    The rotation parts of a face's corners are first brought onto one branch: onto w_ref (3,) or
    (F, 3) when given (e.g. from the cage object's rotation channels, unwrap.channel_rotvec; pivot
    as in unwrap.se3_log_lifted), otherwise onto the branch of the face's first corner, so corners
    near a half turn do not average to zero.
    """
    rest, cur = _check_pose_pair(rest_points, current_points, topology, apex)
    F = topology.n_faces
    triples, face, _ = topology.corner_triples()
    corners = rest_corners(rest, topology)
    usable, weight = corners.usable, corners.weight
    stencil = apex_stencils(rest, topology) if apex == "NEIGHBOURS" else None
    chosen = np.ones(triples.shape[0], dtype=bool)
    if faces is None:
        A, ok = corner_matrices(rest, cur, triples, stencil=stencil, rest_frames=corners.take(chosen))
    else:
        chosen = np.asarray(faces, dtype=bool)[face]
        A = np.broadcast_to(np.eye(4), (triples.shape[0], 4, 4)).copy()
        ok = np.ones(triples.shape[0], dtype=bool)
        sub = None if stencil is None else stencil.take(chosen)
        A[chosen], ok[chosen] = corner_matrices(rest, cur, triples[chosen], stencil=sub,
                                                rest_frames=corners.take(chosen))

    broken = np.zeros(F, dtype=bool)
    np.logical_or.at(broken, face, usable & ~ok)
    has_corner = np.bincount(face, usable.astype(np.float64), F) > 0
    valid = has_corner & ~broken
    use = usable & chosen & valid[face]

    params_t = np.zeros((triples.shape[0], 12))
    if np.any(use):
        params_t[use] = _params_or_nan(A[use], polar)
        finite = np.isfinite(params_t).all(axis=1)
        if not np.all(finite):
            np.logical_and.at(valid, face, finite)
            use &= valid[face]
        if w_ref is None:
            first = np.full(F, -1, dtype=np.intp)
            idx = np.flatnonzero(use)[::-1]
            first[face[idx]] = idx  # reversed assignment leaves the first used corner per face
            ref = params_t[first[face], 0:3]
        else:
            ref = np.broadcast_to(np.asarray(w_ref, dtype=np.float64), (F, 3))[face]
        piv = None
        if pivot is not None:
            piv = np.broadcast_to(np.asarray(pivot, dtype=np.float64), (F, 3))[face][use]
        params_t[use] = lift_params(params_t[use], ref[use], piv)

    contrib = np.where(use[:, None], weight[:, None] * params_t, 0.0)
    params = np.stack([np.bincount(face, contrib[:, k], F) for k in range(12)], axis=1)
    params[~valid] = 0.0

    return FaceMotions(params=params, valid=valid, messages=face_messages(has_corner, valid))


def face_messages(has_corner: np.ndarray, valid: np.ndarray) -> tuple[str, ...]:
    """`FaceMotions.messages` from has_corner (F,) (a usable rest corner) and valid (F,)."""
    messages: list[str] = []
    no_rest = np.flatnonzero(~has_corner)
    if no_rest.size:
        messages.append(
            f"{no_rest.size} cage face(s) are degenerate (zero area or non-finite) in the rest pose "
            "and are ignored: "
            f"{_list_indices(no_rest)}"
        )
    collapsed = np.flatnonzero(has_corner & ~valid)
    if collapsed.size:
        messages.append(
            f"{collapsed.size} cage face(s) collapsed (zero area or non-finite) in the current pose and "
            f"are ignored: {_list_indices(collapsed)}"
        )
    return tuple(messages)


@dataclass(frozen=True, eq=False)
class FaceTables:
    """The rest cage's per-corner data of `face_motions` (apex 'NEIGHBOURS') as flat contiguous
    arrays, for one compiled call over all faces (`affine_deformers.accel.cage_faces`): corners t are
    the rows of `CageTopology.corner_triples` (grouped by face, face f owning first[f] … first[f+1] −
    1); usable, weight (`RestCorners`); rest_ok = rest corner uncollapsed (sin > COLLAPSED_SIN) with
    a finite frame and centroid; centres and inverses the rest centroids and E_rest⁻¹; the stencil
    (`ApexStencil`: vertices, gamma, moments, spread, active); fan the fan triangles
    (`CageTopology.fan_triangles`, for the signed volume). Index arrays int64, flags bool, the rest
    float64."""

    rest: np.ndarray
    triples: np.ndarray
    first: np.ndarray
    usable: np.ndarray
    weight: np.ndarray
    rest_ok: np.ndarray
    centres: np.ndarray
    inverses: np.ndarray
    stencil_vertices: np.ndarray
    stencil_gamma: np.ndarray
    stencil_moments: np.ndarray
    stencil_spread: np.ndarray
    stencil_active: np.ndarray
    fan: np.ndarray


def face_tables(rest_points: np.ndarray, topology: CageTopology) -> FaceTables:
    """`FaceTables` of the rest cage, kept on the topology for the last rest cage it was asked for
    (compared by content: an update passes the same rest cage as a new array, and comparing its bytes
    costs far less than hashing them as `apex_stencils` does)."""
    rest = _check_points(rest_points, topology, "rest_points")
    key = rest.tobytes()
    found = topology._cache.get("face_tables")
    if found is not None and found[0] == key:
        return found[1]
    triples, face, _ = topology.corner_triples()
    corners = rest_corners(rest, topology)
    stencil = apex_stencils(rest, topology)
    count = np.bincount(face, minlength=topology.n_faces)
    first = np.zeros(topology.n_faces + 1, dtype=np.int64)
    np.cumsum(count, out=first[1:])
    rest_ok = (corners.sin > COLLAPSED_SIN) & np.isfinite(corners.frame).all(axis=(1, 2))
    rest_ok &= np.isfinite(corners.centre).all(axis=1)
    fan, _ = topology.fan_triangles()

    def c(a: np.ndarray, dtype: type) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=dtype)

    tables = FaceTables(
        c(rest, np.float64), c(triples, np.int64), first, c(corners.usable, np.bool_),
        c(corners.weight, np.float64), c(rest_ok, np.bool_), c(corners.centre, np.float64),
        c(corners.inverse, np.float64), c(stencil.vertices, np.int64), c(stencil.gamma, np.float64),
        c(stencil.moments, np.float64), c(stencil.spread, np.float64), c(stencil.active, np.bool_),
        c(fan, np.int64))
    topology._cache["face_tables"] = (key, tables)
    return tables


def _check_pose_pair(
    rest_points: np.ndarray, current_points: np.ndarray, topology: CageTopology, apex: str
) -> tuple[np.ndarray, np.ndarray]:
    """Checked float64 (rest, current) cage vertices of equal shape; ValueError on a bad apex mode."""
    rest = _check_points(rest_points, topology, "rest_points")
    cur = _check_points(current_points, topology, "current_points")
    if rest.shape != cur.shape:
        raise ValueError(
            f"rest and current cage differ in vertex count: {rest.shape[0]} vs {cur.shape[0]}"
        )
    if apex not in APEX_MODES:
        raise ValueError(f"apex must be one of {', '.join(APEX_MODES)}, got {apex!r}")
    return rest, cur


def affected_faces(
    rest_points: np.ndarray,
    current_points: np.ndarray,
    topology: CageTopology,
    *,
    apex: str = "NEIGHBOURS",
) -> np.ndarray:
    """(F,) bool: faces whose motion can differ from the identity — a corner vertex or (for the
    'NEIGHBOURS' apex) a stencil vertex of one of its corners is not bitwise at rest (NaN counts as
    moved). Every other face gets params exactly 0 from `face_motions` (unless w_ref lifts them to
    another turn of the identity), so a caller may skip it."""
    rest, cur = _check_pose_pair(rest_points, current_points, topology, apex)
    moved = np.any(cur != rest, axis=1)
    triples, face, _ = topology.corner_triples()
    corner = moved[triples].any(axis=1)
    if apex == "NEIGHBOURS":
        stencil = apex_stencils(rest, topology)
        corner |= (moved[stencil.vertices] & (stencil.gamma != 0.0)).any(axis=1)
    out = np.zeros(topology.n_faces, dtype=bool)
    np.logical_or.at(out, face, corner)
    return out
