"""Bone and cage layouts whose influences tie, measured as tests/core/field_ties.py measures probes.

Bones (distance weights to the bone segments, exponent 2, Normalize Sum, blended down the hierarchy,
MATH.md §14): a ring of 8 and of 16 bones parallel to a cylinder's axis below a short root bone
whose end comes as near the axis as the ring (the root's weight sweeps through the ring's ties
there), a chain of 8 bones curled into an octagon around a cylinder (every bone ties on its axis,
each the parent of the next), a straight chain of 16 bones along a bar, and four mirrored chains of
3 below a root on a bar. One bone moves (0.36 along z, turned 60° about the horizontal axis
tangent to its ring, through its middle, or through its head in a chain) and its descendants with it.

Cages (the Inverse Distance option: inverse distance to each face polygon, exponent 2, half-space
ramp, MATH.md §10, §12): an octagonal prism of 26 faces around a cylinder (the 8 faces of each ring
tie on the axis) and a cube of 54 faces (3 × 3 per side) around a sphere (faces tie at the centre,
on the axes and the diagonals). One face moves (its vertices shifted 0.36 along z and turned 60°
about the face's horizontal axis through its centre).

The measure is field_ties.jump_ratio: (largest jump between neighbours / largest displacement) on
the mesh's edges and along lines of 4,001 points through the tie sets, divided by the same of the
untruncated field (every control kept). "before" is the rule before this table: the bones' pooled
weight given to the root bones (c = 1/2), the cages' divided by D = max(S, 0.1 Σ kept) and pooled to
the faces' uniform mean; "former" the 0.1.x rule (the lowered weights divided by their own sum).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np

from affine_deformers.core import aff3, deform, hierarchy
from affine_deformers.core import weights as wt
from affine_deformers.core.cage import CageTopology, cage_weights, face_motions
from affine_deformers.core.cage.pool import pool_mixes

from .field_ties import RING_LINES, SHIFT, TURN, Ratios, cylinder, icosphere, jump_ratio, segment

#: Max Influences a new bone deformer gets (blender/kinds/bone_tools.DEFAULT_INFLUENCES) and a cage
#: deformer's for the Inverse Distance option (blender/kinds/cage.py set_up).
BONE_DEFAULT = 8
CAGE_DEFAULT = 8

Field = Callable[[np.ndarray, int], np.ndarray]


# --- bones -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BoneLayout:
    name: str
    vertices: np.ndarray
    edges: np.ndarray
    heads: np.ndarray  # (m, 3)
    tails: np.ndarray  # (m, 3)
    parents: np.ndarray  # (m,) the nearest ancestor, −1 for a root
    moved: int  # the bone that moves, its descendants with it
    pivot: np.ndarray  # (3,) the point it turns about
    lines: dict[str, np.ndarray]


def bone_ring(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(heads, tails, parents): a root bone from z = −1.7 to −1.6 on the axis and n child bones parallel
    to z from −1 to 1 on a ring of radius 1: every point of the axis ties the ring, and at z = −0.6 the
    root's end is as near as the ring."""
    angle = 2.0 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], axis=1)
    up = np.array([0.0, 0.0, 1.0])
    heads = np.concatenate([[[0.0, 0.0, -1.7]], ring - up])
    tails = np.concatenate([[[0.0, 0.0, -1.6]], ring + up])
    return heads, tails, np.array([-1] + [0] * n)


def octagon_chain() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A chain of 8 bones (each the parent of the next) along an octagon of radius 1 about z."""
    angle = 2.0 * np.pi * np.arange(9) / 8 + np.pi / 8
    corners = np.stack([np.cos(angle), np.sin(angle), np.zeros(9)], axis=1)
    return corners[:-1], corners[1:], np.arange(8) - 1


def straight_chain(n: int = 16, half: float = 2.4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A chain of n bones (each the parent of the next) along x from −half to half."""
    x = np.linspace(-half, half, n + 1)
    joints = np.stack([x, np.zeros(n + 1), np.zeros(n + 1)], axis=1)
    return joints[:-1], joints[1:], np.arange(n) - 1


