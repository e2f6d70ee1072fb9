"""Throughput of the numerical core's per-vertex kernel (no Blender): vertices per second.

    python bench/core_kernel.py [--vertices 130000] [--controls 8] [--k 4] [--repeat 15] [--profile]

Times, on a random point cloud with random control motions (rotations up to 180°, scales 0.5–2,
shears, translations), in float64:

* sparse top-K: `deform_points_params` (the hot path the Blender layer calls every frame);
* dense (N, m) weights: `DeformKernel.deform_dense` on precomputed parameters (`deform_points` minus
  the m logarithms);
* the 'LINEAR' comparison mode `blend_linear_sparse`;

and prints the median of --repeat runs. --profile adds a per-stage breakdown of one sparse call.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from affine_deformers.core import aff3, deform  # noqa: E402
from affine_deformers.core.weights import top_k_dense  # noqa: E402


def random_motions(rng: np.random.Generator, m: int) -> np.ndarray:
    """m matrices in Aff+(3): rotation (≤ 180°) · symmetric stretch (0.5–2) · shear, plus translation."""
    w = rng.normal(size=(m, 3))
    w *= (rng.uniform(0.0, np.pi, m) / np.linalg.norm(w, axis=1))[:, None]
    Y = rng.normal(scale=0.3, size=(m, 6))
    A = aff3.phi(aff3.xy_from_params(np.concatenate([w, rng.normal(size=(m, 3)), Y], axis=1))[0],
                 aff3.sym_from6(Y))
    A[:, 0, 1] += rng.uniform(-0.3, 0.3, m)  # a shear on top
    return A


def median_time(fn: Callable[[], object], repeat: int) -> float:
    fn()  # warm-up: allocates the kernel's scratch rows
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def profile_stages(points: np.ndarray, params: np.ndarray, idx: np.ndarray, val: np.ndarray, repeat: int) -> None:
    """Split one sparse call into blend, the map itself, and argument checks."""
    kernel = deform.DeformKernel()
    n = points.shape[0]
    table_t = np.ascontiguousarray(params.T)
    idx_p = idx.astype(np.intp)
    out = np.empty_like(points)

    def blend_only() -> None:
        for lo in range(0, n, kernel.chunk_size):
            hi = min(lo + kernel.chunk_size, n)
            kernel._blend_sparse(table_t, idx_p[lo:hi], val[lo:hi], kernel._param_rows(hi - lo))

    pv = np.ascontiguousarray(deform.blend_params(params, idx, val).T)

    def map_only() -> None:
        for lo in range(0, n, kernel.chunk_size):
            hi = min(lo + kernel.chunk_size, n)
            P = kernel._param_rows(hi - lo)
            P[...] = pv[:, lo:hi]
            kernel._apply_chunk(points[lo:hi], P, out[lo:hi])

    def copy_only() -> None:
        for lo in range(0, n, kernel.chunk_size):
            hi = min(lo + kernel.chunk_size, n)
            kernel._param_rows(hi - lo)[...] = pv[:, lo:hi]

    def checks_only() -> None:
        deform._check_sparse(points, params, idx, val, out, 12, "params")

    full = median_time(lambda: kernel.deform(points, params, idx, val, out), repeat)
    stages = {
        "argument checks": median_time(checks_only, repeat),
        "blend (scatter + BLAS)": median_time(blend_only, repeat),
        "map φ(p)v (incl. param copy)": median_time(map_only, repeat),
        "  of which param copy": median_time(copy_only, repeat),
    }
    print(f"\nprofile of one sparse call ({full * 1e3:.2f} ms):")
    for name, t in stages.items():
        print(f"  {name:30s} {t * 1e3:7.2f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vertices", type=int, default=130_000)
    ap.add_argument("--controls", type=int, default=8)
    ap.add_argument("--k", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()

    rng = np.random.default_rng(7)
    n, m = args.vertices, args.controls
    points = rng.uniform(-1.0, 1.0, size=(n, 3))
    transforms = random_motions(rng, m)
    params = aff3.params_from_matrices(transforms)
    dense_w = rng.random((n, m)) ** 4
    dense_w /= dense_w.sum(axis=1, keepdims=True)
    idx, val = top_k_dense(dense_w, args.k, normalize="SUM")
    out = np.empty_like(points)
    dense_kernel = deform.DeformKernel()

    print(f"core kernel, float64: {n} vertices, {m} controls; numpy {np.__version__}, "
          f"Python {platform.python_version()}, {os.cpu_count()} CPUs, chunk {deform.DEFAULT_CHUNK}")
    runs = {
        f"sparse top-K={idx.shape[1]} deform_points_params": lambda: deform.deform_points_params(
            points, params, idx, val, out=out),
        f"dense (N, {m}) weights, params given": lambda: dense_kernel.deform_dense(
            points, params, dense_w),
        f"dense (N, {m}) deform_points (incl. ψ)": lambda: deform.deform_points(points, transforms, dense_w),
        f"LINEAR top-K={idx.shape[1]} blend_linear_sparse": lambda: deform.blend_linear_sparse(
            points, transforms, idx, val, out=out),
    }
    for name, fn in runs.items():
        t = median_time(fn, args.repeat)
        print(f"  {name:44s} {t * 1e3:8.2f} ms  {n / t / 1e6:7.2f} M vertices/s")
    if args.profile:
        profile_stages(points, params, idx, val, args.repeat)


if __name__ == "__main__":
    main()
