"""A cage made for a mesh (issue #50): `enclosing_cage(points, triangles=None, budget, margin,
symmetric) -> EnclosingCage`, a closed, 2-manifold, outward, self-intersection-free quad surface
that follows the shape and holds every point inside at least `margin` from it, with at most `budget`
faces, exactly mirror-symmetric about x = 0 when the points are.

1. Stand-ins. The points, with samples of long mesh triangles (so the faces are inside too), are
   merged per cell of side STAND_IN_CELLS·h into their centroid c with the radius ρ of the cell's
   points about it: a stand-in keeping margin + ρ from the cage keeps every point it stands for at
   least `margin` away.
2. Solid. On a grid of cubes of side h, every cell nearer than margin + ρ to a stand-in (Euclidean
   distance to the cell's box) is occupied, and a closed mesh's inside is filled (every empty cell
   the outside cannot reach through faces). With symmetry the grid is symmetric about x = 0 (a node
   plane there) and the occupancy is OR-ed with its mirror image.
3. Manifold. The boundary of a union of cubes is a 2-manifold iff the set is well-composed (Latecki):
   no 2×2 block of cells with only a diagonal pair occupied (or empty), no 2×2×2 block with only an
   antipodal pair occupied (or empty). Such blocks are filled until none is left (filling only adds
   cells, so it ends and every point stays covered).
4. Budget. The boundary has about area/h² faces; h is searched (log-secant steps, then bisection) for
   the finest grid whose boundary has at most `budget` faces: no decimation.
5. Surface. Each face between an occupied and an empty cell is a quad on grid nodes, wound
   counter-clockwise seen from the empty side (outward). It keeps every stand-in margin + ρ away,
   holds every point (winding number 1) and is embedded: a valid cage, the fallback.
6. Shrink-wrap. RELAX_STEPS steps move each vertex by λ(x̄ − x) − βh·n (x̄ the mean of its edge
   neighbours: smoothing; n its normal: shrinking onto the shape), at most `step` = min(STEP_CELLS·h,
   0.9·margin), mirror-averaged exactly (x ← ((x − x_m)/2, (y + y_m)/2, (z + z_m)/2)). A vertex
   whose move brings a triangle (of either diagonal) nearer than margin + ρ to a stand-in, or makes
   triangles meet or come within GAP_CELLS·h of an unrelated one, stays where it was (repeated
   until no triangle offends). Why every point stays inside: every step starts from a cage at least
   margin + ρ from each stand-in and moves no point of the surface more than `step` < margin, so the
   ball of radius ρ around a stand-in, which holds its points, is never swept: their winding numbers
   cannot change.
Then `check_enclosure` measures all of it (core/cage/enclose_checks.py); should it find a problem,
the voxel surface of 5. is returned instead, with its report.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .enclose_checks import (
    EnclosureReport,
    box_pairs,
    check_enclosure,
    pair_distance_sq,
    quad_topology,
    quad_triangles,
    triangle_distance,
    triangle_pairs_meet,
)
from .topology import CageTopology

#: Default face budget: a cage of a few hundred quads is easy to edit by hand.
DEFAULT_BUDGET = 300

#: Fewest faces asked for: a box around everything has 6, a symmetric one (two cells) 10.
MIN_BUDGET = 10
#: The default margin, in cells (h): points stay at least this far inside the cage.
MARGIN_CELLS = 0.25
#: Long mesh triangles are sampled this many margins apart (< √3: each face point is nearer than
#: the margin to a sample).
SAMPLE_SPACING = 1.7

#: The points (and face samples) are merged per cell of this side (in cells h) into stand-ins:
#: the shrink-wrap's time grows with their count, its fit loosens with their radius.
STAND_IN_CELLS = 0.25

#: Shrink-wrap: steps, smoothing weight λ, shrink β (cells per step), the longest move of a step
#: (cells), and the least distance kept between parts of the cage that share no corner (cells).
RELAX_STEPS = 12
RELAX_LAMBDA = 0.5
RELAX_SHRINK = 0.1
STEP_CELLS = 0.25
GAP_CELLS = 0.1

#: Rounds of keeping offending vertices in place within one shrink-wrap step.
HOLD_ROUNDS = 8

#: Points are taken as symmetric about x = 0 when every mirrored point has a point within this
#: fraction of the bounding-box diagonal.
SYMMETRY_TOL = 5e-4

#: Most cells along any axis of the grid (bounds time and memory for clouds of far-apart points).
MAX_AXIS_CELLS = 160

#: Most cell sizes tried when fitting the budget, and sizes tried between the last two.
SEARCH_STEPS = 24
SEARCH_TRIES = 4


@dataclass(frozen=True)
class EnclosingCage:
    """A made cage: quads (F, 4) over vertices (V, 3), counter-clockwise seen from outside.

    margin: the distance every point keeps from the cage (requested or MARGIN_CELLS·h); cell_size:
    the grid's h; symmetric: made mirror-symmetric about x = 0, `mirror` (V,) then maps each vertex
    to its mirror image (x[mirror] = x·(−1, 1, 1) exactly), else −1; shrink_wrapped: False when the
    voxel surface was kept; report: what check_enclosure measured; seconds: the time to make it,
    the check included."""

    vertices: np.ndarray
    quads: np.ndarray
    margin: float
    cell_size: float
    symmetric: bool
    mirror: np.ndarray
    shrink_wrapped: bool
    report: EnclosureReport | None
    seconds: float

    @property
    def loop_vertices(self) -> np.ndarray:
        """Blender's `loops.vertex_index` (foreach_set layout)."""
        return self.quads.reshape(-1)

    @property
    def loop_start(self) -> np.ndarray:
        return 4 * np.arange(self.quads.shape[0])

    @property
    def loop_total(self) -> np.ndarray:
        return np.full(self.quads.shape[0], 4)

    def topology(self) -> CageTopology:
        return quad_topology(self.quads, self.vertices.shape[0])


