"""Cages made for the mesh (issue #50) measured in one bpy process: the cage the add operator makes, and
a cage edit with it against a hand-made cage and against Blender's Mesh Deform on the same made cage.

Used by tests/blender/test_cage_made_quality.py and bench/cage_enclose.py (part e); it needs bpy and
numpy and the installed add-on (its core, for the time to make and the add-on's own check), not pytest.

Cases (every object at the identity transform, so object space = world space):

* 'SUZANNE' — Suzanne subdivided twice (tests/blender/cage_field.py, 7,958 vertices); hand-made
  reference: cage_field's box cage (8×8 quads per side, 384 quads, 6% of the head's size around it);
* 'FIGURE' — the Figure of samples/cage_deform.blend (2,896 vertices, eight overlapping ellipsoids,
  thin limbs); hand-made reference: that sample's own cage, object "Cage" (38 quads, its rest shape);
* 'FIGURE_130K' — the same figure at 130,064 vertices (tests/core/enclose_shapes.figure_130k, the
  core test's mesh); hand-made reference: the same sample cage.

The made cage: what `object.affine_cage_deformer_add` makes with only the mesh selected (its default
budget). Measured on it: faces, the stated margin (the core's `EnclosingCage.margin`), and over
every vertex of the mesh the smallest distance to the cage and the least and largest winding number,
by the add-on's own check (`check_enclosure`, both diagonals of every quad) and independently here
(`brute_numbers`: solid angles and point–triangle distances by brute force, both diagonals, own
code); the time to make (`enclosing_cage(...).seconds`, the check included, median of `repeats`
runs) and the add operator's whole time (make + bind).

The cage edit (`twist`): the same smooth map applied to every cage's vertices — a turn about the
vertical axis through the mesh's bounding-box centre by TWIST_ANGLE · smoothstep(t), t = (z − z_mid) ÷
(z_top − z_mid) clipped to [0, 1], z_mid and z_top the mesh's middle and top heights: the cage's top
turns by TWIST_ANGLE, its lower half stays. Three rigs on identical copies of the mesh: our cage
deformer (defaults) with the made cage, ours with the hand-made cage, Mesh Deform (precision 5 unless
told) bound to a copy of the made cage. Metrics of the deformed mesh x' against rest x (edges E):

* roughness p99 — the 99th percentile over vertices of |d_v − mean of d over v's edge neighbours| ÷
  max |d| (d = x' − x; cage_field.roughness, the measure of tests/core/enclose_quality.py);
* follow RMS — the RMS of |x' − twist(x)| ÷ the mesh's size (largest bounding-box extent): how far
  the mesh is from the edit applied to it directly;
* edge distortion — max and mean over E of |l'/l − 1|;
* torn edges — edges stretched to more than TEAR_STRETCH × the longer of their rest length and their
  length under the edit applied directly, or with a non-finite end. (The edit itself stretches some
  edges: Suzanne's ears and the figure's hands sit far from the axis in the turning band, up to ~2×
  on Suzanne; the row "the edit applied to the mesh directly" shows its own numbers.)
"""

from __future__ import annotations

import importlib
import math
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run from bench/ too: tests.* are namespace packages under the root
    sys.path.insert(0, str(ROOT))

from tests.blender import cage_field as cf  # noqa: E402
from tests.core import enclose_shapes  # noqa: E402  (numpy only)

#: The installed add-on's inner package (conftest.PACKAGE, bench/ours.INNER).
PACKAGE = "bl_ext.user_default.affine_deformers.affine_deformers"
SAMPLE = ROOT / "samples" / "cage_deform.blend"
CASES = ("SUZANNE", "FIGURE", "FIGURE_130K")
TWIST_ANGLE = math.radians(45.0)
TEAR_STRETCH = 1.5  # an edge longer than this × max(rest, edit-applied) length is torn
MESH_DEFORM_PRECISION = 5
#: Largest mesh checked by brute force at every vertex; larger ones every `stride`-th vertex.
BRUTE_ALL_VERTICES = 20_000
BRUTE_BLOCK = 1 << 21  # point–triangle pairs per block of the brute-force check (memory stays small)

