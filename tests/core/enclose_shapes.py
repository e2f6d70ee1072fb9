"""Meshes for the made-cage tests and bench (core/cage/enclose.py), built in numpy: UV ellipsoids,
the blob figure of samples/cage_deform.blend at any resolution, a torus, thin cylinders, an open
sheet. Each returns (points (N, 3) float64, triangles (T, 3) int)."""

from __future__ import annotations

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def _grid_triangles(rows: int, cols: int, wrap_cols: bool, offset: int = 0) -> np.ndarray:
    """Two triangles per cell of a rows × cols vertex grid (columns wrapped around when asked)."""
    c = cols if wrap_cols else cols - 1
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(c), indexing="ij")
    a = i * cols + j
    b = i * cols + (j + 1) % cols
    cc, d = a + cols, b + cols
    quads = np.stack([a, b, d, cc], axis=-1).reshape(-1, 4) + offset
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def ellipsoid(center: tuple[float, float, float], radii: tuple[float, float, float], segments: int = 24,
              rings: int = 16, along_x: bool = False) -> Mesh:
    """A closed UV ellipsoid (poles on z, or on x when along_x), outward triangles."""
    theta = np.pi * np.arange(1, rings) / rings
    phi = 2.0 * np.pi * np.arange(segments) / segments
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(ct, (rings - 1, segments))], axis=-1)
    unit = np.concatenate([[[0.0, 0.0, 1.0]], ring.reshape(-1, 3), [[0.0, 0.0, -1.0]]])
    n = unit.shape[0]
    body = _grid_triangles(rings - 1, segments, True, 1)[:, ::-1]  # rows run down from the north pole
    j = np.arange(segments)
    top = np.stack([np.zeros(segments, int), 1 + (j + 1) % segments, 1 + j], axis=1)
    last = 1 + (rings - 2) * segments
    bottom = np.stack([np.full(segments, n - 1), last + j, last + (j + 1) % segments], axis=1)
    tri = np.concatenate([top, body, bottom])
    if along_x:  # poles on the x axis: (x, y, z) ← (z, y, −x) keeps the orientation
        unit = np.stack([unit[:, 2], unit[:, 1], -unit[:, 0]], axis=1)
    return np.asarray(center) + unit * np.asarray(radii), tri


def union(*meshes: Mesh) -> Mesh:
    """Several meshes as one (overlapping, not merged: a non-manifold whole)."""
    points, tris, offset = [], [], 0
    for p, t in meshes:
        points.append(p)
        tris.append(t + offset)
        offset += p.shape[0]
    return np.concatenate(points), np.concatenate(tris)


def blob_figure(segments: int = 24, rings: int = 16) -> Mesh:
    """samples/build_samples.py's figure: body, head, arms along x, legs, eyes (7 + 2 ellipsoids)."""
    parts = [ellipsoid((0.0, 0.0, 1.25), (0.55, 0.42, 0.62), segments, rings),
             ellipsoid((0.0, 0.0, 2.12), (0.36, 0.34, 0.36), segments, rings)]
    for side in (-1.0, 1.0):
        parts.append(ellipsoid((side * 0.98, 0.0, 1.52), (0.55, 0.15, 0.15), segments, rings, along_x=True))
        parts.append(ellipsoid((side * 0.27, 0.0, 0.45), (0.17, 0.17, 0.47), segments, rings))
        parts.append(ellipsoid((side * 0.13, -0.3, 2.2), (0.06, 0.06, 0.06), segments, rings))
    return union(*parts)


def torus(major: float = 1.0, minor: float = 0.3, segments: int = 48, sides: int = 16) -> Mesh:
    """A closed torus around z, outward triangles."""
    u = 2.0 * np.pi * np.arange(segments) / segments
    v = 2.0 * np.pi * np.arange(sides) / sides
    uu, vv = np.meshgrid(u, v, indexing="ij")
    r = major + minor * np.cos(vv)
    p = np.stack([r * np.cos(uu), r * np.sin(uu), minor * np.sin(vv)], axis=-1).reshape(-1, 3)
    t = _grid_triangles(segments + 1, sides, True)
    t = np.where(t >= segments * sides, t - segments * sides, t)  # wrap the rows too
    return p, t


def cylinder(a: tuple[float, float, float], b: tuple[float, float, float], radius: float,
             segments: int = 12, rows: int = 16) -> Mesh:
    """An open tube from a to b (no caps)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = (b - a) / np.linalg.norm(b - a)
    u = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    phi = 2.0 * np.pi * np.arange(segments) / segments
    s = np.linspace(0.0, 1.0, rows)
    ring = radius * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * w)
    p = (a + s[:, None, None] * (b - a) + ring[None]).reshape(-1, 3)
    return p, _grid_triangles(rows, segments, True)


def stick_figure() -> Mesh:
    """Thin limbs: five tubes of radius 0.04 joined at a hip and a shoulder point, 2 units tall."""
    hip, neck = (0.0, 0.0, 0.9), (0.0, 0.0, 1.6)
    return union(cylinder(hip, neck, 0.05), cylinder(hip, (-0.35, 0.0, 0.0), 0.04),
                 cylinder(hip, (0.35, 0.0, 0.0), 0.04), cylinder(neck, (-0.8, 0.0, 1.4), 0.03),
                 cylinder(neck, (0.8, 0.0, 1.4), 0.03), cylinder(neck, (0.0, 0.0, 2.0), 0.04))


def sheet(n: int = 20, size: float = 2.0) -> Mesh:
    """An open, gently curved square sheet (z = 0.1·sin) of n × n vertices."""
    s = np.linspace(-0.5 * size, 0.5 * size, n)
    x, y = np.meshgrid(s, s, indexing="ij")
    p = np.stack([x, y, 0.1 * np.sin(2.0 * x) * np.cos(y)], axis=-1).reshape(-1, 3)
    return p, _grid_triangles(n, n, False)


def figure_130k() -> Mesh:
    """The blob figure at 130,064 vertices (8 ellipsoids of 128 segments × 128 rings)."""
    return blob_figure(segments=128, rings=128)
