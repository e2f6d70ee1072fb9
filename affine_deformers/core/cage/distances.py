"""Distances from points to cage faces, and the faces' part of the 'INVERSE_DISTANCE' cage weights.

Weights (`face_weights`; core.cage.pool.cage_weights completes them; MATH.md §10, §12): inverse
distance to the face polygon (exact point–triangle distance, minimum over the polygon's fan
triangles), faded to zero over a band above each face's plane (the half-space rule as a C¹ ramp),
continuous top-K with a bounded slope (what the kept faces leave of 1 near ties, λ, in a column of
index F), rows summing to 1; computed in chunks of vertices. The default harmonic weights:
core/cage/harmonic.py.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..kernel import default_threads
from ..weights import POOL_FLOOR, truncate
from .topology import CageTopology, _check_points, _norm, face_centroids, face_normals

# Points this close to a face plane (relative to the cage size) are not "outside" it, so a target
# vertex lying on the cage surface keeps the face it lies on.
HALF_SPACE_TOL = 1e-9

# Half-space ramp (face_weights): a face's weight fades from full at its plane to 0 where the point
# is this far above the plane relative to its distance to the face (sin of the elevation angle).
HALF_SPACE_BAND = 0.5

# Distances are floored at this fraction of the cage size so a vertex on the cage gets a finite,
# dominant weight from the faces it touches instead of 1/0.
DISTANCE_FLOOR = 1e-6

# Elements per work array of face_weights ((chunks × faces) in its first pass, (chunk points ×
# candidate faces) in its second): bounds memory and keeps the arrays in cache.
BATCH_ELEMENTS = 1 << 17

# Slack on face_weights' pruning bounds, relative to the cage size. It covers their rounding (dot
# products of coordinates of the order of the cage size, some expanded), never the geometry.
BOUND_SLACK = 1e-6

# The truncation's total T (MATH.md §12): the weight of this many nearest faces (or K + 1 when more),
# measured exactly like the (K+1)-th, so D = max(S, c·T) with c = weights.POOL_FLOOR. A sum of the
# largest weights is continuous; the cage measures only the faces that can matter, not all of them
# (T over all faces would bound the slope as well: an octagonal prism's steps were 2.5× the
# untruncated field's at 4 influences with it, 2.7× with this; T = the kept faces' weight and c = 0.1
# stepped 5.5× on its edges and 25× along its axis).
TOTAL_FACES = 16


def _inverse_or_zero(x: np.ndarray) -> np.ndarray:
    ok = x > 0.0
    return np.where(ok, 1.0 / np.where(ok, x, 1.0), 0.0)


def _triangle_table(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> dict[str, np.ndarray]:
    """Per-triangle constants for `_distance_sq_block` (coordinates already relative to an origin)."""
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    abab = np.einsum("ij,ij->i", ab, ab)
    acac = np.einsum("ij,ij->i", ac, ac)
    abac = np.einsum("ij,ij->i", ab, ac)
    bc = ac - ab
    gram = abab * acac - abac * abac
    inv_gram = _inverse_or_zero(gram)
    return {
        "a": a,
        "ab": ab,
        "ac": ac,
        "n": n,
        "aa": np.einsum("ij,ij->i", a, a),
        "ab_a": np.einsum("ij,ij->i", ab, a),
        "ac_a": np.einsum("ij,ij->i", ac, a),
        "n_a": np.einsum("ij,ij->i", n, a),
        "abab": abab,
        "acac": acac,
        "abac": abac,
        "bcbc": np.einsum("ij,ij->i", bc, bc),
        "inv_abab": _inverse_or_zero(abab),
        "inv_acac": _inverse_or_zero(acac),
        "inv_bcbc": _inverse_or_zero(np.einsum("ij,ij->i", bc, bc)),
        # barycentric (v, w) of the projection: v = cv1·d1 + cv2·d2 + v0, w = cw1·d1 + cw2·d2;
        # v0 = −1 marks a degenerate triangle (no interior), so its projection never counts as inside.
        "cv1": acac * inv_gram,
        "cv2": -abac * inv_gram,
        "cw1": -abac * inv_gram,
        "cw2": abab * inv_gram,
        "v0": np.where(gram > 0.0, 0.0, -1.0),
        "inv_nn": _inverse_or_zero(np.einsum("ij,ij->i", n, n)),
    }


def _distance_sq_block(p: np.ndarray, tab: dict[str, np.ndarray]) -> np.ndarray:
    """Exact squared distances (C, T) from points p (C, 3) to triangles (a, a + ab, a + ac).

    If the projection of p onto the triangle's plane has barycentrics v, w ≥ 0, v + w ≤ 1 the
    distance is the plane distance, (n·ap)²/|n|²; otherwise the closest point lies on an edge and the
    distance is the smallest of the three point–segment distances |ap − t·e|², t = clamp(ap·e/|e|²).
    Every dot product of p comes from one matrix product with [a | ab | ac | n]; the rest is
    elementwise on (C, T) arrays. Degenerate triangles reduce to their edges (segments or points).
    """
    T = tab["a"].shape[0]
    G = p @ np.concatenate([tab["a"], tab["ab"], tab["ac"], tab["n"]], axis=0).T
    pa, d1, d2, pn = G[:, :T], G[:, T : 2 * T], G[:, 2 * T : 3 * T], G[:, 3 * T :]
    d1 = d1 - tab["ab_a"]  # ab·ap
    d2 = d2 - tab["ac_a"]  # ac·ap
    ap2 = np.einsum("ij,ij->i", p, p)[:, None] - 2.0 * pa + tab["aa"]

    def clamp01(x: np.ndarray) -> np.ndarray:  # np.clip's dispatch overhead is significant here
        np.maximum(x, 0.0, out=x)
        return np.minimum(x, 1.0, out=x)

    t = clamp01(d1 * tab["inv_abab"])
    edge = ap2 - t * (2.0 * d1 - t * tab["abab"])
    t = clamp01(d2 * tab["inv_acac"])
    np.minimum(edge, ap2 - t * (2.0 * d2 - t * tab["acac"]), out=edge)
    bc_bp = (d2 - tab["abac"]) - (d1 - tab["abab"])  # (ac − ab)·(p − b)
    bp2 = ap2 - 2.0 * d1 + tab["abab"]
    t = clamp01(bc_bp * tab["inv_bcbc"])
    np.minimum(edge, bp2 - t * (2.0 * bc_bp - t * tab["bcbc"]), out=edge)

    v = d1 * tab["cv1"] + d2 * tab["cv2"] + tab["v0"]
    w = d1 * tab["cw1"] + d2 * tab["cw2"]
    inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0)
    n_ap = pn - tab["n_a"]
    plane = n_ap * n_ap * tab["inv_nn"]
    return np.maximum(np.where(inside, plane, edge), 0.0)


def point_triangle_distance_sq(
    points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> np.ndarray:
    """Exact squared distance from each point (N, 3) to each triangle (a, b, c) (T, 3 each) -> (N, T).

    Dense; for tests and small inputs (face_weights works in chunks). Coordinates are taken relative
    to the triangles' mean vertex, which keeps the expanded dot products well conditioned."""
    a, b, c = (np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in (a, b, c))
    origin = (a.mean(axis=0) + b.mean(axis=0) + c.mean(axis=0)) / 3.0 if a.size else np.zeros(3)
    table = _triangle_table(a - origin, b - origin, c - origin)
    return _distance_sq_block(np.asarray(points, dtype=np.float64).reshape(-1, 3) - origin, table)


