"""Shared benchmark plumbing: meshes built from numpy, scene reset, timed updates, machine facts, tables.

Everything here runs inside one bpy process. What a benchmark times is one *interactive update*:
move one control, let the depsgraph settle (`settle()`), then read the evaluated positions back (not
timed) to prove the update really happened. Each method gets its own clean scene so moving a control
re-evaluates only the object under test.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import bpy
import numpy as np

#: How many `view_layer.update()` calls one interactive update takes. Our deformer writes its result
#: from a depsgraph_update_post handler into a mesh attribute, which tags the mesh again; the second
#: pass re-evaluates the modifier stack with the new offsets. For native modifiers the second call finds
#: nothing tagged and returns at once, so every method is timed with the same two calls.
SETTLE_PASSES = 2


# --------------------------------------------------------------------------------------------------
# Meshes and placement


def sphere_grid_for(n_verts: int) -> tuple[int, int]:
    """(segments, rings) of a UV sphere with about `n_verts` vertices: N = S·(R − 1) + 2, S = 2(R − 1)."""
    inner = max(2, round(math.sqrt(max(n_verts - 2, 8) / 2.0)))
    return 2 * inner, inner + 1


def uv_sphere_mesh(name: str, segments: int, rings: int, radius: float = 1.0) -> bpy.types.Mesh:
    """A closed UV sphere (quads, triangle fans at the poles), built with foreach_set.

    bmesh's create_uvsphere takes ~12 s at 130k vertices; this takes well under a second at 1M.
    """
    s, r = segments, rings
    theta = np.pi * np.arange(1, r) / r  # polar angle of the r − 1 latitude circles
    phi = 2.0 * np.pi * np.arange(s) / s
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring_xyz = np.stack(
        [st * np.cos(phi)[None, :], st * np.sin(phi)[None, :], np.broadcast_to(ct, (r - 1, s))], axis=-1
    ).reshape(-1, 3)
    co = np.concatenate([[[0.0, 0.0, 1.0]], ring_xyz, [[0.0, 0.0, -1.0]]]) * radius
    n_verts = co.shape[0]
    bottom = n_verts - 1

    j = np.arange(s)
    jn = (j + 1) % s
    top_fan = np.stack([np.zeros(s, int), 1 + j, 1 + jn], axis=1)
    ring0 = 1 + s * np.arange(r - 2)[:, None]
    quads = np.stack(
        [ring0 + j, ring0 + s + j, ring0 + s + jn, ring0 + jn], axis=-1
    ).reshape(-1, 4)
    last = 1 + s * (r - 2)
    bottom_fan = np.stack([np.full(s, bottom), last + jn, last + j], axis=1)

    loops = np.concatenate([top_fan.ravel(), quads.ravel(), bottom_fan.ravel()]).astype(np.int32)
    sizes = np.concatenate([np.full(s, 3), np.full(quads.shape[0], 4), np.full(s, 3)])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32)

    me = bpy.data.meshes.new(name)
    me.vertices.add(n_verts)
    me.vertices.foreach_set("co", co.astype(np.float32).ravel())
    me.loops.add(loops.size)
    me.loops.foreach_set("vertex_index", loops)
    me.polygons.add(sizes.size)
    me.polygons.foreach_set("loop_start", starts)
    me.update(calc_edges=True)
    return me


def link_object(name: str, data: bpy.types.ID | None) -> bpy.types.Object:
    ob = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def sphere_object(name: str, n_verts: int, radius: float = 1.0) -> bpy.types.Object:
    segments, rings = sphere_grid_for(n_verts)
    return link_object(name, uv_sphere_mesh(name, segments, rings, radius))


def probe_sites(m: int, radius: float = 1.0) -> np.ndarray:
    """`m` points spread evenly over a sphere (Fibonacci lattice), deterministic."""
    k = np.arange(m) + 0.5
    z = 1.0 - 2.0 * k / m
    rho = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    ang = np.pi * (3.0 - math.sqrt(5.0)) * k
    return radius * np.stack([rho * np.cos(ang), rho * np.sin(ang), z], axis=1)


def smooth_falloff(points: np.ndarray, centers: np.ndarray, radius: float) -> np.ndarray:
    """(N, m) weights 3f² − 2f³ with f = max(0, 1 − |p − c|/radius): the Hook modifier's 'Smooth' curve."""
    d = np.linalg.norm(points[:, None, :] - centers[None, :, :], axis=-1)
    f = np.clip(1.0 - d / radius, 0.0, 1.0)
    return f * f * (3.0 - 2.0 * f)


def chain_weights(t: np.ndarray, m: int, reach: float = 1.5) -> np.ndarray:
    """(N, m) skin weights of a chain of m equal bones over t ∈ [0, 1]: bone i's weight is a smoothstep
    bump, 1 at its centre (i + ½)/m and 0 at `reach` bone lengths from it (1 before the first centre and
    after the last), normalised to sum to 1 — two or three bones per point, as a painted skin has."""
    centers = (np.arange(m) + 0.5) / m
    f = np.clip(1.0 - np.abs(t[:, None] - centers[None, :]) * m / reach, 0.0, 1.0)
    bumps = f * f * (3.0 - 2.0 * f)
    bumps[t <= centers[0], 0] = 1.0
    bumps[t >= centers[-1], -1] = 1.0
    return bumps / bumps.sum(axis=1, keepdims=True)


