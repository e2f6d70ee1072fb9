"""(p) Playback: frames per second over a keyed range with every control animated — the figure an
animator feels — ours vs Hooks, Armature (Preserve Volume) and Mesh Deform on the same meshes.

Every control is keyed at every frame (a different small translation + rotation each, from
common.wiggle), so no frame repeats the one before; one timed frame is `scene.frame_set(f)` plus a
depsgraph settle (our frame handler writes the output, the second pass applies it). The cage rows key
a shape key of the cage (its top half bulging), so Mesh Deform and ours both follow a changing cage.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
import traceback
from pathlib import Path

import bpy
import common
import native
import numpy as np
import ours
from common import Samples, Table, fmt_ms, fmt_ratio
from mathutils import Vector


def _key_objects(objects: list, frames: int) -> None:
    """Key location and rotation of every object at frames 1..frames, each with its own path."""
    for j, ob in enumerate(objects):
        base, base_rot = Vector(ob.location), Vector(ob.rotation_euler)
        for f in range(1, frames + 1):
            dt, dr = common.wiggle(f * len(objects) + j)
            ob.location = base + Vector(dt)
            ob.rotation_euler = base_rot + Vector(dr)
            ob.keyframe_insert("location", frame=f)
            ob.keyframe_insert("rotation_euler", frame=f)


def _key_pose_bones(arm: bpy.types.Object, frames: int) -> None:
    bones = list(arm.pose.bones)
    for j, pose_bone in enumerate(bones):
        pose_bone.rotation_mode = "XYZ"
        for f in range(1, frames + 1):
            dt, dr = common.wiggle(f * len(bones) + j)
            pose_bone.location = dt
            pose_bone.rotation_euler = dr
            pose_bone.keyframe_insert("location", frame=f)
            pose_bone.keyframe_insert("rotation_euler", frame=f)


def _key_cage_bulge(cage: bpy.types.Object, frames: int) -> None:
    """A shape key pushing the cage's top half outward, its value keyed differently at every frame."""
    cage.shape_key_add(name="Basis", from_mix=False)
    key = cage.shape_key_add(name="Bulge", from_mix=False)
    co = np.empty(len(cage.data.vertices) * 3, dtype=np.float32)
    key.data.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, :2] *= np.where(co[:, 2:3] > 0.0, 1.0 + 0.3 * co[:, 2:3], 1.0)
    key.data.foreach_set("co", co.ravel())
    for f in range(1, frames + 1):
        key.value = 0.5 + 0.5 * np.sin(0.9 * f)
        key.keyframe_insert("value", frame=f)


def time_playback(target: bpy.types.Object | list[bpy.types.Object], frames: int) -> Samples:
    """Seconds per frame of frame_set(f) + settle over frames 1..frames (after one untimed pass);
    a frame whose evaluated positions equal the previous frame's counts as stale."""
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, frames
    for f in (1, 2, 1):  # warm-up: caches and the compiled kernel
        scene.frame_set(f)
        common.settle()
    targets = target if isinstance(target, list) else [target]
    out = Samples()
    prev = [common.evaluated_positions(t) for t in targets]
    for f in range(2, frames + 1):
        t0 = time.perf_counter()
        scene.frame_set(f)
        common.settle()
        out.seconds.append(time.perf_counter() - t0)
        cur = [common.evaluated_positions(t) for t in targets]
        if any(np.array_equal(c, p) for c, p in zip(cur, prev, strict=True)):
            out.stale += 1
        prev = cur
    return out


def _row(label: str, build, frames: int, report) -> Samples | None:
    try:
        target = build()
        samples = time_playback(target, frames)
        targets = target if isinstance(target, list) else [target]
        status = [d.status for t in targets for d in getattr(t, "affine_deformers", ()) if d.status]
        if status:
            report.notes.append(f"(p) {label}: the deformer reported “{status[0]}”")
        if samples.stale:
            report.problems.append(f"(p) {label}: {samples.stale} frames changed nothing")
        print(f"  {label:<44} {fmt_ms(samples.median):>9} per frame", flush=True)
        return samples
    except Exception as exc:  # one broken row must not hide the others
        traceback.print_exc()
        report.problems.append(f"(p) {label}: {type(exc).__name__}: {exc}")
        return None
    finally:
        common.clear_scene()