# Columns of the stacked triangle table that `_pair_distance_sq` gathers per (point, triangle) pair.
_PAIR_COLUMNS = ("a", "ab", "ac", "n", "abab", "acac", "abac", "bcbc", "inv_abab", "inv_acac",
                 "inv_bcbc", "cv1", "cv2", "cw1", "cw2", "v0", "inv_nn")


def _stack_table(table: dict[str, np.ndarray]) -> np.ndarray:
    """(25, T): the `_PAIR_COLUMNS` of a triangle table as rows, so one fancy index gathers a pair's
    constants as contiguous rows."""
    return np.concatenate([np.atleast_2d(table[key].T) for key in _PAIR_COLUMNS], axis=0)


def _pair_distance_sq(p: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Exact squared distance (P,) from each point p (P, 3) to its triangle, whose `_stack_table`
    column is `rows` (25, P): the regions of `_distance_sq_block`, with every dot product taken on
    ap = p − a directly (no expanded |p|² − 2 p·a + |a|², which cancels near the triangle)."""
    ap = [p[:, k] - rows[k] for k in range(3)]
    d1 = ap[0] * rows[3] + ap[1] * rows[4] + ap[2] * rows[5]  # ab·ap
    d2 = ap[0] * rows[6] + ap[1] * rows[7] + ap[2] * rows[8]  # ac·ap
    n_ap = ap[0] * rows[9] + ap[1] * rows[10] + ap[2] * rows[11]
    ap2 = ap[0] * ap[0] + ap[1] * ap[1] + ap[2] * ap[2]
    abab, acac, abac, bcbc = rows[12], rows[13], rows[14], rows[15]

    def clamp01(x: np.ndarray) -> np.ndarray:
        np.maximum(x, 0.0, out=x)
        return np.minimum(x, 1.0, out=x)

    t = clamp01(d1 * rows[16])
    edge = ap2 - t * (2.0 * d1 - t * abab)
    t = clamp01(d2 * rows[17])
    np.minimum(edge, ap2 - t * (2.0 * d2 - t * acac), out=edge)
    bc_bp = (d2 - abac) - (d1 - abab)  # (ac − ab)·(p − b)
    t = clamp01(bc_bp * rows[18])
    np.minimum(edge, (ap2 - 2.0 * d1 + abab) - t * (2.0 * bc_bp - t * bcbc), out=edge)
    v = d1 * rows[19] + d2 * rows[20] + rows[23]
    w = d1 * rows[21] + d2 * rows[22]
    inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0)
    return np.maximum(np.where(inside, n_ap * n_ap * rows[24], edge), 0.0)


@dataclass(frozen=True)
class _CageFields:
    """What face_weights needs of the rest cage, relative to `origin` (the mean vertex).

    Two cheap bounds on the distance from a point p to face f's polygon prune the exact distances:

        dist(p, box_f) ≤ d_f(p) ≤ |p − s_f| + δ_f,

    box_f the face's oriented bounding box (rows of `frame`: û along the first edge, v̂, n̂ the unit
    Newell normal; `lo`, `hi` the extent of frame·v over its vertices — the polygon, made of convex
    combinations of them, lies inside), s_f the vertex mean and δ_f its exact distance to the
    polygon (0 for a planar convex face)."""

    origin: np.ndarray
    size: float
    table: np.ndarray  # (25, Tf) fan triangles (`_stack_table`), grouped by face
    fan_start: np.ndarray  # (F,) first fan triangle of each face
    fan_count: np.ndarray  # (F,)
    plane_offsets: np.ndarray  # (F,) n̂·s_f; +inf for a zero-area face (never "outside")
    centers: np.ndarray  # (F, 3) s_f
    reach: np.ndarray  # (F,) δ_f
    frame: np.ndarray  # (F, 3, 3) rows û, v̂, n̂ (n̂ = unit normal; any frame for a zero-area face)
    lo: np.ndarray  # (F, 3)
    hi: np.ndarray  # (F, 3)

    @classmethod
    def build(cls, cage: np.ndarray, topology: CageTopology) -> _CageFields:
        origin = cage.mean(axis=0)
        local = cage - origin
        size = float(np.ptp(cage, axis=0).max()) or 1.0
        fan, fan_face = topology.fan_triangles()
        table = _stack_table(_triangle_table(*(local[fan[:, k]] for k in range(3))))
        fan_count = topology.loop_total - 2
        fan_start = np.cumsum(fan_count) - fan_count
        normals = face_normals(local, topology)
        length = _norm(normals)
        flat = ~(length > 0.0)
        unit = normals / np.where(flat, 1.0, length)[:, None]
        centers = face_centroids(local, topology)
        offsets = np.where(flat, np.inf, np.einsum("ij,ij->i", unit, centers))
        frame = _face_frames(local, topology, np.where(flat[:, None], [0.0, 0.0, 1.0], unit))
        vertex, face = topology.corners()
        coords = np.einsum("rki,ri->rk", frame[face], local[vertex])
        lo = np.full((topology.n_faces, 3), np.inf)
        hi = np.full((topology.n_faces, 3), -np.inf)
        np.minimum.at(lo, face, coords)
        np.maximum.at(hi, face, coords)
        own = _pair_distance_sq(centers[fan_face], table)
        reach = np.sqrt(np.minimum.reduceat(own, fan_start))
        return cls(origin, size, table, fan_start, fan_count, offsets, centers, reach, frame, lo, hi)


def _face_frames(local: np.ndarray, topology: CageTopology, normal: np.ndarray) -> np.ndarray:
    """(F, 3, 3) orthonormal rows (û, v̂, n̂): û is the face's first edge made orthogonal to the unit
    vector n̂ (a box aligned with it is tight on rectangles and trapezoids), or any unit vector
    orthogonal to n̂ when that edge is (nearly) along it."""
    loops, start = topology.loop_vertex_indices, topology.loop_start
    edge = local[loops[start + 1]] - local[loops[start]]
    u = edge - np.einsum("ij,ij->i", edge, normal)[:, None] * normal
    other = np.cross(normal, np.eye(3)[np.argmin(np.abs(normal), axis=1)])
    bad = ~(_norm(u) > 1e-6 * _norm(edge))
    u = np.where(bad[:, None], other, u)
    u /= _norm(u)[:, None]
    return np.stack([u, np.cross(normal, u), normal], axis=1)


def _morton_order(p: np.ndarray) -> np.ndarray:
    """Permutation sorting points along a Z-order curve (10 bits per axis), so consecutive chunks are
    spatially compact and the chunk bounds can prune."""
    lo = p.min(axis=0)
    span = float(np.ptp(p, axis=0).max()) or 1.0
    cells = np.clip(((p - lo) / span * 1023.0).astype(np.int64), 0, 1023)

    def spread(x: np.ndarray) -> np.ndarray:
        x = (x | (x << 16)) & 0x030000FF
        x = (x | (x << 8)) & 0x0300F00F
        x = (x | (x << 4)) & 0x030C30C3
        return (x | (x << 2)) & 0x09249249

    code = spread(cells[:, 0]) | (spread(cells[:, 1]) << 1) | (spread(cells[:, 2]) << 2)
    return np.argsort(code, kind="stable")


def polygon_distance_sq(points: np.ndarray, cage_points: np.ndarray, topology: CageTopology) -> np.ndarray:
    """Squared distance (N, F) from points to each face polygon: minimum over its fan triangles. Dense."""
    cage = _check_points(cage_points, topology, "cage_points")
    origin = cage.mean(axis=0)
    local = cage - origin
    fan, _ = topology.fan_triangles()
    table = _triangle_table(*(local[fan[:, k]] for k in range(3)))
    starts = np.cumsum(topology.loop_total - 2) - (topology.loop_total - 2)
    d2 = _distance_sq_block(np.asarray(points, dtype=np.float64) - origin, table)
    return np.minimum.reduceat(d2, starts, axis=1)


def nearest_faces(
    points: np.ndarray, cage_points: np.ndarray, topology: CageTopology, width: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every face whose polygon is within `width` of each point's nearest face:
    (point (P,), face (P,), distance (P,)), grouped by point, faces increasing within a point, so
    d_f(p) ≤ min_g d_g(p) + width for every pair and every such face is listed.

    Exact distances are taken only for faces that bounding spheres cannot rule out: with s_f the
    vertex mean, ρ_f the largest |p_j − s_f| over the face's vertices and δ_f = d_f(s_f),
    |p − s_f| − ρ_f ≤ d_f(p) ≤ |p − s_f| + δ_f, so with U(p) = min_f (|p − s_f| + δ_f) a face
    whose lower bound exceeds U(p) + width is not within width of the nearest. Memory is
    O(BATCH_ELEMENTS) per chunk of points.
    """
    cage = _check_points(cage_points, topology, "cage_points")
    fields = _CageFields.build(cage, topology)
    local = np.asarray(points, dtype=np.float64).reshape(-1, 3) - fields.origin
    vertex, owner = topology.corners()
    radius = np.zeros(topology.n_faces)
    np.maximum.at(radius, owner, _norm(fields.centers[owner] - (cage[vertex] - fields.origin)))
    F = topology.n_faces
    slack = BOUND_SLACK * fields.size
    centre_sq = np.einsum("fi,fi->f", fields.centers, fields.centers)
    out_p, out_f, out_d = [], [], []
    step = max(1, BATCH_ELEMENTS // F)
    for lo in range(0, local.shape[0], step):
        p = local[lo : lo + step]
        dist_sq = np.einsum("ci,ci->c", p, p)[:, None] - 2.0 * (p @ fields.centers.T) + centre_sq
        centre = np.sqrt(np.maximum(dist_sq, 0.0))
        bound = (centre + fields.reach).min(axis=1, keepdims=True) + (width + slack)
        c, f = np.nonzero(centre - radius <= bound)
        count = fields.fan_count[f]
        first = np.cumsum(count) - count
        pair_of_tri = np.repeat(np.arange(f.size), count)
        tri = fields.fan_start[f][pair_of_tri] + (np.arange(pair_of_tri.size) - first[pair_of_tri])
        d2 = _pair_distance_sq(p[c[pair_of_tri]], fields.table[:, tri])
        d = np.sqrt(np.minimum.reduceat(d2, first)) if d2.size else d2
        nearest = np.full(p.shape[0], np.inf)
        np.minimum.at(nearest, c, d)
        close = d <= nearest[c] + width
        out_p.append(c[close] + lo)
        out_f.append(f[close])
        out_d.append(d[close])
    if not out_p:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(0)
    return np.concatenate(out_p), np.concatenate(out_f), np.concatenate(out_d)


def _dot3(x: Sequence[np.ndarray], y: Sequence[np.ndarray]) -> np.ndarray:
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _chunk_candidates(
    fields: _CageFields, q: np.ndarray, rho: np.ndarray, k: int, half_space: bool
) -> np.ndarray:
    """(C, F) bool: faces that can be among the k nearest allowed faces of some point within rho (C,)
    of q (C, 3), one row per chunk of points.

    Every point of a chunk is within dist(q, box_f) − ρ of face f at least and |q − s_f| + δ_f + ρ
    at most. Faces whose inner half-space holds the chunk's whole sphere are allowed for all its
    points, so the k-th smallest of their upper bounds, τ, bounds every point's k-th nearest allowed
    distance; faces with a lower bound above τ are dropped. A chunk with fewer than k such faces keeps
    all faces."""
    F = fields.centers.shape[0]
    coords = (q @ fields.frame.reshape(-1, 3).T).reshape(-1, F, 3)
    gap = np.maximum(np.maximum(fields.lo - coords, coords - fields.hi), 0.0)
    lower = np.sqrt(np.einsum("cfk,cfk->cf", gap, gap)) - rho[:, None]
    centre_sq = (np.einsum("ci,ci->c", q, q)[:, None] - 2.0 * (q @ fields.centers.T)
                 + np.einsum("fi,fi->f", fields.centers, fields.centers))
    upper = np.sqrt(np.maximum(centre_sq, 0.0)) + (fields.reach + rho[:, None])
    if half_space:
        safe = coords[:, :, 2] - fields.plane_offsets + rho[:, None] <= HALF_SPACE_TOL * fields.size
        upper = np.where(safe, upper, np.inf)
    tau = np.partition(upper, k - 1, axis=1)[:, k - 1]
    return lower <= tau[:, None] + BOUND_SLACK * fields.size


def half_space_ramp(elevation: np.ndarray) -> np.ndarray:
    """r(s) = 1 for s ≤ 0, 1 − 3t² + 2t³ (t = s/HALF_SPACE_BAND) up to s = HALF_SPACE_BAND, 0 above:
    C¹ and decreasing; s = (height above the face plane) / (distance to the face) ∈ [−1, 1]."""
    t = np.clip(np.asarray(elevation, dtype=np.float64) / HALF_SPACE_BAND, 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def _batch_weights(
    local: np.ndarray,
    rows: np.ndarray,
    slots: np.ndarray,
    fields: _CageFields,
    k: int,
    exponent: float,
    half_space: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weights of a batch of chunks: rows (B, C) point indices (−1 = padding), slots (B, M) candidate
    faces in increasing order (−1 = padding). Returns (points (R,), face indices (R, k), values (R, k)).

    The M = max(k + 1, TOTAL_FACES) largest weights are needed (continuous truncation subtracts the
    (k+1)-th, and T is the sum of the M largest). Per point, the M-th smallest upper bound over its
    candidates with full weight (ramp 1: in the face's inner half-space), τ_p, bounds its M-th nearest
    such distance; no weight is above d^(−p) (the ramp is ≤ 1), so only candidates with
    dist(p, box_f) ≤ τ_p get exact distances. Kept pairs are listed point by point in increasing face
    order, so ties break by face index as over all faces. The last column of values is the pooled
    weight λ (index F)."""
    size = fields.size
    real_slot = slots >= 0
    f = np.where(real_slot, slots, 0)
    p = local[np.where(rows >= 0, rows, rows.max())]  # (B, C, 3)
    pc = [p[:, :, i, None] for i in range(3)]  # (B, C, 1) each
    frame = fields.frame[f]  # (B, M, 3, 3)
    box_sq = None
    coords = []
    for axis in range(3):
        c = _dot3(pc, [frame[:, None, :, axis, i] for i in range(3)])  # (B, C, M)
        lo, hi = fields.lo[f, axis][:, None, :], fields.hi[f, axis][:, None, :]
        gap = np.maximum(np.maximum(lo - c, c - hi), 0.0)
        box_sq = gap * gap if box_sq is None else box_sq + gap * gap
        coords.append(c)
    centre = fields.centers[f]
    diff = [pc[i] - centre[:, None, :, i] for i in range(3)]
    upper = np.sqrt(_dot3(diff, diff)) + fields.reach[f][:, None, :]
    eligible = np.broadcast_to(real_slot[:, None, :], upper.shape)
    height = coords[2] - fields.plane_offsets[f][:, None, :] - HALF_SPACE_TOL * size
    full = eligible
    plain = np.zeros(upper.shape[:2], dtype=bool)
    if half_space:
        full = (height <= 0.0) & eligible
        # A vertex outside every face's half-space (only possible outside an open or broken cage,
        # where every face is a candidate) keeps plain inverse-distance weights over all faces.
        plain = ~full.any(axis=2)
        full = full | (eligible & plain[:, :, None])
    measured = min(max(k + 1, TOTAL_FACES), int(real_slot.sum(axis=1).max(initial=0)) or 1)
    tau = np.partition(np.where(full, upper, np.inf), measured - 1, axis=2)[:, :, measured - 1]
    floor = DISTANCE_FLOOR * size
    tau = np.maximum(tau, floor) + BOUND_SLACK * size
    keep = eligible & (box_sq <= (tau * tau)[:, :, None]) & (rows >= 0)[:, :, None]

    b, c, m = np.nonzero(keep)
    pair_point = rows[b, c]
    pair_face = slots[b, m]
    # exact distance to each kept polygon: minimum over its fan triangles
    count = fields.fan_count[pair_face]
    if np.all(count == 1):
        d2 = _pair_distance_sq(local[pair_point], fields.table[:, fields.fan_start[pair_face]])
    else:
        first = np.cumsum(count) - count
        pair_of_tri = np.repeat(np.arange(pair_face.size), count)
        tri = fields.fan_start[pair_face][pair_of_tri] + (np.arange(pair_of_tri.size) - first[pair_of_tri])
        d2 = _pair_distance_sq(local[pair_point[pair_of_tri]], fields.table[:, tri])
        d2 = np.minimum.reduceat(d2, first) if d2.size else d2
    d2 = np.maximum(d2, floor * floor)
    w = 1.0 / d2 if exponent == 2.0 else d2 ** (-0.5 * exponent)
    if half_space:
        ramped = ~plain[b, c]
        w[ramped] *= half_space_ramp(np.maximum(height[b, c, m][ramped], 0.0) / np.sqrt(d2[ramped]))

    # one row per point (kept pairs are grouped by point), padded with zero weights
    per_row = keep.sum(axis=2).ravel()
    row_start = np.cumsum(per_row) - per_row
    row_of_pair = b * rows.shape[1] + c
    column = np.arange(pair_face.size) - row_start[row_of_pair]
    width = max(int(per_row.max()) if per_row.size else 0, k + 1)
    W = np.zeros((per_row.size, width))
    faces = np.zeros((per_row.size, width), dtype=np.int32)
    W[row_of_pair, column] = w
    faces[row_of_pair, column] = pair_face
    # D = max(S, c T), T the weight of the M nearest faces (TOTAL_FACES); the pooled rest goes to
    # index F here, to pooled nodes in core.cage.pool.cage_weights
    M = min(max(k + 1, TOTAL_FACES), width)
    total = -np.partition(-W, M - 1, axis=1)[:, :M].sum(axis=1)
    cols, vals, pooled = truncate(W, k, total=total, floor=POOL_FLOOR, with_pooled=True)
    idx = np.take_along_axis(faces, cols, axis=1)
    idx = np.where(vals > 0.0, idx, idx[:, :1])  # zero-weight slots point at the row's best face
    real = rows.ravel() >= 0
    idx = np.concatenate([idx, np.full((len(idx), 1), fields.centers.shape[0], dtype=idx.dtype)], axis=1)
    vals = np.concatenate([vals, pooled[:, None]], axis=1)
    return rows.ravel()[real], idx[real], vals[real]


def _group_weights(
    local: np.ndarray, rows: np.ndarray, fields: _CageFields, k: int, exponent: float, half_space: bool
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(points, indices, values) of the chunks rows (B, C) (−1 = padding), batch by batch: chunks
    with similar candidate counts are measured together, so little of a batch is padding."""
    C = rows.shape[1]
    measured = min(max(k + 1, TOTAL_FACES), fields.centers.shape[0])  # the (k+1)-th weight, and T
    candidates = _chunk_candidates(fields, *_chunk_spheres(local, rows), measured, half_space)
    count = candidates.sum(axis=1)
    order = np.argsort(count, kind="stable")
    start = 0
    while start < order.size:
        stop, total = start + 1, int(count[order[start]])
        while stop < order.size:
            # padded size of the batch if it took one more chunk; at most a quarter is padding
            width = int(count[order[stop]])
            padded = (stop - start + 1) * width
            if padded * C > BATCH_ELEMENTS or padded > 1.25 * (total + width):
                break
            total += width
            stop += 1
        batch = order[start:stop]
        width = max(int(count[batch[-1]]), measured)  # ≤ count unless rounding defeats the slack
        r, f = np.nonzero(candidates[batch])
        slots = np.full((batch.size, width), -1, dtype=np.intp)
        slots[r, np.arange(r.size) - (np.cumsum(count[batch]) - count[batch])[r]] = f
        yield _batch_weights(local, rows[batch], slots, fields, k, exponent, half_space)
        start = stop


def _chunk_spheres(local: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centres (B, 3), radii (B,)) of bounding spheres of the chunks' points (rows (B, C), −1 padding)."""
    p = local[np.where(rows >= 0, rows, rows[:, :1])]  # padding repeats the chunk's first point
    q = 0.5 * (p.min(axis=1) + p.max(axis=1))
    rho = np.sqrt(np.einsum("bci,bci->bc", p - q[:, None], p - q[:, None]).max(axis=1))
    return q, rho


def face_weights(
    points: np.ndarray,
    cage_points: np.ndarray,
    topology: CageTopology,
    *,
    exponent: float = 2.0,
    half_space: bool = True,
    k: int = 8,
    chunk_size: int = 64,
) -> tuple[np.ndarray, np.ndarray]:
    """The faces' part of the cage weights (core.cage.pool.cage_weights adds where the rest is pooled):
    (indices (N, K or K + 1) int32, values float64), K = min(k, F), rows sum to 1 (column K, index F,
    when present: the pooled weight λ, which core.cage.pool.cage_weights shares among pooled nodes).

    w_f(v) = d_f(v)^(−exponent), d_f the exact distance from v to face f's polygon (minimum over its
    fan triangles), floored at DISTANCE_FLOOR × cage size. With half_space (MATH.md §10, made
    continuous) the weight fades to 0 in the outer half-space of f: w_f is multiplied by
    `half_space_ramp`(z_f/d_f), z_f = N̂_f·(v − c_f) − HALF_SPACE_TOL × cage size (N_f the Newell
    normal, c_f the face centroid), so it is full up to f's plane and 0 from HALF_SPACE_BAND above
    it (a hard cut would jump where the plane of a face of a non-convex cage crosses its inside).
    A vertex cut off from every face (outside an open or broken cage) falls back to plain inverse
    distance, so no row is zero. Truncation to the K largest is continuous with a bounded slope
    (weights.truncate, MATH.md §12: the (K+1)-th weight, measured exactly, is subtracted and the
    rest divided by D = max(S, c·T), c = weights.POOL_FLOOR, T the weight of the TOTAL_FACES
    nearest faces (K + 1 when more); zero-weight slots repeat the row's first index), so no weight
    jumps or swings where faces swap ranks or tie; what the kept faces leave of 1 (near such ties)
    is λ.

    Only distances that can matter are measured exactly: vertices are grouped in spatially sorted
    chunks of chunk_size, each chunk keeps the faces its bounding sphere can reach
    (`_chunk_candidates`), and each vertex the candidates its own bounds cannot rule out
    (`_batch_weights`). Memory is O(N·K + BATCH_ELEMENTS). The result does not depend on chunk_size,
    except which of several faces exactly tied at the K-th weight is kept.
    """
    cage = _check_points(cage_points, topology, "cage_points")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(cage))):
        raise ValueError("points or cage contain non-finite coordinates")
    if not exponent > 0.0:
        raise ValueError(f"exponent must be positive, got {exponent}")
    if k < 1 or chunk_size < 1:
        raise ValueError(f"k and chunk_size must be at least 1, got {k} and {chunk_size}")
    K = min(int(k), topology.n_faces)
    N = points.shape[0]
    indices = np.zeros((N, K + 1), dtype=np.int32)  # column K: the pooled control (index F)
    values = np.zeros((N, K + 1), dtype=np.float64)
    if N == 0:
        return indices[:, :K].copy(), values[:, :K].copy()
    fields = _CageFields.build(cage, topology)
    local = points - fields.origin
    C = int(chunk_size)
    n_chunks = -(-N // C)
    chunk_rows = np.full(n_chunks * C, -1, dtype=np.intp)
    chunk_rows[:N] = _morton_order(local)
    chunk_rows = chunk_rows.reshape(n_chunks, C)
    group = max(1, 4 * BATCH_ELEMENTS // topology.n_faces)
    groups = [chunk_rows[lo : lo + group] for lo in range(0, n_chunks, group)]

    def run(rows: np.ndarray) -> None:
        for pts, idx, val in _group_weights(local, rows, fields, K, exponent, half_space):
            indices[pts], values[pts] = idx, val  # groups own disjoint rows

    threads = min(default_threads(), len(groups))
    if threads == 1:
        for rows in groups:
            run(rows)
    else:
        # The work is large numpy calls, which release the GIL.
        with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="affine_cage_weights") as pool:
            for future in [pool.submit(run, rows) for rows in groups]:
                future.result()
    if not np.any(values[:, K]):  # nothing pooled: the faces' weights sum to 1 on every row
        return indices[:, :K].copy(), values[:, :K].copy()
    return indices, values
