"""Cage-field quality against Blender's Mesh Deform: the scenes, the cage edits and the metrics.

Used by tests/blender/test_field_quality.py, bench/suite.py (part b) and docs/make_cage_twist_image.py;
it needs bpy and numpy only (no pytest, nothing of the add-on), so it runs in any bpy process.

Scenes (all objects at the identity transform, so object space = world space):

* 'SUZANNE' — Suzanne subdivided twice (primitive_monkey_add + Subdivision level 2 applied, 7,958
  vertices) inside a box cage with 8×8 quads per side (384 quads) fitted to its bounding box plus
  `SUZANNE_MARGIN` of the largest extent on every side;
* 'CYLINDER' — a capped cylinder (radius 0.5, height 3; 48 segments × 49 rings) inside a coarse
  non-convex cage: a "plus" cross-section (arms of half-width 0.6 reaching ±1.2, re-entrant corners
  at (±0.6, ±0.6), 12 sides) extruded along z in 6 segments, caps of 5 quads each (82 quads).

Cage edits (`edited_cage`), with S the cage size (largest bounding-box extent) and z_c its vertical
centre:

* 'PULL' — one cage vertex moved outwards by PULL_FRACTION·S (`pull_target`): SUZANNE the centre
  of the front (−y) side, in front of the nose; CYLINDER the re-entrant corner (+x, −y) at mid
  height, along its outward diagonal;
* 'TWIST' — every cage vertex with z > z_c turned 45° about the vertical axis through the cage's
  centre (vertices at z = z_c stay, so the cage row just above the middle takes the shear).

Metrics of a displacement field d_v = x'_v − x_v on a mesh (vertices x, edges E):

* roughness p99 — the 99th percentile over vertices of |d_v − mean_{u∈N(v)} d_u| ÷ max_v |d_v|
  (N(v) the edge neighbours): the discrete Laplacian relative to the motion;
* spikes — the number of edges e = (a, b) whose gradient g_e = |d_a − d_b| / |x_a − x_b| exceeds
  10× the median of g over the edges around e: the edges within 45° of e's direction among those
  touching e's endpoints or their neighbours (`aligned_edges_around`), with a noise floor (only
  edges with g_e > 1e-3 · max_E g count). The direction matters because a directional derivative
  of a smooth field varies with direction (a rigid turn about z moves horizontal edges and leaves
  vertical ones): compared with every edge at its endpoints, Mesh Deform's own fields score 6–288
  such "spikes" on these scenes; compared with aligned edges of the 2-ring it scores 0, while a
  seam (a jump across a surface cutting the mesh) still stands out, since the aligned edges beside
  and beyond a cut edge do not cross the seam;
* max |d|;
* for 'TWIST', on the vertices inside the twisted region (z > z_c + one cage cell, where Mesh
  Deform's cage is turned rigidly): the RMS residual of the best rigid fit (Kabsch) ÷ S, and the
  edge-length distortion max |l'/l − 1| over the edges with both ends there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import bmesh
import bpy
import numpy as np

SUZANNE_MARGIN = 0.06  # of the head's largest extent, on every side of the box cage
SUZANNE_CUTS = 7  # 7 cuts per cube edge: 8×8 quads per side, 384 quads
PULL_FRACTION = 0.3  # the pulled cage vertex moves by this fraction of the cage size
TWIST_ANGLE = math.radians(45.0)
SPIKE_RATIO = 10.0  # an edge whose gradient exceeds this many times its neighbours' median
SPIKE_FLOOR = 1e-3  # of the largest edge gradient: below it an edge never counts as a spike
MESH_DEFORM_PRECISION = 5

CASES = ("SUZANNE", "CYLINDER")
EDITS = ("PULL", "TWIST")


# ---------------------------------------------------------------------------------------------- meshes


def link(name: str, mesh: bpy.types.Mesh) -> bpy.types.Object:
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def mesh_from_arrays(name: str, points: np.ndarray, polygons: list[list[int]]) -> bpy.types.Mesh:
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(p) for p in np.asarray(points, dtype=np.float64)], [], polygons)
    mesh.update(calc_edges=True)
    return mesh


def suzanne_mesh(name: str = "Suzanne") -> bpy.types.Mesh:
    """Suzanne with a Subdivision modifier (level 2) applied: 7,958 vertices."""
    bpy.ops.mesh.primitive_monkey_add(size=2.0, location=(0.0, 0.0, 0.0))
    obj = bpy.context.active_object
    mod = obj.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = 2
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = bpy.data.meshes.new_from_object(obj.evaluated_get(depsgraph))
    mesh.name = name
    bpy.data.objects.remove(obj, do_unlink=True)
    bpy.context.view_layer.update()  # no stale entry left in view_layer.objects
    return mesh


def box_mesh(name: str, lo: np.ndarray, hi: np.ndarray, cuts: int) -> bpy.types.Mesh:
    """An axis-aligned box [lo, hi] with `cuts` cuts per edge ((cuts+1)² quads per side), normals out."""
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=2.0)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=cuts, use_grid_fill=True)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    for v in bm.verts:
        v.co = tuple(centre + half * np.array(v.co))
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def cylinder_mesh(name: str = "Cylinder", segments: int = 48, rings: int = 49, radius: float = 0.5,
                  height: float = 3.0) -> bpy.types.Mesh:
    """A capped cylinder along z centred at the origin (the caps are n-gons)."""
    phi = 2.0 * np.pi * np.arange(segments) / segments
    z = np.linspace(-0.5 * height, 0.5 * height, rings)
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    points = np.concatenate([np.broadcast_to(ring, (rings, segments, 2)),
                             np.broadcast_to(z[:, None, None], (rings, segments, 1))], axis=2).reshape(-1, 3)
    j = np.arange(segments)
    polygons = []
    for r in range(rings - 1):
        a = r * segments
        polygons += np.stack([a + j, a + (j + 1) % segments, a + segments + (j + 1) % segments,
                              a + segments + j], axis=1).tolist()
    polygons.append(list(range(segments))[::-1])
    polygons.append(list(range((rings - 1) * segments, rings * segments)))
    return mesh_from_arrays(name, points, polygons)


PLUS_ARM, PLUS_REACH = 0.6, 1.2


def plus_cage_mesh(name: str = "PlusCage", segments: int = 6, height: float = 3.4) -> bpy.types.Mesh:
    """The non-convex 'plus' cage of the CYLINDER case (module docstring), normals out."""
    a, b = PLUS_ARM, PLUS_REACH
    outline = np.array([(a, -a), (b, -a), (b, a), (a, a), (a, b), (-a, b), (-a, a), (-b, a), (-b, -a),
                        (-a, -a), (-a, -b), (a, -b)])  # counter-clockwise seen from +z
    n = len(outline)
    z = np.linspace(-0.5 * height, 0.5 * height, segments + 1)
    points = np.concatenate([np.broadcast_to(outline, (segments + 1, n, 2)),
                             np.broadcast_to(z[:, None, None], (segments + 1, n, 1))], axis=2).reshape(-1, 3)
    polygons = []
    for s in range(segments):
        for j in range(n):
            k = (j + 1) % n
            polygons.append([s * n + j, s * n + k, (s + 1) * n + k, (s + 1) * n + j])
    # caps: the centre square (re-entrant corners 0, 3, 6, 9) and four arms
    squares = [[0, 3, 6, 9], [0, 1, 2, 3], [3, 4, 5, 6], [6, 7, 8, 9], [9, 10, 11, 0]]
    top = segments * n
    for q in squares:
        polygons.append([top + i for i in q])
        polygons.append([i for i in q[::-1]])
    return mesh_from_arrays(name, points, polygons)


# ---------------------------------------------------------------------------------------------- scenes


@dataclass
class Scene:
    """One case: the target's rest vertices and edges, the cage's rest vertices (object = world)."""

    case: str
    target_mesh: bpy.types.Mesh
    cage_mesh: bpy.types.Mesh

    @property
    def rest(self) -> np.ndarray:
        return read_co(self.target_mesh)

    @property
    def edges(self) -> np.ndarray:
        e = np.empty(len(self.target_mesh.edges) * 2, dtype=np.int32)
        self.target_mesh.edges.foreach_get("vertices", e)
        return e.reshape(-1, 2)

    @property
    def cage_rest(self) -> np.ndarray:
        return read_co(self.cage_mesh)


def build_scene(case: str) -> Scene:
    """The meshes of `case` (not linked to the scene; `add_pair` makes the objects)."""
    if case == "SUZANNE":
        target = suzanne_mesh()
        co = read_co(target)
        lo, hi = co.min(axis=0), co.max(axis=0)
        margin = SUZANNE_MARGIN * float((hi - lo).max())
        cage = box_mesh("SuzanneCage", lo - margin, hi + margin, SUZANNE_CUTS)
    elif case == "CYLINDER":
        target, cage = cylinder_mesh(), plus_cage_mesh()
    else:
        raise ValueError(f"unknown case {case!r}")
    return Scene(case, target, cage)


def read_co(mesh: bpy.types.Mesh) -> np.ndarray:
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def write_co(mesh: bpy.types.Mesh, points: np.ndarray) -> None:
    mesh.vertices.foreach_set("co", np.ascontiguousarray(points, dtype=np.float32).ravel())
    mesh.update()


def evaluated(obj: bpy.types.Object) -> np.ndarray:
    ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = ev.to_mesh()
    try:
        return read_co(mesh)
    finally:
        ev.to_mesh_clear()


def add_pair(scene: Scene, suffix: str) -> tuple[bpy.types.Object, bpy.types.Object]:
    """A target object and a cage object of their own (copies of the scene's meshes)."""
    target = link(f"{scene.case.title()}{suffix}", scene.target_mesh.copy())
    cage = link(f"{scene.case.title()}Cage{suffix}", scene.cage_mesh.copy())
    cage.display_type = "WIRE"
    return target, cage


def bind_mesh_deform(target: bpy.types.Object, cage: bpy.types.Object,
                     precision: int = MESH_DEFORM_PRECISION) -> bpy.types.Modifier:
    mod = target.modifiers.new("MeshDeform", "MESH_DEFORM")
    mod.object = cage
    mod.precision = precision
    bpy.context.view_layer.update()
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        result = bpy.ops.object.meshdeform_bind(modifier=mod.name)
    bpy.context.view_layer.update()
    if "FINISHED" not in result or not mod.is_bound:
        raise RuntimeError(f"Mesh Deform bind did not finish ({result}, is_bound={mod.is_bound})")
    return mod


def bind_ours(target: bpy.types.Object, cage: bpy.types.Object, **options) -> object:
    """Our cage deformer at its defaults (the add operator), then `options` set on it."""
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, cage]):
        result = bpy.ops.object.affine_cage_deformer_add()
    if result != {"FINISHED"}:
        raise RuntimeError(f"affine_cage_deformer_add: {result}")
    deformer = target.affine_deformers[len(target.affine_deformers) - 1]
    for key, value in options.items():
        setattr(deformer, key, value)
    return deformer


