"""The benchmark cases (a) probes vs Hook/Armature, (b) cage vs Mesh Deform, (c) scaling, (d) bones vs the
Armature modifier — and the report.

Imported by run.py once bpy is up. Every method runs alone in a fresh scene on the same procedural mesh;
see common.time_updates for what one timed update contains.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path

import cage_enclose
import common
import native
import ours
import playback
import scene_size
import shape
from common import Samples, Table, fmt_ms, fmt_ratio


@dataclass(frozen=True)
class Plan:
    reps: int
    warmup: int
    a_verts: int
    b_verts: int
    cage_grid: tuple[int, int]  # UV-sphere cage (segments, rings): 32 × 32 → 1024 faces
    precision: int  # Mesh Deform precision
    c_verts: tuple[int, ...]
    c_probes: tuple[int, ...]
    radius: float = 1.0  # falloff radius on the unit sphere; the same for every method and probe count
    cage_radius: float = 1.25
    d_verts: tuple[int, ...] = (10_000, 130_000)  # (d): the sphere of (a) and a small one
    d_bones: int = 8
    p_frames: int = 48  # (p) playback: keyed frames
    m_objects: int = 10  # (m) many deformed objects: how many
    m_verts: int = 5_000  # (m) vertices of each
    m_probes: int = 4  # (m) keyed probes on each
    s_verts: tuple[int, ...] = (10_000, 130_000)  # (s) shape preservation: the bar's sizes
    w_verts: int = 5_000  # (w) the deformed mesh beside other objects
    w_others: tuple[int, ...] = (0, 5_000, 20_000)  # (w) how many other objects
    w_large_verts: int = 10_000  # (w) the mesh of the 8-probe playback and drag rows
    w_paths_verts: int = 80_000  # (w) the large mesh of the write-path floors
    e_cases: tuple[str, ...] = ("SUZANNE", "FIGURE", "FIGURE_130K")  # (e) made cages (cage_quality.CASES)
    e_repeats: int = 3  # (e) runs of the cage maker timed per mesh (median)


FULL = Plan(
    reps=15,
    warmup=3,
    a_verts=130_000,
    b_verts=130_000,
    cage_grid=(32, 32),
    precision=5,
    c_verts=(10_000, 130_000, 500_000, 1_000_000),
    c_probes=(1, 8, 64),
)
# Smoke-test sizes: the whole run takes a few seconds (Mesh Deform binds at precision 4 here, because
# precision 5 alone costs seconds even on a tiny mesh).
QUICK = Plan(
    reps=3,
    warmup=1,
    a_verts=3_000,
    b_verts=2_000,
    cage_grid=(16, 16),
    precision=4,
    c_verts=(2_000, 8_000),
    c_probes=(1, 8),
    d_verts=(2_000,),
    p_frames=6,
    m_objects=3,
    m_verts=1_000,
    s_verts=(2_000,),
    w_verts=1_000,
    w_others=(0, 500),
    w_large_verts=2_000,
    w_paths_verts=4_000,
    e_cases=("FIGURE",),
    e_repeats=1,
)

STAGES = (
    ("read", "read transforms"),
    ("read mesh", "read rest + weights"),
    ("psi", "ψ (motions → params)"),
    ("kernel", "kernel"),
    ("write", "write"),
    ("glue", "other"),
    ("handler", "= handler"),
    ("Blender re-evaluation", "Blender"),
    ("total", "= total"),
)


@dataclass
class Report:
    tables: list[Table] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # anything here makes the run exit with status 1
    summary: list[str] = field(default_factory=list)  # one factual line per part, from the numbers
    split_rows: list[tuple[str, Samples]] = field(default_factory=list)


def n_vertices(n_target: int) -> int:
    segments, rings = common.sphere_grid_for(n_target)
    return segments * (rings - 1) + 2


# --------------------------------------------------------------------------------------------------
# Measuring one rig


def measure(rig: native.Rig, plan: Plan, label: str, report: Report, instrument=None) -> Samples:
    """Time `rig`, then check that the timed passes were enough (one more pass must change nothing)."""
    hooks = {}
    if instrument is not None:
        hooks = {"before_rep": instrument.reset, "after_rep": instrument.record}
    samples = common.time_updates(rig.move, rig.target, plan.reps, warmup=plan.warmup, **hooks)
    settled = common.evaluated_positions(rig.target)
    common.settle()
    samples.unsettled = not (common.evaluated_positions(rig.target) == settled).all()
    if instrument is not None:
        samples.extra_source = instrument.source
    flag = validity(samples)
    if flag:
        report.problems.append(f"{label}: {flag} — its time does not cover a real update")
    print(f"  {label:<44} {fmt_ms(samples.median):>9}  {flag}", flush=True)
    return samples


def validity(samples: Samples | None) -> str:
    if samples is None:
        return ""
    notes = []
    if samples.stale:
        notes.append(f"{samples.stale}/{len(samples.seconds)} updates changed nothing")
    if samples.unsettled:
        notes.append("result still changing after the timed passes")
    return "; ".join(notes)


def run_ours_probes(
    plan: Plan, n_target: int, n_probes: int, label: str, report: Report, dense_weights: bool = False,
    move_all: bool = False, shape_keyed: bool = False, influences: int | None = None,
) -> tuple[Samples | None, ours.OurRig | None, object]:
    """(samples, rig, dense weights or None) for our probe deformer; the scene is cleared afterwards.

    rig.influences holds (K, mean non-zero weights per vertex) of the bind when the attributes are readable.
    move_all: every update moves every probe (each differently) instead of the first one only.
    shape_keyed: the target gets two shape keys (Basis, and one at 0) first, so the deformer takes its
    general (motion) path, which applies each vertex's affine map to whatever reaches the modifier,
    instead of the fast path (offsets from the rest shape, exact only first in the stack without shape
    keys).
    influences: Max Influences set after the add (re-weights), instead of the add operator's default.
    """
    try:
        ours.forget_caches()
        target = common.sphere_object("Target", n_target)
        if shape_keyed:
            target.shape_key_add(name="Basis", from_mix=False)
            target.shape_key_add(name="Key", from_mix=False)  # at value 0: a key the rig has, not keyed now
        empties = native.add_empties(common.probe_sites(n_probes))
        rig = ours.probe_rig(target, empties, plan.radius)
        if influences is not None:
            target.affine_deformers[rig.deformer_index].max_influences = influences
            rig.settings["max_influences"] = influences
        if move_all:
            rig.move = native.move_objects(empties)
        weights = ours.bound_weights(target, empties) if dense_weights else None
        influences = ours.mean_influences(target)
        with ours.Instrument() as inst:
            samples = measure(rig, plan, label, report, inst)
        rig.influences = influences
        status = getattr(target.affine_deformers[rig.deformer_index], "status", "")
        if status:
            report.notes.append(f"{label}: the deformer reported “{status}”")
        return samples, rig, weights
    except Exception as exc:  # a broken layer must not hide the native numbers
        traceback.print_exc()
        report.problems.append(f"{label}: {type(exc).__name__}: {exc}")
        return None, None, None
    finally:
        common.clear_scene()


def run_native(
    plan: Plan, n_target: int, n_probes: int, kind: str, label: str, report: Report, weights=None
) -> Samples:
    target = common.sphere_object("Target", n_target)
    sites = common.probe_sites(n_probes)
    if kind == "hook":
        rig = native.hooks(target, native.add_empties(sites), plan.radius)
    else:
        if weights is None:
            weights = common.smooth_falloff(common.rest_positions(target), sites, plan.radius)
        rig = native.armature(target, sites, weights)
    samples = measure(rig, plan, label, report)
    common.clear_scene()
    return samples


def _iqr(s: Samples | None) -> str:
    if s is None:
        return "—"
    lo, hi = s.spread()
    return f"{fmt_ms(lo)} – {fmt_ms(hi)}"


def _influences(rig: ours.OurRig | None) -> str:
    if rig is None or rig.influences is None:
        return "—"
    k, mean = rig.influences
    return f"{mean:.2f} of {k}"


def _median(s: Samples | None) -> float:
    return s.median if s is not None else math.nan


# --------------------------------------------------------------------------------------------------
# (a) (b) (c)


def part_a(plan: Plan, have_ours: bool, report: Report) -> None:
    m = 8
    n = n_vertices(plan.a_verts)
    print(f"(a) {m} probes on a UV sphere of {n:,} vertices, falloff radius {plan.radius}", flush=True)
    mine = rig = weights = None
    if have_ours and ours.operator_exists(ours.PROBE_OP):
        mine, rig, weights = run_ours_probes(
            plan, plan.a_verts, m, f"ours: {m} probes", report, dense_weights=True
        )
        if mine is not None:
            report.split_rows.append((f"(a) {m} probes, {n:,} verts", mine))
    else:
        report.notes.append(f"(a) `{ours.PROBE_OP}` is not registered: only the native side was timed")
    mine_all = None
    if have_ours and ours.operator_exists(ours.PROBE_OP):
        mine_all, _, _ = run_ours_probes(
            plan, plan.a_verts, m, f"ours: {m} probes, all moving", report, move_all=True
        )
        if mine_all is not None:
            report.split_rows.append((f"(a) {m} probes all moving, {n:,} verts", mine_all))
    stack_one = stack_all = None
    if have_ours and ours.operator_exists(ours.PROBE_OP):
        stack_one, _, _ = run_ours_probes(
            plan, plan.a_verts, m, f"ours: {m} probes, motion path", report, shape_keyed=True
        )
        stack_all, _, _ = run_ours_probes(
            plan, plan.a_verts, m, f"ours: {m} probes, motion path, all moving", report, move_all=True,
            shape_keyed=True,
        )
        for name, s in (("", stack_one), (" all moving", stack_all)):
            if s is not None:
                report.split_rows.append((f"(a) {m} probes{name}, motion path, {n:,} verts", s))
    mine_k6 = None
    if have_ours and ours.operator_exists(ours.PROBE_OP):
        # 8 probes, 8 influences (the default): nothing is truncated; 6 (the former default) truncates
        # every vertex, with the pooled column where probes tie (MATH.md §12)
        mine_k6, _, _ = run_ours_probes(plan, plan.a_verts, m, f"ours: {m} probes, 6 influences", report,
                                        influences=6)
    mine_np = None
    if have_ours and ours.operator_exists(ours.PROBE_OP) and ours.kernel_backend().startswith("C kernel"):
        ours.use_compiled_kernel(False)
        try:
            mine_np, _, _ = run_ours_probes(plan, plan.a_verts, m, f"ours: {m} probes, numpy kernel", report)
        finally:
            ours.use_compiled_kernel(True)
        if mine_np is not None:
            report.split_rows.append((f"(a) {m} probes, numpy kernel, {n:,} verts", mine_np))
    hooks = run_native(plan, plan.a_verts, m, "hook", f"Hook ×{m}, Smooth falloff", report)
    arm = run_native(
        plan, plan.a_verts, m, "armature", f"Armature {m} bones, Preserve Volume", report, weights
    )

    t = Table(
        f"(a) {m} probes, {n:,} vertices: one update after moving one control",
        ["method", "median", "IQR", "ours ÷ native", "check"],
    )
    if mine is not None:
        t.add("Affine probes (ours)", fmt_ms(mine.median), _iqr(mine), "1.00×", validity(mine))
    if mine_all is not None:
        t.add(f"Affine probes (ours), all {m} moving", fmt_ms(mine_all.median), _iqr(mine_all),
              fmt_ratio(mine_all.median, _median(mine)), validity(mine_all))
    if stack_one is not None:
        t.add("Affine probes (ours), motion path", fmt_ms(stack_one.median), _iqr(stack_one),
              fmt_ratio(stack_one.median, _median(mine)), validity(stack_one))
    if stack_all is not None:
        t.add(f"Affine probes (ours), motion path, all {m} moving", fmt_ms(stack_all.median),
              _iqr(stack_all), fmt_ratio(stack_all.median, _median(mine_all)), validity(stack_all))
    if mine_k6 is not None:
        t.add("Affine probes (ours), 6 influences", fmt_ms(mine_k6.median), _iqr(mine_k6),
              fmt_ratio(mine_k6.median, _median(mine)), validity(mine_k6))
    if mine_np is not None:
        t.add("Affine probes (ours), numpy kernel", fmt_ms(mine_np.median), _iqr(mine_np),
              fmt_ratio(mine_np.median, _median(mine)), validity(mine_np))
    for name, s in ((f"Hook ×{m}, Smooth, same radius", hooks), (f"Armature ×{m}, Preserve Volume", arm)):
        t.add(name, fmt_ms(s.median), _iqr(s), fmt_ratio(_median(mine), s.median), validity(s))
    if mine is not None:
        report.summary.append(
            f"(a) {m} probes on {n:,} vertices: ours {fmt_ms(mine.median)} per update; {m} Hooks "
            f"{fmt_ms(hooks.median)} ({fmt_ratio(mine.median, hooks.median)}), Armature with Preserve "
            f"Volume {fmt_ms(arm.median)} ({fmt_ratio(mine.median, arm.median)})"
            + (f"; all {m} probes moving: ours {fmt_ms(mine_all.median)} "
               f"({fmt_ratio(mine_all.median, hooks.median)} Hooks)." if mine_all is not None else ".")
        )
    source = "our bind weights (read back from the mesh)" if weights is not None else "smooth falloff"
    t.notes.append(f"Armature vertex groups: {source}, quantised to 1/{native.WEIGHT_LEVELS}")
    t.notes.append(
        f"ours, all {m} moving: every update moves every probe (ratio column: ÷ ours with one moving). "
        "Ours recomputes only vertices influenced by a control that moved, so the one-probe row is its "
        "best case; Blender's modifiers recompute every vertex either way, so their rows hold for both."
    )
    t.notes.append(
        "ours, motion path: the same rig on a mesh with shape keys, so the deformer writes each "
        "vertex's affine map (12 floats) and applies it to what reaches its modifier, as it does after "
        "shape keys, an Armature or another deformer; the other rows are the fast path (first in the "
        "stack, no shape keys: offsets from the rest shape, 3 floats). Ratio column: ÷ the same case on the "
        "fast path."
    )
    if mine_np is not None:
        t.notes.append(
            "ours, numpy kernel: the same rig with the compiled kernel turned off (the add-on preference), "
            "as on a platform without the bundled library (ratio column: ÷ ours with the compiled kernel)"
        )
    if rig is not None:
        settings = ", ".join(f"{k} {v}" for k, v in rig.settings.items())
        t.notes.append(f"ours: {settings}; add + bind took {fmt_ms(rig.bind_seconds)}")
    report.tables.append(t)


def _ours_cage(plan: Plan, target, cage, label: str, report: Report, weights: str = "HARMONIC",
               vertex: int = 0) -> tuple[Samples | None, float]:
    """(update samples, bind seconds) of our cage deformer with `weights` ('HARMONIC', the default:
    bind = the add operator; 'INVERSE_DISTANCE': bind = switching the option, which re-weights);
    the update moves cage vertex `vertex`."""
    try:
        ours.forget_caches()
        rig = ours.cage_rig(target, cage)
        rig.move = native.move_cage_vertex(cage, vertex)
        bind = rig.bind_seconds
        deformer = target.affine_deformers[rig.deformer_index]
        if weights != "HARMONIC":
            t0 = time.perf_counter()
            deformer.cage_weights = weights
            bind = time.perf_counter() - t0
            common.settle()
        with ours.Instrument() as inst:
            samples = measure(rig, plan, label, report, inst)
        if deformer.status:
            report.notes.append(f"{label}: the deformer reported “{deformer.status}”")
        return samples, bind
    except Exception as exc:
        traceback.print_exc()
        report.problems.append(f"{label}: {type(exc).__name__}: {exc}")
        return None, math.nan


def _cage_table(title: str, rows: list[tuple[str, Samples | None, float]], md: Samples, md_bind: float,
                precision: int) -> Table:
    t = Table(title, ["method", "update", "IQR", "ours ÷ native", "bind", "bind ours ÷ native", "check"])
    for name, samples, bind in rows:
        if samples is not None:
            t.add(name, fmt_ms(samples.median), _iqr(samples), fmt_ratio(samples.median, md.median),
                  fmt_ms(bind), fmt_ratio(bind, md_bind), validity(samples))
    t.add(f"Mesh Deform, precision {precision}", fmt_ms(md.median), _iqr(md), "1.00×", fmt_ms(md_bind),
          "1.00×", validity(md))
    t.notes.append("the control moved is one cage vertex (the UV-sphere cage: vertex 0, its pole; "
                   "Suzanne's: the middle of the front side); bind = one run (ours: the add operator; "
                   "inverse-distance row: switching the Cage Weights option, which re-weights)")
    t.notes.append("ratio columns: ours ÷ Mesh Deform (below 1: ours is faster)")
    return t


def part_b(plan: Plan, have_ours: bool, report: Report) -> None:
    seg, rings = plan.cage_grid
    n = n_vertices(plan.b_verts)

    def build():
        target = common.sphere_object("Target", plan.b_verts)
        cage = common.link_object("Cage", common.uv_sphere_mesh("Cage", seg, rings, plan.cage_radius))
        cage.display_type = "WIRE"
        return target, cage

    target, cage = build()
    faces = len(cage.data.polygons)
    print(f"(b) cage of {faces} faces around {n:,} vertices", flush=True)
    rows: list[tuple[str, Samples | None, float]] = []
    if have_ours and ours.operator_exists(ours.CAGE_OP):
        for weights, name in (("HARMONIC", "harmonic weights"), ("INVERSE_DISTANCE", "inverse distance")):
            samples, bind = _ours_cage(plan, target, cage, f"ours: cage, {name}", report, weights)
            rows.append((f"Affine cage (ours), {name}", samples, bind))
            if samples is not None:
                report.split_rows.append((f"(b) cage of {faces} faces, {name}, {n:,} verts", samples))
            common.clear_scene()
            target, cage = build()
    else:
        report.notes.append(f"(b) `{ours.CAGE_OP}` is not registered yet: our cage side was skipped")
        print(f"  ours: {ours.CAGE_OP} is not registered yet — skipped", flush=True)
    rig_md = native.mesh_deform(target, cage, plan.precision)
    print(f"  Mesh Deform bind, precision {plan.precision}: {fmt_ms(rig_md.bind_seconds)}", flush=True)
    md = measure(rig_md, plan, f"Mesh Deform, precision {plan.precision}", report)
    common.clear_scene()
    report.tables.append(_cage_table(f"(b) cage of {faces} faces around {n:,} vertices", rows, md,
                                     rig_md.bind_seconds, plan.precision))
    if rows and rows[0][1] is not None:
        mine, bind = rows[0][1], rows[0][2]
        report.summary.append(
            f"(b) cage of {faces} faces around {n:,} vertices, harmonic weights: ours "
            f"{fmt_ms(mine.median)} per update vs Mesh Deform {fmt_ms(md.median)} "
            f"({fmt_ratio(mine.median, md.median)}); bind ours {fmt_ms(bind)} vs "
            f"{fmt_ms(rig_md.bind_seconds)} ({fmt_ratio(bind, rig_md.bind_seconds)})."
        )
    _part_b_suzanne(plan, have_ours, report)


def _part_b_suzanne(plan: Plan, have_ours: bool, report: Report) -> None:
    """The field-quality scene (tests/blender/test_field_quality.py): Suzanne subdivided twice in a
    384-quad box cage, ours (both weight options) and Mesh Deform bound on the same meshes."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "blender"))
    import cage_field

    scene = cage_field.build_scene("SUZANNE")
    scene.target_mesh.use_fake_user = scene.cage_mesh.use_fake_user = True  # kept by clear_scene
    n, faces = len(scene.target_mesh.vertices), len(scene.cage_mesh.polygons)
    title = f"(b) Suzanne ({n:,} vertices) in a box cage of {faces} quads"
    print(title, flush=True)
    rows: list[tuple[str, Samples | None, float]] = []
    vertex, _ = cage_field.pull_target("SUZANNE", scene.cage_rest)  # in front of the nose
    if have_ours and ours.operator_exists(ours.CAGE_OP):
        for weights, name in (("HARMONIC", "harmonic weights"), ("INVERSE_DISTANCE", "inverse distance")):
            target, cage = cage_field.add_pair(scene, "Ours")
            samples, bind = _ours_cage(plan, target, cage, f"ours: Suzanne, {name}", report, weights,
                                       vertex)
            rows.append((f"Affine cage (ours), {name}", samples, bind))
            if samples is not None:
                report.split_rows.append((f"(b) Suzanne in {faces} quads, {name}, {n:,} verts", samples))
            common.clear_scene()
    target, cage = cage_field.add_pair(scene, "MD")
    rig_md = native.mesh_deform(target, cage, plan.precision)
    rig_md.move = native.move_cage_vertex(cage, vertex)
    print(f"  Mesh Deform bind, precision {plan.precision}: {fmt_ms(rig_md.bind_seconds)}", flush=True)
    md = measure(rig_md, plan, f"Mesh Deform, precision {plan.precision}", report)
    scene.target_mesh.use_fake_user = scene.cage_mesh.use_fake_user = False
    common.clear_scene()
    report.tables.append(_cage_table(title, rows, md, rig_md.bind_seconds, plan.precision))
    if rows and rows[0][1] is not None:
        mine, bind = rows[0][1], rows[0][2]
        report.summary.append(
            f"{title}, harmonic weights: ours {fmt_ms(mine.median)} per update vs Mesh Deform "
            f"{fmt_ms(md.median)} ({fmt_ratio(mine.median, md.median)}); bind ours {fmt_ms(bind)} vs "
            f"{fmt_ms(rig_md.bind_seconds)} ({fmt_ratio(bind, rig_md.bind_seconds)})."
        )


