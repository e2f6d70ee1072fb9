"""Probe layouts whose influences tie, and the seam measure of the tie tests (numpy only, no Blender).

A layout is a mesh (≥ 20,000 vertices, with its edges), probe rest positions, the one probe that moves
(0.36 along its ring's axis or the grid's z, turned 60° about a horizontal axis through itself, every
other probe at rest) and straight lines of 4,001 points through the sets where the strongest probes
tie (a ring's axis, the grid's centre and mid-planes, the bar's mirror planes). The displacement
field d(x) = φ(Σ_k w_k ψ(A_k)) x − x (core.deform's numpy kernel) is measured by

    edge ratio = max over edges |d(a) − d(b)| / max over vertices |d|,
    line ratio = max over neighbours |d(x_i) − d(x_{i+1})| / max over the line |d|,

each divided by the same ratio of the untruncated field (every probe kept) on the same mesh or line.
A seam is a jump between neighbours that the untruncated field does not have: a ratio far above 1.

`python -m tests.core.field_ties [K …]` (from the repository root) prints the table of these ratios
(docs/field_ties.md) for the truncation in core.weights and for the former rule, which divided the
lowered weights w_j − w_{K+1} by their own sum.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np

from affine_deformers.core import aff3, deform
from affine_deformers.core import weights as wt

#: Max Influences a new probe deformer gets (core.weights.PROBE_INFLUENCES, what the add operator sets).
K_DEFAULT = wt.PROBE_INFLUENCES
LINE_POINTS = 4001
SHIFT = 0.36
TURN = math.radians(60.0)

Rule = Callable[[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]]


# --- meshes (vertices, edges) ----------------------------------------------------------------------


def icosphere(subdivisions: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """An icosahedron subdivided `subdivisions` times, on a sphere: 10·4^s + 2 vertices (6: 40,962)."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                  [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                  [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    for _ in range(subdivisions):  # a pass per level: every edge's midpoint once, 4 triangles per one
        E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(E, axis=0, return_inverse=True)
        mid = V[unique[:, 0]] + V[unique[:, 1]]
        base, n = len(V), len(F)
        V = np.concatenate([V, mid / np.linalg.norm(mid, axis=1, keepdims=True)])
        a, b, c = (inverse.ravel()[i * n:(i + 1) * n] + base for i in range(3))
        F = np.concatenate([np.stack([F[:, 0], a, c], 1), np.stack([F[:, 1], b, a], 1),
                            np.stack([F[:, 2], c, b], 1), np.stack([a, b, c], 1)])
    E = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    return radius * V, E


def _grid_edges(shape: tuple[int, int]) -> np.ndarray:
    ids = np.arange(shape[0] * shape[1]).reshape(shape)
    return np.concatenate([np.stack([ids[:-1].ravel(), ids[1:].ravel()], 1),
                           np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], 1)])


def cylinder(radius: float, half_length: float, around: int, along: int) -> tuple[np.ndarray, np.ndarray]:
    """The side of a cylinder about z: `around` × `along` vertices, quads' edges (closed around)."""
    phi = 2.0 * np.pi * np.arange(around) / around
    Z, P = np.meshgrid(np.linspace(-half_length, half_length, along), phi, indexing="ij")
    V = np.stack([radius * np.cos(P), radius * np.sin(P), Z], axis=-1).reshape(-1, 3)
    ids = np.arange(along * around).reshape(along, around)
    E = np.concatenate([np.stack([ids[:-1].ravel(), ids[1:].ravel()], 1),
                        np.stack([ids.ravel(), np.roll(ids, -1, axis=1).ravel()], 1)])
    return V, E


