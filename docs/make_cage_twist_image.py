"""Render docs/images/cage_twist.png: the top half of a box cage around Suzanne turned 45°.

Three panels, the same cage edit on identical copies of the mesh (tests/blender/cage_field.py, the
scene of tests/blender/test_field_quality.py): our cage deformer at its defaults (harmonic weights),
Blender's Mesh Deform (precision 5), and our cage deformer with the inverse-distance weights of 0.1
(Cage Weights option). Cycles on the CPU like samples/render_samples.py, background mode; the
measured field metrics are printed (the README quotes them).

    .venv/bin/python docs/make_cage_twist_image.py [--output docs/images/cage_twist.png]
        [--resolution 262 240] [--cycles-samples 24] [--package dist/….zip] [--user-dir DIR]
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "samples"))
sys.path.insert(0, str(ROOT / "tests" / "blender"))

import build_samples  # noqa: E402  (the sample scripts' Blender start-up and scene furniture)
import render_samples  # noqa: E402

PANELS = (
    ("ours", "Affine cage (harmonic, default)"),
    ("mesh_deform", "Mesh Deform (precision 5)"),
    ("idw", "Affine cage (inverse distance)"),
)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "images" / "cage_twist.png")
    parser.add_argument("--resolution", nargs=2, type=int, default=(262, 240), metavar=("W", "H"),
                        help="size of each panel")
    parser.add_argument("--cycles-samples", type=int, default=24)
    parser.add_argument("--threads", type=int, default=0, help="render threads (0: all cores)")
    build_samples.add_install_arguments(parser)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    package = args.package or build_samples.ensure_package()
    build_samples.start_blender(args.user_dir, package)
    import bpy
    import cage_field as cf

    scene = build_samples.new_scene("CageTwist", 1)
    render_samples.configure_render(scene, tuple(args.resolution), args.cycles_samples, denoise=True,
                                    stamp=False, threads=args.threads)
    source = cf.build_scene("SUZANNE")
    rest, edges, cage_rest = source.rest, source.edges, source.cage_rest
    build_samples.store_rest_attribute(source.target_mesh)
    checker = build_samples.checker_material("Suzanne", (0.75, 0.3, 0.06), (0.92, 0.9, 0.84),
                                             scale=(3.5, 3.5, 3.5))
    source.target_mesh.materials.append(checker)
    for polygon in source.target_mesh.polygons:
        polygon.use_smooth = True

    targets, cages = {}, {}
    for name, _label in PANELS:
        targets[name], cages[name] = cf.add_pair(source, name)
        cages[name].hide_render = True
    cf.bind_mesh_deform(targets["mesh_deform"], cages["mesh_deform"])
    cf.bind_ours(targets["ours"], cages["ours"])
    cf.bind_ours(targets["idw"], cages["idw"], cage_weights="INVERSE_DISTANCE")

    twisted = cf.edited_cage("SUZANNE", "TWIST", cage_rest)
    for cage in cages.values():
        cf.write_co(cage.data, twisted)
    wire = build_samples.link(bpy.data.objects.new("CageWire", source.cage_mesh.copy()))
    cf.write_co(wire.data, twisted)
    modifier = wire.modifiers.new("Wireframe", "WIREFRAME")
    modifier.thickness = 0.012
    wire.data.materials.append(build_samples.plain_material("Wire", (0.1, 0.12, 0.16), roughness=0.6))

    metrics = {}
    for name, _label in PANELS:
        metrics[name] = cf.field_metrics("SUZANNE", "TWIST", rest, cf.evaluated(targets[name]), edges,
                                         cage_rest)
        for deformer in getattr(targets[name], "affine_deformers", ()):
            if deformer.status:
                raise RuntimeError(f"{name}: {deformer.status}")
    for key in metrics["mesh_deform"]:
        print(f"{key:17s} " + "  ".join(f"{name} {metrics[name][key]:.4g}" for name, _ in PANELS))

    centre = cf.twist_centre(cage_rest)
    build_samples.add_camera((centre[0] + 3.4, centre[1] - 7.2, centre[2] + 2.6), tuple(centre), lens=78.0)
    build_samples.add_lights(tuple(centre))
    frames = []
    out_dir = args.output.parent / ".cage_twist_frames"
    out_dir.mkdir(parents=True, exist_ok=True)
    render = scene.render
    render.use_stamp = True
    for prop in render.bl_rna.properties:
        if prop.identifier.startswith("use_stamp_"):
            setattr(render, prop.identifier, prop.identifier == "use_stamp_note")
    render.stamp_font_size = max(9, args.resolution[1] // 20)
    for name, label in PANELS:
        for other, obj in targets.items():
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
    size = args.output.stat().st_size // 1024
    print(f"wrote {args.output} ({size} KB); twist {math.degrees(cf.TWIST_ANGLE):.0f}°")
    return 0


if __name__ == "__main__":
    sys.exit(main())
