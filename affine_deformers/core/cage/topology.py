"""Cage topology and face geometry: `CageTopology` (with the index tables the other modules derive
from it, cached on the topology), face centroids and Newell normals, and the shared argument check.

Topology comes as Blender's flat polygon arrays (`foreach_get` of loops.vertex_index,
polygons.loop_start, polygons.loop_total), wrapped in `CageTopology`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

_MAX_LISTED = 10

_T = TypeVar("_T")


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
        # in int64: a damaged int32 start near its maximum must not wrap around past the check
        if np.any(start < 0) or np.any(start.astype(np.int64) + total > loops.size):
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
