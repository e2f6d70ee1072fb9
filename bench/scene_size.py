"""(w) Studio-size scenes: what a frame costs when the deformed mesh is one of thousands of objects.

Every depsgraph evaluation walks all operations of the scene's graph (a few µs per visible object),
so in a large scene what matters is how many evaluations a frame costs and what a write makes Blender
redo. Rows, in one run on the same meshes:

* one deformed ~5,000-vertex mesh, 4 keyed probes, beside 0 / 5,000 / 20,000 other objects (Empties):
  ours (the store the cost model picks, output_store.py) vs the same rig built with 4 Hooks — the
  Hooks' scene has the add-on enabled and idle (no deformer: what it costs a scene that does not use
  it) — and ours with each store forced, so the choice stays visible: attributes (a raw write, then a
  visibility re-flush over the whole graph) and positions (no re-flush, ~75 ns a point);
* a ~10,000-vertex mesh with 8 probes, playback (every probe keyed) and drag (one probe moved), ours
  vs 8 Hooks.
One frame = frame_set(f) + settle, as (p); one drag = move + settle, as (a).
"""

from __future__ import annotations

import contextlib
import sys
import traceback

import bpy
import common
import native
import ours
import playback
import write_paths
from common import Samples, Table, fmt_ms, fmt_ratio

FRAMES = 24


def _store(forced: str | None) -> None:
    module = sys.modules.get(f"{ours.PKG}.{ours.EXT_ID}.blender.update.output_store")
    if module is not None:
        module.forced = forced


def _others(count: int) -> None:
    """`count` Empties in a collection of their own, visible (each one is in every evaluation's walk)."""
    if not count:
        return
    others = bpy.data.collections.new("Others")
    bpy.context.scene.collection.children.link(others)
    for i in range(count):
        others.objects.link(bpy.data.objects.new(f"Other.{i:05d}", None))


def _rig(n_target: int, probes: int, others: int, build) -> bpy.types.Object:
    _others(others)
    target = common.sphere_object("Target", n_target)
    empties = native.add_empties(common.probe_sites(probes))
    build(target, empties)
    playback._key_objects(empties, FRAMES)
    return target


def _row(label: str, make, report, measure=None) -> Samples | None:
    try:
        target = make()
        samples = (measure or (lambda t: playback.time_playback(t, FRAMES)))(target)
        status = [d.status for d in getattr(target, "affine_deformers", ()) if d.status]
        if status:
            report.notes.append(f"(w) {label}: the deformer reported “{status[0]}”")
        if samples.stale:
            report.problems.append(f"(w) {label}: {samples.stale} frames changed nothing")
        print(f"  {label:<58} {fmt_ms(samples.median):>9}", flush=True)
        return samples
    except Exception as exc:  # one broken row must not hide the others
        traceback.print_exc()
        report.problems.append(f"(w) {label}: {type(exc).__name__}: {exc}")
        return None
    finally:
        _store(None)
        common.clear_scene()


def part_w(plan, have_ours: bool, report) -> None:
    n_target, probes, sizes = plan.w_verts, 4, plan.w_others
    print(f"(w) one ~{n_target:,}-vertex mesh with {probes} keyed probes beside other objects", flush=True)
    radius = plan.radius

    def ours_rig(others: int, forced: str | None = None):
        def make():
            target = _rig(n_target, probes, others, lambda t, e: ours.probe_rig(t, e, radius))
            _store(forced)
            return target
        return make

    def hooks_rig(others: int):
        return lambda: _rig(n_target, probes, others, lambda t, e: native.hooks(t, e, radius))

    table = Table(f"(w) playback of {FRAMES} keyed frames: one ~{n_target:,}-vertex mesh, {probes} keyed "
                  "probes, beside other objects", ["other objects", "method", "per frame", "ours ÷ Hooks",
                                                   "check"])
    summary = []
    for others in sizes:
        hooks = _row(f"beside {others:,}: Hooks ×{probes} (add-on idle)", hooks_rig(others), report)
        rows = []
        if have_ours and ours.operator_exists(ours.PROBE_OP):
            rows.append(("ours (the store the cost model picks)",
                         _row(f"beside {others:,}: ours", ours_rig(others), report)))
            for forced, what in (("ATTRIBUTES", "attributes"), ("POSITIONS", "a position carrier")):
                rows.append((f"ours, written to {what}",
                             _row(f"beside {others:,}: ours, {what}", ours_rig(others, forced), report)))
        for label, s in [*rows, (f"Hook ×{probes} (the add-on enabled, idle)", hooks)]:
            if s is None:
                continue
            ratio = fmt_ratio(s.median, hooks.median) if hooks is not None else "—"
            table.add(f"{others:,}", label, fmt_ms(s.median), ratio, f"{s.stale} stale" if s.stale else "")
        if rows and rows[0][1] is not None and hooks is not None:
            mine = rows[0][1].median
            summary.append(f"beside {others:,}: ours {fmt_ms(mine)}, Hooks {fmt_ms(hooks.median)} "
                           f"({fmt_ratio(mine, hooks.median)})")
    table.notes.append("one frame = frame_set + settle; the Hooks' scene has the add-on enabled with no "
                       "deformer; the forced rows write every update to one store (output_store.forced)")
    report.tables.append(table)
    if summary:
        report.summary.append(f"(w) one ~{n_target:,}-vertex mesh, {probes} keyed probes: "
                              + "; ".join(summary) + ".")
    _part_w_large(plan, have_ours, report)
    write_paths.part_w_paths(plan, report)