LABELS = {"SUZANNE": "Suzanne (subdivided twice)", "FIGURE": "Figure (samples/cage_deform.blend)",
          "FIGURE_130K": "Figure at 130k (core test mesh)"}
REFERENCES = {"SUZANNE": "box cage", "FIGURE": "sample's hand-made cage",
              "FIGURE_130K": "sample's hand-made cage"}
METHODS = ("edit", "ours_made", "ours_hand", "mesh_deform")
METHOD_LABELS = {"edit": "the edit applied to the mesh directly", "ours_made": "ours, made cage",
                 "ours_hand": "ours, hand-made cage", "mesh_deform": "Mesh Deform, made cage"}


# ---------------------------------------------------------------------------------------------- meshes


def mesh_from_polygons(name: str, points: np.ndarray, loop_vertices: np.ndarray, loop_start: np.ndarray,
                       loop_total: np.ndarray) -> bpy.types.Mesh:
    """A new mesh from flat polygon arrays (Blender's layout), built with foreach_set."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(points, dtype=np.float32).ravel())
    mesh.loops.add(len(loop_vertices))
    mesh.loops.foreach_set("vertex_index", np.asarray(loop_vertices, dtype=np.int32))
    mesh.polygons.add(len(loop_start))
    mesh.polygons.foreach_set("loop_start", np.asarray(loop_start, dtype=np.int32))
    mesh.polygons.foreach_set("loop_total", np.asarray(loop_total, dtype=np.int32))
    mesh.update(calc_edges=True)
    mesh.validate(clean_customdata=False)
    return mesh


def polygon_arrays(mesh: bpy.types.Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(loop vertices, loop starts, loop totals) of a mesh."""
    loops = np.empty(len(mesh.loops), dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", loops)
    start = np.empty(len(mesh.polygons), dtype=np.int32)
    total = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_start", start)
    mesh.polygons.foreach_get("loop_total", total)
    return loops, start, total


def quads_of(mesh: bpy.types.Mesh) -> np.ndarray:
    """(F, 4) the faces of an all-quad mesh (ValueError otherwise)."""
    loops, start, total = polygon_arrays(mesh)
    if not np.all(total == 4):
        raise ValueError(f"'{mesh.name}' is not all quads ({sorted(set(total.tolist()))}-gons)")
    return loops[start[:, None] + np.arange(4)]


def triangles_of(mesh: bpy.types.Mesh) -> np.ndarray:
    """(T, 3) the mesh's loop triangles as vertex indices."""
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3)


def edges_of(mesh: bpy.types.Mesh) -> np.ndarray:
    e = np.empty(len(mesh.edges) * 2, dtype=np.int32)
    mesh.edges.foreach_get("vertices", e)
    return e.reshape(-1, 2)


def sample_meshes() -> tuple[bpy.types.Mesh, bpy.types.Mesh]:
    """Fresh copies of the Figure and the hand-made Cage (its rest shape, no shape keys) of
    samples/cage_deform.blend, built from their arrays (the appended originals are removed)."""
    with bpy.data.libraries.load(str(SAMPLE), link=False) as (_, into):
        into.meshes = ["Figure", "Cage"]
    arrays = [(cf.read_co(mesh), *polygon_arrays(mesh)) for mesh in into.meshes]
    for mesh in into.meshes:
        bpy.data.meshes.remove(mesh)  # (the cage's shape keys and the materials stay as orphan data)
    figure, cage = (mesh_from_polygons(name, *a) for name, a in zip(("Figure", "FigureHandCage"), arrays,
                                                                      strict=True))
    return figure, cage


def case_meshes(case: str) -> tuple[bpy.types.Mesh, bpy.types.Mesh]:
    """(target mesh, hand-made cage mesh) of `case` (module docstring); not linked to the scene."""
    if case == "SUZANNE":
        scene = cf.build_scene("SUZANNE")
        return scene.target_mesh, scene.cage_mesh
    if case == "FIGURE":
        return sample_meshes()
    if case == "FIGURE_130K":
        points, tris = enclose_shapes.figure_130k()
        target = mesh_from_polygons("Figure130k", points, tris.ravel(), 3 * np.arange(len(tris)),
                                    np.full(len(tris), 3))
        figure, cage = sample_meshes()
        bpy.data.meshes.remove(figure)
        return target, cage
    raise ValueError(f"unknown case {case!r}")