def part_p(plan, have_ours: bool, report) -> None:
    m, frames, n_target = 8, plan.p_frames, plan.a_verts
    n = n_target  # the sphere is built for this many vertices (common.sphere_grid_for)
    print(f"(p) playback of {frames} keyed frames, {m} controls all animated, ~{n:,} vertices", flush=True)
    sites = common.probe_sites(m)

    def ours_probes():
        target = common.sphere_object("Target", n_target)
        empties = native.add_empties(sites)
        ours.probe_rig(target, empties, plan.radius)
        _key_objects(empties, frames)
        return target

    def hooks():
        target = common.sphere_object("Target", n_target)
        empties = native.add_empties(sites)
        native.hooks(target, empties, plan.radius)
        _key_objects(empties, frames)
        return target

    def armature():
        target = common.sphere_object("Target", n_target)
        weights = common.smooth_falloff(common.rest_positions(target), sites, plan.radius)
        native.armature(target, sites, weights)
        _key_pose_bones(bpy.data.objects["Rig"], frames)
        return target

    def cage_scene():
        target = common.sphere_object("Target", n_target)
        segments, rings = plan.cage_grid
        cage = common.link_object("Cage", common.uv_sphere_mesh("Cage", segments, rings, plan.cage_radius))
        return target, cage

    def ours_cage():
        target, cage = cage_scene()
        ours.cage_rig(target, cage)
        _key_cage_bulge(cage, frames)
        return target

    def mesh_deform():
        target, cage = cage_scene()
        native.mesh_deform(target, cage, plan.precision)
        _key_cage_bulge(cage, frames)
        return target

    hook_label, arm_label = f"Hook ×{m}, Smooth, same radius", f"Armature ×{m}, Preserve Volume"
    md_label = f"Mesh Deform, precision {plan.precision}"
    rows = []
    if have_ours and ours.operator_exists(ours.PROBE_OP):
        rows.append((f"Affine probes (ours), {m} keyed", _row(f"ours: {m} probes", ours_probes, frames,
                                                               report)))
    rows.append((hook_label, _row(f"Hook ×{m}", hooks, frames, report)))
    rows.append((arm_label, _row(arm_label, armature, frames, report)))
    if have_ours and ours.operator_exists(ours.CAGE_OP):
        rows.append(("Affine cage (ours), keyed shape key", _row("ours: cage", ours_cage, frames, report)))
    rows.append((md_label, _row("Mesh Deform", mesh_deform, frames, report)))

    t = Table(f"(p) playback: {frames} keyed frames, every control animated, ~{n:,} vertices",
              ["method", "per frame", "frames/s", "ours ÷ native", "check"])
    probe = next((s for label, s in rows if label.startswith("Affine probes")), None)
    cage = next((s for label, s in rows if label.startswith("Affine cage")), None)
    for label, s in rows:
        if s is None:
            continue
        mine = cage if label.startswith(("Mesh Deform", "Affine cage")) else probe
        native_row = mine is not None and label == hook_label
        ratio = fmt_ratio(mine.median, s.median) if native_row else "1.00×"
        check = f"{s.stale} stale" if s.stale else ""
        t.add(label, fmt_ms(s.median), f"{1.0 / s.median:.1f}", ratio, check)
    t.notes.append("frames/s = 1 / median seconds per frame (frame_set + settle); ratio column: ours ÷ "
                   "native, probes vs Hooks and Armature, cage vs Mesh Deform (below 1: ours is faster)")
    report.tables.append(t)
    by = dict(rows)
    hook_s, arm_s, md_s = by.get(hook_label), by.get(arm_label), by.get(md_label)
    if probe is not None and hook_s is not None and arm_s is not None:
        line = (f"(p) playback, {m} keyed controls on ~{n:,} vertices: ours {1.0 / probe.median:.1f} "
                f"frames/s, Hooks {1.0 / hook_s.median:.1f} ({fmt_ratio(probe.median, hook_s.median)}), "
                f"Armature with Preserve Volume {1.0 / arm_s.median:.1f} "
                f"({fmt_ratio(probe.median, arm_s.median)})")
        if cage is not None and md_s is not None:
            line += (f"; cage ours {1.0 / cage.median:.1f} vs Mesh Deform {1.0 / md_s.median:.1f} frames/s "
                     f"({fmt_ratio(cage.median, md_s.median)})")
        report.summary.append(line + ".")


