"""Cage faces → rest/current tetrahedra → per-face motion parameters; cage weights; cage checks.

Topology comes as Blender's flat polygon arrays (`foreach_get` of loops.vertex_index,
polygons.loop_start, polygons.loop_total), wrapped in `CageTopology`.

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

Weights (`cage_weights`, the 'INVERSE_DISTANCE' option; MATH.md §10, §12): inverse distance to the
face polygon (exact point–triangle distance, minimum over the polygon's fan triangles), faded to zero
over a band above each face's plane (the half-space rule as a C¹ ramp), continuous top-K, rows
normalised to 1; computed in chunks of vertices. The default harmonic weights: core/cage_harmonic.py.
"""

from __future__ import annotations

import contextlib
import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from .aff3 import inverse3, params_from_matrices
from .deform import default_threads
from .unwrap import lift_params
from .weights import truncate

# A rest corner (consecutive triple) of an n-gon whose triangle area is below this fraction of the
# face's largest corner triangle is skipped: a straight or nearly straight corner (e.g. a T-junction
# vertex) has a needle tetrahedron that would turn any bending of the face into a huge stretch.
STRAIGHT_CORNER_RATIO = 1e-2

# A corner counts as collapsed when sin(corner angle) = |n|/(|e1||e2|) is below this.
COLLAPSED_SIN = 1e-10

# Points this close to a face plane (relative to the cage size) are not "outside" it, so a target
# vertex lying on the cage surface keeps the face it lies on.
HALF_SPACE_TOL = 1e-9

# Half-space ramp (cage_weights): a face's weight fades from full at its plane to 0 where the point
# is this far above the plane relative to its distance to the face (sin of the elevation angle).
HALF_SPACE_BAND = 0.5

# Distances are floored at this fraction of the cage size so a vertex on the cage gets a finite,
# dominant weight from the faces it touches instead of 1/0.
DISTANCE_FLOOR = 1e-6

# Elements per (corners × vertices) work array when building apex stencils.
CHUNK_ELEMENTS = 1 << 17

# Elements per work array of cage_weights ((chunks × faces) in its first pass, (chunk points ×
# candidate faces) in its second): bounds memory and keeps the arrays in cache.
BATCH_ELEMENTS = 1 << 17

# Slack on cage_weights' pruning bounds, relative to the cage size. It covers their rounding (dot
# products of coordinates of the order of the cage size, some expanded), never the geometry.
BOUND_SLACK = 1e-6

_MAX_LISTED = 10

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

_T = TypeVar("_T")
#: M (n, 3, 3) ↦ (R, Ŷ) of the polar split, or None (`aff3.params_from_matrices`' `polar`).
PolarSplit = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray] | None"]


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def _list_indices(indices: np.ndarray) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:_MAX_LISTED])
    return shown + (", ..." if len(indices) > _MAX_LISTED else "")