def mirrored_chains() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A root bone along x from −0.2 to 0.2 and four chains of 3 bones below it, from x = ±0.2 to
    ±2.3 at y = ±0.25: mirrored across x = 0 and y = 0, the pairs tie on both planes."""
    heads, tails, parents = [[-0.2, 0.0, 0.0]], [[0.2, 0.0, 0.0]], [-1]
    joints = (0.2, 0.9, 1.6, 2.3)
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            for j in range(3):
                heads.append([sx * joints[j], sy * 0.25, 0.0])
                tails.append([sx * joints[j + 1], sy * 0.25, 0.0])
                parents.append(0 if j == 0 else len(parents) - 1)
    return np.array(heads), np.array(tails), np.array(parents)


BONE_RING_LINES = {
    # the axis ties the whole ring: along it (a hair off, over the bones' length), across it and
    # tilted through the centre (the probes' ring lines)
    "along the axis": segment([0.002, 0.001, -1.0], [0.002, 0.001, 1.0]),
    **{name.replace("probes", "bones"): line for name, line in RING_LINES.items()
       if name != "along the axis"},
}


@cache
def bone_layouts() -> tuple[BoneLayout, ...]:
    from .field_ties import box

    tube = cylinder(0.5, 1.0, 256, 100)
    bar = box((2.5, 0.4, 0.4), 200)
    out = []
    for n in (8, 16):
        heads, tails, parents = bone_ring(n)
        out.append(BoneLayout(f"ring of {n} bones / cylinder", *tube, heads, tails, parents, 1,
                              0.5 * (heads[1] + tails[1]), BONE_RING_LINES))
    heads, tails, parents = octagon_chain()
    out.append(BoneLayout("chain of 8 in an octagon / cylinder", *tube, heads, tails, parents, 3, heads[3],
                          BONE_RING_LINES))
    heads, tails, parents = straight_chain()
    out.append(BoneLayout("chain of 16 / bar", *bar, heads, tails, parents, 8, heads[8], {
        "along the chain, a hair off": segment([-2.5, 0.0, 0.05], [2.5, 0.0, 0.05]),
        "along an edge of the bar": segment([-2.5, 0.4, 0.4], [2.5, 0.4, 0.4]),
        "across at a bone's middle": segment([0.15, -0.4, 0.1], [0.15, 0.4, -0.1]),
    }))
    heads, tails, parents = mirrored_chains()
    out.append(BoneLayout("4 mirrored chains of 3 / bar", *bar, heads, tails, parents, 4, heads[4], {
        "along the axis (mirror plane y = 0)": segment([-2.5, 0.0, 0.05], [2.5, 0.0, 0.05]),
        "across the mirror plane x = 0": segment([0.0, -0.4, 0.1], [0.0, 0.4, -0.1]),
        "across both mirror planes": segment([-0.4, -0.4, -0.3], [0.4, 0.4, 0.3]),
        "in the plane y = 0 at x = 0.8": segment([0.8, 0.0, -0.4], [0.8, 0.0, 0.4]),
    }))
    return tuple(out)


def turned(pivot: np.ndarray) -> np.ndarray:
    """The motion of a moved control: SHIFT along z and TURN about the horizontal axis through `pivot`
    tangent to the circle about z through it (y where the pivot is on the axis)."""
    tangent = np.array([-pivot[1], pivot[0], 0.0])
    length = np.linalg.norm(tangent)
    tangent = tangent / length if length > 0.0 else np.array([0.0, 1.0, 0.0])
    R = aff3.so3_exp(tangent * TURN)
    A = np.eye(4)
    A[:3, :3] = R
    A[:3, 3] = pivot + np.array([0.0, 0.0, SHIFT]) - R @ pivot
    return A


def bone_motions(layout: BoneLayout) -> np.ndarray:
    """(m, 4, 4): the moved bone and every bone below it turned (`turned`), the others at rest."""
    m = len(layout.parents)
    below = np.zeros(m, dtype=bool)
    below[layout.moved] = True
    for _ in range(m):  # a pass per level
        below |= (layout.parents >= 0) & below[np.maximum(layout.parents, 0)]
    A = np.tile(np.eye(4), (m, 1, 1))
    A[below] = turned(layout.pivot)
    return A


def roots_rule(points: np.ndarray, layout: BoneLayout, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The rule before: the same lowered weights with c = 1/2, the pooled weight given to the root
    bones (root r by its tree's share of the bones)."""
    idx, val = wt.probe_weights(points, layout.heads, tails=layout.tails, k=k)
    m = len(layout.parents)
    if not idx.size or int(idx.max()) != m:
        return idx, val
    roots = np.flatnonzero(layout.parents < 0)
    share = hierarchy.pool_mix(layout.parents, np.ones(m))[m, roots]
    return (np.concatenate([idx[:, :-1], np.broadcast_to(roots, (len(idx), len(roots)))], axis=1),
            np.concatenate([val[:, :-1], val[:, -1:] * share], axis=1))


