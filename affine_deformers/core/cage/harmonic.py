"""Harmonic cage weights on a regular grid, blended through grid-node controls (numpy only).

Weights. For each cage face f the weight field w_f is harmonic inside and outside the cage, with
the boundary data g_f on the cage surface:

    Δw_f = 0 off the cage,   w_f = g_f on it,   g_f ∝ max(0, 1 − (d_f − d_min)/b)²,   Σ_f g_f = 1,

d_f the distance from the surface point to face f's polygon, b = max(BOUNDARY_WIDTH·h,
FACE_BLUR·√area) (h the grid spacing): the face indicator, softened so that a face's own weight is
~1 in its middle and shared with its neighbour at an edge, like a hat function, and so that the
grid's sampling of the surface does not print a node-scale pattern into the field.

Discretisation, on a regular grid over the cage (`cage_grid`): every node is an unknown. A node is
inside when its +z ray crosses the cage an odd number of times (`inside_nodes`). A grid edge whose
ends differ is cut by the cage at a fraction θ of its length from a node (found on the grid line's
own crossings, `axis_hits`); in that node's 7-point Laplacian the neighbour across is replaced by
the surface value at the cut, at distance θh:

    Σ_{uncut j} (w_i − w_j) + Σ_{cut e} (w_i − g(e))/θ_e = 0,

a symmetric positive definite system (a first-order, symmetric treatment of a Dirichlet surface
cutting the cells; θ is clamped at THETA_MIN). Both sides are solved the same way, so target vertices
just outside the cage get weights from the exterior harmonic field; at the grid's own border
missing neighbours are dropped (zero flux). All faces are solved at once (the last axis of the
arrays), in batches of faces that bound memory.

Since the data sum to 1 at every cut and the constant is harmonic, Σ_f w_f ≡ 1: the weights are a
partition of unity (rows are renormalised after the iterative solve). They are smooth and
non-negative, and they are local the way harmonic measure is: a face's weight decays away from it
and does not leak through a wall of the cage (another part of a non-convex cage is reached only
through the inside).

Solver: cascadic conjugate gradients. The problem is built on LEVELS nested grids (spacing 2^l·h,
each one fine cell wider on every side than the next finer, every coarse node a fine node:
`coarser_grid`), each with its own inside test and cut edges; the coarsest is solved to a tight
tolerance by Jacobi-preconditioned CG, and each finer level starts from the trilinear prolongation
of the coarser solution and runs CG to a loose tolerance (the smooth part of the error is gone).
float32 arrays.

Blend. A vertex x in the cell with corner nodes c (trilinear weights λ_c(x), 8 of them) gets the
face weights w_f(x) = Σ_c λ_c(x) W_cf, W_cf = w_f at node c (after the per-node cut below). Rather
than storing W per vertex (hundreds of faces each), each used node c is a control of its own: at
every frame its blend parameters are formed from the faces' (`node_params`), and the vertex blends
its 8 nodes. The node blend is pivoted at the node position x_c: with a face's motion A_f =
[M_f, t_f] and ψ(A_f) = (ω_f, u_f, Y_f), the motion of f expressed about x_c, T(−x_c) A_f T(x_c),
has the parameters (ω_f, u_f + B_f x_c, Y_f), B_f = V(ω_f)⁻¹(M_f − I) (V the left Jacobian, u is
V⁻¹t); these are blended linearly,

    ω̄_c = Σ_f W_cf ω_f,   Ȳ_c = Σ_f W_cf Y_f,   ū_c = Σ_f W_cf u_f + (Σ_f W_cf B_f) x_c,

and the blended motion about x_c, y ↦ M̄_c (y − x_c) + x_c + V(ω̄_c) ū_c with M̄_c = R(ω̄_c) e^{Ȳ_c},
is written back in the target's frame: P_c = (ω̄_c, ū_c + V(ω̄_c)⁻¹ (I − M̄_c) x_c, Ȳ_c). Blending
about the node instead of the object's origin matters: log-space blending is not translation
invariant, and partial weights of a strongly sheared face blended about a far origin cancel (a
pulled cage vertex barely moved the mesh). If every face has the same motion A, ū_c = u + B x_c
and P_c = ψ(A) exactly, so common affine motions of the cage stay exact; a region whose faces all
move rigidly moves rigidly.

Node cut: W_c is cut to max(W_cf − NODE_CUT · max_f W_cf, 0) and renormalised (continuous in W,
so no seam), which keeps far faces out of a node's blend — a local edit leaves distant nodes, and
the vertices around them, bitwise at rest.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..aff3 import left_jacobian_inv, matrices_from_params
from ..kernel import default_threads
from .distances import nearest_faces
from .topology import CageTopology, face_normals

#: Largest number of nodes of the finest grid over the cage's bounding box (plus padding): the
#: resolution of the weights, like Mesh Deform's precision. 4000 nodes is 15–16 along a cube's side.
GRID_NODES = 4000

#: Nested grid levels of the cascadic solver (the finest has spacing h, the coarsest 2^(LEVELS−1)·h).
LEVELS = 3

#: Cells between the cage's bounding box and the finest grid's border (exterior nodes).
PAD_CELLS = 1

#: A cut closer to a node than this fraction of the spacing counts as this far (bounds the diagonal).
THETA_MIN = 0.1

#: Width of the soft nearest-face boundary data: at least this many grid spacings, and at least
#: FACE_BLUR times the nearest face's size √area (`boundary_data`).
BOUNDARY_WIDTH = 2.0
FACE_BLUR = 1.0

#: Relative residual the coarsest level is solved to, and the finer levels.
COARSE_TOL = 1e-4
FINE_TOL = 1e-2

#: Iteration cap per level (the loose tolerances are reached long before on any cage tested).
MAX_ITERATIONS = 400

#: A node keeps the faces whose weight exceeds this fraction of its largest (module docstring).
NODE_CUT = 1e-3

#: Work array size (grid nodes × faces of a batch) for the solver: bounds memory.
BATCH_ELEMENTS = 1 << 21

#: Corner order of the trilinear stencil: (dx, dy, dz) per slot.
CORNERS = np.array([(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], dtype=np.intp)


# ---------------------------------------------------------------------------------------------- grids


@dataclass(frozen=True)
class CageGrid:
    """A regular grid: node (i, j, k) sits at origin + spacing·(i, j, k); shape nodes per axis."""

    origin: np.ndarray
    spacing: float
    shape: tuple[int, int, int]

    def points(self, flat: np.ndarray) -> np.ndarray:
        """Positions (..., 3) of nodes given by flat (C-order) indices (...)."""
        ijk = np.stack(np.unravel_index(np.asarray(flat, dtype=np.intp), self.shape), axis=-1)
        return self.origin + self.spacing * ijk

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))


def cage_grid(cage_points: np.ndarray, *, nodes: int = GRID_NODES, pad: int = PAD_CELLS) -> CageGrid:
    """The finest grid: the cage's bounding box plus `pad` cells on every side (exterior nodes),
    centred, with the smallest spacing h (in steps of 2 %) that keeps it within `nodes` nodes."""
    cage = np.asarray(cage_points, dtype=np.float64)
    lo, hi = cage.min(axis=0), cage.max(axis=0)
    extent = np.maximum(hi - lo, 1e-9 * max(float(np.ptp(cage, axis=0).max()), 1e-300))
    spacing = float(np.cbrt(np.prod(extent) / nodes))
    while True:
        shape = np.ceil(extent / spacing).astype(int) + 1 + 2 * pad
        if np.prod(shape) <= nodes:
            break
        spacing *= 1.02
    origin = 0.5 * (lo + hi) - 0.5 * (shape - 1) * spacing
    return CageGrid(origin, spacing, (int(shape[0]), int(shape[1]), int(shape[2])))


def coarser_grid(fine: CageGrid) -> CageGrid:
    """The next level of the cascade: spacing 2h, origin one fine cell further out (every fine node
    lies inside it, and its own nodes are nodes of the fine grid's lattice); refining it by 2 and
    dropping the first node per axis gives the fine grid (`_refine`)."""
    shape = tuple((s + 1) // 2 + 1 for s in fine.shape)
    return CageGrid(fine.origin - fine.spacing, 2.0 * fine.spacing, shape)


def axis_hits(grid: CageGrid, cage_points: np.ndarray, fan: np.ndarray, fan_face: np.ndarray,
              axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Crossings of the grid lines along `axis` with the cage: (coordinate (C, H) sorted, +inf padded;
    face (C, H)), one row per line, lines in C order of the two other axes.

    Each line is tested against every fan triangle's projection along `axis` (barycentric s, t ≥ 0,
    s + t ≤ 1). The lines are shifted by a tiny irrational fraction of a cell across so they miss
    the cage's edges and vertices, whose crossings would otherwise count twice or not at all.
    """
    other = [k for k in range(3) if k != axis]
    shift = grid.spacing * 1e-6 * np.array([np.sqrt(2.0), np.sqrt(3.0)])
    u = grid.origin[other[0]] + grid.spacing * np.arange(grid.shape[other[0]]) + shift[0]
    v = grid.origin[other[1]] + grid.spacing * np.arange(grid.shape[other[1]]) + shift[1]
    p0 = cage_points[fan[:, 0]]
    e1, e2 = cage_points[fan[:, 1]] - p0, cage_points[fan[:, 2]] - p0
    det = e1[:, other[0]] * e2[:, other[1]] - e1[:, other[1]] * e2[:, other[0]]
    usable = det != 0.0  # triangles parallel to the lines have no crossing
    p0, e1, e2, det, face = p0[usable], e1[usable], e2[usable], det[usable], fan_face[usable]
    U, V = np.meshgrid(u, v, indexing="ij")
    lines = np.stack([U.ravel(), V.ravel()], axis=1)
    found_line, found_coord, found_face = [], [], []
    step = max(1, (1 << 20) // max(p0.shape[0], 1))
    for lo in range(0, lines.shape[0], step):  # chunks of lines bound the (lines × triangles) arrays
        q0 = lines[lo : lo + step, None, 0] - p0[None, :, other[0]]
        q1 = lines[lo : lo + step, None, 1] - p0[None, :, other[1]]
        s = (q0 * e2[:, other[1]] - q1 * e2[:, other[0]]) / det
        t = (e1[:, other[0]] * q1 - e1[:, other[1]] * q0) / det
        line, tri = np.nonzero((s >= 0.0) & (t >= 0.0) & (s + t <= 1.0))
        found_line.append(line + lo)
        found_coord.append(p0[tri, axis] + s[line, tri] * e1[tri, axis] + t[line, tri] * e2[tri, axis])
        found_face.append(face[tri])
    line, coord, face = (np.concatenate(x) for x in (found_line, found_coord, found_face))
    order = np.lexsort((coord, line))
    line, coord, face = line[order], coord[order], face[order]
    per_line = np.bincount(line, minlength=lines.shape[0])
    width = max(int(per_line.max(initial=0)), 1)
    slot = np.arange(line.size) - (np.cumsum(per_line) - per_line)[line]
    coords = np.full((lines.shape[0], width), np.inf)
    faces = np.full((lines.shape[0], width), -1, dtype=np.intp)
    coords[line, slot] = coord
    faces[line, slot] = face
    return coords, faces


def inside_nodes(grid: CageGrid, z_hits: np.ndarray) -> np.ndarray:
    """(nx, ny, nz) bool: nodes whose +z ray crosses the closed cage an odd number of times
    (z_hits: `axis_hits` along z)."""
    nx, ny, nz = grid.shape
    z = grid.origin[2] + grid.spacing * np.arange(nz)
    above = (z_hits[:, None, :] > z[None, :, None]).sum(axis=2)  # (lines, nz)
    return (above % 2 == 1).reshape(nx, ny, nz)


#: Nodes of the grid `outside_points` classifies points on: a point within about one cell of this
#: grid's spacing from the cage surface counts as inside.
OUTSIDE_GRID_NODES = 1 << 15


def outside_points(points: np.ndarray, cage_points: np.ndarray, topology: CageTopology) -> np.ndarray:
    """(N,) bool: the points that lie outside the closed cage, by more than about a cell of a grid of
    OUTSIDE_GRID_NODES nodes over the cage (the parity of +z rays at the nodes, `inside_nodes`): a
    point counts as outside when it is off the grid or every corner of its grid cell is outside. So a
    point near the surface counts as inside; the count is of points the cage does not hold."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cage = np.asarray(cage_points, dtype=np.float64)
    grid = cage_grid(cage, nodes=OUTSIDE_GRID_NODES)
    fan, fan_face = topology.fan_triangles()
    inside = inside_nodes(grid, axis_hits(grid, cage, fan, fan_face, 2)[0])
    cell = np.floor((pts - grid.origin) / grid.spacing).astype(np.int64)
    shape = np.array(grid.shape)
    on_grid = np.all((cell >= 0) & (cell < shape - 1), axis=1)
    out = ~on_grid
    c = cell[on_grid]
    corners = inside[c[:, None, 0] + CORNERS[None, :, 0], c[:, None, 1] + CORNERS[None, :, 1],
                     c[:, None, 2] + CORNERS[None, :, 2]]
    out[on_grid] = ~corners.any(axis=1)
    return out


@dataclass(frozen=True)
class _Crossings:
    """Grid edges cut by the cage along one axis, each listed from both ends (2E rows): `node` the flat
    node, `across` its neighbour over the cut, `theta` the fraction of the edge from the node to the
    cut (clamped to ≥ THETA_MIN), `point` the cut."""

    node: np.ndarray
    across: np.ndarray
    theta: np.ndarray
    point: np.ndarray


def _crossings(grid: CageGrid, inside: np.ndarray, hits: np.ndarray, axis: int) -> _Crossings:
    """Edges (k, k+1) along `axis` whose ends differ in `inside`, and where the cage cuts them: the
    first crossing after node k on that grid line (`axis_hits`), or the edge's midpoint when
    rounding left no crossing in between (an even count where the ends' parities differ)."""
    moved = np.moveaxis(inside, axis, 2)  # (a, b, n): lines in C order of the two other axes
    b = moved.shape[1]
    flips = moved[:, :, :-1] != moved[:, :, 1:]
    i, j, k = np.nonzero(flips)
    line = i * b + j
    coord = grid.origin[axis] + grid.spacing * k  # node k's coordinate along the axis
    row = hits[line]
    first = (row <= coord[:, None]).sum(axis=1)
    hit = row[np.arange(line.size), np.minimum(first, row.shape[1] - 1)]
    ok = (first < row.shape[1]) & (hit < coord + grid.spacing)
    frac = np.where(ok, (hit - coord) / grid.spacing, 0.5)
    frac = np.clip(frac, 0.0, 1.0)
    lo = np.stack([i, j, k], axis=1)
    hi = lo.copy()
    hi[:, 2] += 1
    order = [0, 1, 2]
    order.insert(axis, order.pop(2))  # back to (x, y, z) order
    lo_flat = np.ravel_multi_index(tuple(lo[:, order].T), grid.shape)
    hi_flat = np.ravel_multi_index(tuple(hi[:, order].T), grid.shape)
    point = grid.points(lo_flat)
    point[:, axis] += frac * grid.spacing
    theta = np.maximum(np.concatenate([frac, 1.0 - frac]), THETA_MIN)
    return _Crossings(np.concatenate([lo_flat, hi_flat]), np.concatenate([hi_flat, lo_flat]), theta,
                      np.concatenate([point, point]))


@dataclass(frozen=True)
class _Level:
    """One level of the cascade (module docstring): the diagonal of its operator, the cut edges per
    direction (node, neighbour across, both unique within a direction) and the boundary data, sparse:
    each cut contributes g(point)/θ to its node's right-hand side."""

    shape: tuple[int, int, int]
    diagonal: np.ndarray  # (nx, ny, nz, 1) float32
    cuts: tuple[tuple[np.ndarray, np.ndarray], ...]  # per direction (node, across)
    rhs_node: np.ndarray  # (P,) flat node
    rhs_face: np.ndarray  # (P,)
    rhs_value: np.ndarray  # (P,) g_f/θ


def _level(grid: CageGrid, cage: np.ndarray, topology: CageTopology) -> _Level:
    """The operator and data of one grid: every node is unknown; an edge cut by the cage is replaced
    by the cut's boundary value at its distance θh (module docstring)."""
    fan, fan_face = topology.fan_triangles()
    hits = [axis_hits(grid, cage, fan, fan_face, axis) for axis in range(3)]
    inside = inside_nodes(grid, hits[2][0])
    diagonal = _degree(grid.shape)[..., 0]
    cuts = []
    crossings = [_crossings(grid, inside, hits[axis][0], axis) for axis in range(3)]
    for c in crossings:
        np.add.at(diagonal.reshape(-1), c.node, 1.0 / c.theta - 1.0)
        half = c.node.size // 2  # the first half has node = the lower end: unique per direction
        for part in (slice(0, half), slice(half, None)):
            cuts.append((c.node[part], c.across[part]))
    node = np.concatenate([c.node for c in crossings])
    theta = np.concatenate([c.theta for c in crossings])
    # Each cut is listed from both of its ends at the same point (`_Crossings`): its boundary data is
    # taken once and given to both rows, in row order (the right-hand side sums in that order).
    half = np.array([c.node.size // 2 for c in crossings])
    lower = np.arange(half.sum()) + np.repeat(np.cumsum(half) - half, half)  # rows from the lower end
    upper = lower + np.repeat(half, half)  # the same cuts from the upper end
    cuts_at = np.concatenate([c.point[: c.node.size // 2] for c in crossings])
    cut, face, g = boundary_data(cuts_at, cage, topology, grid.spacing)
    rows = np.concatenate([lower[cut], upper[cut]])
    order = np.argsort(rows, kind="stable")
    pair, face, g = rows[order], np.concatenate([face, face])[order], np.concatenate([g, g])[order]
    return _Level(grid.shape, diagonal[..., None].astype(np.float32), tuple(cuts), node[pair], face,
                  g / theta[pair])


def boundary_data(points: np.ndarray, cage_points: np.ndarray, topology: CageTopology,
                  spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Soft nearest-face data at points on the cage: (point (P,), face (P,), g (P,)) with

        g_f ∝ max(0, 1 − (d_f − d_min)/b)²,   b = max(BOUNDARY_WIDTH·spacing, FACE_BLUR·√area(f*)),

    f* the nearest face, normalised per point (sums to 1): a face's own weight is ~1 at its middle
    and shared with its neighbour near an edge, like a hat function, whatever the grid spacing."""
    area = 0.5 * np.linalg.norm(face_normals(cage_points, topology), axis=1)
    widest = max(BOUNDARY_WIDTH * spacing, FACE_BLUR * float(np.sqrt(area.max())))
    node, face, d = nearest_faces(points, cage_points, topology, widest)
    nearest = np.full(len(points), np.inf)
    np.minimum.at(nearest, node, d)
    first = np.full(len(points), -1, dtype=np.intp)
    is_nearest = d == nearest[node]
    first[node[is_nearest][::-1]] = face[is_nearest][::-1]
    width = np.maximum(BOUNDARY_WIDTH * spacing, FACE_BLUR * np.sqrt(area[first]))
    g = np.maximum(1.0 - (d - nearest[node]) / width[node], 0.0) ** 2
    total = np.bincount(node, g, len(points))
    return node, face, g / total[node]


# ---------------------------------------------------------------------------------------------- solver


def _neighbour_sum(u: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out = Σ of the 6 grid neighbours of every node of u (nx, ny, nz, B); missing ones count 0."""
    out[1:] = u[:-1]
    out[:1] = 0.0
    out[:-1] += u[1:]
    out[:, 1:] += u[:, :-1]
    out[:, :-1] += u[:, 1:]
    out[:, :, 1:] += u[:, :, :-1]
    out[:, :, :-1] += u[:, :, 1:]
    return out


def _degree(shape: tuple[int, int, int]) -> np.ndarray:
    """(nx, ny, nz, 1) float32: the number of in-grid 6-neighbours of each node."""
    deg = np.full(shape, 6.0, dtype=np.float32)
    for axis in range(3):
        index = [slice(None)] * 3
        for end in (0, -1):
            index[axis] = end
            deg[tuple(index)] -= 1.0
    return deg[..., None]


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a·b over all entries (float32 BLAS: relative error ~1e-6, far below the solver's tolerances)."""
    return float(np.dot(a.ravel(), b.ravel()))


def _apply(level: _Level, u: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out = A u = diag·u − Σ over uncut edges of the neighbour (see `_level`)."""
    _neighbour_sum(u, out)
    flat_out, flat_u = out.reshape(-1, u.shape[-1]), u.reshape(-1, u.shape[-1])
    for node, across in level.cuts:
        flat_out[node] -= flat_u[across]
    np.subtract(level.diagonal * u, out, out=out)
    return out


def _conjugate_gradients(level: _Level, rhs: np.ndarray, start: np.ndarray, tol: float,
                         max_iterations: int = MAX_ITERATIONS) -> tuple[np.ndarray, int]:
    """Solve A u = rhs (`_apply`; SPD) by Jacobi-preconditioned CG on the stacked fields from
    `start`, until ‖r‖ ≤ tol·‖rhs‖. Returns (u, iterations)."""
    inv_diag = (1.0 / level.diagonal).astype(np.float32)
    x = start
    Ap = np.empty_like(rhs)
    r = rhs - _apply(level, x, Ap)
    z = r * inv_diag
    p = z.copy()
    rz = _dot(r, z)
    limit = tol * tol * max(_dot(rhs, rhs), 1e-300)
    it = 0
    while it < max_iterations and _dot(r, r) > limit:
        _apply(level, p, Ap)
        alpha = np.float32(rz / _dot(p, Ap))
        x += alpha * p
        r -= alpha * Ap
        np.multiply(r, inv_diag, out=z)
        rz_new = _dot(r, z)
        p *= np.float32(rz_new / rz)
        p += z
        rz = rz_new
        it += 1
    return x, it


def _refine(coarse: np.ndarray) -> np.ndarray:
    """Trilinear prolongation (nx, ny, nz, B) → (2nx − 1, 2ny − 1, 2nz − 1, B): coarse nodes are the
    even fine nodes, odd ones the mean of their two coarse neighbours along each axis in turn."""
    fine = coarse
    for axis in range(3):
        n = fine.shape[axis]
        shape = list(fine.shape)
        shape[axis] = 2 * n - 1
        out = np.empty(shape, dtype=fine.dtype)
        even = [slice(None)] * 4
        odd = [slice(None)] * 4
        even[axis] = slice(0, None, 2)
        odd[axis] = slice(1, None, 2)
        out[tuple(even)] = fine
        lo = [slice(None)] * 4
        hi = [slice(None)] * 4
        lo[axis] = slice(0, -1)
        hi[axis] = slice(1, None)
        out[tuple(odd)] = 0.5 * (fine[tuple(lo)] + fine[tuple(hi)])
        fine = out
    return fine


def _levels(grid: CageGrid, cage: np.ndarray, topology: CageTopology, levels: int) -> list[_Level]:
    """The cascade's levels, coarsest first (`coarser_grid`)."""
    grids = [grid]
    for _ in range(levels - 1):
        grids.append(coarser_grid(grids[-1]))
    return [_level(sub, cage, topology) for sub in reversed(grids)]


def _solve_batch(levels: list[_Level], faces: np.ndarray, n_faces: int,
                 used: np.ndarray) -> tuple[np.ndarray, int]:
    """Weights (G, len(faces)) float32 of the faces `faces` (of n_faces) at the finest-grid nodes
    `used` (flat)."""
    index = np.full(n_faces, -1, dtype=np.intp)
    index[faces] = np.arange(faces.size)
    full = None
    iterations = 0
    for depth, level in enumerate(levels):
        rhs = np.zeros((*level.shape, faces.size), dtype=np.float32)
        column = index[level.rhs_face]
        take = column >= 0
        np.add.at(rhs.reshape(-1, faces.size), (level.rhs_node[take], column[take]), level.rhs_value[take])
        if full is None:
            start = np.zeros_like(rhs)
        else:
            nx, ny, nz = level.shape
            start = np.ascontiguousarray(_refine(full)[1 : 1 + nx, 1 : 1 + ny, 1 : 1 + nz])
        tol = COARSE_TOL if depth == 0 else FINE_TOL
        full, it = _conjugate_gradients(level, rhs, start, tol)
        iterations += it
    return full.reshape(-1, faces.size)[used], iterations


@dataclass(frozen=True)
class HarmonicWeights:
    """Bind data of the 'HARMONIC' cage weights.

    grid: the finest grid; node_points (G, 3): the used nodes (corners of the cells holding target
    vertices); node_weights (G, F) float32: the cut face weights of each used node, rows summing to
    1 (to float32 rounding; `node_params` renormalises); indices (N, 8) int32 into the used nodes and
    values (N, 8): each vertex's trilinear weights. iterations: CG iterations of the solve (all
    levels, summed over face batches)."""

    grid: CageGrid
    node_points: np.ndarray
    node_weights: np.ndarray
    indices: np.ndarray
    values: np.ndarray
    iterations: int


def trilinear(grid: CageGrid, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(flat node ids (N, 8), trilinear weights (N, 8)) of each point's grid cell, corners in `CORNERS`
    order. Points outside the grid take the weights of the nearest point of the grid's box (the
    result is continuous, constant along the clamped directions)."""
    shape = np.array(grid.shape)
    f = (np.asarray(points, dtype=np.float64) - grid.origin) / grid.spacing
    f = np.clip(f, 0.0, shape - 1)
    i0 = np.minimum(np.floor(f).astype(np.intp), shape - 2)
    t = f - i0
    w = [np.stack([1.0 - t[:, k], t[:, k]], axis=1) for k in range(3)]  # (N, 2) per axis
    lam = (w[0][:, :, None, None] * w[1][:, None, :, None] * w[2][:, None, None, :]).reshape(-1, 8)
    ny, nz = grid.shape[1:]
    base = (i0[:, 0] * ny + i0[:, 1]) * nz + i0[:, 2]
    offset = (CORNERS[:, 0] * ny + CORNERS[:, 1]) * nz + CORNERS[:, 2]
    return base[:, None] + offset[None, :], lam


def harmonic_weights(points: np.ndarray, cage_points: np.ndarray, topology: CageTopology, *,
                     nodes: int = GRID_NODES, threads: int | None = None) -> HarmonicWeights:
    """'HARMONIC' cage weights of the target vertices `points` (N, 3) (module docstring).

    The cage must be closed (`check_cage`); its faces are solved in batches (in `threads` threads,
    default core.deform.default_threads()). The used nodes are those of the cells holding a vertex.
    """
    cage = np.asarray(cage_points, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(cage))):
        raise ValueError("points or cage contain non-finite coordinates")
    grid = cage_grid(cage, nodes=nodes)
    flat, lam = trilinear(grid, points)
    used, inverse = np.unique(flat, return_inverse=True)
    levels = _levels(grid, cage, topology, LEVELS)
    F = topology.n_faces
    batch = max(1, min(F, BATCH_ELEMENTS // grid.size))
    batches = [np.arange(lo, min(lo + batch, F)) for lo in range(0, F, batch)]
    W = np.zeros((used.size, F), dtype=np.float32)
    iterations = [0] * len(batches)

    def run(i: int) -> None:
        W[:, batches[i]], iterations[i] = _solve_batch(levels, batches[i], F, used)

    _run_all(run, len(batches), threads)
    node_points = grid.points(used)
    empty = np.flatnonzero(~(np.maximum(W, 0.0).sum(axis=1) > 0.0))
    if empty.size:  # no cut edge reached these nodes (a cage thinner than the grid resolves)
        pair, face, g = boundary_data(node_points[empty], cage, topology, grid.spacing)
        W[empty] = 0.0
        W[empty[pair], face] = g
    return HarmonicWeights(grid, node_points, cut_node_weights(W),
                           inverse.reshape(flat.shape).astype(np.int32), lam, int(sum(iterations)))


def _run_all(fn: Callable[[int], None], n: int, threads: int | None) -> None:
    threads = min(default_threads() if threads is None else max(1, threads), n)
    if threads <= 1:
        for i in range(n):
            fn(i)
        return
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="affine_cage_harmonic") as pool:
        for future in [pool.submit(fn, i) for i in range(n)]:
            future.result()


def cut_node_weights(W: np.ndarray, cut: float = NODE_CUT) -> np.ndarray:
    """max(W − cut·rowmax, 0) of non-negative weights, rows renormalised to 1 (float32)."""
    W = np.maximum(np.asarray(W, dtype=np.float64), 0.0)
    W = np.maximum(W - cut * W.max(axis=1, keepdims=True), 0.0)
    total = W.sum(axis=1, keepdims=True)
    return (W / np.where(total > 0.0, total, 1.0)).astype(np.float32)


# ---------------------------------------------------------------------------------------------- blend


def linear_maps(params: np.ndarray) -> np.ndarray:
    """The linear parts M = R(ω) exp(Y) (n, 3, 3) of φ(P) for parameters (n, 12) (the default `maps`
    of `node_params`; a caller may pass a faster evaluation of the same map)."""
    return matrices_from_params(params)[:, :3, :3]


def face_blend_terms(face_params: np.ndarray, maps: Callable[[np.ndarray], np.ndarray] = linear_maps
                     ) -> np.ndarray:
    """(F, 21): per face (ω, u, Y, B) with B = V(ω)⁻¹ (M − I) row-major — the quantities the
    pivoted node blend is linear in (module docstring); `maps` gives M (see `linear_maps`)."""
    P = np.asarray(face_params, dtype=np.float64)
    M = maps(P)
    B = left_jacobian_inv(P[:, 0:3]) @ (M - np.eye(3))
    return np.concatenate([P, B.reshape(-1, 9)], axis=1)


def face_columns(W: np.ndarray, faces: np.ndarray | None, valid: np.ndarray | None,
                  values: np.ndarray) -> np.ndarray:
    """Σ_f W_cf values_f over `faces` ∩ `valid` (all faces when None), rows renormalised over the
    valid faces (rows without any give 0): (G, C) for values (len(faces) or F, C) given per face of
    `faces`. A dense product when most faces take part (no gather of W's columns)."""
    F = W.shape[1]
    keep = np.ones(F, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    total = W @ keep.astype(np.float64)
    scale = np.where(total > 0.0, 1.0 / np.where(total > 0.0, total, 1.0), 0.0)
    if faces is None:
        faces = np.arange(F)
    use = keep[faces]
    faces, values = faces[use], values[use]
    if faces.size == 0:
        return np.zeros((W.shape[0], values.shape[1]))
    if 4 * faces.size >= F:
        table = np.zeros((F, values.shape[1]))
        table[faces] = values
        out = W @ table
    else:
        out = W[:, faces] @ values
    return out * scale[:, None]


def node_params(node_points: np.ndarray, node_weights: np.ndarray, face_params: np.ndarray, *,
                faces: np.ndarray | None = None, valid: np.ndarray | None = None,
                maps: Callable[[np.ndarray], np.ndarray] = linear_maps) -> np.ndarray:
    """Blend parameters (G, 12) of the nodes: the pivoted blend of the module docstring.

    maps: evaluates the linear part of φ for a batch of parameters (`linear_maps`; the Blender layer
    passes the compiled kernel's, the same map to ~1e-15).

    faces: the faces whose parameters may be non-zero (the others are skipped: their terms are 0);
    valid (F,) bool: faces to leave out, their weight going to the node's other faces (rows are
    renormalised over the valid faces; a node left without any keeps the rest, params 0).
    """
    W = np.asarray(node_weights, dtype=np.float64)
    x = np.asarray(node_points, dtype=np.float64)
    P = np.asarray(face_params, dtype=np.float64)
    faces = np.arange(W.shape[1]) if faces is None else np.asarray(faces, dtype=np.intp)
    blend = face_columns(W, faces, valid, face_blend_terms(P[faces], maps))
    omega, Y = blend[:, 0:3], blend[:, 6:12]
    u = blend[:, 3:6] + np.einsum("gij,gj->gi", blend[:, 12:21].reshape(-1, 3, 3), x)
    linear = np.concatenate([omega, np.zeros_like(omega), Y], axis=1)
    M = maps(linear)
    u += np.einsum("gij,gj->gi", left_jacobian_inv(omega), x - np.einsum("gij,gj->gi", M, x))
    return np.concatenate([omega, u, Y], axis=1)


def node_matrices_linear(node_weights: np.ndarray, face_matrices: np.ndarray, *,
                         faces: np.ndarray | None = None, valid: np.ndarray | None = None) -> np.ndarray:
    """(G, 4, 4) I + Σ_f W_cf (A_f − I) (rows renormalised over `valid`): the nodes' matrices for the
    'LINEAR' comparison blend, so a vertex gets the linear blend of the faces with its weights."""
    W = np.asarray(node_weights, dtype=np.float64)
    faces = np.arange(W.shape[1]) if faces is None else np.asarray(faces, dtype=np.intp)
    delta = (np.asarray(face_matrices, dtype=np.float64)[faces] - np.eye(4)).reshape(-1, 16)
    return np.eye(4) + face_columns(W, faces, valid, delta).reshape(-1, 4, 4)