# --- topology -----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CageTopology:
    """Polygons as Blender stores them: face f uses loop_vertex_indices[loop_start[f] :
    loop_start[f] + loop_total[f]] in order (counter-clockwise seen from outside for outward faces).
    Build with `from_arrays` (validates) or `from_polygons`."""

    loop_vertex_indices: np.ndarray
    loop_start: np.ndarray
    loop_total: np.ndarray
    n_vertices: int
    _cache: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def from_arrays(
        cls,
        loop_vertex_indices: np.ndarray,
        loop_start: np.ndarray,
        loop_total: np.ndarray,
        n_vertices: int | None = None,
    ) -> CageTopology:
        """Validated topology; ValueError on malformed arrays (n_vertices bounds the indices)."""
        loops = np.asarray(loop_vertex_indices)
        start = np.asarray(loop_start)
        total = np.asarray(loop_total)
        for name, arr in (("loop_vertex_indices", loops), ("loop_start", start), ("loop_total", total)):
            if arr.ndim != 1 or not (arr.size == 0 or np.issubdtype(arr.dtype, np.integer)):
                raise ValueError(f"{name} must be a 1-D integer array, got {arr.dtype} {arr.shape}")
        if start.shape != total.shape:
            raise ValueError(f"loop_start and loop_total differ in length: {start.size} vs {total.size}")
        if start.size == 0:
            raise ValueError("the cage has no faces")
        if np.any(total < 3):
            bad = np.flatnonzero(total < 3)
            raise ValueError(f"cage faces with fewer than 3 corners: {_list_indices(bad)}")
        if np.any(start < 0) or np.any(start + total > loops.size):
            raise ValueError("loop_start/loop_total point outside loop_vertex_indices")
        if loops.size and loops.min() < 0:
            raise ValueError("negative vertex index in loop_vertex_indices")
        top = int(loops.max()) + 1 if loops.size else 0
        if n_vertices is None:
            n_vertices = top
        elif top > n_vertices:
            raise ValueError(
                f"loop_vertex_indices refers to vertex {top - 1} but the cage has {n_vertices}"
            )
        return cls(loops.astype(np.intp), start.astype(np.intp), total.astype(np.intp), int(n_vertices))

    @classmethod
    def from_polygons(
        cls, polygons: Sequence[Sequence[int]], n_vertices: int | None = None
    ) -> CageTopology:
        """Topology from a list of vertex-index lists (one per face)."""
        total = np.array([len(p) for p in polygons], dtype=np.intp)
        start = np.concatenate([[0], np.cumsum(total)[:-1]]).astype(np.intp)
        loops = np.array([i for p in polygons for i in p], dtype=np.intp)
        return cls.from_arrays(loops, start, total, n_vertices)

    @property
    def n_faces(self) -> int:
        return int(self.loop_total.size)

    def _cached(self, key: str, build: Callable[[], _T]) -> _T:
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    def _loop_columns(
        self, count: np.ndarray, columns: Sequence[Callable[[np.ndarray], np.ndarray]]
    ) -> tuple[np.ndarray, np.ndarray]:
        """For each face f, `count[f]` rows j = 0..count−1; column c holds the vertex at loop position
        columns[c](j) (mod n) of the face. Returns (vertex indices (R, len(columns)), face (R,))."""
        face = np.repeat(np.arange(self.n_faces), count)
        j = np.arange(face.size) - np.repeat(np.cumsum(count) - count, count)
        start, n = self.loop_start[face], self.loop_total[face]
        cols = [self.loop_vertex_indices[start + position(j) % n] for position in columns]
        return np.stack(cols, axis=1), face

    def corner_triples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(triples (T, 3) vertex indices, face (T,), weight (T,)): every consecutive triple
        (v_j, v_j+1, v_j+2) of each n-gon (one for a triangle), weight 1/count per face."""

        def build() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            count = np.where(self.loop_total == 3, 1, self.loop_total)
            triples, face = self._loop_columns(count, (lambda j: j, lambda j: j + 1, lambda j: j + 2))
            return triples, face, 1.0 / count[face]

        return self._cached("triples", build)

    def fan_triangles(self) -> tuple[np.ndarray, np.ndarray]:
        """(triangles (Tf, 3), face (Tf,)): the fan (v0, v_j+1, v_j+2) of each face, grouped by face."""

        def build() -> tuple[np.ndarray, np.ndarray]:
            columns = (lambda j: 0 * j, lambda j: j + 1, lambda j: j + 2)
            return self._loop_columns(self.loop_total - 2, columns)

        return self._cached("fan", build)

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertex (R,), face (R,)) of every face corner, face by face in loop order."""

        def build() -> tuple[np.ndarray, np.ndarray]:
            vertex, face = self._loop_columns(self.loop_total, (lambda j: j,))
            return vertex[:, 0], face

        return self._cached("corners", build)

    def face_of_loop(self) -> np.ndarray:
        """(L,) the face owning each entry of loop_vertex_indices, in storage order (−1 for a loop no
        face uses), so `bincount(face_of_loop(), x[loop_vertex_indices])` sums per face."""

        def build() -> np.ndarray:
            face = np.repeat(np.arange(self.n_faces), self.loop_total)
            j = np.arange(face.size) - np.repeat(np.cumsum(self.loop_total) - self.loop_total,
                                                 self.loop_total)
            owner = np.full(self.loop_vertex_indices.size, -1, dtype=np.intp)
            owner[self.loop_start[face] + j] = face
            return owner

        return self._cached("face_of_loop", build)

    def directed_edges(self) -> np.ndarray:
        """(E, 2) vertex pairs (v_j, v_j+1) of every face boundary, in loop order."""

        def build() -> np.ndarray:
            pairs, _ = self._loop_columns(self.loop_total, (lambda j: j, lambda j: j + 1))
            return pairs

        return self._cached("edges", build)