def former_bone_rule(points: np.ndarray, layout: BoneLayout, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The 0.1.x truncation: (w_j − w_{K+1}) / Σ_{i≤K} (w_i − w_{K+1}), nothing pooled."""
    W = wt.inverse_distance(wt.segment_distances(points, layout.heads, layout.tails))
    if k >= W.shape[1]:
        idx, val = wt.top_k(W, k)
        return idx, wt.normalize(val)
    idx, val = wt.top_k(W, k + 1)
    return former_cage_rule(idx, val, k)


def bone_field(points: np.ndarray, layout: BoneLayout, matrices: np.ndarray, k: int,
               rule: str = "now") -> np.ndarray:
    """d(x) of the bones of `layout` moved by `matrices`, distance weights with k influences, blended
    down the hierarchy: the bone deformer's rule ("now": the pooled weight to a point on the tree,
    core.hierarchy.PoolPoint), the rule before this table ("before", `roots_rule`) or 0.1.x's
    ("former", `former_bone_rule`)."""
    parents = layout.parents
    params = aff3.params_from_matrices(hierarchy.local_motions(matrices, parents))
    if rule == "before":
        idx, val = roots_rule(points, layout, k)
    elif rule == "former":
        idx, val = former_bone_rule(points, layout, k)
    else:
        idx, val = wt.probe_weights(points, layout.heads, tails=layout.tails, k=k,
                                    floor=hierarchy.BONE_POOL_FLOOR, pool=hierarchy.PoolPoint(parents))
    if idx.size and int(idx.max()) >= len(parents):
        params, matrices = hierarchy.pool_tables(params, matrices,
                                                 hierarchy.pool_mix(parents, np.ones(len(parents))))
        parents = hierarchy.pool_parents(parents)
    layout_ = hierarchy.chain_layout(idx, val, parents)
    return hierarchy.chain_points(points, params, hierarchy.prefix_table(matrices), layout_) - points


# --- cages -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CageLayout:
    name: str
    vertices: np.ndarray
    edges: np.ndarray
    cage: np.ndarray  # (V, 3) rest cage
    topology: CageTopology
    moved: int  # the face that moves
    lines: dict[str, np.ndarray]


def prism_cage(sides: int = 8, radius: float = 0.8, half: float = 1.3,
               rings: int = 4) -> tuple[np.ndarray, CageTopology]:
    """A prism with `sides` sides about z (its faces' middles at `radius`), `rings` − 1 quads up each
    side, closed by two n-gon caps; outward faces."""
    angle = 2.0 * np.pi * (np.arange(sides) + 0.5) / sides
    corner = radius / math.cos(math.pi / sides)
    z = np.linspace(-half, half, rings)
    points = np.array([[corner * math.cos(a), corner * math.sin(a), h] for h in z for a in angle])
    faces = [[r * sides + i, r * sides + (i + 1) % sides, (r + 1) * sides + (i + 1) % sides,
              (r + 1) * sides + i] for r in range(rings - 1) for i in range(sides)]
    faces.append(list(range(sides))[::-1])
    faces.append([(rings - 1) * sides + i for i in range(sides)])
    return points, _topology(faces, len(points))


def cube_cage(half: float = 1.2, cells: int = 3) -> tuple[np.ndarray, CageTopology]:
    """A cube of half-size `half`, each side `cells` × `cells` quads (shared vertices), outward faces."""
    g = np.linspace(-half, half, cells + 1)
    points = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    on_surface = np.any(np.isclose(np.abs(points), half), axis=1)
    number = np.full(len(points), -1)
    number[on_surface] = np.arange(on_surface.sum())
    ids = number.reshape(cells + 1, cells + 1, cells + 1)
    faces = []
    for axis in range(3):
        for side in (0, cells):
            sheet = np.take(ids, side, axis=axis)
            for i in range(cells):
                for j in range(cells):
                    faces.append([int(q) for q in (sheet[i, j], sheet[i + 1, j], sheet[i + 1, j + 1],
                                                   sheet[i, j + 1])])
    surface = points[on_surface]
    for f in faces:  # outward: counter-clockwise seen from outside
        a, b, c = surface[f[:3]]
        if np.dot(np.cross(b - a, c - a), a + b + c) < 0.0:
            f.reverse()
    return surface, _topology(faces, int(on_surface.sum()))


def _topology(faces: list[list[int]], n_vertices: int) -> CageTopology:
    total = np.array([len(f) for f in faces])
    return CageTopology.from_arrays(np.concatenate(faces), np.cumsum(total) - total, total, n_vertices)


@cache
def cage_layouts() -> tuple[CageLayout, ...]:
    tube = cylinder(0.5, 1.0, 256, 100)
    sphere = icosphere(6, 0.9)
    prism, prism_topology = prism_cage()
    cube, cube_topology = cube_cage()
    centre_face = int(np.argmax(_face_centres(cube, cube_topology)[:, 0]))  # the middle of the +x side
    return (
        CageLayout("octagonal prism of 26 faces / cylinder", *tube, prism, prism_topology, 8, {
            "along the axis": segment([0.002, 0.001, -1.0], [0.002, 0.001, 1.0]),
            "across the axis, through face middles": segment([-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]),
            "across the axis, through edges": segment([-0.35, -0.15, 0.2], [0.35, 0.15, 0.2]),
            "tilted through the centre": segment([-0.45, -0.2, -0.9], [0.45, 0.2, 0.9]),
        }),
        CageLayout("cube of 54 faces / sphere", *sphere, cube, cube_topology, centre_face, {
            "along the x axis": segment([-0.9, 0.002, 0.001], [0.9, 0.002, 0.001]),
            "along the z axis": segment([0.002, 0.001, -0.9], [0.002, 0.001, 0.9]),
            "along a diagonal": segment([-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]),
            "across a face diagonal plane": segment([-0.6, 0.6, -0.3], [0.6, -0.6, 0.3]),
        }),
    )


def _face_centres(points: np.ndarray, topology: CageTopology) -> np.ndarray:
    from affine_deformers.core.cage import face_centroids

    return face_centroids(points, topology)


def cage_current(layout: CageLayout) -> np.ndarray:
    """The moved cage: the moved face's vertices turned (`turned`, about the face's centre)."""
    loops = layout.topology.loop_vertex_indices
    start = layout.topology.loop_start[layout.moved]
    corners = loops[start:start + layout.topology.loop_total[layout.moved]]
    A = turned(layout.cage[corners].mean(axis=0))
    current = layout.cage.copy()
    current[corners] = layout.cage[corners] @ A[:3, :3].T + A[:3, 3]
    return current


def former_cage_rule(idx: np.ndarray, val: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The 0.1.x truncation of untruncated weights (rows sorted, strongest first): (w_j − w_{K+1}) /
    Σ_{i≤K} (w_i − w_{K+1}), the plain top-K where that sum is 0."""
    excess = val[:, :k] - val[:, k:k + 1]
    S = excess.sum(axis=1, keepdims=True)
    return idx[:, :k], np.where(S > 0.0, excess / np.where(S > 0.0, S, 1.0), wt.normalize(val[:, :k]))


