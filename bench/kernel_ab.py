"""Kernel-level timings: the same inputs through `affine_deformers.accel` of the source tree given as
argv[1] (default: this one), min of argv[2] repetitions (default 25), printed as one JSON line.

Run it with two trees' venvs one after the other (this tree and a checkout of another kernel) and
interleave the runs a few times: a shared machine varies more between runs than kernels differ.
$AFFINE_DEFORMERS_THREADS and $AFFINE_DEFORMERS_KERNEL_VARIANT pick threads and build.

Usage: python bench/kernel_ab.py [TREE] [REPS]
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).resolve().parents[1]))
from affine_deformers import accel
from affine_deformers.core import aff3
from affine_deformers.core import cage as cg
from affine_deformers.core.weights import top_k_dense

RNG = np.random.default_rng(1)


def random_affine(m: int, log_scale: float, t_scale: float) -> np.ndarray:
    """m motions (4, 4): a rotation times a stretch of log-normal scales, a normal translation."""
    out = np.tile(np.eye(4), (m, 1, 1))
    for i in range(m):
        Q, _ = np.linalg.qr(RNG.normal(size=(3, 3)))
        Q *= np.sign(np.linalg.det(Q))
        out[i, :3, :3] = Q @ np.diag(np.exp(RNG.normal(scale=log_scale, size=3)))
        out[i, :3, 3] = RNG.normal(scale=t_scale, size=3)
    return out


def sphere_cage(segments: int = 16, rings: int = 12, radius: float = 1.3) -> tuple[np.ndarray, list]:
    """A UV-sphere cage: vertices (V, 3) and polygons (triangle fans at the poles, quads between)."""
    verts = [(0.0, 0.0, 1.0)]
    for i in range(1, rings):
        polar = np.pi * i / rings
        turns = 2 * np.pi * np.arange(segments) / segments
        verts += [(np.sin(polar) * np.cos(t), np.sin(polar) * np.sin(t), np.cos(polar)) for t in turns]
    verts.append((0.0, 0.0, -1.0))
    faces = [[0, 1 + (j + 1) % segments, 1 + j] for j in range(segments)]
    for i in range(rings - 2):
        for j in range(segments):
            a, b = 1 + i * segments + j, 1 + i * segments + (j + 1) % segments
            faces.append([a, b, b + segments, a + segments])
    last, base = len(verts) - 1, 1 + (rings - 2) * segments
    faces += [[last, base + j, base + (j + 1) % segments] for j in range(segments)]
    return np.array(verts) * radius, faces


def cases() -> dict[str, Callable[[], object]]:
    n, m = 130_000, 8
    pts = RNG.normal(scale=3.0, size=(n, 3))
    stretched = aff3.params_from_matrices(random_affine(m, 0.3, 2.0))
    rigid = stretched.copy()
    rigid[:, 6:] = RNG.normal(scale=1e-6, size=(m, 6))
    idx4, val4 = top_k_dense(RNG.random((n, m)) ** 3, 4)
    idx8, val8 = top_k_dense(RNG.random((n, m)) ** 3, 8)
    rows = np.sort(RNG.choice(n, n // 4, replace=False))
    out, motions32 = np.empty((n, 3)), np.empty((4, n, 3), np.float32)
    prefix = (np.arange(n) % 2).astype(np.int32)
    mats = np.zeros((2, 12))
    mats[:, [0, 4, 8]] = 1.0
    verts, faces = sphere_cage()
    topology = cg.CageTopology.from_polygons(faces)
    moved = verts.copy()
    moved[verts[:, 2] > 0.3] *= 1.2
    n_faces, n_nodes = topology.n_faces, 800
    node_weights = np.abs(RNG.normal(size=(n_nodes, n_faces))) ** 4
    node_weights /= node_weights.sum(axis=1, keepdims=True)
    node_points = RNG.normal(size=(n_nodes, 3))
    face_params = aff3.params_from_matrices(random_affine(n_faces, 0.1, 0.3))
    passes_idx, passes_val = np.stack([idx4, idx4]), np.stack([val4, val4])
    return {
        "points stretched K4": lambda: accel.deform_points_params(pts, stretched, idx4, val4, out, key=1),
        "points rigid K4": lambda: accel.deform_points_params(pts, rigid, idx4, val4, out, key=1),
        "points stretched K8": lambda: accel.deform_points_params(pts, stretched, idx8, val8, out, key=2),
        "rows (1/4) stretched K8": lambda: accel.deform_points_params_rows(pts, stretched, idx8, val8, rows,
                                                                           out, key=2),
        "motions32 stretched K8": lambda: accel.vertex_motions(stretched, idx8, val8, motions32, key=2),
        "chain 2 passes K4": lambda: accel.chain_points(pts, stretched, passes_idx, passes_val, prefix, mats,
                                                        key=3),
        f"cage_faces ({n_faces} faces)": lambda: accel.cage_faces(verts, moved, topology),
        f"cage_nodes ({n_nodes} nodes)": lambda: accel.cage_nodes(node_points, node_weights, face_params,
                                                                  np.arange(n_faces)),
        "psi of 8 controls": lambda: accel.params_from_matrices(random_affine(8, 0.3, 1.0)),
    }


def main() -> None:
    reps = int(sys.argv[2]) if len(sys.argv) > 2 else 25
    result = {}
    for name, call in cases().items():
        call()
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            call()
            times.append(time.perf_counter() - t0)
        result[name] = min(times) * 1e3
    print(json.dumps({"backend": accel.backend(), "ms": result}))


if __name__ == "__main__":
    main()