def part_m(plan, have_ours: bool, report) -> None:
    """(m) Many deformed objects: a crowd or a prop-heavy shot multiplies whatever an update costs per
    object. `plan.m_objects` spheres of ~`plan.m_verts` vertices side by side, each with its own
    `plan.m_probes` keyed probes; playback as (p): ours vs the same rigs built with Hooks. Beside them
    what bounds ours from below: the floor of a Python handler feeding a Geometry Nodes modifier
    (`ours.write_only_updates`), the compiled per-vertex map alone (`ours.kernel_seconds`), and the
    rigs baked to PC2, the crowd's way to play."""
    count, n_target, m, frames = plan.m_objects, plan.m_verts, plan.m_probes, plan.p_frames
    print(f"(m) playback of {frames} keyed frames, {count} objects of ~{n_target:,} vertices, {m} probes "
          f"each", flush=True)
    sites = common.probe_sites(m)

    def scene(rig) -> list:
        targets = []
        for i in range(count):
            offset = np.array([3.0 * i, 0.0, 0.0])
            target = common.sphere_object(f"Target.{i:02d}", n_target)
            target.location = tuple(offset)
            empties = native.add_empties(sites + offset, prefix=f"Probe.{i:02d}")
            bpy.context.view_layer.update()
            rig(target, empties)
            _key_objects(empties, frames)
            targets.append(target)
        return targets

    def ours_rigs() -> list:
        return scene(lambda target, empties: ours.probe_rig(target, empties, plan.radius))

    def hook_rigs() -> list:
        return scene(lambda target, empties: native.hooks(target, empties, plan.radius))

    kernel: list[float | None] = []

    def ours_kernel_alone() -> list:
        targets = ours_rigs()
        kernel.append(ours.kernel_seconds(targets))
        return targets

    def ours_floor() -> list:
        targets = ours_rigs()
        stack.enter_context(ours.write_only_updates())  # left when the row's scene is cleared
        return targets

    def ours_replayed() -> list:
        targets = ours_rigs()
        scene = bpy.context.scene
        for f in range(1, frames + 1):  # every control's motion and parameters at every frame memoised
            scene.frame_set(f)
            common.settle()
        return targets

    def ours_baked() -> list:
        targets = ours_rigs()
        ours.bake_to_pc2(targets, frames, Path(tempfile.mkdtemp(prefix="affdef-bench-pc2-")))
        return targets

    hook_label = f"Hook ×{m} per object, Smooth, same radius"
    baked_label = "Affine probes baked to PC2 (Mesh Cache modifier; the deformers muted)"
    replay_label = "Affine probes, the frames played again (the per-control memos hit)"
    floor_label = "floor of a handler: writes only (no control read, nothing computed)"
    rows = []
    if have_ours and ours.operator_exists(ours.PROBE_OP):
        rows.append((f"Affine probes (ours), {m} per object", _row("ours: many objects", ours_kernel_alone,
                                                                   frames, report)))
        rows.append((replay_label, _row("replayed: many objects", ours_replayed, frames, report)))
        with contextlib.ExitStack() as stack:
            rows.append((floor_label, _row("floor: many objects", ours_floor, frames, report)))
        if ours.operator_exists(ours.BAKE_OP):
            rows.append((baked_label, _row("baked: many objects", ours_baked, frames, report)))
    rows.append((hook_label, _row("Hooks: many objects", hook_rigs, frames, report)))
    t, mine = _playback_table(f"(m) playback: {count} objects of ~{n_target:,} vertices, {m} keyed probes "
                              f"each, {frames} frames", rows, hook_label)
    t.notes.append("one frame = frame_set + settle with every object's probes keyed; ratio: ours ÷ Hooks")
    floor_s = dict(rows).get(floor_label)
    hook_s = dict(rows).get(hook_label)
    if floor_s is not None and hook_s is not None:
        t.notes.append(f"floor: our update replaced by one that writes a constant offset into every mesh "
                       f"(our Geometry Nodes modifier and Blender's re-evaluation stay): "
                       f"{fmt_ratio(floor_s.median, hook_s.median)} the Hook rigs' frame before anything "
                       "is read or computed")
    replay_s = dict(rows).get(replay_label)
    if replay_s is not None and mine is not None:
        t.notes.append(f"played again: every control's motion and parameters come from the memos, so the "
                       f"difference is their numerics: {fmt_ms(mine.median - replay_s.median)} of "
                       f"{fmt_ms(mine.median)}; the rest is the checks, the bookkeeping, the kernel and the "
                       "floor")
    baked_s = dict(rows).get(baked_label)
    if baked_s is not None and hook_s is not None:
        t.notes.append(f"baked: each object's deformer baked over the {frames} frames (Bake ▸ PC2); a muted "
                       f"deformer costs nothing per frame: {fmt_ratio(baked_s.median, hook_s.median)} the "
                       "Hook rigs' frame — the way to play a crowd")
    if kernel and kernel[0] is not None:
        t.notes.append(f"our compiled per-vertex map alone, all {count} objects once (no Python around it): "
                       f"{fmt_ms(kernel[0])}")
    report.tables.append(t)
    if mine is not None and hook_s is not None:
        report.summary.append(
            f"(m) {count} objects of ~{n_target:,} vertices, {m} keyed probes each: ours "
            f"{fmt_ms(mine.median)} per frame, Hooks {fmt_ms(hook_s.median)} "
            f"({fmt_ratio(mine.median, hook_s.median)})"
            + (f"; a handler that only writes: {fmt_ms(floor_s.median)} "
               f"({fmt_ratio(floor_s.median, hook_s.median)})" if floor_s is not None else "") + ".")
    _part_m_bones(plan, have_ours, report)


