"""Cage validation: `check_cage` reports whether a cage can be bound — closed, manifold, consistently
oriented, outward and without zero-area faces — without raising for geometric problems;
`validate_cage` raises with every problem found; `signed_volume` (positive for a closed cage with
outward normals).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .topology import CageTopology, _check_points, _list_indices, _norm, face_normals


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
