"""Render the sample scenes at their key frames with Cycles on the CPU, plus one contact sheet each.

`make demo` runs `.venv/bin/python samples/render_samples.py --output-dir out`. For every sample the
script opens the .blend afresh (the extension installed into an isolated Blender user directory),
renders each key frame to out/<sample>/frame_NNNN.png and composes the frames side by side into
out/<sample>/contact_sheet.png with numpy and bpy's image API. Missing .blend files are built first
with build_samples.py.

Defaults give small pictures quickly (240×160, 8 samples, OIDN denoising when this Blender has it);
`--resolution 32 24 --cycles-samples 1 --frames 1 24 --no-denoise` is the tiny run the tests use.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import build_samples  # a sibling script, found through the path entry above

SHEET_GAP = 4  # pixels of background between frames on a contact sheet
SHEET_BACKGROUND = (1.0, 1.0, 1.0, 1.0)


def configure_render(
    scene: object,
    resolution: Sequence[int],
    cycles_samples: int,
    denoise: bool,
    stamp: bool,
    threads: int,
) -> None:
    """Small, CPU-only Cycles settings; optionally burn the frame number into the corner."""
    import _cycles

    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = cycles_samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = bool(denoise and _cycles.with_openimagedenoise)
    if scene.cycles.use_denoising:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
    render.resolution_x, render.resolution_y = resolution
    render.resolution_percentage = 100
    render.threads_mode = "FIXED" if threads > 0 else "AUTO"
    if threads > 0:
        render.threads = threads
    render.image_settings.file_format = "PNG"
    render.image_settings.color_mode = "RGB"
    render.image_settings.color_depth = "8"
    render.image_settings.compression = 100
    render.use_stamp = stamp
    if stamp:
        for prop in render.bl_rna.properties:
            if prop.identifier.startswith("use_stamp_"):
                setattr(render, prop.identifier, prop.identifier in ("use_stamp_frame", "use_stamp_labels"))
        render.stamp_font_size = max(8, resolution[1] // 13)


def image_pixels(path: Path) -> np.ndarray:
    """An image file as a (height, width, 4) float32 array, bottom row first (bpy's order)."""
    import bpy

    image = bpy.data.images.load(str(path), check_existing=False)
    try:
        width, height = image.size
        pixels = np.empty(width * height * image.channels, dtype=np.float32)
        image.pixels.foreach_get(pixels)
        pixels = pixels.reshape(height, width, image.channels)
        if image.channels == 3:
            pixels = np.concatenate([pixels, np.ones((height, width, 1), np.float32)], axis=-1)
        return pixels
    finally:
        bpy.data.images.remove(image)


def compose_sheet(frames: Sequence[np.ndarray], gap: int = SHEET_GAP) -> np.ndarray:
    """Frames (all the same size) side by side with `gap` background pixels around and between them."""
    height, width = frames[0].shape[:2]
    sheet_width = len(frames) * width + (len(frames) + 1) * gap
    sheet = np.empty((height + 2 * gap, sheet_width, 4), dtype=np.float32)
    sheet[:] = SHEET_BACKGROUND
    for k, frame in enumerate(frames):
        left = gap + k * (width + gap)
        sheet[gap : gap + height, left : left + width] = frame
    return sheet


def save_png(pixels: np.ndarray, path: Path) -> None:
    """Write a (height, width, 4) array in bpy's row order as an 8-bit RGB PNG (maximum compression)."""
    import bpy

    height, width = pixels.shape[:2]
    image = bpy.data.images.new(path.stem, width, height, alpha=False)
    # Image.save() ignores the PNG compression level; save_render() takes it from a scene, and with the
    # 'Standard' view it writes the byte values read from the frames back unchanged.
    writer = bpy.data.scenes.new("contact_sheet_writer")
    try:
        writer.view_settings.view_transform = "Standard"
        writer.view_settings.look = "None"
        settings = writer.render.image_settings
        settings.file_format, settings.color_mode, settings.color_depth = "PNG", "RGB", "8"
        settings.compression = 100
        image.pixels.foreach_set(np.ascontiguousarray(pixels, dtype=np.float32).ravel())
        image.save_render(str(path), scene=writer)
    finally:
        bpy.data.images.remove(image)
        bpy.data.scenes.remove(writer)


def deformer_problems() -> list[str]:
    """Status messages of every deformer in the open file (empty when all are fine)."""
    import bpy

    problems = []
    for obj in bpy.data.objects:
        for deformer in getattr(obj, "affine_deformers", ()):
            status = getattr(deformer, "status", "")
            if status:
                problems.append(f"{obj.name}: {status}")
    return problems


def render_sample(
    blend: Path, out_dir: Path, frames: Sequence[int] | None, settings: dict
) -> tuple[list[Path], list[str]]:
    """Open blend afresh, render the frames to out_dir and write out_dir/contact_sheet.png.

    Returns the written images (the sheet last) and the deformer problems seen at any frame."""
    import bpy

    bpy.ops.wm.open_mainfile(filepath=str(blend), load_ui=False)
    scene = bpy.context.scene
    frames = list(frames) if frames else [int(f) for f in scene.get("affdef_key_frames", [scene.frame_start])]
    configure_render(scene, **settings)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    problems = []
    for frame in frames:
        scene.frame_set(frame)
        for problem in deformer_problems():
            problems.append(f"{blend.stem}, frame {frame}: {problem}")
            print(f"  warning, frame {frame}: {problem}")
        path = out_dir / f"frame_{frame:04d}.png"
        scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        if not path.exists():
            raise RuntimeError(f"Cycles wrote no image for {blend.name} frame {frame}")
        written.append(path)
    sheet = out_dir / "contact_sheet.png"
    save_png(compose_sheet([image_pixels(path) for path in written]), sheet)
    return [*written, sheet], problems


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    names = list(build_samples.SAMPLES)
    parser = argparse.ArgumentParser(description="Render the sample scenes and their contact sheets.")
    parser.add_argument("--output-dir", type=Path, default=Path("out"), help="images go to DIR/<sample>/")
    parser.add_argument(
        "--samples",
        nargs="+",
        choices=names,
        default=names,
        metavar="NAME",
        help=f"samples to render (default: all of {', '.join(names)})",
    )
    parser.add_argument(
        "--frames",
        nargs="+",
        type=int,
        default=None,
        help="frames to render (default: each sample's key frames)",
    )
    parser.add_argument("--resolution", nargs=2, type=int, default=(240, 160), metavar=("W", "H"))
    parser.add_argument("--cycles-samples", type=int, default=8)
    parser.add_argument(
        "--no-denoise",
        dest="denoise",
        action="store_false",
        help="skip OIDN denoising (used when this Blender has it)",
    )
    parser.add_argument(
        "--no-stamp", dest="stamp", action="store_false", help="do not burn the frame number into the images"
    )
    parser.add_argument("--threads", type=int, default=0, help="render threads (0: all cores)")
    parser.add_argument(
        "--blend-dir",
        type=Path,
        default=build_samples.SAMPLES_DIR,
        help="where the sample .blend files are (missing ones are built there)",
    )
    build_samples.add_install_arguments(parser)
    parser.add_argument(
        "--sheets-dir",
        type=Path,
        default=None,
        help="also copy each contact sheet to DIR/<sample>.png (e.g. docs/images for the README)",
    )
    args = parser.parse_args(argv)
    if min(args.resolution) < 1 or args.cycles_samples < 1:
        parser.error("--resolution and --cycles-samples must be positive")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    package = args.package or build_samples.ensure_package()
    build_samples.start_blender(args.user_dir, package)
    blend_dir = args.blend_dir.resolve()
    missing = [name for name in args.samples if not (blend_dir / f"{name}.blend").exists()]
    if missing:
        print(f"building missing samples: {', '.join(missing)}")
        for name, info in build_samples.build_samples(missing, blend_dir).items():
            for item in info.todo:
                print(f"  TODO ({name}): {item}")
    settings = {
        "resolution": tuple(args.resolution),
        "cycles_samples": args.cycles_samples,
        "denoise": args.denoise,
        "stamp": args.stamp,
        "threads": args.threads,
    }
    output_dir = args.output_dir.resolve()
    problems: list[str] = []
    for name in args.samples:
        started = time.perf_counter()
        blend = blend_dir / f"{name}.blend"
        paths, sample_problems = render_sample(blend, output_dir / name, args.frames, settings)
        problems += sample_problems
        print(f"{name}: {len(paths) - 1} frames in {time.perf_counter() - started:.1f} s")
        for path in paths:
            print(f"  {path}")
        if args.sheets_dir is not None:
            args.sheets_dir.mkdir(parents=True, exist_ok=True)
            copy = args.sheets_dir / f"{name}.png"
            shutil.copyfile(paths[-1], copy)
            print(f"  {copy} ({copy.stat().st_size // 1024} KB)")
    print(f"contact sheets: {output_dir}/<sample>/contact_sheet.png")
    if problems:
        # Images of a deformer that fell back to its rest shape are not a demo: fail loudly.
        print(f"{len(problems)} deformer problem(s) while rendering:", *problems, sep="\n  ")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