# --- arguments ----------------------------------------------------------------------------------


def _checked_points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {p.shape}")
    if p.shape[0] == 0:
        raise ValueError("no vertices to make a cage around (the mesh is empty)")
    bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1))
    if bad.size:
        raise ValueError(f"vertex {bad[0]} has a non-finite coordinate ({bad.size} such vertices)")
    return p


def _checked_triangles(triangles: np.ndarray | None, n: int) -> np.ndarray:
    if triangles is None:
        return np.zeros((0, 3), np.intp)
    t = np.asarray(triangles)
    if t.size == 0:
        return np.zeros((0, 3), np.intp)
    if t.ndim != 2 or t.shape[1] != 3 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"triangles must be an (T, 3) integer array, got {t.dtype} {t.shape}")
    if t.min() < 0 or t.max() >= n:
        raise ValueError(f"triangles refer to vertices outside 0..{n - 1}")
    return t.astype(np.intp)


def mirror_symmetric(points: np.ndarray, tol: float) -> bool:
    """True when every point mirrored in x = 0 lands within `tol` (per axis, up to 1.5 tol) of a
    point: the points are hashed into cells of side tol, and the mirrored point's 8 nearest cells
    looked up (sorted keys, binary search). A sample of 1024 points is tried first."""
    if tol <= 0.0:
        return bool(np.all(points[:, 0] == 0.0))
    base = points.min(axis=0) - 2.0 * tol
    base[0] = -max(abs(points[:, 0].min()), abs(points[:, 0].max())) - 2.0 * tol
    cells = np.floor((points - base) / tol).astype(np.int64)
    keys = np.unique((cells[:, 0] << 42) + (cells[:, 1] << 21) + cells[:, 2])

    def found(sample: np.ndarray) -> bool:
        m = sample * np.array([-1.0, 1.0, 1.0])
        c0 = np.floor((m - base) / tol - 0.5).astype(np.int64)
        hit = np.zeros(m.shape[0], dtype=bool)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    k = ((c0[:, 0] + dx) << 42) + ((c0[:, 1] + dy) << 21) + c0[:, 2] + dz
                    at = np.minimum(np.searchsorted(keys, k), keys.size - 1)
                    hit |= keys[at] == k
        return bool(hit.all())

    return found(points[:: max(1, points.shape[0] // 1024)]) and found(points)


# --- the solid ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Grid:
    """Cells of side h; node (i, j, k) at origin + (i, j, k)·h; shape counts cells per axis."""

    origin: np.ndarray
    h: float
    shape: tuple[int, int, int]


def _grid_for(lo: np.ndarray, hi: np.ndarray, h: float, r: float, symmetric: bool) -> _Grid:
    """A grid with at least one empty cell around every point's box [p − r, p + r]; centred on the
    points' box, or on x = 0 (an even count of cells along x, a node plane at 0) with symmetry."""
    n = np.floor((hi - lo + 2.0 * r) / h).astype(np.int64) + 3
    origin = 0.5 * (lo + hi) - 0.5 * n * h
    if symmetric:
        half = int(np.floor((max(abs(lo[0]), abs(hi[0])) + r) / h)) + 2
        n[0], origin[0] = 2 * half, -half * h
    return _Grid(origin, float(h), (int(n[0]), int(n[1]), int(n[2])))


def _triangle_samples(corners: np.ndarray, lengths: np.ndarray, spacing: float) -> np.ndarray:
    """Points on every triangle (T, 3, 3) longer than `spacing` (longest edge L): a barycentric
    grid of n = ⌈L/spacing⌉ steps a side (corners left out: they are mesh vertices). Its
    sub-triangles are at most `spacing` long, so every point of the triangle is within spacing/√3 of
    a sample or a corner. Triangles are grouped by n."""
    long = lengths > spacing
    if not np.any(long):
        return np.zeros((0, 3))
    steps = np.ceil(lengths[long] / spacing).astype(np.int64)
    out = []
    for n in np.unique(steps):
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = (i + j <= n) & (np.maximum(i, j) < n) & ((i > 0) | (j > 0))
        w = np.stack([n - i[keep] - j[keep], i[keep], j[keep]], axis=1) / float(n)
        out.append(np.einsum("mk,tkd->tmd", w, corners[long][steps == n]).reshape(-1, 3))
    return np.concatenate(out)


def _occupancy(centres: np.ndarray, need: np.ndarray, grid: _Grid) -> np.ndarray:
    """Cells nearer than need[i] to centre i (Euclidean distance from the centre to the cell's
    box): each centre tries the cells of its box [c − need, c + need], offset by offset. Every
    point nearer than need to a centre is then in an occupied cell, so the boundary of the union
    keeps that distance."""
    rel = (centres - grid.origin) / grid.h
    reach = need / grid.h
    lo = np.floor(rel - reach[:, None]).astype(np.int64)
    span = int((np.floor(rel + reach[:, None]).astype(np.int64) - lo).max()) + 1
    occupied = np.zeros(int(np.prod(grid.shape)), dtype=bool)
    for offset in np.ndindex(span, span, span):
        cell = lo + np.array(offset)
        gap = np.maximum(np.maximum(cell - rel, rel - (cell + 1)), 0.0)
        ok = np.einsum("ij,ij->i", gap, gap) < reach * reach
        c = cell[ok]
        occupied[(c[:, 0] * grid.shape[1] + c[:, 1]) * grid.shape[2] + c[:, 2]] = True
    return occupied.reshape(grid.shape)


def _outside(occupied: np.ndarray) -> np.ndarray:
    """Empty cells 6-connected to the grid's border (which is empty): runs of empty cells along
    each axis take 'outside' from any cell of the run, axis after axis until nothing changes."""
    empty = ~occupied
    out = np.zeros_like(empty)
    for a in range(3):
        index = [slice(None)] * 3
        for end in (0, -1):
            index[a] = end
            out[tuple(index)] = empty[tuple(index)]
    count = -1
    while count != int(out.sum()):
        count = int(out.sum())
        for a in range(3):
            e, o = np.moveaxis(empty, a, -1), np.moveaxis(out, a, -1)
            n = e.shape[-1]
            run = np.cumsum(~e, axis=-1) + (n + 1) * np.arange(e.size // n).reshape((*e.shape[:-1], 1))
            reached = np.bincount(run[o], minlength=(n + 1) * (e.size // n)) > 0
            out = np.moveaxis(e & reached[run], -1, a)
    return out


def _critical(occ: np.ndarray) -> np.ndarray:
    """Cells of the 2×2 and 2×2×2 blocks that keep the set from being well-composed (module
    docstring, 2.): a block with only a diagonal (antipodal) pair occupied, or only one empty."""
    fill = np.zeros_like(occ)
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3

        def part(db: int, dc: int, b: int = b, c: int = c) -> tuple[slice, ...]:
            index = [slice(None)] * 3
            index[b] = slice(db, occ.shape[b] - 1 + db)
            index[c] = slice(dc, occ.shape[c] - 1 + dc)
            return tuple(index)

        x00, x10, x01, x11 = occ[part(0, 0)], occ[part(1, 0)], occ[part(0, 1)], occ[part(1, 1)]
        bad = (x00 & x11 & ~x10 & ~x01) | (x10 & x01 & ~x00 & ~x11)
        for db in (0, 1):
            for dc in (0, 1):
                fill[part(db, dc)] |= bad
    cube = [occ[i:occ.shape[0] - 1 + i, j:occ.shape[1] - 1 + j, k:occ.shape[2] - 1 + k]
            for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    count = sum(x.astype(np.int8) for x in cube)
    bad = np.zeros_like(cube[0])
    for m in range(4):  # antipodal pairs: corner m and corner 7 − m
        bad |= ((count == 2) & cube[m] & cube[7 - m]) | ((count == 6) & ~cube[m] & ~cube[7 - m])
    for m in range(8):
        i, j, k = m >> 2, (m >> 1) & 1, m & 1
        fill[i:occ.shape[0] - 1 + i, j:occ.shape[1] - 1 + j, k:occ.shape[2] - 1 + k] |= bad
    return fill & ~occ


def _well_composed(occ: np.ndarray, symmetric: bool) -> np.ndarray:
    """Fill enclosed cavities and critical blocks until neither is left (each pass only adds cells)."""
    while True:
        occ = ~_outside(occ)
        fill = _critical(occ)
        if not fill.any():
            return occ
        occ = occ | fill
        if symmetric:
            occ = occ | occ[::-1]


def _face_count(occ: np.ndarray) -> int:
    return sum(int(np.count_nonzero(np.diff(occ, axis=a))) for a in range(3))


def representatives(points: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """(centres (R, 3), radius (R,)): the points of each cell of side `side` (a grid anchored at
    the origin, so a mirror-symmetric point set gives mirror-symmetric cells) merged into their
    centroid, radius the largest distance of those points from it."""
    if not points.shape[0]:
        return np.zeros((0, 3)), np.zeros(0)
    cell = np.floor(points / side).astype(np.int64)
    cell -= cell.min(axis=0)
    keys, inverse = np.unique((cell[:, 0] << 42) + (cell[:, 1] << 21) + cell[:, 2], return_inverse=True)
    inverse = inverse.reshape(-1)
    count = np.bincount(inverse)
    centres = np.stack([np.bincount(inverse, points[:, d]) / count for d in range(3)], axis=1)
    off = points - centres[inverse]
    radius = np.zeros(keys.size)
    np.maximum.at(radius, inverse, np.sqrt(np.einsum("ij,ij->i", off, off)))
    # the centroid and the distances are rounded; 1e-12 of the cell more than covers that
    return centres, radius + 1e-12 * side


@dataclass(frozen=True)
class _Solid:
    grid: _Grid
    occupied: np.ndarray
    faces: int
    margin: float
    centres: np.ndarray  # the stand-ins and the face samples
    need: np.ndarray  # the distance each must keep from the cage


class _Shape:
    """The stand-ins and long triangles to enclose, and the solid for a cell size."""

    def __init__(self, points: np.ndarray, triangles: np.ndarray, margin: float | None, symmetric: bool):
        self.margin, self.symmetric = margin, symmetric
        self.points = points
        self.lo, self.hi = points.min(axis=0), points.max(axis=0)
        self.corners = points[triangles]
        edges = self.corners - np.roll(self.corners, 1, axis=1)
        self.lengths = np.sqrt(np.einsum("tkd,tkd->tk", edges, edges)).max(axis=1, initial=0.0)

    def solid(self, h: float) -> _Solid:
        margin = MARGIN_CELLS * h if self.margin is None else self.margin
        # every point of a face within spacing/√3 < margin of a sample or corner: the occupancy
        # covers the faces (no leak into a closed mesh) and the faces end inside the cage;
        # samples are merged like the points when there are many
        samples = _triangle_samples(self.corners, self.lengths, SAMPLE_SPACING * margin)
        centres, radius = representatives(np.concatenate([self.points, samples]), STAND_IN_CELLS * h)
        need = margin + radius
        grid = _grid_for(self.lo, self.hi, h, float(need.max()), self.symmetric)
        occ = _occupancy(centres, need, grid)
        if self.symmetric:
            occ = occ | occ[::-1]
        occ = _well_composed(occ, self.symmetric)
        return _Solid(grid, occ, _face_count(occ), margin, centres, need)

    def smallest_h(self) -> float:
        """No finer than MAX_AXIS_CELLS cells along the longest side (nor than the margin allows)."""
        extent = float(np.max(self.hi - self.lo))
        if self.symmetric:
            extent = max(extent, 2.0 * float(np.max(np.abs([self.lo[0], self.hi[0]]))))
        return max(extent / (MAX_AXIS_CELLS - 8), (self.margin or 0.0) / 8.0, 1e-300)


def _fit_budget(shape: _Shape, budget: int) -> _Solid:
    """The finest solid (smallest h) whose boundary has at most `budget` faces: faces ≈ c/h², so
    log-secant steps h ← h·√(faces/target) until the budget is bracketed, then bisection in log h."""
    extent = np.maximum(shape.hi - shape.lo, 1e-9 * max(float(np.max(shape.hi - shape.lo)), 1e-300))
    if shape.margin:
        extent = extent + 2.0 * shape.margin
    area = 2.0 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[2] * extent[0])
    h = max(float(np.sqrt(area / budget)), shape.smallest_h())
    fine, best = None, None  # the largest h over the budget, the smallest within it
    for _ in range(SEARCH_STEPS):
        solid = shape.solid(h)
        if solid.faces <= budget:
            best = solid if best is None or h < best.grid.h else best
        elif fine is None or h > fine:
            fine = h
        if best is not None and (best.grid.h <= shape.smallest_h() * (1 + 1e-9)):
            break
        if best is not None and fine is not None:
            if best.grid.h / fine < 1.03:
                break
            h = float(np.sqrt(best.grid.h * fine))
        else:
            step = np.sqrt(solid.faces / (0.95 * budget))
            h = h * (max(step, 1.25) if best is None else min(step, 0.9))
            h = max(h, shape.smallest_h())
    if best is None:
        raise ValueError(f"no cage of at most {budget} faces found (the coarsest had {solid.faces}): "
                         "raise the face budget")
    if fine is not None:
        # the face count is not monotonic in h (the voxels snap): try a few sizes in the bracket and
        # keep the one nearest the budget
        for k in range(1, SEARCH_TRIES + 1):
            solid = shape.solid(fine * (best.grid.h / fine) ** (k / (SEARCH_TRIES + 1)))
            if best.faces < solid.faces <= budget:
                best = solid
    return best


# --- the surface ----------------------------------------------------------------------------------


def _boundary_quads(solid: _Solid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (V, 3), quads (F, 4), mirror (V,)) of the faces between occupied and empty cells,
    counter-clockwise seen from the empty side: for the face normal to axis a at node plane i, the
    corners go (0,0), (1,0), (1,1), (0,1) in the next two axes (b, c) = (a+1, a+2) for +a (b × c =
    a), reversed for −a. With a grid symmetric about x = 0, x = (i − n/2)·h exactly and mirror maps
    node i to node n − i (−1 otherwise)."""
    occ, grid = solid.occupied, solid.grid
    n1 = np.array(grid.shape) + 1
    quads = []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        step = np.diff(occ.astype(np.int8), axis=a)  # −1: occupied → empty along +a (normal +a)
        for sign in (-1, 1):
            cell = np.argwhere(step == sign)
            cell[:, a] += 1  # the node plane between the two cells
            corners = []
            for db, dc in ((0, 0), (1, 0), (1, 1), (0, 1)):
                node = cell.copy()
                node[:, b] += db
                node[:, c] += dc
                corners.append((node[:, 0] * n1[1] + node[:, 1]) * n1[2] + node[:, 2])
            q = np.stack(corners, axis=1)
            quads.append(q if sign == -1 else q[:, ::-1])
    flat = np.concatenate(quads)
    nodes, inverse = np.unique(flat, return_inverse=True)
    ijk = np.stack([nodes // (n1[1] * n1[2]), (nodes // n1[2]) % n1[1], nodes % n1[2]], axis=1)
    vertices = grid.origin + ijk * grid.h
    mirror = np.full(nodes.size, -1)
    half = grid.shape[0] // 2
    if grid.shape[0] % 2 == 0 and grid.origin[0] == -half * grid.h:
        vertices[:, 0] = (ijk[:, 0] - half) * grid.h
        twin = ((grid.shape[0] - ijk[:, 0]) * n1[1] + ijk[:, 1]) * n1[2] + ijk[:, 2]
        at = np.minimum(np.searchsorted(nodes, twin), nodes.size - 1)
        mirror = np.where(nodes[at] == twin, at, -1)
    return vertices, inverse.reshape(-1, 4), mirror


def _vertex_normals(x: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Unit normals: the sum of the incident quads' Newell normals (area-weighted)."""
    a, b, c, d = (x[quads[:, k]] for k in range(4))
    n = np.cross(c - a, d - b)  # twice the vector area of the quad
    out = np.zeros_like(x)
    for k in range(4):
        np.add.at(out, quads[:, k], n)
    return out / np.maximum(np.linalg.norm(out, axis=1), 1e-300)[:, None]


def _symmetrise(x: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """Exact mirror average: x ← (x − x_m)/2, (y, z) ← ((y, z) + (y, z)_m)/2 (x = 0 on the plane)."""
    m = x[mirror]
    out = 0.5 * (x + m)
    out[:, 0] = 0.5 * (x[:, 0] - m[:, 0])
    return out


def _pairs_by_vertex(quads: np.ndarray) -> np.ndarray:
    """Sorted keys a·F + b (a < b) of the quads sharing at least one corner."""
    f = quads.shape[0]
    order = np.argsort(quads.reshape(-1), kind="stable")
    vertex, quad = quads.reshape(-1)[order], np.repeat(np.arange(f), 4)[order]
    start = np.flatnonzero(np.r_[True, vertex[1:] != vertex[:-1]])
    size = np.diff(np.r_[start, vertex.size])
    rank = np.arange(vertex.size) - np.repeat(start, size)
    later = np.repeat(size, size) - rank - 1
    first = np.repeat(np.arange(vertex.size), later)
    other = first + 1 + np.arange(first.size) - np.repeat(np.cumsum(later) - later, later)
    a, b = quad[first], quad[other]
    return np.unique(np.minimum(a, b) * f + np.maximum(a, b))


def _cell_key(cell: np.ndarray) -> np.ndarray:
    return (cell[..., 0] * (1 << 21) + cell[..., 1]) * (1 << 21) + cell[..., 2]


class _Rules:
    """The shrink-wrap's rules (module docstring, 6.), checked incrementally. A step moves each
    vertex by m_v ≤ step; distances then shrink by at most the moves, so only what a bound no longer
    covers is measured exactly:
    - stand-in i keeps a lower bound L_i of its distance to the cage (exact when measured, capped at
      need_i + slack), lowered after each step by the largest move of the triangles that can reach
      it (`_around`: a hash of the stand-ins); measured when that bound falls under need_i;
    - triangles of quads sharing a corner: those sharing a corner or an edge are tested every step
      (cheap); those sharing none keep their distance c_ij, lowered by M_i + M_j (M the largest move
      of a triangle's corners), and are measured when that reaches 0;
    - triangles of quads sharing no corner: boxes grown by gap/2, paired each step, must be ≥ gap apart.
    Both diagonals' triangles are checked (4F triangles), each diagonal against its own kind."""

    def __init__(self, x0: np.ndarray, quads: np.ndarray, centres: np.ndarray, need: np.ndarray,
                 gap: float, slack: float):
        f = quads.shape[0]
        self.quads, self.centres, self.need, self.gap, self.slack = quads, centres, need, gap, slack
        self.tris = np.concatenate([quad_triangles(quads, 0), quad_triangles(quads, 1)])
        self.adjacent = _pairs_by_vertex(quads)
        qa = np.concatenate([self.adjacent // f, np.arange(f)])
        qb = np.concatenate([self.adjacent % f, np.arange(f)])
        i, j = [], []
        for base in (0, 2 * f):  # each diagonal's triangles against its own kind only
            for da in (0, f):
                for db in (0, f):
                    keep = (qa != qb) | (da < db)  # a quad with itself: its two triangles once
                    i.append(base + da + qa[keep])
                    j.append(base + db + qb[keep])
        i, j = np.concatenate(i), np.concatenate(j)
        shared = (self.tris[i][:, :, None] == self.tris[j][:, None, :]).any(axis=(1, 2))
        self.tight = (i[shared], j[shared])
        self.loose = (i[~shared], j[~shared])
        corners = x0[self.tris]
        self.clear = triangle_distance(corners[self.loose[0]], corners[self.loose[1]])
        # a hash of the (fixed) stand-ins in cells of the reach: triangles find the stand-ins near them
        self.reach = float(need.max()) + slack
        self.cell = max(float(np.median(np.ptp(corners, axis=1).max(axis=1))), self.reach)
        self.base = np.minimum(centres.min(axis=0), x0.min(axis=0)) - 4.0 * self.cell
        key = _cell_key(np.floor((centres - self.base) / self.cell).astype(np.int64))
        self.order = np.argsort(key)
        self.sorted_key = key[self.order]
        tri, who = self._around(corners, corners)
        self.bound = self._stand_in_distances(corners, tri, who, np.ones(centres.shape[0], dtype=bool))[0]

    def _around(self, before: np.ndarray, after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (triangle, stand-in) holding every stand-in within reach of a triangle, before or
        after a step (T, 3, 3 each): the stand-ins of the hash cells each triangle's box covers."""
        both = np.concatenate([before, after], axis=1)
        lo = np.floor((both.min(axis=1) - self.reach - self.base) / self.cell).astype(np.int64)
        hi = np.floor((both.max(axis=1) + self.reach - self.base) / self.cell).astype(np.int64)
        span = hi - lo + 1
        count = span.prod(axis=1)
        item = np.repeat(np.arange(lo.shape[0]), count)
        k = np.arange(item.size) - np.repeat(np.cumsum(count) - count, count)
        sy, sz = span[item, 1], span[item, 2]
        key = _cell_key(lo[item] + np.stack([k // (sy * sz), (k // sz) % sy, k % sz], axis=1))
        first = np.searchsorted(self.sorted_key, key, "left")
        found = np.searchsorted(self.sorted_key, key, "right") - first
        tri = np.repeat(item, found)
        at = np.repeat(first - (np.cumsum(found) - found), found) + np.arange(tri.size)
        return tri, self.order[at]

    def _stand_in_distances(self, corners: np.ndarray, tri: np.ndarray, who: np.ndarray,
                            which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances from the stand-ins (all; those not in `which` (bool) or beyond need + slack
        read need + slack) to the triangles, and the triangles nearer than need to one of them."""
        keep = which[who]
        tri, who = tri[keep], who[keep]
        cap = self.need + self.slack
        centroid = corners.mean(axis=1)
        radius = np.sqrt(((corners - centroid[:, None, :]) ** 2).sum(axis=2).max(axis=1))
        rel = self.centres[who] - centroid[tri]
        keep = np.einsum("ij,ij->i", rel, rel) < (cap[who] + radius[tri]) ** 2  # the circumscribed ball
        tri, who, rel = tri[keep], who[keep], rel[keep]
        n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
        keep = np.abs(np.einsum("ij,ij->i", rel, n[tri])) < cap[who]  # the plane (through the centroid)
        tri, who = tri[keep], who[keep]
        d = np.sqrt(pair_distance_sq(self.centres[who], corners[tri, 0], corners[tri, 1], corners[tri, 2]))
        best = cap.copy()
        np.minimum.at(best, who, d)
        return best, tri[d < self.need[who]]

    def check(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(offending vertices of y (V,) bool, what was measured) for the step x → y from an
        accepted x."""
        move = np.sqrt(np.einsum("ij,ij->i", y - x, y - x))
        tri_move = move[self.tris].max(axis=1)
        corners = y[self.tris]
        bad_tri = np.zeros(self.tris.shape[0], dtype=bool)
        tri, who = self._around(x[self.tris], corners)
        drop = np.zeros(self.centres.shape[0])  # the largest move of a triangle within reach
        np.maximum.at(drop, who, tri_move[tri])
        near = self.bound - drop < self.need
        measured, close = self._stand_in_distances(corners, tri, who, near)
        bad_tri[close] = True
        i, j = self.tight
        hit = triangle_pairs_meet(y, self.tris, i, j, 0.0)
        bad_tri[i[hit]] = bad_tri[j[hit]] = True
        i, j = self.loose
        tested = np.flatnonzero(self.clear - tri_move[i] - tri_move[j] <= 0.0)
        clear = triangle_distance(corners[i[tested]], corners[j[tested]])
        hit = clear <= 0.0
        bad_tri[i[tested[hit]]] = bad_tri[j[tested[hit]]] = True
        for a, b in self._far_pairs(y):
            bad_tri[a] = bad_tri[b] = True
        bad = np.zeros(y.shape[0], dtype=bool)
        bad[self.tris[bad_tri].reshape(-1)] = True
        return bad, {"drop": drop, "tri_move": tri_move, "near": near, "measured": measured,
                     "tested": tested, "clear": clear}

    def _far_pairs(self, y: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Triangle pairs of quads sharing no corner that are nearer than the gap."""
        f = self.quads.shape[0]
        qc = y[self.quads]
        lo, hi = qc.min(axis=1) - 0.5 * self.gap, qc.max(axis=1) + 0.5 * self.gap
        qa, qb = box_pairs(lo, hi, float(np.median((hi - lo).max(axis=1))))
        far = ~np.isin(qa * f + qb, self.adjacent)
        qa, qb = qa[far], qb[far]
        if not qa.size:
            return []
        i = np.concatenate([base + da + qa for base in (0, 2 * f) for da in (0, f) for _ in (0, f)])
        j = np.concatenate([base + db + qb for base in (0, 2 * f) for _ in (0, f) for db in (0, f)])
        hit = triangle_pairs_meet(y, self.tris, i, j, self.gap)
        return [(i[hit], j[hit])]

    def accept(self, y: np.ndarray, measured: dict[str, np.ndarray]) -> None:
        """Lower the bounds by the accepted step's moves and store what was measured exactly."""
        self.bound = self.bound - measured["drop"]
        near = measured["near"]
        self.bound[near] = measured["measured"][near]
        i, j = self.loose
        self.clear = self.clear - measured["tri_move"][i] - measured["tri_move"][j]
        self.clear[measured["tested"]] = measured["clear"]


def shrink_wrap(x0: np.ndarray, quads: np.ndarray, solid: _Solid, mirror: np.ndarray | None) -> np.ndarray:
    """The shrink-wrap of the module docstring (6.) from the voxel surface x0."""
    h, margin = solid.grid.h, solid.margin
    step = min(STEP_CELLS * h, 0.9 * margin)
    edges = np.concatenate([quads[:, [k, (k + 1) % 4]] for k in range(4)])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    degree = np.bincount(edges.reshape(-1), minlength=x0.shape[0]).astype(np.float64)
    rules = _Rules(x0, quads, solid.centres, solid.need, GAP_CELLS * h, 2.0 * step)
    sym = mirror is not None and bool(np.all(mirror >= 0))
    x = x0.copy()
    scale = np.ones(x.shape[0])  # halved for a vertex held back, doubled (up to 1) when it moves
    for _ in range(RELAX_STEPS):
        mean = np.stack([(np.bincount(edges[:, 0], x[edges[:, 1], d], x.shape[0])
                          + np.bincount(edges[:, 1], x[edges[:, 0], d], x.shape[0])) / degree
                         for d in range(3)], axis=1)
        move = RELAX_LAMBDA * (mean - x) - RELAX_SHRINK * h * _vertex_normals(x, quads)
        length = np.linalg.norm(move, axis=1)
        y = x + move * np.minimum(1.0, step * scale / np.maximum(length, 1e-300))[:, None]
        if sym:
            y = _symmetrise(y, mirror)
        held = np.zeros(x.shape[0], dtype=bool)
        for _ in range(HOLD_ROUNDS):
            bad, measured = rules.check(x, y)
            if not bad.any():
                break
            if sym:
                bad |= bad[mirror]
            held |= bad
            y[bad] = x[bad]
        else:
            break
        rules.accept(y, measured)
        scale = np.where(held, np.maximum(0.5 * scale, 1.0 / 64.0), np.minimum(2.0 * scale, 1.0))
        moved = float(np.abs(y - x).max())
        x = y
        if moved < 1e-3 * step:
            break
    return x


def enclosing_cage(points: np.ndarray, triangles: np.ndarray | None = None, budget: int = DEFAULT_BUDGET,
                   margin: float | None = None, symmetric: bool | None = None, *,
                   check: bool = True) -> EnclosingCage:
    """A quad cage around the points (N, 3) with at most `budget` faces (module docstring).

    triangles (T, 3), optional: the mesh's faces, so that long faces lie inside the cage too and a
    closed mesh's inside is solid; any mesh works (open, non-manifold, loose vertices: every point
    is enclosed). margin: the least distance from any point to the cage (default MARGIN_CELLS cells).
    symmetric: make the cage mirror-symmetric about x = 0 (None: when the points are, within
    SYMMETRY_TOL of their size). check: run check_enclosure on the result (`report`; the voxel
    surface is returned if it finds a problem). ValueError with the reason when no cage can be
    made: no points, a non-finite coordinate, a budget under MIN_BUDGET, a non-positive margin, all
    points at one place without a margin."""
    start = time.perf_counter()
    p = _checked_points(points)
    tri = _checked_triangles(triangles, p.shape[0])
    if int(budget) < MIN_BUDGET:
        raise ValueError(f"a face budget of {budget} is too small: a cage needs at least {MIN_BUDGET} faces")
    if margin is not None and not (np.isfinite(margin) and margin > 0.0):
        raise ValueError(f"the margin must be a positive distance, got {margin}")
    size = float(np.linalg.norm(np.ptp(p, axis=0)))
    if size == 0.0 and margin is None:
        raise ValueError("all vertices are at one place: give a margin to size the cage")
    sym = mirror_symmetric(p, SYMMETRY_TOL * size) if symmetric is None else bool(symmetric)
    solid = _fit_budget(_Shape(p, tri, None if margin is None else float(margin), sym), int(budget))
    x0, quads, mirror = _boundary_quads(solid)
    mirror = mirror if sym else np.full(x0.shape[0], -1)
    x = shrink_wrap(x0, quads, solid, mirror if sym else None)
    report = check_enclosure(p, x, quads, solid.margin) if check else None
    wrapped = True
    if report is not None and not report.ok:
        x, wrapped = x0, False
        report = check_enclosure(p, x, quads, solid.margin)
    return EnclosingCage(x, quads, solid.margin, solid.grid.h, sym, mirror, wrapped, report,
                         time.perf_counter() - start)
