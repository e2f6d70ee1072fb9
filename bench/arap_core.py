"""The shape-preserving pass at the core level (no Blender): cost, fill and quality, as a markdown report.

    python bench/arap_core.py [--sizes 10000 130000] [--repeat 5] [--quality-side 24] [--quick]

On a closed box bar (4 × 1 × 1, right triangles; tests/core/arap_rigs.py) bound to probes along its
axis, with the default probe weights (inverse distance², normalised) at the vertices and at the
triangles' centroids:

* Solver: assembly (numpy), ordering + symbolic + numeric factorisation (one compiled call), the
  nonzeros of the Cholesky factor with nested dissection, natural order and SuperLU's minimum degree
  (scipy, as a yardstick), the factor's memory, and per frame the element maps (`vertex_motions` at the
  elements), the per-vertex field (`deform_points_params`), the pass's right-hand side + solve
  (1 iteration) and each extra iteration; the numpy fallback (multigrid CG) per frame, cold and warm
  started, for the iterative alternative.
* Quality on a 90° and a 180° elbow and a 270° twist: volume ratio, edge-length distortion (max and
  p99 of |l/l0 − 1|), roughness (RMS change of the dihedral angles), for the field and the pass
  (1, 2 and 3 iterations), and the anchor strength's trade-off.
* Exactness: a motion shared by every control (affine, rigid, the rest pose), both backends.

Times are the minimum of --repeat runs (the machine is shared: the minimum is what the code costs).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from core_kernel import time_runs

from affine_deformers import accel
from affine_deformers.core import aff3, arap
from affine_deformers.core.arap import system as arap_system
from tests.core.arap_rigs import bend_rig, box_bar, quality, rig_weights, twist_rig
from tests.core.conftest import random_affine


def best(fn: Callable[[], object], repeat: int) -> float:
    """Minimum wall time of `repeat` calls after one warm-up call."""
    return time_runs(fn, repeat)[1]


def side_for(n_vertices: int) -> int:
    """The bar's squares per side for about n_vertices vertices (N ≈ 18 side²)."""
    return max(2, round(np.sqrt(n_vertices / 18.0)))


class Case:
    """A bar bound to a rig: elements, weights, the bound system, one frame's inputs."""

    def __init__(self, n_side: int, rig, strength: float = arap.ANCHOR_STRENGTH) -> None:
        self.P, self.T = box_bar(n_side)
        self.rig = rig
        self.el = arap.triangle_elements(self.P, self.T)
        self.idx, self.val = rig_weights(self.P, rig)
        self.eidx, self.evals = rig_weights(self.el.centroids, rig)
        self.anchors = arap.anchor_weights(self.el, self.idx, self.val, strength=strength)
        self.system = arap.bind_system(self.el, self.anchors)
        self.frame_inputs(rig.params)

    def frame_inputs(self, params: np.ndarray) -> None:
        self.motions = accel.vertex_motions(params, self.eidx, self.evals)
        self.field = accel.deform_points_params(self.P, params, self.idx, self.val)


def fmt_s(seconds: float) -> str:
    return f"{seconds * 1e3:.1f} ms" if seconds < 1.0 else f"{seconds:.2f} s"


def fmt_n(n: int) -> str:
    return f"{n / 1e6:.2f} M" if n >= 1e6 else f"{n / 1e3:.0f} k"