def kept_floor_rule(idx: np.ndarray, val: np.ndarray, k: int, n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """The cage rule before this table, on untruncated weights: D = max(S, 0.1 Σ kept), the pooled
    weight to the faces' uniform mean (index F)."""
    W = np.zeros((len(idx), n_faces))
    np.put_along_axis(W, idx.astype(np.intp), val, axis=1)
    cols, vals, pooled = wt.truncate(W, k, floor=0.1, with_pooled=True)
    return (np.concatenate([cols, np.full((len(idx), 1), n_faces, dtype=np.int32)], axis=1),
            np.concatenate([vals, pooled[:, None]], axis=1))


def cage_field(points: np.ndarray, layout: CageLayout, params: np.ndarray, k: int,
               rule: str = "now") -> np.ndarray:
    """d(x) of the cage of `layout` whose faces move by `params`: the Inverse Distance option's
    weights with k influences ("now"), the rule before this table ("before", `kept_floor_rule`) or
    the 0.1.x truncation ("former")."""
    F = layout.topology.n_faces
    if rule in ("before", "former") and k < F:
        idx, val = cage_weights(points, layout.cage, layout.topology, k=F)
        if rule == "before":
            idx, val = kept_floor_rule(idx, val, k, F)
            return deform.deform_points_params(points, wt.with_pool(params, np.full(F, 1.0 / F)), idx, val,
                                               cache_weights=False) - points
        order = np.argsort(-val, axis=1, kind="stable")
        idx, val = former_cage_rule(np.take_along_axis(idx, order, 1), np.take_along_axis(val, order, 1), k)
    else:
        idx, val = cage_weights(points, layout.cage, layout.topology, k=k)
    if idx.size and int(idx.max()) >= F:  # rows that pool weight read the pooled nodes (core.cage.pool)
        params = np.concatenate([params, pool_mixes(layout.cage, layout.topology) @ params])
    return deform.deform_points_params(points, params, idx, val, cache_weights=False) - points


# --- the measure -----------------------------------------------------------------------------------


@cache
def _field_of(kind: str, index: int) -> tuple[object, Callable[..., np.ndarray], int]:
    """(layout, d(points, k, rule), control count) of bone or cage layout `index`."""
    if kind == "bones":
        layout = bone_layouts()[index]
        matrices = bone_motions(layout)
        return layout, lambda p, k, rule="now": bone_field(p, layout, matrices, k, rule), len(layout.parents)
    layout = cage_layouts()[index]
    params = face_motions(layout.cage, cage_current(layout), layout.topology).params
    F = layout.topology.n_faces
    return layout, lambda p, k, rule="now": cage_field(p, layout, params, k, rule), F


@cache
def _untruncated(kind: str, index: int) -> tuple[float, dict[str, float]]:
    layout, field, m = _field_of(kind, index)
    return (jump_ratio(field(layout.vertices, m), layout.edges),
            {name: jump_ratio(field(line, m)) for name, line in layout.lines.items()})


def ratios(kind: str, index: int, k: int, rule: str = "now") -> Ratios:
    """The seam measure of bone (kind "bones") or cage ("cages") layout `index` with k influences,
    relative to its untruncated field."""
    layout, field, _ = _field_of(kind, index)
    edges, lines = _untruncated(kind, index)
    return Ratios(jump_ratio(field(layout.vertices, k, rule), layout.edges) / edges,
                  {name: jump_ratio(field(line, k, rule)) / lines[name]
                   for name, line in layout.lines.items()})


def layouts(kind: str) -> tuple[BoneLayout, ...] | tuple[CageLayout, ...]:
    return bone_layouts() if kind == "bones" else cage_layouts()


def markdown_table(kind: str, ks: tuple[int, ...]) -> str:
    """The ratios of every bone or cage layout at each k in `ks`: the rule in the code ("now"), the
    rule before this table and 0.1.x's, edges and the worst line (its name in the last column)."""
    rows = ["| layout | K | edges, now | worst line, now | edges, before | worst line, before | edges, 0.1.x "
            "| worst line, 0.1.x | worst line (now) |", "|---|---|---|---|---|---|---|---|---|"]
    for index, layout in enumerate(layouts(kind)):
        m = len(layout.parents) if kind == "bones" else layout.topology.n_faces
        for k in ks:
            now, before, former = (ratios(kind, index, k, rule) for rule in ("now", "before", "former"))
            name, worst = now.worst_line
            kept = " (all kept)" if k >= m else ""
            rows.append(f"| {layout.name} | {k}{kept} | {now.edges:.2f} | {worst:.2f} | {before.edges:.2f} | "
                        f"{before.worst_line[1]:.1f} | {former.edges:.2f} | {former.worst_line[1]:.1f} "
                        f"| {name} |")
    return "\n".join(rows)