# ---------------------------------------------------------------------------------------------- edits


def cage_size(cage_rest: np.ndarray) -> float:
    return float(np.ptp(cage_rest, axis=0).max())


def cage_cell(case: str, cage_rest: np.ndarray) -> float:
    """Height of one cage row (the twisted region starts one row above the middle)."""
    rows = {"SUZANNE": SUZANNE_CUTS + 1, "CYLINDER": 6}[case]
    return float(np.ptp(cage_rest[:, 2])) / rows


def pull_target(case: str, cage_rest: np.ndarray) -> tuple[int, np.ndarray]:
    """(cage vertex, unit outward direction) of the 'PULL' edit: SUZANNE the centre of the front (−y)
    side, in front of the nose; CYLINDER the re-entrant corner (+x, −y) at mid height, along its
    outward diagonal."""
    lo, hi = cage_rest.min(axis=0), cage_rest.max(axis=0)
    centre = 0.5 * (lo + hi)
    if case == "SUZANNE":
        spot, direction = np.array([centre[0], lo[1], centre[2]]), np.array([0.0, -1.0, 0.0])
    elif case == "CYLINDER":
        spot = np.array([PLUS_ARM, -PLUS_ARM, centre[2]])
        direction = np.array([1.0, -1.0, 0.0]) / math.sqrt(2.0)
    else:
        raise ValueError(f"unknown case {case!r}")
    return int(np.argmin(np.linalg.norm(cage_rest - spot, axis=1))), direction


