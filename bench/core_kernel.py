"""Throughput of the numerical core's per-vertex kernel (no Blender): vertices per second.

    python bench/core_kernel.py [--vertices 130000] [--controls 8] [--k 4] [--repeat 15] [--profile]

Times, on a random point cloud with random control motions (rotations up to 180°, stretches, shears,
translations), in float64, for 1 thread and for the default thread count:

* sparse top-K (`deform_points_params`, the call the Blender layer makes every frame), with the same
  bind weights as the previous call (the steady state) and with new ones (first frame after a bind);
* dense (N, m) weights (`deform_points` minus its m logarithms);
* the 'LINEAR' comparison mode (`blend_linear_sparse`);

and prints the median and best of --repeat runs. The machine is shared: the median is what a user
sees under load, the best is what the code costs. --profile adds a per-stage breakdown.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from affine_deformers.core import aff3, deform
from affine_deformers.core.weights import top_k_dense


def random_motions(rng: np.random.Generator, m: int) -> np.ndarray:
    """m matrices in Aff+(3): rotation (≤ 180°) · symmetric stretch (0.5–2) · shear, plus translation."""
    w = rng.normal(size=(m, 3))
    w *= (rng.uniform(0.0, np.pi, m) / np.linalg.norm(w, axis=1))[:, None]
    Y = rng.normal(scale=0.3, size=(m, 6))
    A = aff3.phi(
        aff3.xy_from_params(np.concatenate([w, rng.normal(size=(m, 3)), Y], axis=1))[0], aff3.sym_from6(Y)
    )
    A[:, 0, 1] += rng.uniform(-0.3, 0.3, m)  # a shear on top
    return A


def time_runs(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(median, best) wall time of `repeat` calls after one warm-up call (scratch rows, caches)."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times)


def median_time(fn: Callable[[], object], repeat: int) -> float:
    return time_runs(fn, repeat)[0]


def profile_stages(
    points: np.ndarray, params: np.ndarray, idx: np.ndarray, val: np.ndarray, repeat: int
) -> None:
    """Split one sparse call into argument checks, blend and the map itself (single thread)."""
    kernel = deform.DeformKernel(threads=1)
    n = points.shape[0]
    table_t = np.ascontiguousarray(params.T)
    out = np.empty_like(points)
    kernel.deform(points, params, idx, val, out)  # warm the weights cache
    _, _, dense = kernel._sparse_weights(idx, val, n, params.shape[0])
    pv = np.ascontiguousarray(deform.blend_params(params, idx, val).T)

    def chunks() -> list[tuple[int, int]]:
        return [(a, min(a + kernel.chunk_size, n)) for a in range(0, n, kernel.chunk_size)]

    def blend_cached() -> None:
        for a, b in chunks():
            kernel._blend(table_t, idx, val, dense, a, b, kernel._param_rows(b - a))

    def blend_uncached() -> None:
        for a, b in chunks():
            kernel._blend_sparse(table_t, idx[a:b], val[a:b], kernel._param_rows(b - a))

    def map_only() -> None:
        for a, b in chunks():
            P = kernel._param_rows(b - a)
            P[...] = pv[:, a:b]
            kernel._apply_chunk(points[a:b], P, out[a:b])

    def copy_only() -> None:
        for a, b in chunks():
            kernel._param_rows(b - a)[...] = pv[:, a:b]

    full = median_time(lambda: kernel.deform(points, params, idx, val, out), repeat)
    stages = {
        "weights check (cache hit)": median_time(lambda: kernel._sparse_weights(idx, val, n, 8), repeat),
        "blend, cached dense weights": median_time(blend_cached, repeat),
        "blend, scatter per chunk": median_time(blend_uncached, repeat),
        "map φ(p)v (+ param copy)": median_time(map_only, repeat),
        "  of which param copy": median_time(copy_only, repeat),
    }
    print(f"\nprofile of one sparse call, 1 thread ({full * 1e3:.2f} ms):")
    for name, t in stages.items():
        print(f"  {name:30s} {t * 1e3:7.2f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vertices", type=int, default=130_000)
    ap.add_argument("--controls", type=int, default=8)
    ap.add_argument("--k", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=21)
    ap.add_argument("--threads", type=int, nargs="*", default=None, help="thread counts (default: 1 and all)")
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
    K = idx.shape[1]
    # more different weight arrays in turn than the kernel's weights cache holds
    alternating = itertools.cycle([val * (1.0 + i * 2.0**-50) for i in range(deform.WEIGHTS_CACHE_SIZE + 1)])

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"core kernel, float64: {n} vertices, {m} controls, top-K = {K}; numpy {np.__version__}, "
        f"Python {platform.python_version()}, {os.cpu_count()} CPUs (load {load:.2f}), "
        f"chunk {deform.DEFAULT_CHUNK}"
    )
    print(f"  {'':52s} {'median':>9s} {'best':>9s}   vertices/s (median)")
    for threads in args.threads or sorted({1, deform.default_threads()}):
        kernel = deform.DeformKernel(threads=threads)
        runs: dict[str, Callable[[], object]] = {
            "sparse, same weights as last frame (hot path)": lambda k=kernel: k.deform(
                points, params, idx, val, out
            ),
            "sparse, new weights every call (re-bind)": lambda k=kernel: k.deform(
                points, params, idx, next(alternating), out
            ),
            f"dense (N, {m}) weights, params given": lambda k=kernel: k.deform_dense(points, params, dense_w),
            "LINEAR mode, same weights": lambda k=kernel: k.linear(points, transforms, idx, val, out),
        }
        print(f" threads = {threads}")
        for name, fn in runs.items():
            t_med, t_best = time_runs(fn, args.repeat)
            print(f"  {name:52s} {t_med * 1e3:6.2f} ms {t_best * 1e3:6.2f} ms   {n / t_med / 1e6:6.2f} M")
    t_med, _ = time_runs(lambda: deform.deform_points(points, transforms, dense_w), args.repeat)
    print(f"  deform_points (script contract, incl. {m} ψ), default threads: {t_med * 1e3:.2f} ms")
    if args.profile:
        profile_stages(points, params, idx, val, args.repeat)


if __name__ == "__main__":
    main()
