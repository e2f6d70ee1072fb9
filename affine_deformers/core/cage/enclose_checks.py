"""What a made cage must be, checked: closed, 2-manifold, outward, free of self-intersections, and
every target point inside it by a margin (core/cage/enclose.py makes the cage; the tests check it
with these, and these on deliberately broken cages).

Winding number. For a closed triangulated surface the generalised winding number of a point x is

    W(x) = Σ_t Ω_t(x) / 4π,   tan(Ω_t/2) = a·(b × c) / (|a||b||c| + (a·b)|c| + (a·c)|b| + (b·c)|a|)

(Van Oosterom & Strackee; a, b, c the triangle's corners relative to x): an integer off the surface,
1 inside a closed outward surface, 0 outside. W is constant on every connected set that misses the
surface, which `enclosure_report` uses to evaluate it rigorously at a few points only: if the cage
is farther than ρ from the centre c of a cell of half-diagonal ρ, the ball B(c, ρ) holds the cell
and misses the cage, so every point in the cell has the winding number of c.

Self-intersection (`self_intersections`). Triangles whose boxes overlap are paired through a
spatial hash and tested by how many corners they share:
- none: they meet iff an edge of one crosses the other's plane strictly inside the other (closed
  test), or their distance (the least of 6 vertex–triangle and 9 edge–edge distances) is within
  TOUCH_TOL of the cage size — every contact, coplanar ones included, is one of these;
- one corner v: the intersection of two non-coplanar triangles is a segment from v along the line
  L = n₁ × n₂, so they meet beyond v iff ±L points into both corners' sectors at v; coplanar ones
  iff the sectors overlap;
- an edge: only a fold can make them overlap — the far corner of one in the other's plane on the
  same side of the edge.

Manifold vertices (`pinched_vertices`): the corners around a vertex, each followed by the corner of
the face across its outgoing edge, form cycles; a 2-manifold has one cycle per vertex. Counted with
pointer doubling (min label over the cycle, log₂ of the valence rounds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .checks import check_cage
from .topology import CageTopology

#: Distances within this fraction of the cage size count as contact (coplanar overlap, touching).
TOUCH_TOL = 1e-9

#: Cosine within this of 1 makes two triangles coplanar (shared corner) or folded (shared edge).
COPLANAR_TOL = 1e-12

#: Elements of the (queries × triangles) blocks of the winding number and distance sums.
BLOCK_ELEMENTS = 1 << 20


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a × b over the last axis (np.cross's axis shuffling costs more than the arithmetic here)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def quad_triangles(quads: np.ndarray, diagonal: int = 0) -> np.ndarray:
    """(2F, 3) triangles of quads (F, 4): split along v0–v2 (diagonal 0, Blender's fan and the
    cage deformer's) or v1–v3 (diagonal 1), orientation kept."""
    q = np.asarray(quads)
    if diagonal == 0:
        return np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    return np.concatenate([q[:, [0, 1, 3]], q[:, [1, 2, 3]]])


def quad_topology(quads: np.ndarray, n_vertices: int) -> CageTopology:
    """The quads as Blender's flat polygon arrays."""
    q = np.asarray(quads, dtype=np.intp)
    total = np.full(q.shape[0], 4, dtype=np.intp)
    return CageTopology.from_arrays(q.reshape(-1), 4 * np.arange(q.shape[0]), total, n_vertices)


# --- point–triangle, segment–segment, winding --------------------------------------------------


def pair_distance_sq(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Squared distance from p to triangle (a, b, c), row by row (all (P, 3)): the plane distance
    when p projects inside the triangle (the signs of n·((b−a)×(p−a)) and its cyclic versions),
    else the least distance to its three edges; degenerate triangles fall to the edges."""
    n = _cross(b - a, c - a)
    nn = _dot(n, n)
    inside = nn > 0.0
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= _dot(_cross(v - u, p - u), n) >= 0.0
    plane = _dot(p - a, n) ** 2 / np.where(inside, nn, 1.0)
    edge = np.minimum(np.minimum(_point_segment_sq(p, a, b), _point_segment_sq(p, b, c)),
                      _point_segment_sq(p, c, a))
    return np.where(inside, np.minimum(plane, edge), edge)


def _point_segment_sq(p: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    d = v - u
    dd = _dot(d, d)
    t = np.clip(_dot(p - u, d) / np.where(dd > 0.0, dd, 1.0), 0.0, 1.0)
    r = p - u - t[:, None] * d
    return _dot(r, r)


def segment_distance_sq(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Squared distance between segments [p1, q1] and [p2, q2], row by row: the closest parameters
    s, t of the two lines, s clamped to [0, 1], t from s and clamped, s again from the clamped t
    (exact for segments; parallel ones take s = 0)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    c, f = _dot(d1, r), _dot(d2, r)
    safe_a, safe_e = np.where(a > 0.0, a, 1.0), np.where(e > 0.0, e, 1.0)
    denom = a * e - b * b
    s = np.where(denom > 1e-14 * a * e, np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / safe_e
    s = np.where(t < 0.0, np.clip(-c / safe_a, 0, 1), np.where(t > 1.0, np.clip((b - c) / safe_a, 0, 1), s))
    t = np.clip(t, 0.0, 1.0)
    s = np.where(a > 0.0, s, 0.0)
    t = np.where(e > 0.0, t, 0.0)
    w = r + s[:, None] * d1 - t[:, None] * d2
    return _dot(w, w)


def winding_numbers(queries: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Generalised winding number (Q,) of each query point with respect to the triangles: the sum of
    the triangles' signed solid angles over 4π, in blocks of BLOCK_ELEMENTS (memory stays bounded)."""
    q = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]  # (T, 3, 3)
    out = np.empty(q.shape[0])
    step = max(1, BLOCK_ELEMENTS // max(corners.shape[0], 1))
    for start in range(0, q.shape[0], step):
        rel = corners[None, :, :, :] - q[start:start + step, None, None, :]  # (Qc, T, 3, 3)
        a, b, c = rel[..., 0, :], rel[..., 1, :], rel[..., 2, :]
        la, lb, lc = (np.sqrt(_dot(x, x)) for x in (a, b, c))
        num = _dot(a, _cross(b, c))
        den = la * lb * lc + _dot(a, b) * lc + _dot(a, c) * lb + _dot(b, c) * la
        out[start:start + step] = np.arctan2(num, den).sum(axis=1) / (2.0 * np.pi)
    return out


# --- spatial pairing ----------------------------------------------------------------------------


def _cell_keys(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(item, key) for every grid cell each box [lo, hi] (integer cell ranges, (n, 3)) covers."""
    span = hi - lo + 1
    count = span.prod(axis=1)
    item = np.repeat(np.arange(lo.shape[0]), count)
    j = np.arange(item.size) - np.repeat(np.cumsum(count) - count, count)
    sy, sz = span[item, 1], span[item, 2]
    cell = lo[item] + np.stack([j // (sy * sz), (j // sz) % sy, j % sz], axis=1)
    return item, (cell[:, 0] * (1 << 21) + cell[:, 1]) * (1 << 21) + cell[:, 2]


def box_pairs(lo: np.ndarray, hi: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i < j) of boxes (n, 3) lo..hi that overlap (closed), found through a hash of grid
    cells of the given size: the boxes sharing a cell are paired, duplicates dropped."""
    if lo.shape[0] < 2:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    base = lo.min(axis=0)
    ilo = np.floor((lo - base) / cell).astype(np.int64)
    ihi = np.floor((hi - base) / cell).astype(np.int64)
    item, key = _cell_keys(ilo, ihi)
    order = np.lexsort((item, key))
    item, key = item[order], key[order]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    size = np.diff(np.r_[start, key.size])
    rank = np.arange(key.size) - np.repeat(start, size)
    later = np.repeat(size, size) - rank - 1  # entries after this one in its cell
    first = np.repeat(np.arange(key.size), later)
    offset = np.arange(first.size) - np.repeat(np.cumsum(later) - later, later)
    i, j = item[first], item[first + 1 + offset]
    pair = np.unique(np.minimum(i, j) * lo.shape[0] + np.maximum(i, j))
    i, j = pair // lo.shape[0], pair % lo.shape[0]
    keep = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    return i[keep], j[keep]


# --- triangle–triangle intersection -------------------------------------------------------------


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(b − a)·((c − a) × (d − a)): six times the signed volume of the tetrahedron."""
    return _dot(b - a, _cross(c - a, d - a))


def _separated(t1: np.ndarray, t2: np.ndarray, tol: float) -> np.ndarray:
    """Rows where t2's corners all lie farther than tol on one side of t1's plane."""
    n = _cross(t1[:, 1] - t1[:, 0], t1[:, 2] - t1[:, 0])
    reach = tol * np.sqrt(_dot(n, n))
    s = np.stack([_dot(t2[:, k] - t1[:, 0], n) for k in range(3)], axis=1)
    return np.all(s > reach[:, None], axis=1) | np.all(s < -reach[:, None], axis=1)


def _disjoint_meet(t1: np.ndarray, t2: np.ndarray, tol: float) -> np.ndarray:
    """Rows of (P, 3, 3) triangle pairs with no shared corner that intersect or come within tol
    (pairs with one wholly beyond tol on one side of the other's plane are skipped first)."""
    hit = np.zeros(t1.shape[0], dtype=bool)
    rows = np.flatnonzero(~(_separated(t1, t2, tol) | _separated(t2, t1, tol)))
    if rows.size:
        hit[rows] = triangle_distance(t1[rows], t2[rows]) <= tol
    return hit


def triangle_distance(t1: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Distance (P,) between triangles t1, t2 (P, 3, 3): 0 when an edge of one crosses the other's
    plane strictly inside it (closed test), else the least of the 6 vertex–triangle and 9 edge–edge
    distances (which is 0 for every other contact, coplanar overlaps included)."""
    d2 = np.full(t1.shape[0], np.inf)
    crossing = np.zeros(t1.shape[0], dtype=bool)
    for s, t in ((t1, t2), (t2, t1)):
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        for k in range(3):
            p, q = s[:, k], s[:, (k + 1) % 3]
            sp, sq = _orient(a, b, c, p), _orient(a, b, c, q)
            o1, o2, o3 = _orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)
            same = ((o1 >= 0) & (o2 >= 0) & (o3 >= 0)) | ((o1 <= 0) & (o2 <= 0) & (o3 <= 0))
            crossing |= (((sp > 0) & (sq < 0)) | ((sp < 0) & (sq > 0))) & same
            d2 = np.minimum(d2, pair_distance_sq(p, a, b, c))
    for k in range(3):
        for m in range(3):
            near = segment_distance_sq(t1[:, k], t1[:, (k + 1) % 3], t2[:, m], t2[:, (m + 1) % 3])
            d2 = np.minimum(d2, near)
    return np.where(crossing, 0.0, np.sqrt(d2))


def _in_sector(u: np.ndarray, e: np.ndarray, f: np.ndarray, n: np.ndarray, strict: bool) -> np.ndarray:
    """Direction u within the sector spanned by e, f (n = e × f): u = αe + βf, α, β ≥ 0 (> 0)."""
    s1, s2 = _dot(_cross(e, u), n), _dot(_cross(u, f), n)
    return (s1 > 0) & (s2 > 0) if strict else (s1 >= 0) & (s2 >= 0)


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of `v` scaled to length 1."""
    return v / np.linalg.norm(v, axis=1)[:, None]


def _corner_meet(v: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Triangles (v, a, b) and (v, c, d) sharing only corner v: do they meet anywhere else?"""
    e1, f1, e2, f2 = t1[:, 0] - v, t1[:, 1] - v, t2[:, 0] - v, t2[:, 1] - v
    n1, n2 = _cross(e1, f1), _cross(e2, f2)
    line = _cross(n1, n2)
    scale = _dot(n1, n1) * _dot(n2, n2)
    coplanar = _dot(line, line) <= COPLANAR_TOL * scale
    in1, out1 = _in_sector(line, e1, f1, n1, False), _in_sector(-line, e1, f1, n1, False)
    in2, out2 = _in_sector(line, e2, f2, n2, False), _in_sector(-line, e2, f2, n2, False)
    crossing = (in1 & in2) | (out1 & out2)
    # coplanar: the sectors overlap iff an edge ray of one lies strictly inside the other, or both
    # bisectors coincide (identical sectors); n2 is flipped to n1's side for a folded pair
    g2 = np.where((_dot(n1, n2) < 0)[:, None], -n2, n2)
    e2s, f2s = np.where((_dot(n1, n2) < 0)[:, None], f2, e2), np.where((_dot(n1, n2) < 0)[:, None], e2, f2)
    overlap = (_in_sector(e2, e1, f1, n1, True) | _in_sector(f2, e1, f1, n1, True)
               | _in_sector(e1, e2s, f2s, g2, True) | _in_sector(f1, e2s, f2s, g2, True)
               | _in_sector(_unit(e2) + _unit(f2), e1, f1, n1, True))
    return np.where(coplanar, overlap, crossing)


def _edge_meet(u: np.ndarray, w: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Triangles (u, w, a) and (w, u, b) sharing edge uw: folded flat onto each other?"""
    n1, m = _cross(w - u, a - u), _cross(w - u, b - u)
    along = _dot(n1, m)
    return (along > 0) & (_dot(_cross(n1, m), _cross(n1, m)) <= COPLANAR_TOL * _dot(n1, n1) * _dot(m, m))


def triangle_pairs_meet(vertices: np.ndarray, triangles: np.ndarray, i: np.ndarray, j: np.ndarray,
                        tol: float) -> np.ndarray:
    """For pairs (i, j) of triangles, whether they meet other than along what they share (module
    docstring); triangles without a common corner also meet when closer than tol."""
    x = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.intp)
    corners = x[tri]
    shared = (tri[i][:, :, None] == tri[j][:, None, :])  # (P, 3, 3)
    count = shared.sum(axis=(1, 2))
    hit = count == 3  # the same triangle twice
    rows = np.flatnonzero(count == 0)
    hit[rows] = _disjoint_meet(corners[i[rows]], corners[j[rows]], tol)
    rows = np.flatnonzero(count == 1)
    if rows.size:
        k1 = shared[rows].any(axis=2).argmax(axis=1)  # the shared corner's position in each
        k2 = shared[rows].any(axis=1).argmax(axis=1)
        r = np.arange(rows.size)
        c1, c2 = corners[i[rows]], corners[j[rows]]
        t1 = np.stack([c1[r, (k1 + 1) % 3], c1[r, (k1 + 2) % 3]], axis=1)
        t2 = np.stack([c2[r, (k2 + 1) % 3], c2[r, (k2 + 2) % 3]], axis=1)
        hit[rows] = _corner_meet(c1[r, k1], t1, t2)
    rows = np.flatnonzero(count == 2)
    if rows.size:
        far1 = (~shared[rows].any(axis=2)).argmax(axis=1)  # the corner not shared
        far2 = (~shared[rows].any(axis=1)).argmax(axis=1)
        r = np.arange(rows.size)
        c1, c2 = corners[i[rows]], corners[j[rows]]
        hit[rows] = _edge_meet(c1[r, (far1 + 1) % 3], c1[r, (far1 + 2) % 3], c1[r, far1], c2[r, far2])
    return hit


def self_intersections(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(K, 2) pairs of triangles (indices, i < j) that intersect other than along the corners or
    edge they share (see the module docstring); empty for an embedded surface."""
    x = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.intp)
    if tri.shape[0] < 2:
        return np.zeros((0, 2), np.intp)
    corners = x[tri]
    tol = TOUCH_TOL * (float(np.ptp(x, axis=0).max()) or 1.0)
    lo, hi = corners.min(axis=1) - tol, corners.max(axis=1) + tol
    extent = np.sort((hi - lo).max(axis=1))
    i, j = box_pairs(lo, hi, max(float(extent[extent.size // 2]), tol))
    hit = triangle_pairs_meet(x, tri, i, j, tol)
    return np.stack([i[hit], j[hit]], axis=1)


# --- manifold vertices ---------------------------------------------------------------------------


def pinched_vertices(topology: CageTopology) -> np.ndarray:
    """Vertices where the surface is not a disc (two or more fans of faces meet only at the vertex),
    for an edge-manifold, consistently oriented topology: the corners around each vertex, corner →
    the corner at the same vertex in the face across its outgoing edge, form one cycle per fan."""
    vertex, face = topology.corners()
    total = topology.loop_total[face]
    offset = np.repeat(np.cumsum(topology.loop_total) - topology.loop_total, topology.loop_total)
    j = np.arange(vertex.size) - offset
    nxt = vertex[offset + (j + 1) % total]
    prv = vertex[offset + (j - 1) % total]
    n = max(topology.n_vertices, 1)
    have = vertex.astype(np.int64) * n + prv  # a corner is found by (its vertex, the vertex before it)
    order = np.argsort(have)
    want = vertex.astype(np.int64) * n + nxt
    at = np.clip(np.searchsorted(have[order], want), 0, vertex.size - 1)
    if not np.all(have[order][at] == want):
        raise ValueError("pinched_vertices needs a closed, consistently oriented surface")
    jump = order[at]
    label = np.arange(vertex.size)
    valence = np.bincount(vertex, minlength=n)
    for _ in range(int(np.ceil(np.log2(max(int(valence.max()), 2)))) + 1):
        label = np.minimum(label, label[jump])
        jump = jump[jump]
    cycles = np.bincount(vertex[label == np.arange(vertex.size)], minlength=n)
    return np.flatnonzero(cycles > 1)


# --- distances and winding numbers of many points ---------------------------------------------


def query_pairs(queries: np.ndarray, corners: np.ndarray, reach: float | np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs (query, triangle) holding every triangle (T, 3, 3) within `reach` (a number
    or one per query) of a query: the triangles' boxes grown by the largest reach are hashed into
    cells of the triangles' median size, each query is paired with the triangles of its own cell,
    and pairs farther apart than reach plus the triangle's circumradius about its centroid dropped."""
    reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), queries.shape[:1])
    if not queries.shape[0] or not corners.shape[0]:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    grow = float(reach.max())
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    cell = max(float(np.median((hi - lo).max(axis=1))), grow / 2.0, 1e-300)
    base = np.minimum(lo.min(axis=0), queries.min(axis=0)) - grow - cell
    item, key = _cell_keys(np.floor((lo - grow - base) / cell).astype(np.int64),
                           np.floor((hi + grow - base) / cell).astype(np.int64))
    order = np.argsort(key)
    item, key = item[order], key[order]
    qc = np.floor((queries - base) / cell).astype(np.int64)
    qkey = (qc[:, 0] * (1 << 21) + qc[:, 1]) * (1 << 21) + qc[:, 2]
    first, last = np.searchsorted(key, qkey, "left"), np.searchsorted(key, qkey, "right")
    count = last - first
    query = np.repeat(np.arange(queries.shape[0]), count)
    tri = item[np.repeat(first - (np.cumsum(count) - count), count) + np.arange(query.size)]
    centre = corners.mean(axis=1)
    radius = np.sqrt(((corners - centre[:, None, :]) ** 2).sum(axis=2).max(axis=1))
    d = queries[query] - centre[tri]
    keep = _dot(d, d) <= (reach[query] + radius[tri]) ** 2
    return query[keep], tri[keep]


def capped_distances(queries: np.ndarray, corners: np.ndarray, cap: float | np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """min(distance from each query to the triangles (T, 3, 3), cap) (Q,), and the pairs (query,
    triangle, distance) nearer than the query's cap: `query_pairs`' candidates, those whose plane
    alone is beyond the cap dropped, the rest measured exactly."""
    cap = np.broadcast_to(np.asarray(cap, dtype=np.float64), queries.shape[:1])
    query, tri = query_pairs(queries, corners, cap)
    a = corners[:, 0]
    n = _cross(corners[:, 1] - a, corners[:, 2] - a)
    n = n / np.maximum(np.sqrt(_dot(n, n)), 1e-300)[:, None]
    h = _dot(queries[query] - a[tri], n[tri])
    keep = np.abs(h) < cap[query]
    query, tri = query[keep], tri[keep]
    d = np.sqrt(pair_distance_sq(queries[query], corners[tri, 0], corners[tri, 1], corners[tri, 2]))
    best = np.array(cap, dtype=np.float64)
    np.minimum.at(best, query, d)
    close = d < cap[query]
    return best, query[close], tri[close], d[close]


def nearest_within(queries: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                   reach: float) -> np.ndarray:
    """Distance (Q,) from each query to the nearest triangle if that is within `reach`, else inf."""
    q = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]
    best = np.empty(q.shape[0])
    step = max(1, BLOCK_ELEMENTS // 64)
    for start in range(0, q.shape[0], step):
        best[start:start + step] = capped_distances(q[start:start + step], corners, reach)[0]
    return np.where(best < reach, best, np.inf)


@dataclass(frozen=True)
class EnclosureNumbers:
    """Smallest distance from the points to the cage and the range of their winding numbers (for
    each triangulation of the quads), with how many points were evaluated one by one."""

    smallest_distance: float
    winding_min: float
    winding_max: float
    evaluated_points: int
    evaluated_cells: int


def enclosure_numbers(points: np.ndarray, vertices: np.ndarray, triangulations: list[np.ndarray],
                      levels: int = 6) -> EnclosureNumbers:
    """Smallest point–cage distance and winding numbers of every point, rigorous but mostly per cell:

    cells of side s = s₀/2^l (s₀ the triangles' median size) around the points, centre c, half-
    diagonal ρ; d(c) the distance from c to the cage (the triangles of all triangulations). If d(c)
    > ρ, every point of the cell has c's winding number (module docstring); its points are at least
    d(c) − ρ and the cage is at most d(c) + ρ from one of them, so cells whose lower bound exceeds
    the best upper bound so far drop out of the minimum. Points left after the last level are
    measured one by one."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    x = np.asarray(vertices, dtype=np.float64)
    every = np.concatenate(triangulations)
    corners = x[every]
    sample = p[:: max(1, p.shape[0] // 64)]
    d0 = np.sqrt(pair_distance_sq(np.repeat(sample, every.shape[0], axis=0), *(
        np.tile(corners[:, k], (sample.shape[0], 1)) for k in range(3))))
    best = float(d0.min())
    s = float(np.median(np.ptp(corners, axis=1).max(axis=1)))
    base = p.min(axis=0)
    need_w = np.ones(p.shape[0], dtype=bool)
    need_d = np.ones(p.shape[0], dtype=bool)
    query = np.full(p.shape[0], -1)  # each point's row in `centres`, whose winding number it has
    centres: list[np.ndarray] = []
    count = 0
    for _ in range(levels):
        rows = np.flatnonzero(need_w | need_d)
        if rows.size < 256:
            break
        rho = s * np.sqrt(3.0) / 2.0
        cell = np.floor((p[rows] - base) / s).astype(np.int64)
        _key, first, inverse = np.unique((cell[:, 0] << 42) + (cell[:, 1] << 21) + cell[:, 2],
                                        return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
        centre = base + (cell[first] + 0.5) * s
        d = nearest_within(centre, x, every, best + rho)
        best = min(best, float((d + rho).min()))
        take = (d > rho * (1.0 + 1e-9))[inverse] & need_w[rows]
        used, local = np.unique(inverse[take], return_inverse=True)
        centres.append(centre[used])
        query[rows[take]] = count + local.reshape(-1)
        count += used.size
        need_w[rows[take]] = False
        need_d[rows[(d - rho)[inverse] >= best]] = False
        s *= 0.5
    rest = np.flatnonzero(need_w | need_d)
    d = nearest_within(p[rest], x, every, best * (1.0 + 1e-9))
    smallest = float(d[need_d[rest]].min()) if np.any(need_d[rest]) else best
    alone = rest[need_w[rest]]
    centres.append(p[alone])
    query[alone] = count + np.arange(alone.size)
    queries = np.concatenate(centres)
    wmin, wmax = np.inf, -np.inf
    for tri in triangulations:
        w = winding_numbers(queries, x, tri)[query]
        wmin, wmax = min(wmin, float(w.min(initial=np.inf))), max(wmax, float(w.max(initial=-np.inf)))
    return EnclosureNumbers(smallest, wmin, wmax, int(rest.size), int(queries.shape[0] - alone.size))


@dataclass(frozen=True)
class EnclosureReport:
    """Everything `check_enclosure` found; `problems` is empty when the cage is a closed, 2-manifold,
    outward, embedded surface holding every point inside (winding number 1) at least `margin` away."""

    faces: int
    boundary_edges: int
    nonmanifold_edges: int
    misoriented_edges: int
    pinched_vertices: int
    degenerate_faces: int
    signed_volume: float
    self_intersections: int
    smallest_distance: float
    winding_min: float
    winding_max: float
    problems: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.problems


def check_enclosure(points: np.ndarray, vertices: np.ndarray, quads: np.ndarray,
                    margin: float = 0.0) -> EnclosureReport:
    """Check a quad cage (F, 4) around points: closed, 2-manifold (edges and vertices), outward,
    no zero-area face, no self-intersection for either diagonal of the quads, and every point at
    winding number 1 (either diagonal) and at least `margin` from the cage. Never raises for
    geometric problems; they are listed in `problems`."""
    x = np.asarray(vertices, dtype=np.float64)
    q = np.asarray(quads, dtype=np.intp)
    topo = quad_topology(q, x.shape[0])
    report = check_cage(x, topo)
    problems = list(report.problems)
    edges_ok = not (report.boundary_edges or report.nonmanifold_edges or report.misoriented_edges)
    pinched = pinched_vertices(topo).size if edges_ok else 0
    if pinched:
        problems.append(f"cage is non-manifold at {pinched} vertices (faces meet only at a corner)")
    tris = [quad_triangles(q, 0), quad_triangles(q, 1)]
    crossing = sum(self_intersections(x, t).shape[0] for t in tris)
    if crossing:
        problems.append(f"cage intersects itself: {crossing} pairs of triangles")
    numbers = enclosure_numbers(points, x, tris)
    if not (numbers.winding_min > 0.5 and numbers.winding_max < 1.5):
        problems.append(f"points not inside the cage: winding numbers {numbers.winding_min:.3f} to "
                        f"{numbers.winding_max:.3f}")
    if not numbers.smallest_distance >= margin:
        problems.append(f"a point is {numbers.smallest_distance:.3g} from the cage, "
                        f"under the margin {margin:.3g}")
    return EnclosureReport(
        faces=q.shape[0], boundary_edges=report.boundary_edges, nonmanifold_edges=report.nonmanifold_edges,
        misoriented_edges=report.misoriented_edges, pinched_vertices=int(pinched),
        degenerate_faces=int(report.degenerate_faces.size), signed_volume=report.signed_volume,
        self_intersections=int(crossing), smallest_distance=numbers.smallest_distance,
        winding_min=numbers.winding_min, winding_max=numbers.winding_max, problems=tuple(problems))