def part_c(plan: Plan, have_ours: bool, report: Report) -> None:
    have = have_ours and ours.operator_exists(ours.PROBE_OP)
    t = Table(
        "(c) scaling: one update, vertices × probes (ours vs Hook modifiers)",
        ["vertices", "probes", "ours", "ns/vertex", "kernel", "influences/vertex", "Hooks", "ours ÷ Hooks",
         "check"],
    )
    print("(c) scaling", flush=True)
    per_vertex: dict[int, list[float]] = {}
    largest: dict[int, tuple[int, float]] = {}
    for n_target in plan.c_verts:
        n = n_vertices(n_target)
        for m in plan.c_probes:
            mine = rig = None
            if have:
                label = f"ours: {n:,} verts, {m} probe(s)"
                mine, rig, _ = run_ours_probes(plan, n_target, m, label, report)
                if mine is not None:
                    report.split_rows.append((f"(c) {m} probe(s), {n:,} verts", mine))
            hooks = run_native(plan, n_target, m, "hook", f"Hook ×{m}: {n:,} verts", report)
            if mine is not None:
                per_vertex.setdefault(m, []).append(mine.median / n * 1e9)
                largest[m] = (n, mine.median / hooks.median)
            t.add(
                f"{n:,}",
                m,
                fmt_ms(_median(mine)),
                f"{mine.median / n * 1e9:.0f}" if mine is not None else "—",
                fmt_ms(mine.extra_median("kernel")) if mine is not None else "—",
                _influences(rig),
                fmt_ms(hooks.median),
                fmt_ratio(_median(mine), hooks.median),
                "; ".join(x for x in (validity(mine), validity(hooks)) if x),
            )
    t.notes.append("same falloff radius for every probe count, so more probes overlap more: Hooks pay for "
                   "every hook at every vertex, ours for the top-K influences only")
    t.notes.append("influences/vertex: mean non-zero weights per vertex of our bind (of K stored slots)")
    if per_vertex:
        ns_text = "; ".join(
            f"{m} probe(s) {min(v):.0f}–{max(v):.0f} ns" for m, v in sorted(per_vertex.items())
        )
        ratio_text = ", ".join(f"{m} probe(s) {r:.2f}×" for m, (_, r) in sorted(largest.items()))
        n_big = max(n for n, _ in largest.values())
        report.summary.append(
            f"(c) ours per vertex over {', '.join(f'{n_vertices(v):,}' for v in plan.c_verts)} vertices: "
            f"{ns_text}. At {n_big:,} vertices ours ÷ Hooks: {ratio_text}."
        )
    if not have:
        t.notes.append(f"`{ours.PROBE_OP}` is not registered: only the Hook side was timed")
    report.tables.append(t)


