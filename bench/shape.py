"""(s) Shape preservation under large poses: a bar bent 90° and 180° and twisted 270° by two bones, and a
cage pull on Suzanne — ours (the per-vertex field, and the shape-preserving pass where the deformer has
it) vs the Armature modifier with Preserve Volume and Mesh Deform on the same rigs.

Bar: a capped cylinder along z (radius 0.3, length 4) skinned by two connected bones (z −2 → 0 → 2) through
vertex groups that blend smoothly over |z| < 0.5; the tip bone turns about the world x axis (bend) or
about its own axis (twist). Mesh Deform follows a coarse cylinder cage around the bar, skinned by the
same bones with Preserve Volume (how riggers drive Mesh Deform). Suzanne: the cage pull of
tests/blender/cage_field.py (ours: the cage deformer at its defaults; Mesh Deform, precision 5).

Metrics on the evaluated mesh: volume ratio (signed volume of the closed mesh ÷ rest; Suzanne is open:
—), edge-length distortion |l/l0 − 1| (max and p99 over edges), roughness (`curvature_change`: the
change of the umbrella Laplacian's length, p99, blind to rigid motion), and the update time (pose the
tip bone anew + settle) at
each size in `plan.s_verts`.
"""

from __future__ import annotations

import importlib
import math
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import bpy
import common
import native
import numpy as np
import ours
from common import Table, fmt_ms
from mathutils import Vector

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from tests.blender import cage_field as cf  # the Suzanne scene and its pull

BAR_RADIUS, BAR_LENGTH, BLEND_HALF_WIDTH = 0.3, 4.0, 0.5
POSES = (("bend 90°", "BEND", 90.0), ("bend 180°", "BEND", 180.0), ("twist 270°", "TWIST", 270.0))
#: Our deformer's settings per row: the per-vertex field, then the shape-preserving pass where the
#: deformer has it (rows whose properties the deformer lacks are left out).
OUR_ROWS = (("ours, per-vertex field", {}),
            ("ours, shape pass", {"preserve_shape": True}),
            ("ours, shape pass, 2 iterations", {"preserve_shape": True, "shape_iterations": 2}))


# ---------------------------------------------------------------------------------------------- metrics


def volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume Σ a · (b × c) / 6 over the triangles (a closed mesh with outward normals)."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def triangles_of(mesh: bpy.types.Mesh) -> np.ndarray:
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3)


def edge_ratios(rest: np.ndarray, moved: np.ndarray, edges: np.ndarray) -> np.ndarray:
    a, b = edges[:, 0], edges[:, 1]
    lengths = np.linalg.norm(moved[a] - moved[b], axis=1)
    return np.abs(lengths / np.linalg.norm(rest[a] - rest[b], axis=1) - 1.0)


def curvature_change(rest: np.ndarray, moved: np.ndarray, edges: np.ndarray) -> float:
    """p99 over vertices of ||L x'| − |L x|| ÷ the mean |L x|, L x = x − the mean of x over the
    neighbours (the umbrella Laplacian): zero for any rigid motion, small for a smooth bend, large at
    creases, kinks and dents — a roughness that large rotations leave alone."""
    before = np.linalg.norm(rest - cf.neighbour_mean(rest, edges), axis=1)
    after = np.linalg.norm(moved - cf.neighbour_mean(moved, edges), axis=1)
    return float(np.percentile(np.abs(after - before), 99.0) / before.mean())


def mid_turn(rest: np.ndarray, moved: np.ndarray) -> float:
    """Degrees the bar's side turns about its axis at z = 0, the middle of the blend (a twist by θ keyed
    on the tip bone gives θ/2 there): the mean unwrapped angle of the side vertices nearest z = 0."""
    side = np.hypot(rest[:, 0], rest[:, 1]) > 0.99 * BAR_RADIUS
    z = np.where(side, np.abs(rest[:, 2]), np.inf)
    ring = np.flatnonzero(z <= z.min() + 1e-6)
    before = np.arctan2(rest[ring, 1], rest[ring, 0])
    after = np.arctan2(moved[ring, 1], moved[ring, 0])
    return float(np.degrees(np.angle(np.exp(1j * (after - before)).mean())) % 360.0)