def _part_w_large(plan, have_ours: bool, report) -> None:
    """A ~10k mesh with 8 probes: playback and drag, ours vs 8 Hooks, in a scene of its own."""
    n_target, probes = plan.w_large_verts, 8
    sites = common.probe_sites(probes)
    print(f"(w) a ~{n_target:,}-vertex mesh with {probes} probes: playback and drag", flush=True)

    def make(build):
        def inner():
            target = common.sphere_object("Target", n_target)
            empties = native.add_empties(sites)
            build(target, empties)
            playback._key_objects(empties, FRAMES)
            inner.empties = empties
            return target
        return inner

    def drag(make_rig):
        def measure(target):
            scene = bpy.context.scene
            scene.frame_set(1)
            for empty in make_rig.empties:  # a drag: no animation, one probe moved
                empty.animation_data_clear()
            move = native.move_object(make_rig.empties[0])
            return common.time_updates(move, target, plan.reps, plan.warmup)
        return measure

    ours_make = make(lambda t, e: ours.probe_rig(t, e, plan.radius))
    hooks_make = make(lambda t, e: native.hooks(t, e, plan.radius))
    kernel: list[float | None] = []
    floor_label = "floor: a handler that only writes"

    def floor_make():
        target = ours_make()
        kernel.append(ours.kernel_seconds([target]))
        stack.enter_context(ours.write_only_updates())  # left when the row's scene is cleared
        return target

    rows = []
    for what, measure_of in (("playback", None), ("drag", drag)):
        if have_ours and ours.operator_exists(ours.PROBE_OP):
            rows.append((what, "ours", _row(f"{what}: ours", ours_make, report,
                                            measure_of(ours_make) if measure_of else None)))
            if what == "playback":
                with contextlib.ExitStack() as stack:
                    rows.append((what, floor_label, _row(f"{what}: floor", floor_make, report)))
        rows.append((what, f"Hook ×{probes}", _row(f"{what}: Hooks", hooks_make, report,
                                                   measure_of(hooks_make) if measure_of else None)))
    table = Table(f"(w) a ~{n_target:,}-vertex mesh with {probes} probes: playback ({FRAMES} keyed frames) "
                  "and drag (one probe moved)", ["case", "method", "per frame / update", "ours ÷ Hooks"])
    for what in ("playback", "drag"):
        found = {method: s for case, method, s in rows if case == what}
        hooks = found.get(f"Hook ×{probes}")
        for method, s in found.items():
            if s is None:
                continue
            ratio = fmt_ratio(s.median, hooks.median) if hooks is not None else "—"
            table.add(what, method, fmt_ms(s.median), ratio)
    table.notes.append(f"{floor_label}: our update replaced by one that writes a constant offset and the "
                       "stamp each frame (our modifier and Blender's re-evaluation stay): what no faster "
                       "computation goes below")
    if kernel and kernel[0] is not None:
        table.notes.append(f"our compiled per-vertex map alone, every vertex: {fmt_ms(kernel[0])}")
    report.tables.append(table)
    mine = {case: s for case, method, s in rows if method == "ours" and s is not None}
    hooks = {case: s for case, method, s in rows if method.startswith("Hook") and s is not None}
    if mine and len(hooks) == len(mine):
        report.summary.append(f"(w) a ~{n_target:,}-vertex mesh, {probes} probes: " + "; ".join(
            f"{case} ours {fmt_ms(mine[case].median)} vs Hooks {fmt_ms(hooks[case].median)} "
            f"({fmt_ratio(mine[case].median, hooks[case].median)})" for case in mine) + ".")