# ---------------------------------------------------------------------------------------------- the edit


def twist(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, angle: float = TWIST_ANGLE) -> np.ndarray:
    """The cage edit of the module docstring for a mesh of bounding box [lo, hi]."""
    centre = 0.5 * (lo + hi)
    t = np.clip((points[:, 2] - centre[2]) / (hi[2] - centre[2]), 0.0, 1.0)
    a = angle * t * t * (3.0 - 2.0 * t)
    c, s = np.cos(a), np.sin(a)
    dx, dy = points[:, 0] - centre[0], points[:, 1] - centre[1]
    out = points.copy()
    out[:, 0] = centre[0] + c * dx - s * dy
    out[:, 1] = centre[1] + s * dx + c * dy
    return out


def edit_metrics(rest: np.ndarray, moved: np.ndarray, edges: np.ndarray, expected: np.ndarray
                 ) -> dict[str, float]:
    """The cage-edit metrics of the module docstring."""
    size = float(np.ptp(rest, axis=0).max())
    finite = np.isfinite(moved).all(axis=1)
    a, b = edges[:, 0], edges[:, 1]
    rest_length = np.linalg.norm(rest[a] - rest[b], axis=1)
    usable = rest_length > 0.0
    ends_finite = finite[a] & finite[b]
    asked = np.maximum(rest_length, np.linalg.norm(expected[a] - expected[b], axis=1))
    with np.errstate(invalid="ignore", over="ignore"):
        length = np.linalg.norm(moved[a] - moved[b], axis=1)
        ratio = length / np.where(usable, rest_length, 1.0)
    torn = int(np.count_nonzero(~ends_finite | (usable & (length > TEAR_STRETCH * asked))))
    distortion = np.abs(ratio[usable & ends_finite] - 1.0)
    out = {"torn": float(torn), "non_finite": float(np.count_nonzero(~finite)),
           "edge_max": float(distortion.max()) if distortion.size else 0.0,
           "edge_mean": float(distortion.mean()) if distortion.size else 0.0}
    if finite.all():
        d = moved - rest
        out["roughness_p99"] = cf.roughness(d, edges)
        out["follow_rms"] = float(np.sqrt(((moved - expected) ** 2).sum(axis=1).mean())) / size
        out["max_displacement"] = float(np.linalg.norm(d, axis=1).max()) / size
    else:
        out["roughness_p99"] = out["follow_rms"] = out["max_displacement"] = math.nan
    return out


# ---------------------------------------------------------------------------------------------- enclosure


def quad_triangles(quads: np.ndarray, diagonal: int) -> np.ndarray:
    """(2F, 3) the quads split along v0–v2 (diagonal 0) or v1–v3 (diagonal 1), orientation kept."""
    if diagonal == 0:
        return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return np.concatenate([quads[:, [0, 1, 3]], quads[:, [1, 2, 3]]])