def _check_points(points: np.ndarray, topology: CageTopology, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (V, 3), got {points.shape}")
    if points.shape[0] < topology.n_vertices:
        raise ValueError(
            f"{name} has {points.shape[0]} vertices but the cage topology uses {topology.n_vertices}"
        )
    return points


# --- face geometry ------------------------------------------------------------------------------


def face_centroids(points: np.ndarray, topology: CageTopology) -> np.ndarray:
    """Mean of each face's corner positions, (F, 3)."""
    vertex, face = topology.corners()
    p = points[vertex]
    sums = np.stack([np.bincount(face, p[:, k], topology.n_faces) for k in range(3)], axis=1)
    return sums / topology.loop_total[:, None]


def face_normals(points: np.ndarray, topology: CageTopology) -> np.ndarray:
    """Newell normal of each face, (F, 3): Σ_j (v_j − c) × (v_j+1 − c) = 2·(vector area).

    For a triangle this is exactly (b − a) × (c − a); for a non-planar n-gon it is the normal of the
    best-fitting plane. Not normalised.
    """
    points = _check_points(points, topology, "points")
    c = face_centroids(points, topology)
    edges = topology.directed_edges()
    _, face = topology.corners()  # same row order as directed_edges
    a = points[edges[:, 0]] - c[face]
    b = points[edges[:, 1]] - c[face]
    cr = np.cross(a, b)
    return np.stack([np.bincount(face, cr[:, k], topology.n_faces) for k in range(3)], axis=1)


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


# --- distances and weights ----------------------------------------------------------------------


def _inverse_or_zero(x: np.ndarray) -> np.ndarray:
    ok = x > 0.0
    return np.where(ok, 1.0 / np.where(ok, x, 1.0), 0.0)


def _triangle_table(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> dict[str, np.ndarray]:
    """Per-triangle constants for `_distance_sq_block` (coordinates already relative to an origin)."""
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    abab = np.einsum("ij,ij->i", ab, ab)
    acac = np.einsum("ij,ij->i", ac, ac)
    abac = np.einsum("ij,ij->i", ab, ac)
    bc = ac - ab
    gram = abab * acac - abac * abac
    inv_gram = _inverse_or_zero(gram)
    return {
        "a": a,
        "ab": ab,
        "ac": ac,
        "n": n,
        "aa": np.einsum("ij,ij->i", a, a),
        "ab_a": np.einsum("ij,ij->i", ab, a),
        "ac_a": np.einsum("ij,ij->i", ac, a),
        "n_a": np.einsum("ij,ij->i", n, a),
        "abab": abab,
        "acac": acac,
        "abac": abac,
        "bcbc": np.einsum("ij,ij->i", bc, bc),
        "inv_abab": _inverse_or_zero(abab),
        "inv_acac": _inverse_or_zero(acac),
        "inv_bcbc": _inverse_or_zero(np.einsum("ij,ij->i", bc, bc)),
        # barycentric (v, w) of the projection: v = cv1·d1 + cv2·d2 + v0, w = cw1·d1 + cw2·d2;
        # v0 = −1 marks a degenerate triangle (no interior), so its projection never counts as inside.
        "cv1": acac * inv_gram,
        "cv2": -abac * inv_gram,
        "cw1": -abac * inv_gram,
        "cw2": abab * inv_gram,
        "v0": np.where(gram > 0.0, 0.0, -1.0),
        "inv_nn": _inverse_or_zero(np.einsum("ij,ij->i", n, n)),
    }


def _distance_sq_block(p: np.ndarray, tab: dict[str, np.ndarray]) -> np.ndarray:
    """Exact squared distances (C, T) from points p (C, 3) to triangles (a, a + ab, a + ac).

    If the projection of p onto the triangle's plane has barycentrics v, w ≥ 0, v + w ≤ 1 the
    distance is the plane distance, (n·ap)²/|n|²; otherwise the closest point lies on an edge and the
    distance is the smallest of the three point–segment distances |ap − t·e|², t = clamp(ap·e/|e|²).
    Every dot product of p comes from one matrix product with [a | ab | ac | n]; the rest is
    elementwise on (C, T) arrays. Degenerate triangles reduce to their edges (segments or points).
    """
    T = tab["a"].shape[0]
    G = p @ np.concatenate([tab["a"], tab["ab"], tab["ac"], tab["n"]], axis=0).T
    pa, d1, d2, pn = G[:, :T], G[:, T : 2 * T], G[:, 2 * T : 3 * T], G[:, 3 * T :]
    d1 = d1 - tab["ab_a"]  # ab·ap
    d2 = d2 - tab["ac_a"]  # ac·ap
    ap2 = np.einsum("ij,ij->i", p, p)[:, None] - 2.0 * pa + tab["aa"]

    def clamp01(x: np.ndarray) -> np.ndarray:  # np.clip's dispatch overhead is significant here
        np.maximum(x, 0.0, out=x)
        return np.minimum(x, 1.0, out=x)

    t = clamp01(d1 * tab["inv_abab"])
    edge = ap2 - t * (2.0 * d1 - t * tab["abab"])
    t = clamp01(d2 * tab["inv_acac"])
    np.minimum(edge, ap2 - t * (2.0 * d2 - t * tab["acac"]), out=edge)
    bc_bp = (d2 - tab["abac"]) - (d1 - tab["abab"])  # (ac − ab)·(p − b)
    bp2 = ap2 - 2.0 * d1 + tab["abab"]
    t = clamp01(bc_bp * tab["inv_bcbc"])
    np.minimum(edge, bp2 - t * (2.0 * bc_bp - t * tab["bcbc"]), out=edge)

    v = d1 * tab["cv1"] + d2 * tab["cv2"] + tab["v0"]
    w = d1 * tab["cw1"] + d2 * tab["cw2"]
    inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0)
    n_ap = pn - tab["n_a"]
    plane = n_ap * n_ap * tab["inv_nn"]
    return np.maximum(np.where(inside, plane, edge), 0.0)


def point_triangle_distance_sq(
    points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> np.ndarray:
    """Exact squared distance from each point (N, 3) to each triangle (a, b, c) (T, 3 each) -> (N, T).

    Dense; for tests and small inputs (cage_weights works in chunks). Coordinates are taken relative
    to the triangles' mean vertex, which keeps the expanded dot products well conditioned."""
    a, b, c = (np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in (a, b, c))
    origin = (a.mean(axis=0) + b.mean(axis=0) + c.mean(axis=0)) / 3.0 if a.size else np.zeros(3)
    table = _triangle_table(a - origin, b - origin, c - origin)
    return _distance_sq_block(np.asarray(points, dtype=np.float64).reshape(-1, 3) - origin, table)


# Columns of the stacked triangle table that `_pair_distance_sq` gathers per (point, triangle) pair.
_PAIR_COLUMNS = ("a", "ab", "ac", "n", "abab", "acac", "abac", "bcbc", "inv_abab", "inv_acac",
                 "inv_bcbc", "cv1", "cv2", "cw1", "cw2", "v0", "inv_nn")


def _stack_table(table: dict[str, np.ndarray]) -> np.ndarray:
    """(25, T): the `_PAIR_COLUMNS` of a triangle table as rows, so one fancy index gathers a pair's
    constants as contiguous rows."""
    return np.concatenate([np.atleast_2d(table[key].T) for key in _PAIR_COLUMNS], axis=0)


def _pair_distance_sq(p: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Exact squared distance (P,) from each point p (P, 3) to its triangle, whose `_stack_table`
    column is `rows` (25, P): the regions of `_distance_sq_block`, with every dot product taken on
    ap = p − a directly (no expanded |p|² − 2 p·a + |a|², which cancels near the triangle)."""
    ap = [p[:, k] - rows[k] for k in range(3)]
    d1 = ap[0] * rows[3] + ap[1] * rows[4] + ap[2] * rows[5]  # ab·ap
    d2 = ap[0] * rows[6] + ap[1] * rows[7] + ap[2] * rows[8]  # ac·ap
    n_ap = ap[0] * rows[9] + ap[1] * rows[10] + ap[2] * rows[11]
    ap2 = ap[0] * ap[0] + ap[1] * ap[1] + ap[2] * ap[2]
    abab, acac, abac, bcbc = rows[12], rows[13], rows[14], rows[15]

    def clamp01(x: np.ndarray) -> np.ndarray:
        np.maximum(x, 0.0, out=x)
        return np.minimum(x, 1.0, out=x)

    t = clamp01(d1 * rows[16])
    edge = ap2 - t * (2.0 * d1 - t * abab)
    t = clamp01(d2 * rows[17])
    np.minimum(edge, ap2 - t * (2.0 * d2 - t * acac), out=edge)
    bc_bp = (d2 - abac) - (d1 - abab)  # (ac − ab)·(p − b)
    t = clamp01(bc_bp * rows[18])
    np.minimum(edge, (ap2 - 2.0 * d1 + abab) - t * (2.0 * bc_bp - t * bcbc), out=edge)
    v = d1 * rows[19] + d2 * rows[20] + rows[23]
    w = d1 * rows[21] + d2 * rows[22]
    inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0)
    return np.maximum(np.where(inside, n_ap * n_ap * rows[24], edge), 0.0)


@dataclass(frozen=True)
class _CageFields:
    """What cage_weights needs of the rest cage, relative to `origin` (the mean vertex).

    Two cheap bounds on the distance from a point p to face f's polygon prune the exact distances:

        dist(p, box_f) ≤ d_f(p) ≤ |p − s_f| + δ_f,

    box_f the face's oriented bounding box (rows of `frame`: û along the first edge, v̂, n̂ the unit
    Newell normal; `lo`, `hi` the extent of frame·v over its vertices — the polygon, made of convex
    combinations of them, lies inside), s_f the vertex mean and δ_f its exact distance to the
    polygon (0 for a planar convex face)."""

    origin: np.ndarray
    size: float
    table: np.ndarray  # (25, Tf) fan triangles (`_stack_table`), grouped by face
    fan_start: np.ndarray  # (F,) first fan triangle of each face
    fan_count: np.ndarray  # (F,)
    plane_offsets: np.ndarray  # (F,) n̂·s_f; +inf for a zero-area face (never "outside")
    centers: np.ndarray  # (F, 3) s_f
    reach: np.ndarray  # (F,) δ_f
    frame: np.ndarray  # (F, 3, 3) rows û, v̂, n̂ (n̂ = unit normal; any frame for a zero-area face)
    lo: np.ndarray  # (F, 3)
    hi: np.ndarray  # (F, 3)

    @classmethod
    def build(cls, cage: np.ndarray, topology: CageTopology) -> _CageFields:
        origin = cage.mean(axis=0)
        local = cage - origin
        size = float(np.ptp(cage, axis=0).max()) or 1.0
        fan, fan_face = topology.fan_triangles()
        table = _stack_table(_triangle_table(*(local[fan[:, k]] for k in range(3))))
        fan_count = topology.loop_total - 2
        fan_start = np.cumsum(fan_count) - fan_count
        normals = face_normals(local, topology)
        length = _norm(normals)
        flat = ~(length > 0.0)
        unit = normals / np.where(flat, 1.0, length)[:, None]
        centers = face_centroids(local, topology)
        offsets = np.where(flat, np.inf, np.einsum("ij,ij->i", unit, centers))
        frame = _face_frames(local, topology, np.where(flat[:, None], [0.0, 0.0, 1.0], unit))
        vertex, face = topology.corners()
        coords = np.einsum("rki,ri->rk", frame[face], local[vertex])
        lo = np.full((topology.n_faces, 3), np.inf)
        hi = np.full((topology.n_faces, 3), -np.inf)
        np.minimum.at(lo, face, coords)
        np.maximum.at(hi, face, coords)
        own = _pair_distance_sq(centers[fan_face], table)
        reach = np.sqrt(np.minimum.reduceat(own, fan_start))
        return cls(origin, size, table, fan_start, fan_count, offsets, centers, reach, frame, lo, hi)


def _face_frames(local: np.ndarray, topology: CageTopology, normal: np.ndarray) -> np.ndarray:
    """(F, 3, 3) orthonormal rows (û, v̂, n̂): û is the face's first edge made orthogonal to the unit
    vector n̂ (a box aligned with it is tight on rectangles and trapezoids), or any unit vector
    orthogonal to n̂ when that edge is (nearly) along it."""
    loops, start = topology.loop_vertex_indices, topology.loop_start
    edge = local[loops[start + 1]] - local[loops[start]]
    u = edge - np.einsum("ij,ij->i", edge, normal)[:, None] * normal
    other = np.cross(normal, np.eye(3)[np.argmin(np.abs(normal), axis=1)])
    bad = ~(_norm(u) > 1e-6 * _norm(edge))
    u = np.where(bad[:, None], other, u)
    u /= _norm(u)[:, None]
    return np.stack([u, np.cross(normal, u), normal], axis=1)


def _morton_order(p: np.ndarray) -> np.ndarray:
    """Permutation sorting points along a Z-order curve (10 bits per axis), so consecutive chunks are
    spatially compact and the chunk bounds can prune."""
    lo = p.min(axis=0)
    span = float(np.ptp(p, axis=0).max()) or 1.0
    cells = np.clip(((p - lo) / span * 1023.0).astype(np.int64), 0, 1023)

    def spread(x: np.ndarray) -> np.ndarray:
        x = (x | (x << 16)) & 0x030000FF
        x = (x | (x << 8)) & 0x0300F00F
        x = (x | (x << 4)) & 0x030C30C3
        return (x | (x << 2)) & 0x09249249

    code = spread(cells[:, 0]) | (spread(cells[:, 1]) << 1) | (spread(cells[:, 2]) << 2)
    return np.argsort(code, kind="stable")


def polygon_distance_sq(points: np.ndarray, cage_points: np.ndarray, topology: CageTopology) -> np.ndarray:
    """Squared distance (N, F) from points to each face polygon: minimum over its fan triangles. Dense."""
    cage = _check_points(cage_points, topology, "cage_points")
    origin = cage.mean(axis=0)
    local = cage - origin
    fan, _ = topology.fan_triangles()
    table = _triangle_table(*(local[fan[:, k]] for k in range(3)))
    starts = np.cumsum(topology.loop_total - 2) - (topology.loop_total - 2)
    d2 = _distance_sq_block(np.asarray(points, dtype=np.float64) - origin, table)
    return np.minimum.reduceat(d2, starts, axis=1)


def nearest_faces(
    points: np.ndarray, cage_points: np.ndarray, topology: CageTopology, width: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every face whose polygon is within `width` of each point's nearest face:
    (point (P,), face (P,), distance (P,)), grouped by point, faces increasing within a point, so
    d_f(p) ≤ min_g d_g(p) + width for every pair and every such face is listed.

    Exact distances are taken only for faces that bounding spheres cannot rule out: with s_f the
    vertex mean, ρ_f the largest |p_j − s_f| over the face's vertices and δ_f = d_f(s_f),
    |p − s_f| − ρ_f ≤ d_f(p) ≤ |p − s_f| + δ_f, so with U(p) = min_f (|p − s_f| + δ_f) a face
    whose lower bound exceeds U(p) + width is not within width of the nearest. Memory is
    O(BATCH_ELEMENTS) per chunk of points.
    """
    cage = _check_points(cage_points, topology, "cage_points")
    fields = _CageFields.build(cage, topology)
    local = np.asarray(points, dtype=np.float64).reshape(-1, 3) - fields.origin
    vertex, owner = topology.corners()
    radius = np.zeros(topology.n_faces)
    np.maximum.at(radius, owner, _norm(fields.centers[owner] - (cage[vertex] - fields.origin)))
    F = topology.n_faces
    slack = BOUND_SLACK * fields.size
    centre_sq = np.einsum("fi,fi->f", fields.centers, fields.centers)
    out_p, out_f, out_d = [], [], []
    step = max(1, BATCH_ELEMENTS // F)
    for lo in range(0, local.shape[0], step):
        p = local[lo : lo + step]
        dist_sq = np.einsum("ci,ci->c", p, p)[:, None] - 2.0 * (p @ fields.centers.T) + centre_sq
        centre = np.sqrt(np.maximum(dist_sq, 0.0))
        bound = (centre + fields.reach).min(axis=1, keepdims=True) + (width + slack)
        c, f = np.nonzero(centre - radius <= bound)
        count = fields.fan_count[f]
        first = np.cumsum(count) - count
        pair_of_tri = np.repeat(np.arange(f.size), count)
        tri = fields.fan_start[f][pair_of_tri] + (np.arange(pair_of_tri.size) - first[pair_of_tri])
        d2 = _pair_distance_sq(p[c[pair_of_tri]], fields.table[:, tri])
        d = np.sqrt(np.minimum.reduceat(d2, first)) if d2.size else d2
        nearest = np.full(p.shape[0], np.inf)
        np.minimum.at(nearest, c, d)
        close = d <= nearest[c] + width
        out_p.append(c[close] + lo)
        out_f.append(f[close])
        out_d.append(d[close])
    if not out_p:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(0)
    return np.concatenate(out_p), np.concatenate(out_f), np.concatenate(out_d)


def _dot3(x: Sequence[np.ndarray], y: Sequence[np.ndarray]) -> np.ndarray:
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _chunk_candidates(
    fields: _CageFields, q: np.ndarray, rho: np.ndarray, k: int, half_space: bool
) -> np.ndarray:
    """(C, F) bool: faces that can be among the k nearest allowed faces of some point within rho (C,)
    of q (C, 3), one row per chunk of points.

    Every point of a chunk is within dist(q, box_f) − ρ of face f at least and |q − s_f| + δ_f + ρ
    at most. Faces whose inner half-space holds the chunk's whole sphere are allowed for all its
    points, so the k-th smallest of their upper bounds, τ, bounds every point's k-th nearest allowed
    distance; faces with a lower bound above τ are dropped. A chunk with fewer than k such faces keeps
    all faces."""
    F = fields.centers.shape[0]
    coords = (q @ fields.frame.reshape(-1, 3).T).reshape(-1, F, 3)
    gap = np.maximum(np.maximum(fields.lo - coords, coords - fields.hi), 0.0)
    lower = np.sqrt(np.einsum("cfk,cfk->cf", gap, gap)) - rho[:, None]
    centre_sq = (np.einsum("ci,ci->c", q, q)[:, None] - 2.0 * (q @ fields.centers.T)
                 + np.einsum("fi,fi->f", fields.centers, fields.centers))
    upper = np.sqrt(np.maximum(centre_sq, 0.0)) + (fields.reach + rho[:, None])
    if half_space:
        safe = coords[:, :, 2] - fields.plane_offsets + rho[:, None] <= HALF_SPACE_TOL * fields.size
        upper = np.where(safe, upper, np.inf)
    tau = np.partition(upper, k - 1, axis=1)[:, k - 1]
    return lower <= tau[:, None] + BOUND_SLACK * fields.size


def half_space_ramp(elevation: np.ndarray) -> np.ndarray:
    """r(s) = 1 for s ≤ 0, 1 − 3t² + 2t³ (t = s/HALF_SPACE_BAND) up to s = HALF_SPACE_BAND, 0 above:
    C¹ and decreasing; s = (height above the face plane) / (distance to the face) ∈ [−1, 1]."""
    t = np.clip(np.asarray(elevation, dtype=np.float64) / HALF_SPACE_BAND, 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def _batch_weights(
    local: np.ndarray,
    rows: np.ndarray,
    slots: np.ndarray,
    fields: _CageFields,
    k: int,
    exponent: float,
    half_space: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weights of a batch of chunks: rows (B, C) point indices (−1 = padding), slots (B, M) candidate
    faces in increasing order (−1 = padding). Returns (points (R,), face indices (R, k), values (R, k)).

    The k + 1 largest weights are needed (continuous truncation subtracts the (k+1)-th). Per point,
    the (k+1)-th smallest upper bound over its candidates with full weight (ramp 1: in the face's inner
    half-space), τ_p, bounds its (k+1)-th nearest such distance; no weight is above d^(−p) (the ramp is
    ≤ 1), so only candidates with dist(p, box_f) ≤ τ_p get exact distances. Kept pairs are listed point
    by point in increasing face order, so ties break by face index as over all faces."""
    size = fields.size
    real_slot = slots >= 0
    f = np.where(real_slot, slots, 0)
    p = local[np.where(rows >= 0, rows, rows.max())]  # (B, C, 3)
    pc = [p[:, :, i, None] for i in range(3)]  # (B, C, 1) each
    frame = fields.frame[f]  # (B, M, 3, 3)
    box_sq = None
    coords = []
    for axis in range(3):
        c = _dot3(pc, [frame[:, None, :, axis, i] for i in range(3)])  # (B, C, M)
        lo, hi = fields.lo[f, axis][:, None, :], fields.hi[f, axis][:, None, :]
        gap = np.maximum(np.maximum(lo - c, c - hi), 0.0)
        box_sq = gap * gap if box_sq is None else box_sq + gap * gap
        coords.append(c)
    centre = fields.centers[f]
    diff = [pc[i] - centre[:, None, :, i] for i in range(3)]
    upper = np.sqrt(_dot3(diff, diff)) + fields.reach[f][:, None, :]
    eligible = np.broadcast_to(real_slot[:, None, :], upper.shape)
    height = coords[2] - fields.plane_offsets[f][:, None, :] - HALF_SPACE_TOL * size
    full = eligible
    plain = np.zeros(upper.shape[:2], dtype=bool)
    if half_space:
        full = (height <= 0.0) & eligible
        # A vertex outside every face's half-space (only possible outside an open or broken cage,
        # where every face is a candidate) keeps plain inverse-distance weights over all faces.
        plain = ~full.any(axis=2)
        full = full | (eligible & plain[:, :, None])
    measured = min(k + 1, int(real_slot.sum(axis=1).max(initial=0)) or 1)
    tau = np.partition(np.where(full, upper, np.inf), measured - 1, axis=2)[:, :, measured - 1]
    floor = DISTANCE_FLOOR * size
    tau = np.maximum(tau, floor) + BOUND_SLACK * size
    keep = eligible & (box_sq <= (tau * tau)[:, :, None]) & (rows >= 0)[:, :, None]

    b, c, m = np.nonzero(keep)
    pair_point = rows[b, c]
    pair_face = slots[b, m]
    # exact distance to each kept polygon: minimum over its fan triangles
    count = fields.fan_count[pair_face]
    if np.all(count == 1):
        d2 = _pair_distance_sq(local[pair_point], fields.table[:, fields.fan_start[pair_face]])
    else:
        first = np.cumsum(count) - count
        pair_of_tri = np.repeat(np.arange(pair_face.size), count)
        tri = fields.fan_start[pair_face][pair_of_tri] + (np.arange(pair_of_tri.size) - first[pair_of_tri])
        d2 = _pair_distance_sq(local[pair_point[pair_of_tri]], fields.table[:, tri])
        d2 = np.minimum.reduceat(d2, first) if d2.size else d2
    d2 = np.maximum(d2, floor * floor)
    w = 1.0 / d2 if exponent == 2.0 else d2 ** (-0.5 * exponent)
    if half_space:
        ramped = ~plain[b, c]
        w[ramped] *= half_space_ramp(np.maximum(height[b, c, m][ramped], 0.0) / np.sqrt(d2[ramped]))

    # one row per point (kept pairs are grouped by point), padded with zero weights
    per_row = keep.sum(axis=2).ravel()
    row_start = np.cumsum(per_row) - per_row
    row_of_pair = b * rows.shape[1] + c
    column = np.arange(pair_face.size) - row_start[row_of_pair]
    width = max(int(per_row.max()) if per_row.size else 0, k + 1)
    W = np.zeros((per_row.size, width))
    faces = np.zeros((per_row.size, width), dtype=np.int32)
    W[row_of_pair, column] = w
    faces[row_of_pair, column] = pair_face
    # D = max(S, c Σ kept): the cage measures only the faces that can matter, so the divisor's floor
    # is relative to the kept faces' weight (c = weights.LOCAL_FLOOR); the pooled rest goes to index F
    cols, vals, pooled = truncate(W, k, with_pooled=True)
    idx = np.take_along_axis(faces, cols, axis=1)
    idx = np.where(vals > 0.0, idx, idx[:, :1])  # zero-weight slots point at the row's best face
    real = rows.ravel() >= 0
    idx = np.concatenate([idx, np.full((len(idx), 1), fields.centers.shape[0], dtype=idx.dtype)], axis=1)
    vals = np.concatenate([vals, pooled[:, None]], axis=1)
    return rows.ravel()[real], idx[real], vals[real]


def _group_weights(
    local: np.ndarray, rows: np.ndarray, fields: _CageFields, k: int, exponent: float, half_space: bool
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(points, indices, values) of the chunks rows (B, C) (−1 = padding), batch by batch: chunks
    with similar candidate counts are measured together, so little of a batch is padding."""
    C = rows.shape[1]
    measured = min(k + 1, fields.centers.shape[0])  # continuous truncation needs the (k+1)-th weight
    candidates = _chunk_candidates(fields, *_chunk_spheres(local, rows), measured, half_space)
    count = candidates.sum(axis=1)
    order = np.argsort(count, kind="stable")
    start = 0
    while start < order.size:
        stop, total = start + 1, int(count[order[start]])
        while stop < order.size:
            # padded size of the batch if it took one more chunk; at most a quarter is padding
            width = int(count[order[stop]])
            padded = (stop - start + 1) * width
            if padded * C > BATCH_ELEMENTS or padded > 1.25 * (total + width):
                break
            total += width
            stop += 1
        batch = order[start:stop]
        width = max(int(count[batch[-1]]), measured)  # ≤ count unless rounding defeats the slack
        r, f = np.nonzero(candidates[batch])
        slots = np.full((batch.size, width), -1, dtype=np.intp)
        slots[r, np.arange(r.size) - (np.cumsum(count[batch]) - count[batch])[r]] = f
        yield _batch_weights(local, rows[batch], slots, fields, k, exponent, half_space)
        start = stop


def _chunk_spheres(local: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centres (B, 3), radii (B,)) of bounding spheres of the chunks' points (rows (B, C), −1 padding)."""
    p = local[np.where(rows >= 0, rows, rows[:, :1])]  # padding repeats the chunk's first point
    q = 0.5 * (p.min(axis=1) + p.max(axis=1))
    rho = np.sqrt(np.einsum("bci,bci->bc", p - q[:, None], p - q[:, None]).max(axis=1))
    return q, rho


def cage_weights(
    points: np.ndarray,
    cage_points: np.ndarray,
    topology: CageTopology,
    *,
    exponent: float = 2.0,
    half_space: bool = True,
    k: int = 8,
    chunk_size: int = 64,
) -> tuple[np.ndarray, np.ndarray]:
    """Sparse cage weights: (indices (N, K or K + 1) int32, values float64), K = min(k, F), rows sum to 1
    (index F in column K, when present: the pooled control, the mean of all faces' parameters).

    w_f(v) = d_f(v)^(−exponent), d_f the exact distance from v to face f's polygon (minimum over its
    fan triangles), floored at DISTANCE_FLOOR × cage size. With half_space (MATH.md §10, made
    continuous) the weight fades to 0 in the outer half-space of f: w_f is multiplied by
    `half_space_ramp`(z_f/d_f), z_f = N̂_f·(v − c_f) − HALF_SPACE_TOL × cage size (N_f the Newell
    normal, c_f the face centroid), so it is full up to f's plane and 0 from HALF_SPACE_BAND above
    it (a hard cut would jump where the plane of a face of a non-convex cage crosses its inside).
    A vertex cut off from every face (outside an open or broken cage) falls back to plain inverse
    distance, so no row is zero. Truncation to the K largest is continuous with a bounded slope
    (weights.truncate, MATH.md §12: the (K+1)-th weight, measured exactly, is subtracted and the
    rest divided by D = max(S, c Σ kept), c = weights.LOCAL_FLOOR; zero-weight slots repeat the
    row's first index), so no weight jumps or swings where faces swap ranks or tie; what the kept
    faces leave of 1 (only near such ties) goes to the pooled control, so any motion shared by all
    faces stays exact.

    Only distances that can matter are measured exactly: vertices are grouped in spatially sorted
    chunks of chunk_size, each chunk keeps the faces its bounding sphere can reach
    (`_chunk_candidates`), and each vertex the candidates its own bounds cannot rule out
    (`_batch_weights`). Memory is O(N·K + BATCH_ELEMENTS). The result does not depend on chunk_size,
    except which of several faces exactly tied at the K-th weight is kept.
    """
    cage = _check_points(cage_points, topology, "cage_points")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(cage))):
        raise ValueError("points or cage contain non-finite coordinates")
    if not exponent > 0.0:
        raise ValueError(f"exponent must be positive, got {exponent}")
    if k < 1 or chunk_size < 1:
        raise ValueError(f"k and chunk_size must be at least 1, got {k} and {chunk_size}")
    K = min(int(k), topology.n_faces)
    N = points.shape[0]
    indices = np.zeros((N, K + 1), dtype=np.int32)  # column K: the pooled control (index F)
    values = np.zeros((N, K + 1), dtype=np.float64)
    if N == 0:
        return indices[:, :K].copy(), values[:, :K].copy()
    fields = _CageFields.build(cage, topology)
    local = points - fields.origin
    C = int(chunk_size)
    n_chunks = -(-N // C)
    chunk_rows = np.full(n_chunks * C, -1, dtype=np.intp)
    chunk_rows[:N] = _morton_order(local)
    chunk_rows = chunk_rows.reshape(n_chunks, C)
    group = max(1, 4 * BATCH_ELEMENTS // topology.n_faces)
    groups = [chunk_rows[lo : lo + group] for lo in range(0, n_chunks, group)]

    def run(rows: np.ndarray) -> None:
        for pts, idx, val in _group_weights(local, rows, fields, K, exponent, half_space):
            indices[pts], values[pts] = idx, val  # groups own disjoint rows

    threads = min(default_threads(), len(groups))
    if threads == 1:
        for rows in groups:
            run(rows)
    else:
        # The work is large numpy calls, which release the GIL.
        with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="affine_cage_weights") as pool:
            for future in [pool.submit(run, rows) for rows in groups]:
                future.result()
    if not np.any(values[:, K]):  # nothing pooled: the faces' weights sum to 1 on every row
        return indices[:, :K].copy(), values[:, :K].copy()
    return indices, values


# --- validation ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class CageReport:
    """Result of `check_cage`. problems is empty when the cage can be bound."""

    n_vertices: int
    n_faces: int
    boundary_edges: int
    nonmanifold_edges: int
    misoriented_edges: int
    degenerate_faces: np.ndarray
    signed_volume: float
    problems: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.problems


def signed_volume(points: np.ndarray, topology: CageTopology) -> float:
    """Σ over fan triangles of a·(b × c)/6 (positive for a closed cage with outward normals)."""
    points = _check_points(points, topology, "points")
    fan, _ = topology.fan_triangles()
    origin = points.mean(axis=0)
    a, b, c = (points[fan[:, k]] - origin for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def check_cage(points: np.ndarray, topology: CageTopology) -> CageReport:
    """Structured check that the cage is closed, manifold, consistently oriented, outward and has
    no zero-area faces. Never raises for geometric problems (only for malformed arrays)."""
    points = _check_points(points, topology, "cage points")
    problems: list[str] = []
    if not np.all(np.isfinite(points)):
        problems.append("cage has non-finite vertex coordinates")

    edges = topology.directed_edges()
    self_loops = int(np.count_nonzero(edges[:, 0] == edges[:, 1]))
    lo, hi = np.minimum(edges[:, 0], edges[:, 1]), np.maximum(edges[:, 0], edges[:, 1])
    key = lo.astype(np.int64) * max(topology.n_vertices, 1) + hi
    forward = edges[:, 0] < edges[:, 1]
    uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    n_forward = np.bincount(inverse, forward.astype(np.int64), uniq.size)
    boundary = int(np.count_nonzero(counts == 1))
    nonmanifold = int(np.count_nonzero(counts > 2))
    misoriented = int(np.count_nonzero((counts == 2) & (n_forward != 1)))
    if self_loops:
        problems.append(f"cage has {self_loops} face corner(s) repeating a vertex (zero-length edges)")
    if boundary:
        problems.append(f"cage is open: {boundary} boundary edges (every edge must be shared by two faces)")
    if nonmanifold:
        problems.append(f"cage is non-manifold: {nonmanifold} edges are shared by more than two faces")
    if misoriented:
        problems.append(
            f"cage normals are inconsistent: {misoriented} edges join faces of opposite orientation "
            "(recalculate normals outside)"
        )

    finite = bool(np.all(np.isfinite(points)))
    normals = face_normals(points, topology) if finite else np.zeros((topology.n_faces, 3))
    extent = float(np.ptp(points, axis=0).max()) if points.size else 0.0
    degenerate = np.flatnonzero(~(_norm(normals) > 1e-12 * extent * extent))
    if degenerate.size:
        problems.append(f"cage has {degenerate.size} zero-area face(s): {_list_indices(degenerate)}")

    volume = signed_volume(points, topology) if np.all(np.isfinite(points)) else float("nan")
    if not (boundary or nonmanifold or misoriented) and np.isfinite(volume):
        if volume < 0.0:
            problems.append("cage is inside-out (normals point inward): flip normals")
        elif not volume > (1e-12 * extent) ** 3:
            problems.append("cage encloses no volume (flat or collapsed)")
    return CageReport(
        n_vertices=topology.n_vertices,
        n_faces=topology.n_faces,
        boundary_edges=boundary,
        nonmanifold_edges=nonmanifold,
        misoriented_edges=misoriented,
        degenerate_faces=degenerate,
        signed_volume=volume,
        problems=tuple(problems),
    )


def validate_cage(points: np.ndarray, topology: CageTopology) -> CageReport:
    """`check_cage`, raising ValueError with every problem found (one per line) unless the cage is a
    closed, consistently and outward oriented surface without zero-area faces."""
    report = check_cage(points, topology)
    if not report.ok:
        raise ValueError("; ".join(report.problems))
    return report