def _bone_case(plan: Plan, n_target: int, which: list[int], method: str, label: str,
               report: Report) -> tuple[Samples | None, dict[str, object]]:
    """(samples, our deformer's settings or {}) of one (d) case: the sphere skinned by a chain of
    plan.d_bones bones through the same vertex groups, by `method` ('ours', 'PRESERVE_VOLUME' or
    'LINEAR': the Armature modifier with and without Preserve Volume); each update turns the bones
    `which`. The scene is cleared after."""
    try:
        ours.forget_caches()
        target = common.sphere_object("Target", n_target)
        arm = native.bone_chain(target, plan.d_bones, with_modifier=method != "ours",
                                preserve_volume=method == "PRESERVE_VOLUME")
        move = native.move_bones(arm, which)
        if method != "ours":
            return measure(native.Rig(target, move, 0.0), plan, label, report), {}
        rig = ours.bone_rig(target, arm, move)
        with ours.Instrument() as inst:
            samples = measure(rig, plan, label, report, inst)
        status = target.affine_deformers[rig.deformer_index].status
        if status:
            report.notes.append(f"{label}: the deformer reported “{status}”")
        return samples, rig.settings
    except Exception as exc:  # a broken layer must not hide the other numbers
        traceback.print_exc()
        report.problems.append(f"{label}: {type(exc).__name__}: {exc}")
        return None, {}
    finally:
        common.clear_scene()