def superlu_fill(system: arap.ArapSystem) -> int | None:
    """nnz(L) of our factor under SuperLU's minimum degree on AᵀA + A (scipy; None without it)."""
    try:
        import scipy.sparse as sp
        import scipy.sparse.linalg as spl
    except ImportError:
        return None
    A = system.matrix
    csc = sp.csr_matrix((A.data, A.indices, A.indptr), shape=A.shape).tocsc()
    lu = spl.splu(csc, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    solver = accel.arap_bind(system, ordering=np.argsort(lu.perm_c))
    fill = solver.stats["nnz_factor"]
    solver.close()
    return fill


def warm_cg_iterations(case: Case, frames: int = 8) -> tuple[float, float, float, float]:
    """The numpy fallback over an animation of the rig (0 → full motion in `frames` steps): mean CG
    iterations and seconds per frame cold (d₀ = 0, what the fallback does) and warm (d₀ = the previous
    frame's d: L δ = r − L d_prev, stopped at the same absolute residual, tol · ‖r‖)."""
    solver = arap.NumpyArapSolver(case.system)
    el, A = case.el, case.system.matrix
    cold_it = warm_it = 0
    cold_t = warm_t = 0.0
    d_prev = np.zeros((case.P.shape[0], 3))
    for k in range(1, frames + 1):
        case.frame_inputs(case.rig.params * (k / frames))
        r = arap.right_hand_side(el, arap.linear_maps(case.motions), case.field)
        start = time.perf_counter()
        solver.solve(r)
        cold_t += time.perf_counter() - start
        cold_it += solver.stats["cg_iterations"]
        start = time.perf_counter()
        rest = r - A.matmul(d_prev)
        solver.tolerance = arap_system.CG_TOLERANCE * float(np.min(np.linalg.norm(r, axis=0) /
                                                                   np.linalg.norm(rest, axis=0)))
        d_prev = d_prev + solver.solve(rest)
        solver.tolerance = arap_system.CG_TOLERANCE
        warm_t += time.perf_counter() - start
        warm_it += solver.stats["cg_iterations"]
    case.frame_inputs(case.rig.params)
    return cold_it / frames, cold_t / frames, warm_it / frames, warm_t / frames


SOLVER_COLUMNS = ("vertices", "triangles", "nnz(A)", "assembly (numpy)", "order + factor (C)",
                  "nnz(L) nested dissection", "nnz(L) natural (factor time)", "nnz(L) SuperLU MMD",
                  "factor memory", "element maps", "field", "pass, 1 iteration", "each extra iteration",
                  "numpy fallback per frame (CG iterations), cold / warm")


def solver_row(n_target: int, repeat: int, natural_max: int, numpy_max: int) -> str:
    """One mesh size of the solver table."""
    case = Case(side_for(n_target), bend_rig(4.0, np.pi / 2))
    n, E = case.P.shape[0], case.el.count
    assemble = best(lambda: arap.bind_system(case.el, case.anchors), max(1, repeat // 2))
    binds = []
    for _ in range(max(1, repeat // 2)):
        solver = accel.arap_bind(case.system)
        binds.append(solver.stats["bind_seconds"])
        solver.close()
    solver = accel.arap_bind(case.system)
    st = dict(solver.stats)  # at bind: the factor alone
    natural = "—"
    if n <= natural_max:
        nat = accel.arap_bind(case.system, ordering="NATURAL")
        natural = f"{fmt_n(nat.stats['nnz_factor'])} ({fmt_s(nat.stats['bind_seconds'])})"
        nat.close()
    mmd = superlu_fill(case.system)
    maps = best(lambda: accel.vertex_motions(case.rig.params, case.eidx, case.evals), repeat)
    field = best(lambda: accel.deform_points_params(case.P, case.rig.params, case.idx, case.val), repeat)
    out = np.empty((n, 3))
    one = best(lambda: solver.frame(case.motions, case.field, 1, out), repeat)
    two = best(lambda: solver.frame(case.motions, case.field, 2, out), repeat)
    memory = solver.stats["bytes"]
    solver.close()
    fallback = "—"
    if n <= numpy_max:
        cold_it, cold_t, warm_it, warm_t = warm_cg_iterations(case)
        fallback = f"{fmt_s(cold_t)} ({cold_it:.0f}) / {fmt_s(warm_t)} ({warm_it:.0f})"
    cells = [f"{n:,}", f"{E:,}", fmt_n(st["nnz_matrix"]), fmt_s(assemble), fmt_s(min(binds)),
             fmt_n(st["nnz_factor"]), natural, fmt_n(mmd) if mmd else "—",
             f"{st['bytes'] / 2**20:.0f} MiB (+{(memory - st['bytes']) / 2**20:.0f} MiB iterating)",
             fmt_s(maps), fmt_s(field), fmt_s(one), fmt_s(two - one), fallback]
    return "| " + " | ".join(cells) + " |"


def solver_rows(sizes: list[int], repeat: int, natural_max: int, numpy_max: int) -> list[str]:
    return ["| " + " | ".join(SOLVER_COLUMNS) + " |", "|" + "---|" * len(SOLVER_COLUMNS),
            *(solver_row(n, repeat, natural_max, numpy_max) for n in sizes)]


RIGS = {
    "bend 90°": lambda: bend_rig(4.0, np.pi / 2),
    "bend 180°": lambda: bend_rig(4.0, np.pi),
    "twist 270°": lambda: twist_rig(4.0, 1.5 * np.pi),
}


def q_row(label: str, method: str, q) -> str:
    return (f"| {label} | {method} | {q.volume_ratio:.4f} | {q.edge_max:.3f} | {q.edge_p99:.3f} | "
            f"{q.roughness:.4f} |")


def quality_rows(n_side: int) -> list[str]:
    rows = ["| rig | method | volume ratio | edge max | edge p99 | roughness (rad) |", "|" + "---|" * 6]
    for label, make in RIGS.items():
        case = Case(n_side, make())
        solver = accel.arap_bind(case.system)
        rows.append(q_row(label, "per-vertex field", quality(case.P, case.field, case.T)))
        for iterations in (1, 2, 3):
            x = solver.frame(case.motions, case.field, iterations)
            rows.append(q_row(label, f"pass, {iterations} iteration{'s' * (iterations > 1)}",
                              quality(case.P, x, case.T)))
        solver.close()
    return rows


def strength_rows(n_side: int) -> list[str]:
    rows = ["| rig | strength | volume ratio | edge max | edge p99 | roughness (rad) |", "|" + "---|" * 6]
    for label in ("bend 90°", "twist 270°"):
        for strength in (1.0, 10.0, 100.0, 1000.0, 10000.0):
            case = Case(n_side, RIGS[label](), strength)
            solver = accel.arap_bind(case.system)
            x = solver.frame(case.motions, case.field)
            rows.append(q_row(label, f"{strength:g}", quality(case.P, x, case.T)))
            solver.close()
    return rows


def exactness_rows(n_side: int) -> list[str]:
    rng = np.random.default_rng(42)
    rows = ["| shared motion | max ‖x − G v‖∞ / max ‖G v‖∞, compiled | numpy fallback | per-vertex field |",
            "|---|---|---|---|"]
    rig = twist_rig(4.0, 1.5 * np.pi)
    case = Case(n_side, rig)
    compiled = accel.arap_bind(case.system)
    fallback = arap.NumpyArapSolver(case.system)
    rigid = np.eye(4)
    rigid[:3, :3] = aff3.so3_exp(rng.normal(size=3))
    rigid[:3, 3] = rng.normal(size=3) * 100.0
    for label, G in (("affine (stretch, shear, ‖t‖ ≈ 100)", random_affine(rng, 1, 0.5, 100.0)[0]),
                     ("rigid (‖t‖ ≈ 100)", rigid), ("rest pose", np.eye(4))):
        params = np.repeat(aff3.params_from_matrices(G)[None], rig.params.shape[0], axis=0)
        case.frame_inputs(params)
        expect = case.P @ G[:3, :3].T + G[:3, 3]
        scale = np.abs(expect).max()
        errors = []
        for solver in (compiled, fallback):
            errors.append(max(np.abs(solver.frame(case.motions, case.field, it) - expect).max() / scale
                              for it in (1, 2, 3)))
        rows.append(f"| {label} | {errors[0]:.1e} | {errors[1]:.1e} | "
                    f"{np.abs(case.field - expect).max() / scale:.1e} |")
    compiled.close()
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 130_000])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--quality-side", type=int, default=24, help="bar squares per side for quality")
    parser.add_argument("--natural-max", type=int, default=200_000,
                        help="largest mesh also factored in natural order")
    parser.add_argument("--numpy-max", type=int, default=200_000,
                        help="largest mesh also run on the numpy fallback")
    parser.add_argument("--quick", action="store_true", help="small sizes, one repeat (a smoke run)")
    ns = parser.parse_args()
    if ns.quick:
        ns.sizes, ns.repeat, ns.quality_side = [2_000], 1, 8
    print(f"# The shape-preserving pass, core level ({accel.backend()})\n")
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared), "
          f"numpy {np.__version__}; times: minimum of {ns.repeat} runs.\n")
    print("## Solver (bar, 90° elbow, default anchors)\n")
    print("\n".join(solver_rows(ns.sizes, ns.repeat, ns.natural_max, ns.numpy_max)))
    n_q = box_bar(ns.quality_side)[0].shape[0]
    print(f"\n## Quality ({n_q:,} vertices, strength {arap.ANCHOR_STRENGTH:g}, level {arap.ANCHOR_LEVEL})\n")
    print("\n".join(quality_rows(ns.quality_side)))
    print("\n## Anchor strength (1 iteration)\n")
    print("\n".join(strength_rows(ns.quality_side)))
    print("\n## Exactness (worst of 1, 2 and 3 iterations)\n")
    print("\n".join(exactness_rows(ns.quality_side)))


if __name__ == "__main__":
    main()
