"""Meshes, rigs and quality measures for the shape-preserving pass (tests/core/test_arap*.py and
bench/arap_core.py): a closed box bar of right triangles, probe rigs that bend or twist it, and the
measures of the issue (volume ratio, edge-length distortion, roughness)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from affine_deformers.core import aff3
from affine_deformers.core.weights import probe_weights


def box_bar(n_side: int, length: float = 4.0, width: float = 1.0,
            n_length: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A closed box [0, length] × [−width/2, width/2]² (outward triangles), its surface a grid of
    n_length × n_side squares along and n_side × n_side across (n_length defaults to keep the squares
    square), each split in two. About 4 n_side n_length + 2 n_side² vertices."""
    nc = n_side
    nx = n_length or max(1, round(n_side * length / width))
    shape = (nx + 1, nc + 1, nc + 1)
    i, j, k = np.meshgrid(np.arange(nx + 1), np.arange(nc + 1), np.arange(nc + 1), indexing="ij")
    lattice = np.stack([i * length / nx, j * width / nc - width / 2, k * width / nc - width / 2], -1)
    lid = np.arange(np.prod(shape)).reshape(shape)

    def quads(a, b, c, d):
        return np.stack([a.ravel(), b.ravel(), c.ravel(), d.ravel()], axis=1)

    faces = []
    for side, flip in ((0, False), (nx, True)):  # x = 0 (normal −x) and x = length
        g = lid[side]
        q = quads(g[:-1, :-1], g[:-1, 1:], g[1:, 1:], g[1:, :-1])
        faces.append(q[:, ::-1] if flip else q)
    for side, flip in ((0, False), (nc, True)):  # y sides
        g = lid[:, side, :]
        q = quads(g[:-1, :-1], g[1:, :-1], g[1:, 1:], g[:-1, 1:])
        faces.append(q[:, ::-1] if flip else q)
    for side, flip in ((0, False), (nc, True)):  # z sides
        g = lid[:, :, side]
        q = quads(g[:-1, :-1], g[:-1, 1:], g[1:, 1:], g[1:, :-1])
        faces.append(q[:, ::-1] if flip else q)
    Q = np.concatenate(faces)
    tris = np.concatenate([Q[:, [0, 1, 2]], Q[:, [0, 2, 3]]])
    used, inverse = np.unique(tris, return_inverse=True)
    return lattice.reshape(-1, 3)[used], inverse.reshape(-1, 3).astype(np.int64)


def signed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    p = points[triangles]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def edges_of(triangles: np.ndarray) -> np.ndarray:
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def dihedral_angles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The angle between the normals of the two triangles at each interior edge (sorted edge order)."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    owner = np.tile(np.arange(triangles.shape[0]), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    pair = np.flatnonzero((key[1:] == key[:-1]).all(axis=1))
    p = points[triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", n[owner[pair]], n[owner[pair + 1]])
    return np.arccos(np.clip(cos, -1.0, 1.0))


@dataclass(frozen=True)
class Quality:
    volume_ratio: float
    edge_max: float
    edge_p99: float
    roughness: float  # RMS change of the dihedral angles (radians)


def quality(rest: np.ndarray, deformed: np.ndarray, triangles: np.ndarray) -> Quality:
    """Volume ratio (signed volume / rest), max and p99 of |l/l0 − 1| over edges, and roughness: the
    RMS change of the dihedral angles from the rest shape (a smooth bend spreads it, bumps raise it)."""
    e = edges_of(triangles)
    l0 = np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1)
    l1 = np.linalg.norm(deformed[e[:, 0]] - deformed[e[:, 1]], axis=1)
    strain = np.abs(l1 / l0 - 1.0)
    change = dihedral_angles(deformed, triangles) - dihedral_angles(rest, triangles)
    return Quality(signed_volume(deformed, triangles) / signed_volume(rest, triangles),
                   float(strain.max()), float(np.percentile(strain, 99)), float(np.sqrt(np.mean(change**2))))


def rigid_params(rotvec: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(m, 12) parameters of rigid motions x ↦ R(ω) x + t with ω as given (any length: lifted past π)."""
    w = np.asarray(rotvec, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(translation, dtype=np.float64).reshape(-1, 3)
    u = np.einsum("mij,mj->mi", aff3.left_jacobian_inv(w), t)
    return np.concatenate([w, u, np.zeros((w.shape[0], 6))], axis=1)


@dataclass(frozen=True)
class Rig:
    centers: np.ndarray  # (m, 3) probe rest positions
    params: np.ndarray  # (m, 12) their motions' parameters


def probes_along(length: float, count: int) -> np.ndarray:
    x = (np.arange(count) + 0.5) * length / count
    return np.stack([x, np.zeros(count), np.zeros(count)], axis=1)


def bend_rig(length: float, angle: float, count: int = 6) -> Rig:
    """Probes along the bar's axis; those past the middle turned by `angle` about z through the axis'
    midpoint (an elbow), the others at rest."""
    centers = probes_along(length, count)
    pivot = np.array([length / 2, 0.0, 0.0])
    far = centers[:, 0] > length / 2
    w = np.zeros((count, 3))
    w[far, 2] = angle
    R = aff3.so3_exp(w)
    t = pivot - np.einsum("mij,j->mi", R, pivot)
    return Rig(centers, rigid_params(w, t))


def twist_rig(length: float, angle: float, count: int = 6) -> Rig:
    """Probes along the bar's axis, each turned about the axis in proportion to its distance along it
    (the last one by `angle` · (x/length)); the axis passes through the origin, so no translation."""
    centers = probes_along(length, count)
    w = np.zeros((count, 3))
    w[:, 0] = angle * centers[:, 0] / length
    return Rig(centers, rigid_params(w, np.zeros((count, 3))))


def rig_weights(points: np.ndarray, rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """The default probe weights (inverse distance², normalised) of `points` for the rig's probes."""
    return probe_weights(points, rig.centers, mode="INVERSE_DISTANCE", exponent=2.0, k=8)