def twist_centre(cage_rest: np.ndarray) -> np.ndarray:
    return 0.5 * (cage_rest.min(axis=0) + cage_rest.max(axis=0))


def edited_cage(case: str, edit: str, cage_rest: np.ndarray) -> np.ndarray:
    """The cage vertices after `edit` (module docstring)."""
    out = cage_rest.copy()
    if edit == "PULL":
        vertex, direction = pull_target(case, cage_rest)
        out[vertex] += PULL_FRACTION * cage_size(cage_rest) * direction
    elif edit == "TWIST":
        c = twist_centre(cage_rest)
        top = cage_rest[:, 2] > c[2] + 1e-6 * cage_size(cage_rest)
        out[top] = rotate_z(cage_rest[top], c, TWIST_ANGLE)
    else:
        raise ValueError(f"unknown edit {edit!r}")
    return out


def rotate_z(points: np.ndarray, centre: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (points - centre) @ R.T + centre


def twisted_region(case: str, rest: np.ndarray, cage_rest: np.ndarray) -> np.ndarray:
    """(N,) bool: target vertices above the sheared row (z > z_c + one cage row)."""
    return rest[:, 2] > twist_centre(cage_rest)[2] + cage_cell(case, cage_rest)


# ---------------------------------------------------------------------------------------------- metrics


def neighbour_mean(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Mean of `values` (N, 3) over each vertex's edge neighbours (a vertex without edges: itself)."""
    n = values.shape[0]
    a, b = edges[:, 0], edges[:, 1]
    count = np.bincount(a, minlength=n) + np.bincount(b, minlength=n)
    total = np.stack([np.bincount(a, values[b, k], n) + np.bincount(b, values[a, k], n) for k in range(3)], 1)
    return np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], values)