def metrics(rest: np.ndarray, moved: np.ndarray, edges: np.ndarray, triangles: np.ndarray | None) -> dict:
    distortion = edge_ratios(rest, moved, edges)
    kept = volume(moved, triangles) / volume(rest, triangles) if triangles is not None else math.nan
    return {"volume": kept,
            "edge max": float(distortion.max()), "edge p99": float(np.percentile(distortion, 99.0)),
            "roughness": curvature_change(rest, moved, edges)}


# ---------------------------------------------------------------------------------------------- the bar


def bar_object(name: str, n_verts: int) -> bpy.types.Object:
    """The capped cylinder bar with about `n_verts` vertices (rings ≈ 2.5 × segments: square-ish quads)."""
    segments = max(16, round(math.sqrt(n_verts / 2.5)))
    rings = max(8, n_verts // segments)
    mesh = cf.cylinder_mesh(name, segments, rings, BAR_RADIUS, BAR_LENGTH)
    return common.link_object(name, mesh)


def tip_weight(z: np.ndarray) -> np.ndarray:
    """The tip bone's weight: smoothstep over |z| < BLEND_HALF_WIDTH (the root bone has 1 − it)."""
    t = np.clip((z + BLEND_HALF_WIDTH) / (2.0 * BLEND_HALF_WIDTH), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def two_bones(name: str) -> bpy.types.Object:
    """An armature with Root (z −2 → 0) and Tip (0 → 2, connected), rotations as XYZ Euler channels."""
    arm = common.link_object(name, bpy.data.armatures.new(name))
    previous = bpy.context.view_layer.objects.active
    bpy.context.view_layer.objects.active = arm
    bpy.context.view_layer.update()
    with bpy.context.temp_override(active_object=arm, object=arm, selected_objects=[arm]):
        bpy.ops.object.mode_set(mode="EDIT")
        root = arm.data.edit_bones.new("Root")
        root.head, root.tail = (0.0, 0.0, -0.5 * BAR_LENGTH), (0.0, 0.0, 0.0)
        tip = arm.data.edit_bones.new("Tip")
        tip.head, tip.tail = (0.0, 0.0, 0.0), (0.0, 0.0, 0.5 * BAR_LENGTH)
        tip.parent, tip.use_connect = root, True
        bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.objects.active = previous
    for pose_bone in arm.pose.bones:
        pose_bone.rotation_mode = "XYZ"
    return arm


def skin_groups(obj: bpy.types.Object) -> None:
    w = tip_weight(common.rest_positions(obj)[:, 2])
    native.assign_vertex_group(obj, "Root", 1.0 - w)
    native.assign_vertex_group(obj, "Tip", w)


def armature_modifier(obj: bpy.types.Object, arm: bpy.types.Object, preserve_volume: bool = True) -> None:
    mod = obj.modifiers.new("Armature", "ARMATURE")
    mod.object, mod.use_vertex_groups, mod.use_bone_envelopes = arm, True, False
    mod.use_deform_preserve_volume = preserve_volume


def pose_tip(arm: bpy.types.Object, how: str, degrees: float) -> None:
    """Turn the Tip bone by `degrees` about world x (BEND) or its own axis, world z (TWIST), as one Euler
    channel: a turn past 180° is what the artist keyed (a quaternion would make 270° and −90° the same
    rotation for any blend of matrices)."""
    bone = arm.data.bones["Tip"]
    axis = Vector((1.0, 0.0, 0.0)) if how == "BEND" else Vector((0.0, 0.0, 1.0))
    local = bone.matrix_local.to_3x3().inverted() @ axis
    k = max(range(3), key=lambda i: abs(local[i]))
    assert abs(abs(local[k]) - 1.0) < 1e-6, "the bones have no roll: world axes are bone axes"
    euler = [0.0, 0.0, 0.0]
    euler[k] = math.copysign(math.radians(degrees), local[k])
    arm.pose.bones["Tip"].rotation_euler = euler


def move_tip(arm: bpy.types.Object, how: str, degrees: float) -> Callable[[int], None]:
    """move(i) for the timing: the pose at `degrees` plus a small different turn every rep."""
    def move(i: int) -> None:
        pose_tip(arm, how, degrees + 2.0 * math.sin(0.7 * i + 0.3))
    return move


def bar_rigs(n_verts: int, have_ours: bool) -> dict[str, tuple[bpy.types.Object, bpy.types.Object]]:
    """{row label: (bar, armature)} — every row on its own bar and armature, side by side in one scene."""
    rigs = {}
    labels = ["Armature, Preserve Volume", "Mesh Deform (cage skinned, Preserve Volume)"]
    if have_ours and ours.operator_exists(ours.BONE_OP):
        labels = [label for label, _ in OUR_ROWS] + labels
    for label in labels:
        bar, arm = bar_object(f"Bar {label}", n_verts), two_bones(f"Bones {label}")
        skin_groups(bar)
        if label.startswith("ours"):
            ours.bone_rig(bar, arm, move_tip(arm, "BEND", 90.0))
            deformer = bar.affine_deformers[0]
            settings = dict(OUR_ROWS)[label]
            if not all(hasattr(deformer, key) for key in settings):
                _remove(bar, arm)
                continue
            for key, value in settings.items():
                setattr(deformer, key, value)
        elif label.startswith("Armature"):
            armature_modifier(bar, arm)
        else:
            cage_mesh = cf.cylinder_mesh(f"Cage {label}", 8, 9, 1.6 * BAR_RADIUS, 1.1 * BAR_LENGTH)
            cage = common.link_object(f"Cage {label}", cage_mesh)
            skin_groups(cage)
            armature_modifier(cage, arm)
            cage.display_type = "WIRE"
            binds[label] = fmt_ms(native.mesh_deform(bar, cage, 5).bind_seconds)
        rigs[label] = (bar, arm)
    bpy.context.view_layer.update()
    return rigs


#: Mesh Deform's bind time per row label of the last `bar_rigs`.
binds: dict[str, str] = {}


def factor_summary(obj: bpy.types.Object) -> str:
    """Our deformer's Preserve Shape factor (time, memory) as its panel shows it, or ''."""
    deformers = getattr(obj, "affine_deformers", ())
    if not len(deformers) or not getattr(deformers[0], "preserve_shape", False):
        return ""
    try:
        module = importlib.import_module(f"{ours.INNER}.blender.update.shape_pass")
    except ImportError:
        return ""
    return module.summary(obj, deformers[0])


def _remove(*objects: bpy.types.Object) -> None:
    for obj in objects:
        bpy.data.objects.remove(obj, do_unlink=True)


# ---------------------------------------------------------------------------------------------- the part


def part_s(plan, have_ours: bool, report) -> None:
    sizes = plan.s_verts
    print(f"(s) shape preservation: bar bent / twisted by two bones at {', '.join(f'{n:,}' for n in sizes)} "
          "vertices; Suzanne cage pull", flush=True)
    quality = Table("(s) shape preservation: a bar bent and twisted by two bones, Suzanne's cage pulled",
                    ["rig", "method", "volume ratio", "edge |l/l0 − 1| max", "p99", "roughness p99",
                     "turn at mid-blend"])
    timing = Table("(s) update time under a large pose (bar bent 90°, tip bone re-posed)",
                   ["vertices", "method", "per update", "bind"])
    for n in sizes:
        try:
            _bar_part(n, n == sizes[0], have_ours, plan, quality, timing)
        except Exception as exc:  # one broken size must not hide the others
            traceback.print_exc()
            report.problems.append(f"(s) bar at {n:,} vertices: {type(exc).__name__}: {exc}")
        finally:
            common.clear_scene()
    try:
        _suzanne_part(have_ours, quality)
    except Exception as exc:
        traceback.print_exc()
        report.problems.append(f"(s) Suzanne: {type(exc).__name__}: {exc}")
    finally:
        common.clear_scene()
    quality.notes.append("volume ratio: signed volume ÷ rest (1 = kept; Suzanne is open: —); edge "
                         "distortion over all edges; roughness: p99 of ||L x′| − |L x|| ÷ mean |L x| "
                         "(L: x − the mean of its neighbours; 0 for any rigid motion)")
    quality.notes.append("twist: the tip bone's Euler channel is keyed to 270°; a method that takes the "
                         "shortest way turns −90° (270° mod 360 at the tip, −45° = 315° mid-blend) and "
                         "stretches less because it twists less")
    quality.notes.append("Mesh Deform on the bar follows a 72-vertex cylinder cage skinned by the same "
                         "bones with Preserve Volume; precision 5")
    timing.notes.append("one update = re-pose the tip bone near 90° + settle; bind: Mesh Deform's bind, "
                        "or the Preserve Shape factor (assembly, ordering, factorisation; built once at the "
                        "first update with the option on) as our panel reports it")
    report.tables += [quality, timing]


def _bar_part(n: int, measure_quality: bool, have_ours: bool, plan, quality: Table, timing: Table) -> None:
    t0 = time.perf_counter()
    rigs = bar_rigs(n, have_ours)
    print(f"  bar rigs at {n:,} vertices built in {time.perf_counter() - t0:.1f} s", flush=True)
    some_bar = next(iter(rigs.values()))[0]
    rest, edges = common.rest_positions(some_bar), cf.Scene("BAR", some_bar.data, some_bar.data).edges
    triangles = triangles_of(some_bar.data)
    if measure_quality:
        for pose_label, how, degrees in POSES:
            for _, arm in rigs.values():
                pose_tip(arm, how, degrees)
            common.settle()
            for label, (bar, _) in rigs.items():
                moved = common.evaluated_positions(bar).astype(np.float64)
                m = metrics(rest, moved, edges, triangles)
                turn = f"{mid_turn(rest, moved):.0f}° of {degrees / 2:.0f}°" if how == "TWIST" else ""
                quality.add(f"bar {pose_label} ({len(rest):,} verts)", label, f"{m['volume']:.3f}",
                            f"{m['edge max']:.3f}", f"{m['edge p99']:.3f}", f"{m['roughness']:.4f}", turn)
    for label, (bar, arm) in rigs.items():
        for _, other in rigs.values():  # only this rig moves while it is timed
            pose_tip(other, "BEND", 90.0)
        common.settle()
        samples = common.time_updates(move_tip(arm, "BEND", 90.0), bar, plan.reps, plan.warmup)
        timing.add(f"{len(rest):,}", label, fmt_ms(samples.median), binds.get(label) or factor_summary(bar))
        print(f"  {label:<48} {fmt_ms(samples.median):>9} per update at {len(rest):,}", flush=True)


def _suzanne_part(have_ours: bool, quality: Table) -> None:
    scene = cf.build_scene("SUZANNE")
    rest, edges = scene.rest, scene.edges
    pulled = cf.edited_cage("SUZANNE", "PULL", scene.cage_rest)
    rows = {}
    if have_ours and ours.operator_exists(ours.CAGE_OP):
        for label, settings in OUR_ROWS:
            target, cage = cf.add_pair(scene, label)
            deformer = cf.bind_ours(target, cage)
            if not all(hasattr(deformer, key) for key in settings):
                _remove(target, cage)
                continue
            for key, value in settings.items():
                setattr(deformer, key, value)
            rows[label] = (target, cage)
    target, cage = cf.add_pair(scene, "mesh_deform")
    cf.bind_mesh_deform(target, cage)
    rows["Mesh Deform, precision 5"] = (target, cage)
    for _target, cage in rows.values():
        cf.write_co(cage.data, pulled)
    common.settle()
    for label, (target, _) in rows.items():
        m = metrics(rest, cf.evaluated(target), edges, None)
        quality.add(f"Suzanne, cage pull ({len(rest):,} verts)", label, "—", f"{m['edge max']:.3f}",
                    f"{m['edge p99']:.3f}", f"{m['roughness']:.4f}", "")

