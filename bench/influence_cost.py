"""Cost of one more influence per vertex in the numpy kernel (no Blender): one update's time against K.

    python bench/influence_cost.py [--vertices 130052] [--repeat 9] [--controls 16 64]

For each number of probes m and each Max Influences K (4, 6, 8, 12, 16) the probe deformer's weights
(inverse distance, 'SUM', probes on a Fibonacci lattice of the unit sphere, points on it) are built
once, then `deform_points_params` runs with every probe's parameters new each time (all probes
moved: no row is spared) and the same bind weights (the steady state of dragging). With m ≤ 48 the
numpy kernel blends through a dense (m, N) weight matrix, so its time depends on m and not on K;
above, it gathers K parameter rows per vertex. Where more probes than K tie, a row has one more
column, the pooled control (MATH.md §12): `columns` reports what the kernel sees. Prints the median
and best of --repeat runs per K and the cost of each influence beyond 4 relative to K = 4. The
machine is shared: compare rows of one run only.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from affine_deformers.core import aff3, deform
from affine_deformers.core import weights as wt


def fibonacci(n: int) -> np.ndarray:
    """n nearly evenly spread points on the unit sphere."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    angle = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(angle), r * np.sin(angle), z], axis=1)


def motions(rng: np.random.Generator, m: int) -> np.ndarray:
    """ψ (m, 12) of m rigid-plus-stretch motions: turns up to 1 rad, stretches 0.8–1.25, shifts."""
    A = np.tile(np.eye(4), (m, 1, 1))
    axes = rng.normal(size=(m, 3))
    axes *= (rng.uniform(0.2, 1.0, m) / np.linalg.norm(axes, axis=1))[:, None]
    A[:, :3, :3] = aff3.so3_exp(axes) @ (np.exp(rng.uniform(-0.2, 0.2, (m, 3)))[:, :, None] * np.eye(3))
    A[:, :3, 3] = rng.normal(scale=0.2, size=(m, 3))
    return aff3.params_from_matrices(A)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vertices", type=int, default=130_052)
    parser.add_argument("--repeat", type=int, default=9)
    parser.add_argument("--controls", type=int, nargs="+", default=[16, 64])
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    points = fibonacci(args.vertices)
    out = np.empty_like(points)
    print(f"numpy kernel, {args.vertices:,} vertices, {deform.default_threads()} thread(s), median (best)")
    for m in args.controls:
        probes = 1.2 * fibonacci(m)
        params = motions(rng, m)
        base = None
        for k in (4, 6, 8, 12, 16):
            idx, val = wt.probe_weights(points, probes, k=k)
            table = wt.with_pool(params, wt.pool_weights(np.ones(m))) if idx.max() == m else params
            key = ("influence_cost", m, k)
            deform.deform_points_params(points, table, idx, val, out, key=key)  # caches the weights
            times = []
            for r in range(args.repeat):
                moved = table * (1.0 + 1e-9 * (r + 1))  # new parameters for every probe
                t0 = time.perf_counter()
                deform.deform_points_params(points, moved, idx, val, out, key=key)
                times.append(time.perf_counter() - t0)
            median = statistics.median(times)
            base = median if base is None else base
            per = 100.0 * (median / base - 1.0) / (k - 4) if k > 4 else 0.0
            extra = f", {per:+.1f}% per influence beyond 4" if k > 4 else ""
            print(f"m = {m:3d}  K = {k:2d} ({idx.shape[1]:2d} columns): {1e3 * median:7.2f} ms "
                  f"({1e3 * min(times):.2f}){extra}", flush=True)


if __name__ == "__main__":
    main()
