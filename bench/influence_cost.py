"""Cost of one more influence per vertex (no Blender): one update's time against K.

    python bench/influence_cost.py [--vertices 130052] [--repeat 9] [--controls 16 64] [--compiled]

For each number of probes m and each Max Influences K (4, 6, 8, 12, 16) the probe deformer's weights
(inverse distance, 'SUM', probes on a Fibonacci lattice of the unit sphere, points on it) are built
once, then `deform_points_params` runs with every probe's parameters new each time (all probes
moved: no row is spared) and the same bind weights (the steady state of dragging), in the numpy
kernel, or with --compiled in the C kernel (accel; its library as accel/native.py finds it, e.g.
AFFINE_DEFORMERS_KERNEL_LIB). With m ≤ 48 the numpy kernel blends through a dense (m, N) weight
matrix, so its time depends on m and not on K; above, it gathers K parameter rows per vertex; the C
kernel reads K rows per vertex. Where more probes than K tie, a row has one more column, the
pooled control (MATH.md §12): `columns` reports what the kernel sees. The C kernel's K are timed in
rounds (one update of each per round), so a burst of load hits all alike; the numpy kernel's one K
after the other (its dense weights are cached for 4 weight sets). Prints the median and best of
--repeat runs per K and the cost of each influence beyond 4 relative to K = 4, from the bests (what
the code costs). The machine is shared: compare rows of one run only.
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
    parser.add_argument("--compiled", action="store_true", help="time the C kernel (accel) instead")
    args = parser.parse_args()
    if args.compiled:
        from affine_deformers import accel

        accel.warm_up()
        if not accel.active():
            sys.exit(f"the compiled kernel is not available: {accel.backend()}")
        run, name, threads = accel.deform_points_params, accel.backend(), "its"
    else:
        run, name, threads = deform.deform_points_params, "numpy kernel", str(deform.default_threads())
    rng = np.random.default_rng(0)
    points = fibonacci(args.vertices)
    out = np.empty_like(points)
    print(f"{name}, {args.vertices:,} vertices, {threads} thread(s), median (best)")
    ks = (4, 6, 8, 12, 16)
    for m in args.controls:
        probes = 1.2 * fibonacci(m)
        params = motions(rng, m)
        cases = []
        for k in ks:
            idx, val = wt.probe_weights(points, probes, k=k)
            table = wt.with_pool(params, wt.pool_weights(np.ones(m))) if idx.max() == m else params
            key = ("influence_cost", m, k)
            run(points, table, idx, val, out, key=key)  # caches the weights
            cases.append((k, idx, val, table, key, []))
        # The C kernel: rounds over every K in turn, so a burst of load on the shared machine hits all
        # alike. The numpy kernel keeps the dense form of at most 4 weight sets (deform.WEIGHTS_CACHE_SIZE):
        # rounds over 5 would rebuild it every call, so each K runs its repetitions in a row there.
        order = ([(r, case) for r in range(args.repeat) for case in cases] if args.compiled
                 else [(r, case) for case in cases for r in range(args.repeat)])
        for r, (_k, idx, val, table, key, times) in order:
            moved = table * (1.0 + 1e-9 * (r + 1))  # new parameters for every probe
            t0 = time.perf_counter()
            run(points, moved, idx, val, out, key=key)
            times.append(time.perf_counter() - t0)
        base = min(cases[0][5])
        for k, idx, _val, _table, _key, times in cases:
            best = min(times)
            per = 100.0 * (best / base - 1.0) / (k - 4) if k > 4 else 0.0
            extra = f", {per:+.1f}% of K = 4 per influence beyond 4" if k > 4 else ""
            median = 1e3 * statistics.median(times)
            print(f"m = {m:3d}  K = {k:2d} ({idx.shape[1]:2d} columns): {median:7.2f} ms "
                  f"(best {1e3 * best:.2f}){extra}", flush=True)


if __name__ == "__main__":
    main()