def _playback_table(title: str, rows: list[tuple[str, Samples | None]], native_label: str
                    ) -> tuple[Table, Samples | None]:
    """The table of (label, samples) rows, ours first (its label starts with 'Affine'): the native row
    gets ours ÷ native, ours 1.00×, the others (floors, variants of ours) a dash. Returns (table, ours)."""
    t = Table(title, ["method", "per frame", "frames/s", "ours ÷ native", "check"])
    mine = rows[0][1] if rows and rows[0][0].startswith("Affine") else None
    for label, s in rows:
        if s is None:
            continue
        native_row = mine is not None and label == native_label
        ratio = fmt_ratio(mine.median, s.median) if native_row else "1.00×" if s is mine else "—"
        t.add(label, fmt_ms(s.median), f"{1.0 / s.median:.1f}", ratio, f"{s.stale} stale" if s.stale else "")
    return t, mine


def _part_m_bones(plan, have_ours: bool, report) -> None:
    """(m) the crowd as characters: each of the objects skinned by its own armature (a chain of
    `plan.m_probes` bones, keyed), our bone deformer vs the Armature modifier with Preserve Volume."""
    count, n_target, m, frames = plan.m_objects, plan.m_verts, plan.m_probes, plan.p_frames

    def scene(ours_rig: bool) -> list:
        targets = []
        for i in range(count):
            target = common.sphere_object(f"Target.{i:02d}", n_target)
            arm = native.bone_chain(target, m, with_modifier=not ours_rig, preserve_volume=True)
            target.location = arm.location = (3.0 * i, 0.0, 0.0)
            if ours_rig:
                ours.bone_rig(target, arm, lambda _i: None)
            _key_pose_bones(arm, frames)
            targets.append(target)
        return targets

    rows = []
    if have_ours and ours.operator_exists(ours.BONE_OP):
        ours_row = _row("ours: many characters", lambda: scene(True), frames, report)
        rows.append((f"Affine bones (ours), {m} per object", ours_row))
    native_label = f"Armature ×{m} bones per object, Preserve Volume"
    rows.append((native_label, _row("Armature: many characters", lambda: scene(False), frames, report)))
    t, mine = _playback_table(f"(m) playback: {count} objects of ~{n_target:,} vertices, each skinned by its "
                              f"own armature ({m} keyed bones), {frames} frames", rows, native_label)
    t.notes.append("as above, the controls are each armature's keyed pose bones; ratio: ours ÷ Armature")
    report.tables.append(t)
    native_s = dict(rows).get(native_label)
    if mine is not None and native_s is not None:
        report.summary.append(f"(m) {count} characters of ~{n_target:,} vertices, {m} keyed bones each: ours "
                              f"{fmt_ms(mine.median)} per frame, Armature (Preserve Volume) "
                              f"{fmt_ms(native_s.median)} ({fmt_ratio(mine.median, native_s.median)}).")
