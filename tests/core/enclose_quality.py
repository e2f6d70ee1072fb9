"""A cage edit's quality, at the core level (no Blender): bind the default harmonic cage weights to a
cage, edit the cage, deform the mesh, measure the result. Used by tests/core/test_cage_enclose.py
and bench/cage_enclose.py to compare a made cage (core/cage/enclose.py) with a box cage of about
the same face count around the same mesh.

Edits, S the mesh's size (largest bounding-box extent), c its bounding-box centre:
* 'AFFINE' — every cage vertex through one shear + stretch + shift (tests/blender/test_field_quality
  's SHEAR and SHIFT): the mesh must follow exactly; the error is max |x' − (M x + t)| ÷ S;
* 'TWIST' — the cage vertices above c turned 45° about the vertical axis through c (the edit of
  tests/blender/cage_field.py). Measured: roughness p99 (the 99th percentile over vertices of
  |d_v − mean of d over v's edge neighbours| ÷ max |d|), and over the vertices in the top quarter
  of the mesh, which the cage turns rigidly, the RMS residual of the best rigid fit ÷ S.
"""

from __future__ import annotations

import numpy as np

from affine_deformers.core.cage import CageTopology, face_motions
from affine_deformers.core.cage import harmonic as ch
from affine_deformers.core.deform import deform_points_params

SHEAR = np.array([[1.1, 0.45, 0.0], [0.0, 0.9, 0.3], [0.25, 0.0, 1.2]])
SHIFT = np.array([0.3, -0.2, 0.4])
TWIST_ANGLE = np.radians(45.0)


def box_cage(lo: np.ndarray, hi: np.ndarray, cuts: int) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, quads (F, 4)) of the closed box [lo, hi] with cuts × cuts quads per side, outward."""
    n = cuts
    g = np.stack(np.meshgrid(*(np.arange(n + 1),) * 3, indexing="ij"), -1).reshape(-1, 3)
    on_surface = np.any((g == 0) | (g == n), axis=1)
    index = np.full(len(g), -1)
    index[on_surface] = np.arange(on_surface.sum())
    quads = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, n):
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            corners = []
            for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                c = np.zeros((n * n, 3), int)
                c[:, axis], c[:, u], c[:, v] = side, (i + di).ravel(), (j + dj).ravel()
                corners.append(index[(c[:, 0] * (n + 1) + c[:, 1]) * (n + 1) + c[:, 2]])
            q = np.stack(corners, axis=1)
            quads.append(q if side == n else q[:, ::-1])
    vertices = lo + g[on_surface] / n * (hi - lo)
    return vertices, np.concatenate(quads)


def _deformed(points: np.ndarray, hw: ch.HarmonicWeights, w: np.ndarray, cage: np.ndarray,
              moved: np.ndarray, topo: CageTopology) -> np.ndarray:
    motion = face_motions(cage, moved, topo)
    params = ch.node_params(hw.node_points, w, motion.params)
    return deform_points_params(points, params, hw.indices, hw.values)


def edit_quality(points: np.ndarray, triangles: np.ndarray, cage: np.ndarray, quads: np.ndarray
                 ) -> dict[str, float]:
    """The module docstring's numbers for this cage around this mesh."""
    topo = CageTopology.from_arrays(quads.reshape(-1), 4 * np.arange(len(quads)), np.full(len(quads), 4))
    hw = ch.harmonic_weights(points, cage, topo)
    w = hw.node_weights.astype(np.float64)
    w /= w.sum(axis=1, keepdims=True)
    lo, hi = points.min(axis=0), points.max(axis=0)
    size, centre = float((hi - lo).max()), 0.5 * (lo + hi)
    got = _deformed(points, hw, w, cage, cage @ SHEAR.T + SHIFT, topo)
    affine = float(np.abs(got - (points @ SHEAR.T + SHIFT)).max()) / size
    c, s = np.cos(TWIST_ANGLE), np.sin(TWIST_ANGLE)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = cage.copy()
    top = cage[:, 2] > centre[2]
    moved[top] = (cage[top] - centre) @ turn.T + centre
    d = _deformed(points, hw, w, cage, moved, topo) - points
    sides = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = np.unique(np.sort(sides, axis=1), axis=0)
    degree = np.bincount(edges.ravel(), minlength=len(points))
    mean = np.stack([(np.bincount(edges[:, 0], d[edges[:, 1], k], len(points))
                      + np.bincount(edges[:, 1], d[edges[:, 0], k], len(points))) for k in range(3)], 1)
    used = degree > 0
    lap = np.linalg.norm(d[used] - mean[used] / degree[used, None], axis=1)
    rough = float(np.percentile(lap, 99) / np.linalg.norm(d, axis=1).max())
    part = points[:, 2] > hi[2] - 0.25 * (hi[2] - lo[2])
    a, b = points[part], points[part] + d[part]
    ac, bc = a - a.mean(axis=0), b - b.mean(axis=0)
    u, _, vt = np.linalg.svd(ac.T @ bc)
    r = (u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt).T
    residual = float(np.sqrt(((ac @ r.T - bc) ** 2).sum(axis=1).mean())) / size
    return {"affine": affine, "roughness": rough, "residual": residual}