def box(half: tuple[float, float, float], cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The surface of a box with half-sizes `half`, each face a grid (the longest side `cells` cells,
    the others in proportion); faces do not share their border vertices (they coincide, so the
    measure sees no edge across a border: what it measures is within faces)."""
    half_a = np.asarray(half, dtype=np.float64)
    V, E, base = [], [], 0
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        na, nb = (max(2, round(cells * half_a[i] / half_a.max()) + 1) for i in (a, b))
        A, B = np.meshgrid(np.linspace(-half_a[a], half_a[a], na), np.linspace(-half_a[b], half_a[b], nb),
                           indexing="ij")
        for sign in (-1.0, 1.0):
            P = np.zeros((na, nb, 3))
            P[..., a], P[..., b], P[..., axis] = A, B, sign * half_a[axis]
            V.append(P.reshape(-1, 3))
            E.append(_grid_edges((na, nb)) + base)
            base += na * nb
    return np.concatenate(V), np.concatenate(E)


# --- layouts ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Layout:
    name: str
    vertices: np.ndarray
    edges: np.ndarray
    probes: np.ndarray  # (m, 3) rest positions
    moved: int  # the probe that moves
    lines: dict[str, np.ndarray]  # name -> (LINE_POINTS, 3)


def segment(a, b) -> np.ndarray:  # type: ignore[no-untyped-def]
    t = np.linspace(0.0, 1.0, LINE_POINTS)[:, None]
    return np.asarray(a, dtype=np.float64) + t * (np.asarray(b, dtype=np.float64) - np.asarray(a))


def ring(m: int) -> np.ndarray:
    angle = 2.0 * np.pi * np.arange(m) / m
    return np.stack([np.cos(angle), np.sin(angle), np.zeros(m)], axis=1)


RING_LINES = {
    # every point of the axis ties all the ring's probes: along it (a hair off), and across it
    "along the axis": segment([0.002, 0.001, -1.5], [0.002, 0.001, 1.5]),
    "across the axis, through probes": segment([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
    "across the axis, between probes": segment([-math.cos(0.2), -math.sin(0.2), 0.0],
                                               [math.cos(0.2), math.sin(0.2), 0.0]),
    "tilted through the centre": segment([-0.8, -0.3, -0.52], [0.8, 0.3, 0.52]),
    "across the axis at z = 0.3": segment([-1.0, -0.2, 0.2], [1.0, 0.2, 0.4]),
}


@cache
def layouts() -> tuple[Layout, ...]:
    sphere = icosphere(6, 0.9)
    tube = cylinder(0.5, 1.5, 256, 160)
    cube = box((1.0, 1.0, 1.0), 64)
    bar = box((2.5, 0.4, 0.4), 200)
    out = []
    for m in (8, 12, 16):
        out.append(Layout(f"ring of {m} / sphere", *sphere, ring(m), 0, RING_LINES))
        out.append(Layout(f"ring of {m} / cylinder", *tube, ring(m), 0, RING_LINES))
    g = np.array([-0.5, 0.0, 0.5])
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    out.append(Layout("3×3×3 grid / cube", *cube, grid, int(np.flatnonzero((grid == 0.5).all(axis=1))[0]), {
        "through the centre": segment([-1.0, -0.37, -0.21], [1.0, 0.37, 0.21]),
        "mid-planes x = y = 0.25": segment([0.25, 0.25, -1.0], [0.25, 0.25, 1.0]),
        "in the mid-plane x = 0.25": segment([0.25, -1.0, -0.6], [0.25, 1.0, 0.6]),
        "in the mid-plane z = −0.25": segment([-1.0, -0.7, -0.25], [1.0, 0.7, -0.25]),
    }))
    # mirrored across x = 0 and y = 0: pairs tie on both planes
    mirrored = np.array([[sx * x, sy * 0.25, 0.0]
                         for x in (0.4, 1.2, 2.0) for sx in (-1, 1) for sy in (-1, 1)])
    moved = int(np.flatnonzero(np.all(np.isclose(mirrored, [0.4, 0.25, 0.0]), axis=1))[0])
    out.append(Layout("12 mirrored / bar", *bar, mirrored, moved, {
        "along the axis (mirror plane y = 0)": segment([-2.5, 0.0, 0.05], [2.5, 0.0, 0.05]),
        "across the mirror plane x = 0": segment([0.0, -0.4, 0.1], [0.0, 0.4, -0.1]),
        "across both mirror planes": segment([-0.4, -0.4, -0.3], [0.4, 0.4, 0.3]),
        "in the plane y = 0 at x = 0.8": segment([0.8, 0.0, -0.4], [0.8, 0.0, 0.4]),
    }))
    return tuple(out)


def motion_params(layout: Layout) -> np.ndarray:
    """ψ of each probe's motion (m, 12): the moved probe shifted by SHIFT along z and turned TURN
    about the horizontal axis through it tangent to a ring (y for a probe on the x axis); the rest 0."""
    m = len(layout.probes)
    A = np.tile(np.eye(4), (m, 1, 1))
    c = layout.probes[layout.moved]
    tangent = np.array([-c[1], c[0], 0.0]) if np.hypot(c[0], c[1]) > 0 else np.array([0.0, 1.0, 0.0])
    R = aff3.so3_exp(tangent / np.linalg.norm(tangent) * TURN)
    A[layout.moved, :3, :3] = R
    A[layout.moved, :3, 3] = c + np.array([0.0, 0.0, SHIFT]) - R @ c
    return aff3.params_from_matrices(A)


# --- weights: the deformer's, and the former rule -------------------------------------------------


def deformer_weights(points: np.ndarray, probes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The probe deformer's defaults but k: inverse distance, exponent 2, 'SUM'."""
    return wt.probe_weights(points, probes, mode="INVERSE_DISTANCE", exponent=2.0, normalize="SUM", k=k)


def former_weights(points: np.ndarray, probes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The former truncation: (w_j − w_{K+1}) / Σ_{i≤K} (w_i − w_{K+1}) (the plain top-K where that is
    0): continuous, but steep without bound where the K+1 strongest nearly tie."""
    W = wt.inverse_distance(np.linalg.norm(points[:, None, :] - probes[None, :, :], axis=2))
    if k >= W.shape[1]:
        idx, val = wt.top_k(W, k)
        return idx, wt.normalize(val, "SUM")
    idx, top = wt.top_k(W, k + 1)
    excess = top[:, :k] - top[:, k:]
    S = excess.sum(axis=1, keepdims=True)
    return idx[:, :k], np.where(S > 0.0, excess / np.where(S > 0.0, S, 1.0), wt.normalize(top[:, :k]))


def field(points: np.ndarray, layout: Layout, params: np.ndarray, k: int,
          rule: Rule = deformer_weights) -> np.ndarray:
    """d(x) for the probes of `layout` moved by `params`, weighted by `rule` with k influences."""
    idx, val = rule(points, layout.probes, k)
    m = len(layout.probes)
    if idx.size and int(idx.max()) == m:  # rows that pool weight read the pooled control (index m)
        params = wt.with_pool(params, wt.pool_weights(np.ones(m)))
    return deform.deform_points_params(points, params, idx, val, cache_weights=False) - points


def jump_ratio(d: np.ndarray, pairs: np.ndarray | None = None) -> float:
    """Largest jump between neighbours (`pairs` of indices; None: consecutive points) / largest |d|."""
    jumps = (d[pairs[:, 0]] - d[pairs[:, 1]]) if pairs is not None else np.diff(d, axis=0)
    largest = float(np.linalg.norm(d, axis=1).max())
    return float(np.linalg.norm(jumps, axis=1).max()) / largest if largest > 0.0 else 0.0


@dataclass(frozen=True)
class Ratios:
    edges: float  # edge ratio ÷ the untruncated field's
    lines: dict[str, float]  # line ratio ÷ the untruncated field's, per line

    @property
    def worst_line(self) -> tuple[str, float]:
        return max(self.lines.items(), key=lambda item: item[1])


@cache
def _untruncated(index: int) -> tuple[float, dict[str, float]]:
    layout = layouts()[index]
    params = motion_params(layout)
    m = len(layout.probes)
    return (jump_ratio(field(layout.vertices, layout, params, m), layout.edges),
            {name: jump_ratio(field(line, layout, params, m)) for name, line in layout.lines.items()})


def ratios(index: int, k: int, rule: Rule = deformer_weights) -> Ratios:
    """The seam measure of layout `index` with k influences, relative to its untruncated field."""
    layout = layouts()[index]
    params = motion_params(layout)
    edges, lines = _untruncated(index)
    return Ratios(jump_ratio(field(layout.vertices, layout, params, k, rule), layout.edges) / edges,
                  {name: jump_ratio(field(line, layout, params, k, rule)) / lines[name]
                   for name, line in layout.lines.items()})


def markdown_table(ks: tuple[int, ...] = (4, K_DEFAULT)) -> str:
    """The ratios of every layout at each k in `ks`: the truncation in core.weights ("now") and the
    former rule, edges and the worst line (its name in the last column)."""
    rows = ["| layout | K | edges, now | worst line, now | edges, former | worst line, former "
            "| worst line (now) |", "|---|---|---|---|---|---|---|"]
    for index, layout in enumerate(layouts()):
        for k in ks:
            now, former = ratios(index, k), ratios(index, k, former_weights)
            name, worst = now.worst_line
            kept = " (all kept)" if k >= len(layout.probes) else ""
            rows.append(f"| {layout.name} | {k}{kept} | {now.edges:.2f} | {worst:.2f} | {former.edges:.2f} | "
                        f"{former.worst_line[1]:.1f} | {name} |")
    return "\n".join(rows)


HEADER = """# Seams where influences tie: the measured ratios

Generated by `python -m tests.core.field_ties --markdown docs/field_ties.md {ks}` (numpy kernel, no
Blender); do not edit by hand. Layouts, motion and measure: tests/core/field_ties.py (probes) and
tests/core/field_ties_rigs.py (bones, cages); the rule: docs/MATH.md §12. Each number is (largest
jump between neighbours / largest displacement) divided by the same for the untruncated field (every
control kept) on the same mesh (edges) or line (the worst of the layout's lines of {points:,} points
through its tie sets); 1 means as smooth as keeping every control. "now": the truncation in the code;
"former": the lowered weights w_j − w_{{K+1}} divided by their own sum (the rule of 0.1.x). Inverse
distance, exponent 2, Normalize Sum; one control moved {shift} and turned 60°.

## Probes

Max Influences of a new probe deformer: {default}. Rings of probes about a sphere and a cylinder, a
3×3×3 grid inside a cube, 12 mirrored probes on a bar.

"""

BONES = """
## Bones (distance weights)

Max Influences of a new bone deformer: {default}. Blended down the hierarchy (MATH.md §14); the
moved bone's descendants move with it. "before": the rule this table replaced (the pooled weight given
to the root bones, c = 1/2).

"""

CAGES = """
## Cages (the Inverse Distance option)

Max Influences of a new cage deformer: {default}. Half-space rule on; one face's vertices moved and
turned. "before": the rule this table replaced (D = max(S, 0.1 Σ kept), the pooled weight to the
faces' uniform mean).

"""


if __name__ == "__main__":
    args = sys.argv[1:]
    target = None
    if args[:1] == ["--markdown"]:
        target, args = args[1], args[2:]
    ks = tuple(int(a) for a in args) or (4, K_DEFAULT)
    from tests.core import field_ties_rigs as rigs

    header = HEADER.format(ks=" ".join(map(str, ks)), points=LINE_POINTS, default=K_DEFAULT, shift=SHIFT)
    text = (header + markdown_table(ks) + "\n" + BONES.format(default=rigs.BONE_DEFAULT)
            + rigs.markdown_table("bones", ks) + "\n" + CAGES.format(default=rigs.CAGE_DEFAULT)
            + rigs.markdown_table("cages", ks) + "\n")
    if target is None:
        print(text)
    else:
        with open(target, "w", encoding="utf-8") as f:
            f.write(text)