def part_d(plan: Plan, have_ours: bool, report: Report) -> None:
    m = plan.d_bones
    have = have_ours and ours.operator_exists(ours.BONE_OP)
    t = Table(
        f"(d) {m} bones skinning a UV sphere through the same vertex groups: one update (ours vs the "
        "Armature modifier)",
        ["vertices", "bones turned", "ours", "IQR", "Armature, Preserve Volume", "ours ÷ PV",
         "Armature, linear", "ours ÷ linear", "check"],
    )
    print(f"(d) {m} bones", flush=True)
    moves = (("tip bone", [m - 1]), (f"all {m}", list(range(m))))
    lines = []
    settings: dict[str, object] = {}
    for n_target in plan.d_verts:
        n = n_vertices(n_target)
        for moved, which in moves:
            mine = None
            if have:
                mine, settings = _bone_case(plan, n_target, which, "ours",
                                            f"ours: {m} bones, {n:,} verts, {moved}", report)
                if mine is not None:
                    report.split_rows.append((f"(d) {m} bones, {moved} turned, {n:,} verts", mine))
            pv, _ = _bone_case(plan, n_target, which, "PRESERVE_VOLUME",
                               f"Armature PV: {n:,} verts, {moved}", report)
            linear, _ = _bone_case(plan, n_target, which, "LINEAR",
                                   f"Armature linear: {n:,} verts, {moved}", report)
            t.add(f"{n:,}", moved, fmt_ms(_median(mine)), _iqr(mine), fmt_ms(_median(pv)),
                  fmt_ratio(_median(mine), _median(pv)), fmt_ms(_median(linear)),
                  fmt_ratio(_median(mine), _median(linear)),
                  "; ".join(x for x in (validity(mine), validity(pv), validity(linear)) if x))
            if mine is not None and pv is not None:
                lines.append(f"{n:,} vertices, {moved} turned: ours {fmt_ms(mine.median)} "
                             f"({fmt_ratio(mine.median, pv.median)} Preserve Volume, "
                             f"{fmt_ratio(mine.median, _median(linear))} linear)")
    t.notes.append(
        f"a chain of {m} connected bones up the sphere's axis (pole to pole); vertex groups named after "
        f"them, smooth in height (two or three bones per vertex), quantised to 1/{native.WEIGHT_LEVELS}: "
        "the Armature modifier and our bone deformer (weight mode Vertex Groups, as the add operator "
        "sets it) read the same groups"
    )
    t.notes.append(
        "tip bone: only the last bone turns (a bone's children follow it, so this is the only one-bone "
        f"move of a chain); all {m}: every bone turns, each differently. Ours recomputes only vertices a "
        "moved bone influences; the Armature modifier recomputes every vertex either way"
    )
    if settings:
        t.notes.append("ours: " + ", ".join(f"{k} {v}" for k, v in settings.items()))
    if not have:
        t.notes.append(f"`{ours.BONE_OP}` is not registered: only the Armature side was timed")
    report.tables.append(t)
    if lines:
        report.summary.append(f"(d) {m} bones: " + "; ".join(lines) + ".")