def rest_positions(ob: bpy.types.Object) -> np.ndarray:
    buf = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", buf)
    return buf.reshape(-1, 3).astype(np.float64)


def clear_scene() -> None:
    """Remove every object and the data it used, so the next case starts from an empty scene."""
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob, do_unlink=True)
    for coll in (bpy.data.meshes, bpy.data.armatures):
        for block in list(coll):
            if block.users == 0:
                coll.remove(block)
    bpy.context.view_layer.update()


# --------------------------------------------------------------------------------------------------
# Timing


def settle() -> None:
    for _ in range(SETTLE_PASSES):
        bpy.context.view_layer.update()


def evaluated_positions(ob: bpy.types.Object) -> np.ndarray:
    """Vertex positions of `ob` after its modifier stack, read from the evaluated depsgraph."""
    dg = bpy.context.evaluated_depsgraph_get()
    me = ob.evaluated_get(dg).data
    buf = np.empty(len(me.vertices) * 3, np.float32)
    me.attributes["position"].data.foreach_get("vector", buf)
    return buf.reshape(-1, 3)


@dataclass
class Samples:
    """Wall-clock seconds of repeated interactive updates."""

    seconds: list[float] = field(default_factory=list)
    stale: int = 0  # updates after which the evaluated positions did not change (should stay 0)
    extra: dict[str, list[float]] = field(default_factory=dict)  # per-rep side measurements
    extra_source: str = ""  # where the side measurements came from
    unsettled: bool = False  # a further depsgraph pass still changed the result (timing incomplete)

    @property
    def median(self) -> float:
        return statistics.median(self.seconds) if self.seconds else math.nan

    def spread(self) -> tuple[float, float]:
        """(25th, 75th) percentiles."""
        if len(self.seconds) < 2:
            return self.median, self.median
        q = statistics.quantiles(self.seconds, n=4)
        return q[0], q[2]

    def extra_median(self, key: str) -> float:
        vals = self.extra.get(key)
        return statistics.median(vals) if vals else math.nan


def time_updates(
    move: Callable[[int], None],
    target: bpy.types.Object,
    reps: int,
    warmup: int = 2,
    after_rep: Callable[[Samples], None] | None = None,
    before_rep: Callable[[], None] | None = None,
) -> Samples:
    """Median-ready samples of `move(i); settle()` — the whole interactive update, handlers included.

    `move(i)` must change the control differently for every i so that no layer can skip the work.
    The evaluated positions are read after each rep (untimed) and compared with the previous rep's: an
    unchanged result means the update did not really happen, which is counted in `Samples.stale`.
    """
    out = Samples()
    prev = evaluated_positions(target)
    for i in range(-warmup, reps):
        if before_rep is not None:
            before_rep()
        t0 = time.perf_counter()
        move(i)
        settle()
        dt = time.perf_counter() - t0
        cur = evaluated_positions(target)
        if i >= 0:
            out.seconds.append(dt)
            if np.array_equal(cur, prev):
                out.stale += 1
            if after_rep is not None:
                after_rep(out)
        prev = cur
    return out


def wiggle(i: int) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A different small (translation, Euler rotation) for every rep index i — never repeats."""
    a = 0.7 * i + 0.3
    return (
        (0.08 * math.sin(a), 0.06 * math.cos(1.3 * a), 0.05 * math.sin(0.7 * a + 1.0)),
        (0.3 * math.sin(0.9 * a), 0.25 * math.cos(1.1 * a), 0.2 * math.sin(1.7 * a)),
    )


# --------------------------------------------------------------------------------------------------
# Reporting


def machine_info() -> dict[str, str]:
    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        load = "n/a"
    return {
        "cpu": cpu,
        "cores": str(os.cpu_count()),
        "bpy": bpy.app.version_string,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "date": _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "load": load,
        "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE", "(unset)"),
    }


def fmt_ms(seconds: float) -> str:
    if seconds is None or math.isnan(seconds):
        return "—"
    ms = seconds * 1e3
    if ms >= 1000:
        return f"{ms / 1e3:.2f} s"
    if ms >= 100:
        return f"{ms:.0f} ms"
    if ms >= 10:
        return f"{ms:.1f} ms"
    return f"{ms:.2f} ms"


def fmt_ratio(ours: float, native: float) -> str:
    if any(x is None or math.isnan(x) for x in (ours, native)) or native <= 0:
        return "—"
    return f"{ours / native:.2f}×"


@dataclass
class Table:
    """A titled table that prints as aligned text and renders as GitHub markdown."""

    title: str
    header: list[str]
    rows: list[list[str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def add(self, *cells: object) -> None:
        self.rows.append([str(c) for c in cells])

    def text(self) -> str:
        widths = [max(len(r[i]) for r in [self.header, *self.rows]) for i in range(len(self.header))]
        line = "  ".join("-" * w for w in widths)
        fmt = "  ".join(f"{{:<{w}}}" for w in widths)
        out = [self.title, fmt.format(*self.header), line]
        out += [fmt.format(*r) for r in self.rows]
        out += [f"  note: {n}" for n in self.notes]
        return "\n".join(out)

    def markdown(self) -> str:
        out = [f"### {self.title}", "", "| " + " | ".join(self.header) + " |"]
        out.append("|" + "|".join("---" for _ in self.header) + "|")
        out += ["| " + " | ".join(r) + " |" for r in self.rows]
        if self.notes:
            out.append("")
            out += [f"- {n}" for n in self.notes]
        return "\n".join(out)