def _rows(n_tris: int) -> int:
    """Points per block of the brute-force check."""
    return max(1, BRUTE_BLOCK // max(n_tris, 1))


def winding_numbers(points: np.ndarray, x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(N,) Σ over the triangles of their solid angle seen from each point ÷ 4π (the formula of van
    Oosterom and Strackee), in blocks of points."""
    corners = x[tris]  # (T, 3, 3)
    out = np.empty(len(points))
    step = _rows(len(tris))
    for s in range(0, len(points), step):
        rel = corners[None] - points[s:s + step, None, None, :]
        a, b, c = rel[:, :, 0], rel[:, :, 1], rel[:, :, 2]
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        triple = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ptk,ptk->pt", a, b) * lc + np.einsum("ptk,ptk->pt", a, c) * lb
               + np.einsum("ptk,ptk->pt", b, c) * la)
        out[s:s + step] = np.arctan2(triple, den).sum(axis=1) / (2.0 * np.pi)
    return out


def _segment_sq(p: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Squared distance from points p (P, 1, 3) to segments u → v (1, T, 3): (P, T)."""
    e = v - u
    t = np.clip(np.einsum("ptk,ptk->pt", p - u, np.broadcast_to(e, (p.shape[0], *e.shape[1:])))
                / np.maximum(np.einsum("tk,tk->t", e[0], e[0]), 1e-300), 0.0, 1.0)
    r = p - (u + t[..., None] * e)
    return np.einsum("ptk,ptk->pt", r, r)


def smallest_distances(points: np.ndarray, x: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(N,) the distance of each point to the nearest triangle: to its plane where the point projects
    inside the triangle, else to the nearest of its three sides."""
    a, b, c = (x[tris[:, k]][None] for k in range(3))  # (1, T, 3)
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    nn = np.einsum("ptk,ptk->pt", n, n)[0]
    d00, d01, d11 = (np.einsum("tk,tk->t", u[0], v[0]) for u, v in ((ab, ab), (ab, ac), (ac, ac)))
    denom = d00 * d11 - d01 * d01
    out = np.empty(len(points))
    step = _rows(len(tris))
    for s in range(0, len(points), step):
        p = points[s:s + step, None, :]
        ap = p - a
        d20, d21 = np.einsum("ptk,tk->pt", ap, ab[0]), np.einsum("ptk,tk->pt", ap, ac[0])
        v = (d11 * d20 - d01 * d21) / denom
        w = (d00 * d21 - d01 * d20) / denom
        inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0)
        plane = np.einsum("ptk,tk->pt", ap, n[0]) ** 2 / nn
        sides = np.minimum(np.minimum(_segment_sq(p, a, b), _segment_sq(p, b, c)), _segment_sq(p, c, a))
        out[s:s + step] = np.sqrt(np.where(inside, plane, sides).min(axis=1))
    return out


def brute_numbers(points: np.ndarray, x: np.ndarray, quads: np.ndarray, stride: int = 1
                  ) -> dict[str, float]:
    """Smallest distance and least / largest winding number over every `stride`-th point, both quad
    diagonals, by brute force (independent of the add-on's check)."""
    p = points[::stride]
    tris = [quad_triangles(quads, k) for k in (0, 1)]
    wind = np.concatenate([winding_numbers(p, x, t) for t in tris])
    smallest = min(float(smallest_distances(p, x, t).min()) for t in tris)
    return {"smallest": smallest, "winding_min": float(wind.min()), "winding_max": float(wind.max()),
            "points": float(len(p))}


# ---------------------------------------------------------------------------------------------- rigs


def add_made_cage(target: bpy.types.Object) -> tuple[object, bpy.types.Object, float]:
    """(deformer, made cage, seconds): our cage deformer added with only the mesh selected."""
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        t0 = time.perf_counter()
        result = bpy.ops.object.affine_cage_deformer_add()
        seconds = time.perf_counter() - t0
    if result != {"FINISHED"}:
        raise RuntimeError(f"affine_cage_deformer_add with no cage selected: {result}")
    deformer = target.affine_deformers[len(target.affine_deformers) - 1]
    if deformer.cage is None:
        raise RuntimeError("the added cage deformer has no cage")
    return deformer, deformer.cage, seconds


def rebind(target: bpy.types.Object, index: int = 0) -> float:
    """Seconds of binding our deformer `index` again (Rebind), the cage unchanged."""
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        t0 = time.perf_counter()
        result = bpy.ops.object.affine_deformer_bind(index=index)
        seconds = time.perf_counter() - t0
    if result != {"FINISHED"}:
        raise RuntimeError(f"affine_deformer_bind: {result}")
    return seconds


def timed(fn, *args, **kwargs) -> tuple[object, float]:
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


@dataclass
class CaseResult:
    """Everything measured on one case (module docstring); `edit[method]` the metrics per rig."""

    case: str
    vertices: int
    faces: int = 0
    cage_vertices: int = 0
    hand_faces: int = 0
    margin: float = math.nan  # stated: EnclosingCage.margin
    cell_size: float = math.nan
    symmetric: bool = False
    shrink_wrapped: bool = False
    same_as_core: bool = False  # the operator's cage is the core's enclosing_cage of the same mesh
    check: dict[str, float] = field(default_factory=dict)  # the add-on's check_enclosure
    problems: tuple[str, ...] = ()
    brute: dict[str, float] = field(default_factory=dict)
    size: float = math.nan
    make_seconds: list[float] = field(default_factory=list)
    add_seconds: float = math.nan  # the add operator: make + bind
    bind: dict[str, float] = field(default_factory=dict)  # per method
    status: dict[str, str] = field(default_factory=dict)  # our deformers' status after the edit
    edit: dict[str, dict[str, float]] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)  # a rig that could not be set up

    @property
    def make_median(self) -> float:
        return statistics.median(self.make_seconds) if self.make_seconds else math.nan


def measure_case(case: str, package: str = PACKAGE, repeats: int = 3, mesh_deform: bool = True,
                 precision: int = MESH_DEFORM_PRECISION, brute_stride: int | None = None) -> CaseResult:
    """Build `case` in the current scene, measure it (module docstring), remove what it made."""
    enclose = importlib.import_module(f"{package}.core.cage.enclose")
    checks = importlib.import_module(f"{package}.core.cage.enclose_checks")
    target_mesh, hand_mesh = case_meshes(case)
    rest, edges = cf.read_co(target_mesh), edges_of(target_mesh)
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    out = CaseResult(case, len(rest), hand_faces=len(hand_mesh.polygons), size=float((hi - lo).max()))
    made_objects: list[bpy.types.Object] = []

    def target(suffix: str) -> bpy.types.Object:
        obj = cf.link(f"{target_mesh.name}.{suffix}", target_mesh.copy())
        made_objects.append(obj)
        return obj

    try:
        # the made cage, as the artist gets it
        made_target = target("made")
        _, made_cage, out.add_seconds = add_made_cage(made_target)
        made_objects.append(made_cage)
        out.bind["ours_made"] = rebind(made_target)
        cage_x, quads = cf.read_co(made_cage.data), quads_of(made_cage.data)
        out.faces, out.cage_vertices = len(quads), len(cage_x)
        tris = triangles_of(target_mesh)
        budget = importlib.import_module(f"{package}.blender.kinds.cage_tools").DEFAULT_FACES
        for _ in range(repeats):
            core = enclose.enclosing_cage(rest, tris, budget=budget)
            out.make_seconds.append(core.seconds)
        out.margin, out.cell_size = float(core.margin), float(core.cell_size)
        out.symmetric, out.shrink_wrapped = bool(core.symmetric), bool(core.shrink_wrapped)
        out.same_as_core = (core.vertices.shape == cage_x.shape and np.array_equal(core.quads, quads)
                            and float(np.abs(core.vertices - cage_x).max()) <= 1e-6 * out.size)
        report = checks.check_enclosure(rest, cage_x, quads, core.margin)
        out.check = {"smallest": float(report.smallest_distance), "winding_min": float(report.winding_min),
                     "winding_max": float(report.winding_max)}
        out.problems = tuple(report.problems)
        stride = brute_stride or (1 if len(rest) <= BRUTE_ALL_VERTICES else -(-len(rest) // 10_000))
        out.brute = brute_numbers(rest, cage_x, quads, stride)

        # the other rigs on identical copies
        rigs = {"ours_made": (made_target, made_cage)}
        hand_target = target("hand")
        hand_cage = cf.link(f"{hand_mesh.name}.hand", hand_mesh.copy())
        hand_cage.display_type = "WIRE"
        made_objects.append(hand_cage)
        _, out.bind["ours_hand"] = timed(cf.bind_ours, hand_target, hand_cage)
        rigs["ours_hand"] = (hand_target, hand_cage)
        if mesh_deform:
            md_target = target("mesh_deform")
            md_cage = cf.link(f"{made_cage.name}.mesh_deform", made_cage.data.copy())
            md_cage.display_type = "WIRE"
            made_objects.append(md_cage)
            try:
                _, out.bind["mesh_deform"] = timed(cf.bind_mesh_deform, md_target, md_cage, precision)
                rigs["mesh_deform"] = (md_target, md_cage)
            except RuntimeError as exc:
                out.errors["mesh_deform"] = str(exc)

        # the same edit on every cage
        rests = {}
        for name, (_, cage) in rigs.items():
            rests[name] = cf.read_co(cage.data)
            cf.write_co(cage.data, twist(rests[name], lo, hi))
        bpy.context.view_layer.update()
        expected = twist(rest, lo, hi)
        out.edit["edit"] = edit_metrics(rest, expected, edges, expected)
        for name, (obj, _) in rigs.items():
            out.edit[name] = edit_metrics(rest, cf.evaluated(obj), edges, expected)
            if len(getattr(obj, "affine_deformers", ())):
                out.status[name] = obj.affine_deformers[0].status
        for name, (_, cage) in rigs.items():
            cf.write_co(cage.data, rests[name])
    finally:
        meshes = {o.data for o in made_objects if o.type == "MESH"} | {target_mesh, hand_mesh}
        for obj in made_objects:
            bpy.data.objects.remove(obj, do_unlink=True)
        for mesh in meshes:
            if mesh.users == 0:
                bpy.data.meshes.remove(mesh)
        bpy.context.view_layer.update()
    return out


# ---------------------------------------------------------------------------------------------- rows


def _num(x: float, fmt: str = ".3g") -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def _seconds(x: float) -> str:
    if x is None or math.isnan(x):
        return "—"
    return f"{x:.2f} s" if x >= 1.0 else f"{1e3 * x:.0f} ms"


MADE_HEADER = ["mesh", "vertices", "cage faces", "stated margin", "smallest distance (check / brute)",
               "winding min – max (check / brute)", "symmetric", "make (median)", "add (make + bind)"]


def made_rows(results: list[CaseResult]) -> list[list[str]]:
    """One row per case: the made cage (MADE_HEADER); distances in units of the mesh's size too."""
    rows = []
    for r in results:
        check, brute = r.check, r.brute
        points = int(brute.get("points", r.vertices))
        sampled = "" if points >= r.vertices else f" (brute: {points:,} vertices)"
        rows.append([
            LABELS[r.case], f"{r.vertices:,}", f"{r.faces} ({r.cage_vertices} verts)",
            f"{_num(r.margin, '.4f')} ({r.margin / r.size:.1%})",
            f"{_num(check.get('smallest'), '.4f')} / {_num(brute.get('smallest'), '.4f')}{sampled}",
            f"{_num(check.get('winding_min'), '.6f')} – {_num(check.get('winding_max'), '.6f')} / "
            f"{_num(brute.get('winding_min'), '.6f')} – {_num(brute.get('winding_max'), '.6f')}",
            "yes" if r.symmetric else "no",
            f"{_seconds(r.make_median)} (of {len(r.make_seconds)}: {_seconds(min(r.make_seconds))} – "
            f"{_seconds(max(r.make_seconds))})" if r.make_seconds else "—",
            _seconds(r.add_seconds),
        ])
    return rows


EDIT_HEADER = ["mesh", "rig", "cage faces", "bind", "roughness p99", "follow RMS", "edge Δl/l max",
               "edge Δl/l mean", f"torn (> {TEAR_STRETCH}× rest or edit)"]


def edit_rows(results: list[CaseResult]) -> list[list[str]]:
    """One row per case and rig: the cage edit (EDIT_HEADER)."""
    rows = []
    for r in results:
        for method in METHODS:
            label = METHOD_LABELS[method].replace("hand-made cage", REFERENCES[r.case])
            faces = {"edit": "—", "ours_hand": str(r.hand_faces)}.get(method, str(r.faces))
            bind = "—" if method == "edit" else _seconds(r.bind.get(method, math.nan))
            m = r.edit.get(method)
            if m is None:
                rows.append([LABELS[r.case], label, faces, bind, r.errors.get(method, "not measured"),
                             "", "", "", ""])
                continue
            torn = f"{int(m['torn'])}" + (f" ({int(m['non_finite'])} non-finite vertices)"
                                          if m["non_finite"] else "")
            rows.append([LABELS[r.case], label, faces, bind, _num(m["roughness_p99"], ".4f"),
                         _num(m["follow_rms"], ".4f"), _num(m["edge_max"], ".3f"),
                         _num(m["edge_mean"], ".4f"), torn])
    return rows


def text_table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    rule = "  ".join("-" * w for w in widths)
    return "\n".join([fmt.format(*header), rule, *(fmt.format(*r) for r in rows)])