def split_table(rows: list[tuple[str, Samples]]) -> Table:
    present = {k for _, s in rows for k in s.extra}
    stages = [(k, label) for k, label in STAGES if k in present]
    stages += [(k, k) for k in sorted(present - {k for k, _ in STAGES})]
    t = Table(
        "Where our update time goes (median per stage; medians need not add up exactly)",
        ["case", *[label for _, label in stages]],
    )
    for label, s in rows:
        t.add(label, *[fmt_ms(s.extra_median(k)) for k, _ in stages])
    sources = sorted({s.extra_source for _, s in rows if s.extra_source})
    t.notes.append("handler = our bpy.app.handlers entries, timed by wrapping them (both passes)")
    t.notes.append(f"stages inside the handler: {'; '.join(sources) or 'n/a'}; other = handler − stages")
    t.notes.append("Blender = whole update − handler: both depsgraph passes, Geometry Nodes applying offsets")
    return t


# --------------------------------------------------------------------------------------------------
# Running and reporting


def run(ns: argparse.Namespace) -> int:
    plan = QUICK if ns.quick else FULL
    if ns.reps:
        plan = replace(plan, reps=ns.reps)
    info_before = common.machine_info()
    if ns.zip is None:
        print("[ours] no dist/affine_deformers-*.zip — run `make build`; our side is skipped")
        have_ours = False
    else:
        have_ours = ours.install(ns.zip) is not None
    if have_ours:
        info_before["kernel"] = ours.kernel_backend()
        print(f"[ours] kernel: {info_before['kernel']}")

    report = Report()
    t0 = time.perf_counter()
    for part, fn in (("a", part_a), ("b", part_b), ("c", part_c), ("d", part_d), ("p", playback.part_p),
                     ("m", playback.part_m), ("s", shape.part_s), ("w", scene_size.part_w),
                     ("e", cage_enclose.part_e)):
        if part in ns.parts:
            fn(plan, have_ours, report)
    if report.split_rows:
        report.tables.append(split_table(report.split_rows))
    elapsed = time.perf_counter() - t0
    info_after = common.machine_info()

    print()
    for table in report.tables:
        print(table.text(), end="\n\n")
    for note in report.notes:
        print(f"note: {note}")
    for line in report.summary:
        print(f"summary: {line}")
    print(
        f"machine: {info_after['cpu']}, {info_after['cores']} cores; bpy {info_after['bpy']}, "
        f"numpy {info_after['numpy']}; load average before {info_before['load']}, "
        f"after {info_after['load']}; {elapsed:.0f} s"
    )
    if ns.markdown:
        write_markdown(ns.markdown, plan, report, info_before, info_after, elapsed, quick=ns.quick)
        print(f"wrote {ns.markdown}")
    for problem in report.problems:
        print(f"PROBLEM: {problem}")
    return 1 if report.problems else 0