def roughness(d: np.ndarray, edges: np.ndarray, q: float = 99.0) -> float:
    top = float(np.linalg.norm(d, axis=1).max())
    if top == 0.0:
        return 0.0
    return float(np.percentile(np.linalg.norm(d - neighbour_mean(d, edges), axis=1), q)) / top


def edge_gradients(rest: np.ndarray, d: np.ndarray, edges: np.ndarray) -> np.ndarray:
    a, b = edges[:, 0], edges[:, 1]
    return np.linalg.norm(d[a] - d[b], axis=1) / np.linalg.norm(rest[a] - rest[b], axis=1)


def incident_edges(edges: np.ndarray, n_vertices: int) -> np.ndarray:
    """(N, max valence) the edges at each vertex, −1 padded."""
    ends = edges.ravel()  # incidence i belongs to edge i // 2
    order = np.argsort(ends, kind="stable")
    per_vertex = np.bincount(ends, minlength=n_vertices)
    table = np.full((n_vertices, max(int(per_vertex.max(initial=0)), 1)), -1, dtype=np.int64)
    table[ends[order], np.arange(ends.size) - (np.cumsum(per_vertex) - per_vertex)[ends[order]]] = order // 2
    return table


def aligned_edges_around(rest: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E, M) for each edge e the other edges within 45° of its direction that touch e's endpoints or
    their neighbours (−1 padded, each listed once); all of those edges when none is aligned."""
    n, E = rest.shape[0], edges.shape[0]
    table = incident_edges(edges, n)
    other = np.where(table >= 0, edges[np.maximum(table, 0)].sum(axis=-1) - np.arange(n)[:, None], -1)
    verts = np.concatenate([other[edges[:, 0]], other[edges[:, 1]], edges], axis=1)  # 2-ring of e
    around = np.where(verts[..., None] >= 0, table[np.maximum(verts, 0)], -1).reshape(E, -1)
    around = np.where(around == np.arange(E)[:, None], -1, np.sort(around, axis=1))
    around[:, 1:] = np.where(around[:, 1:] == around[:, :-1], -1, around[:, 1:])
    u = rest[edges[:, 1]] - rest[edges[:, 0]]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    cos = np.abs(np.einsum("ei,eki->ek", u, u[np.maximum(around, 0)]))
    aligned = (around >= 0) & (cos >= math.cos(math.pi / 4))
    use = np.where(aligned.any(axis=1, keepdims=True), aligned, around >= 0)
    return np.where(use, around, -1)


def spikes(rest: np.ndarray, d: np.ndarray, edges: np.ndarray) -> int:
    """Edges whose gradient exceeds SPIKE_RATIO × the median over `aligned_edges_around` (module
    docstring), above the SPIKE_FLOOR noise floor."""
    g = edge_gradients(rest, d, edges)
    if not g.size or g.max() == 0.0:
        return 0
    around = aligned_edges_around(rest, edges)
    med = np.nanmedian(np.where(around >= 0, g[np.maximum(around, 0)], np.nan), axis=1)
    hot = (g > SPIKE_RATIO * med) & (g > SPIKE_FLOOR * g.max())
    return int(np.count_nonzero(hot))


def kabsch_residual(x: np.ndarray, y: np.ndarray) -> float:
    """RMS of |R x + t − y| for the best rotation R and translation t."""
    cx, cy = x.mean(axis=0), y.mean(axis=0)
    H = (x - cx).T @ (y - cy)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    r = (x - cx) @ R.T + cy - y
    return float(np.sqrt(np.einsum("ij,ij->i", r, r).mean()))


def edge_distortion(rest: np.ndarray, moved: np.ndarray, edges: np.ndarray) -> float:
    a, b = edges[:, 0], edges[:, 1]
    ratio = np.linalg.norm(moved[a] - moved[b], axis=1) / np.linalg.norm(rest[a] - rest[b], axis=1)
    return float(np.abs(ratio - 1.0).max()) if ratio.size else 0.0


def field_metrics(case: str, edit: str, rest: np.ndarray, moved: np.ndarray, edges: np.ndarray,
                  cage_rest: np.ndarray) -> dict[str, float]:
    """The metrics of the module docstring for one deformed result."""
    d = moved - rest
    out = {"roughness_p99": roughness(d, edges), "spikes": float(spikes(rest, d, edges)),
           "max_displacement": float(np.linalg.norm(d, axis=1).max())}
    if edit == "TWIST":
        inside = twisted_region(case, rest, cage_rest)
        out["rigid_residual"] = kabsch_residual(rest[inside], moved[inside]) / cage_size(cage_rest)
        both = inside[edges[:, 0]] & inside[edges[:, 1]]
        out["edge_distortion"] = edge_distortion(rest, moved, edges[both])
    return out
