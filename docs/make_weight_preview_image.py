"""Render docs/images/weight_preview.png: what Show Weights puts in the viewport, three panels.

1. A probe deformer on Suzanne (Surface weights, eight probes), the left-ear probe pulled out and
   turned; the preview shows that probe's weights on the weight-paint ramp (blue 0 → red 1).
2. The same rig with the preview in 'All Controls': each probe's colour mixed by the weights (the
   small spheres mark the probes in their colours).
3. A cage deformer (the 384-quad box cage of tests/blender/cage_field.py, harmonic weights): the
   weights of one cage face (outlined) in front of the cheek, with Fit Range (the ramp up to the
   face's largest weight: one face of 384 holds little weight anywhere).

"Viewport-like": Workbench in background mode with Solid-style flat-studio lighting and attribute
colours, as the 3D view draws them. The preview modifier is viewport-only by design (renders never
see it), so each panel renders a snapshot of the mesh as the viewport evaluates it
(`Mesh.new_from_object` of the viewport depsgraph: the deformed shape with the preview colours) —
checked against the add-on's own `weight_preview.preview_colors` before rendering.

    .venv/bin/python docs/make_weight_preview_image.py [--output docs/images/weight_preview.png]
        [--resolution 300 270] [--package dist/….zip] [--user-dir DIR]
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "samples"))
sys.path.insert(0, str(ROOT / "tests" / "blender"))

import build_samples  # noqa: E402  (the sample scripts' Blender start-up and scene furniture)
import render_samples  # noqa: E402

PREVIEW_MODULE = f"{build_samples.ADDON_MODULE}.affine_deformers.blender.tools.weight_preview"
BACKGROUND = (0.16, 0.17, 0.19)
PANELS = ("Probe weights: the active probe (left ear)", "All probes, each in its colour",
          "Cage: one face (Fit Range, max {top:.2f})")


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "images" / "weight_preview.png")
    parser.add_argument("--resolution", nargs=2, type=int, default=(300, 270), metavar=("W", "H"),
                        help="size of each panel")
    build_samples.add_install_arguments(parser)
    return parser.parse_args(argv)


def colored(obj, color: Sequence[float]):
    """Give `obj` a constant point colour (linear RGB) as its active colour attribute."""
    mesh = obj.data
    attr = mesh.color_attributes.new("Color", "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", np.tile([*color, 1.0], len(mesh.vertices)).astype(np.float32))
    mesh.color_attributes.active_color = attr
    return obj


def marker(name: str, location, color, radius: float = 0.07):
    import bmesh
    import bpy

    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=16, v_segments=8, radius=radius)
    bm.to_mesh(mesh)
    bm.free()
    obj = build_samples.link(bpy.data.objects.new(name, mesh))
    obj.location = location
    return colored(obj, color)


def wire(name: str, mesh, thickness: float, color):
    import bpy

    obj = build_samples.link(bpy.data.objects.new(name, mesh))
    modifier = obj.modifiers.new("Wireframe", "WIREFRAME")
    modifier.thickness = thickness
    return colored(obj, color)


def snapshot(obj, preview) -> object:
    """A static copy of `obj` as the viewport shows it (deformed, preview colours), checked against the
    colours the add-on computes."""
    import bpy

    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = bpy.data.meshes.new_from_object(evaluated, preserve_all_data_layers=True, depsgraph=depsgraph)
    display = obj.data.color_attributes.active_color_name
    attr = mesh.color_attributes.get(display)
    if attr is None:
        raise RuntimeError(f"{obj.name}: the evaluated mesh has no colour attribute '{display}'")
    mesh.color_attributes.active_color = attr
    shown = np.empty(len(mesh.vertices) * 4, dtype=np.float32)
    attr.data.foreach_get("color", shown)
    deformer = next(d for d in obj.affine_deformers if d.show_weights)
    expected = preview.preview_colors(obj, deformer)
    if np.abs(shown.reshape(-1, 4)[:, :3] - expected).max() > 1e-6:
        raise RuntimeError(f"{obj.name}: the viewport colours differ from the preview's")
    copy = build_samples.link(bpy.data.objects.new(f"{obj.name}.Snapshot", mesh))
    copy.matrix_world = obj.matrix_world
    obj.hide_render = True
    return copy


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    package = args.package or build_samples.ensure_package()
    build_samples.start_blender(args.user_dir, package)
    import bpy
    import cage_field as cf

    preview = importlib.import_module(PREVIEW_MODULE)
    scene = build_samples.new_scene("WeightPreview", 1)
    render = scene.render
    render.engine = "BLENDER_WORKBENCH"
    render.resolution_x, render.resolution_y = args.resolution
    render.resolution_percentage = 100
    render.image_settings.file_format = "PNG"
    render.image_settings.color_mode = "RGB"
    shading = scene.display.shading
    shading.light = "STUDIO"
    shading.color_type = "VERTEX"
    shading.show_specular_highlight = False
    scene.display.render_aa = "16"
    scene.view_settings.view_transform = "Standard"  # the ramp's colours as designed
    scene.view_settings.look = "None"
    scene.world.color = BACKGROUND

    source = cf.build_scene("SUZANNE")
    rest = source.rest
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    ear = (0.93 * hi[0], 0.1, 0.25)
    probe_spots = {"LeftEar": ear, "RightEar": (0.93 * lo[0], 0.1, 0.25), "Crown": (0.0, 0.1, 0.92 * hi[2]),
                   "Chin": (0.0, -0.55, 0.9 * lo[2]), "Back": (0.0, 0.85 * hi[1], 0.0),
                   "Nose": (0.0, 0.97 * lo[1], -0.05), "LeftBrow": (0.4, -0.62, 0.42),
                   "RightBrow": (-0.4, -0.62, 0.42)}
    probes = []
    for name, location in probe_spots.items():
        probe = build_samples.link(bpy.data.objects.new(name, None))
        probe.location = location
        probes.append(probe)
    bpy.context.view_layer.update()

    panels = []
    for k, mode in enumerate(("ACTIVE", "ALL")):
        target = cf.link(f"Suzanne{mode.title()}", source.target_mesh.copy())
        with bpy.context.temp_override(active_object=target, object=target,
                                       selected_objects=[target, *probes]):
            if bpy.ops.object.affine_probe_deformer_add() != {"FINISHED"}:
                raise RuntimeError("adding the probe deformer failed")
        deformer = target.affine_deformers[0]
        deformer.weight_mode = "SURFACE"
        deformer.exponent = 3.0
        deformer.weight_preview = mode
        deformer.active_probe_index = 0
        deformer.show_weights = True
        panels.append((target, deformer, k))
    probes[0].location.x += 0.35
    probes[0].location.z += 0.15
    probes[0].rotation_euler = (0.0, math.radians(-30.0), math.radians(20.0))
    bpy.context.view_layer.update()

    cage_target, cage = cf.add_pair(source, "Cage")
    cage.hide_render = True
    cage_deformer = cf.bind_ours(cage_target, cage)
    centres = np.array([p.center for p in cage.data.polygons])
    size = hi - lo
    front = np.where(centres[:, 1] < lo[1], 0.0, np.inf)  # a face of the cage's front side
    face = int(np.argmin(front + np.abs(centres[:, 0] - 0.3 * size[0]) + np.abs(centres[:, 2] - 0.05)))
    cage_deformer.weight_preview_face = face
    cage_deformer.weight_preview_fit = True
    cage_deformer.show_weights = True
    panels.append((cage_target, cage_deformer, 2))
    bpy.context.view_layer.update()
    for target, deformer, _k in panels:
        if deformer.status and not deformer.status.startswith("Surface weights"):
            raise RuntimeError(f"{target.name}: {deformer.status}")

    snapshots = [snapshot(target, preview) for target, _deformer, _k in panels]
    palette = preview.control_palette(len(probes))
    grey, white = (0.85, 0.85, 0.85), (1.0, 1.0, 1.0)
    rest_markers = [marker(f"Mark{i}", p.matrix_world.translation, grey if i else white)
                    for i, p in enumerate(probes)]
    colour_markers = [marker(f"Dot{i}", p.matrix_world.translation, palette[i]) for i, p in enumerate(probes)]
    cage_wire = wire("CageWire", cage.data.copy(), 0.008, (0.55, 0.57, 0.6))
    outline_mesh = bpy.data.meshes.new("Face")
    corners = [tuple(cage.data.vertices[v].co) for v in cage.data.polygons[face].vertices]
    outline_mesh.from_pydata(corners, [], [list(range(len(corners)))])
    outline = wire("FaceOutline", outline_mesh, 0.03, (1.0, 0.45, 0.0))

    centre = 0.5 * (lo + hi)
    build_samples.add_camera((centre[0] + 2.4, centre[1] - 7.0, centre[2] + 1.8), tuple(centre), lens=68.0)
    top = float(preview.control_weights(cage_target, cage_deformer, face).max())
    render.use_stamp = True
    for prop in render.bl_rna.properties:
        if prop.identifier.startswith("use_stamp_"):
            setattr(render, prop.identifier, prop.identifier == "use_stamp_note")
    render.stamp_font_size = max(9, args.resolution[1] // 22)
    shown = {0: [snapshots[0], *rest_markers], 1: [snapshots[1], *colour_markers],
             2: [snapshots[2], cage_wire, outline]}
    extras = [*rest_markers, *colour_markers, cage_wire, outline, *snapshots]
    out_dir = args.output.parent / ".weight_preview_frames"
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for k, label in enumerate(PANELS):
        for obj in extras:
            obj.hide_render = obj not in shown[k]
        render.stamp_note_text = label.format(top=top)
        path = out_dir / f"panel{k}.png"
        render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        frames.append(render_samples.image_pixels(path))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    render_samples.save_png(render_samples.compose_sheet(frames), args.output)
    for path in out_dir.iterdir():
        path.unlink()
    out_dir.rmdir()
    print(f"wrote {args.output} ({args.output.stat().st_size // 1024} KB); cage face {face}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