def write_markdown(
    path: Path, plan: Plan, report: Report, before: dict, after: dict, elapsed: float, quick: bool
) -> None:
    try:
        shown = path.resolve().relative_to(Path(__file__).resolve().parent.parent)
    except ValueError:
        shown = path
    command = "python bench/run.py" + (" --quick" if quick else "") + f" --markdown {shown}"
    lines = [
        "# Benchmarks: Affine Deformers vs Blender's native deformers",
        "",
        f"Generated by `make bench` / `{command}`; do not edit by hand, re-run on a quiet machine.",
        "",
        "## What is measured",
        "",
        "One interactive update: move one control (an Empty, a pose bone or one cage vertex; a different",
        "small translation + rotation each time), then `view_layer.update()` twice. The first pass moves",
        "the control and runs our `depsgraph_update_post` handler, which writes the offsets into a mesh",
        "attribute; the second pass re-evaluates the Geometry Nodes modifier that adds them (for native",
        "modifiers the second pass finds nothing to do). After every repetition the evaluated vertex",
        "positions are read back (untimed) and must differ from the previous repetition's, and after the",
        "last one a third pass must change nothing; column *check* is empty when both hold.",
        "",
        f"Median of {plan.reps} repetitions after {plan.warmup} untimed warm-up run(s); IQR = 25th – 75th",
        "percentile. Every method runs alone in a fresh scene of the same bpy process, on the same",
        "procedurally built UV sphere (radius 1). Probes sit on a Fibonacci lattice on its surface; the",
        f"falloff radius is {plan.radius} for every method. Ratios are ours ÷ native: below 1 means we",
        "are faster.",
        "",
        "Keep in mind: Blender's modifiers are compiled C++ (Armature and Mesh Deform multi-threaded);",
        "ours is a Python handler whose per-vertex map runs in the compiled kernel (C, bundled with",
        "the extension; multi-threaded) or, without it, in numpy. On a 2-core machine shared with other",
        "work both sides are sensitive to load, so compare numbers from the same run only (the run keeps",
        "about one core busy, which shows in the load average afterwards). Mesh Deform's bind is a",
        "one-off cost (Dynamic off); our bind is the add operator, which binds.",
        "",
        "## Summary (computed from the tables below)",
        "",
        *[f"- {line}" for line in report.summary],
        "",
        "## Machine",
        "",
        f"- CPU: {after['cpu']}, {after['cores']} cores (shared with other work)",
        f"- bpy {after['bpy']}, numpy {after['numpy']}, Python {after['python']}, "
        f"OPENBLAS_CORETYPE={after['OPENBLAS_CORETYPE']}",
        f"- our kernel: {before.get('kernel', 'n/a')}",
        f"- date: {after['date']}; the run took {elapsed:.0f} s",
        f"- load average (1, 5, 15 min) before: {before['load']}; after: {after['load']}",
        "",
        "## Results",
        "",
    ]
    for table in report.tables:
        lines += [table.markdown(), ""]
    extra = report.notes + [f"**problem**: {p}" for p in report.problems]
    if extra:
        lines += ["## Notes", "", *[f"- {n}" for n in extra], ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines), encoding="utf-8")
