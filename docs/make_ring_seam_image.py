"""Render docs/images/ring_seam.png: 8 probes on a ring around an icosphere, one probe moved (issue 39).

The layout of the issue: an icosphere of radius 0.9 (40,962 vertices) inside a ring of 8 Empties of
radius 1, the probe deformer with inverse distance, Normalize Sum; probe 0 moved 0.36 up and turned
60° about the ring's tangent. Three panels, seen from above the pole where the ring's axis meets the
sphere (every probe ties there):

* before: the former truncation at the former default of 6 influences (the lowered weights
  w_j − w_{K+1} divided by their own sum, tests/core/field_ties.former_weights), computed with the
  numpy core and written into a copy of the mesh — the add-on no longer has that rule;
* now, at the defaults (8 influences: all 8 probes kept);
* now, at 4 influences (the pooled weight of docs/MATH.md §12 near the axis).

Cycles on the CPU like samples/render_samples.py, background mode; the seam measure of
tests/core/field_ties.py (largest edge jump / largest displacement, ÷ the untruncated field's) is
printed for each panel.

    .venv/bin/python docs/make_ring_seam_image.py [--output docs/images/ring_seam.png]
        [--resolution 300 280] [--cycles-samples 24] [--package dist/….zip] [--user-dir DIR]
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "samples"))
sys.path.insert(0, str(ROOT))

import build_samples  # noqa: E402  (the sample scripts' Blender start-up and scene furniture)
import render_samples  # noqa: E402

PANELS = (
    ("before", "Before: 6 influences, former rule"),
    ("defaults", "Now: defaults (8 influences)"),
    ("four", "Now: 4 influences"),
)
SPHERE_RADIUS = 0.9
PROBES = 8
SHIFT = 0.36
TURN = math.radians(60.0)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "images" / "ring_seam.png")
    parser.add_argument("--resolution", nargs=2, type=int, default=(300, 280), metavar=("W", "H"),
                        help="size of each panel")
    parser.add_argument("--cycles-samples", type=int, default=24)
    parser.add_argument("--threads", type=int, default=0, help="render threads (0: all cores)")
    build_samples.add_install_arguments(parser)
    return parser.parse_args(argv)


def icosphere(name: str, material: object) -> object:
    """An icosphere of radius SPHERE_RADIUS subdivided 6 times (40,962 vertices), smooth shaded."""
    import bmesh
    import bpy

    bm = bmesh.new()
    bmesh.ops.create_icosphere(bm, subdivisions=6, radius=SPHERE_RADIUS)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    obj = build_samples.add_mesh_object(name, mesh, material)
    for polygon in mesh.polygons:
        polygon.use_smooth = True
    return obj


def positions(obj: object, evaluated: bool) -> np.ndarray:
    import bpy

    mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data if evaluated else obj.data
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def edges(obj: object) -> np.ndarray:
    pairs = np.empty(len(obj.data.edges) * 2, dtype=np.int64)
    obj.data.edges.foreach_get("vertices", pairs)
    return pairs.reshape(-1, 2)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    package = args.package or build_samples.ensure_package()
    build_samples.start_blender(args.user_dir, package)
    import bpy
    from mathutils import Matrix

    from affine_deformers.core import aff3, deform
    from tests.core import field_ties as ft

    scene = build_samples.new_scene("RingSeam", 1)
    render_samples.configure_render(scene, tuple(args.resolution), args.cycles_samples, denoise=True,
                                    stamp=False, threads=args.threads)
    checker = build_samples.checker_material("Sphere", (0.75, 0.3, 0.06), (0.92, 0.9, 0.84),
                                             scale=(6.0, 6.0, 6.0))
    spheres = {name: icosphere(f"Sphere.{name}", checker) for name, _label in PANELS}
    ring = ft.ring(PROBES)
    probes, todo = {}, []
    for name in ("defaults", "four"):
        probes[name] = [build_samples.add_probe(f"{name}.P{i}", tuple(c), size=0.2)
                        for i, c in enumerate(ring)]
        settings = {"weight_mode": "INVERSE_DISTANCE", "normalize": "SUM"}
        build_samples.add_deformer("probe", spheres[name], probes[name], settings, todo)
    if todo:
        raise RuntimeError("; ".join(todo))
    spheres["four"].affine_deformers[0].max_influences = 4
    assert spheres["defaults"].affine_deformers[0].max_influences == 8, "the add operator's default"
    for name in ("defaults", "four"):
        moved = probes[name][0]  # on the +x axis: its ring's tangent there is y
        moved.location.z += SHIFT
        moved.rotation_euler.y = TURN

    rest = positions(spheres["before"], evaluated=False)
    layout = ft.Layout("ring", rest, edges(spheres["before"]), ring, 0, {})
    params = ft.motion_params(layout)
    idx, val = ft.former_weights(rest, ring, 6)
    before = deform.deform_points_params(rest, params, idx, val)
    spheres["before"].data.vertices.foreach_set("co", before.ravel())
    spheres["before"].data.update()
    moved = aff3.matrices_from_params(params)[0]  # the probes of the before panel: markers only
    for i, c in enumerate(ring):
        marker = build_samples.add_probe(f"before.P{i}", tuple(c), size=0.2)
        if i == 0:
            marker.matrix_world = Matrix(moved.tolist()) @ Matrix.Translation(tuple(c))

    untruncated = deform.deform_points_params(rest, params, *ft.deformer_weights(rest, ring, PROBES))
    full = ft.jump_ratio(untruncated - rest, layout.edges)
    shown = {"before": before - rest, "defaults": positions(spheres["defaults"], True) - rest,
             "four": positions(spheres["four"], True) - rest}
    for name, label in PANELS:
        for deformer in getattr(spheres[name], "affine_deformers", ()):
            if deformer.status:
                raise RuntimeError(f"{name}: {deformer.status}")
        ratio = ft.jump_ratio(shown[name], layout.edges) / full
        print(f"{label:36s} edge jump ratio ÷ untruncated: {ratio:.2f}")

    build_samples.add_camera((1.4, -2.1, 3.5), (0.0, 0.0, 0.5), lens=55.0)  # over the pole: the ring's axis
    build_samples.add_lights((0.0, 0.0, 0.5))
    frames = []
    out_dir = args.output.parent / ".ring_seam_frames"
    out_dir.mkdir(parents=True, exist_ok=True)
    render = scene.render
    render.use_stamp = True
    for prop in render.bl_rna.properties:
        if prop.identifier.startswith("use_stamp_"):
            setattr(render, prop.identifier, prop.identifier == "use_stamp_note")
    render.stamp_font_size = max(9, args.resolution[1] // 20)
    panel_objects = {}
    for name, _label in PANELS:
        prefixes = (f"Sphere.{name}", f"{name}.")
        panel_objects[name] = [obj for obj in bpy.data.objects if obj.name.startswith(prefixes)]
    for name, label in PANELS:
        for other, objects in panel_objects.items():
            for obj in objects:
                obj.hide_render = other != name
        render.stamp_note_text = label
        path = out_dir / f"{name}.png"
        render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        frames.append(render_samples.image_pixels(path))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    render_samples.save_png(render_samples.compose_sheet(frames), args.output)
    for path in out_dir.iterdir():
        path.unlink()
    out_dir.rmdir()
    print(f"wrote {args.output} ({args.output.stat().st_size // 1024} KB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
