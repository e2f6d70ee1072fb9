"""`make bench`: Affine Deformers against Blender's native deformers, in one bpy process, same meshes.

Measured: the wall time of one interactive update — move one control, let the depsgraph settle (our
handler and Blender's re-evaluation included) — median of `--reps` repetitions after warm-up.

  (a) 8 probes on a ~130k-vertex UV sphere vs 8 Hook modifiers (Smooth falloff, same radius) and vs an
      Armature with 8 bones, Preserve Volume (vertex groups from the same weights);
  (b) a ~1k-face cage around the same sphere vs Mesh Deform (precision 5): per update and bind;
  (c) scaling over vertex count × probe count, ours vs Hooks;
  (d) a chain of 8 bones skinning the sphere of (a) (and a 10k-vertex one) through the same vertex
      groups: our bone deformer vs the Armature modifier with and without Preserve Volume, turning the
      tip bone or all bones;
  (p) playback: frames per second over 48 keyed frames with every control animated, ours vs Hooks,
      Armature (Preserve Volume) and Mesh Deform;
  (m) many deformed objects: playback of 10 objects of ~5k vertices with 4 keyed probes each, ours
      vs the same rigs built with Hooks; with the floor of this design (a handler that only writes,
      our modifier and Blender's re-evaluation left), the same rigs baked to PC2, and our compiled
      per-vertex map alone; and 10 characters each skinned by its own armature, ours vs the Armature
      modifier (Preserve Volume);
  (w) studio-size scenes: one deformed 5k mesh beside 0 / 5,000 / 20,000 other objects, ours (each
      output store, output_store.py) vs Hooks; a 10k mesh with 8 probes, playback and drag;
  (s) shape preservation: a bar bent 90° / 180° and twisted 270° by two bones, Suzanne's cage pulled:
      volume, edge distortion, roughness and update time, ours vs Armature (Preserve Volume) and Mesh
      Deform;
  (e) cages made for the mesh (the cage deformer added with no cage selected) on Suzanne, the figure of
      samples/cage_deform.blend and that figure at 130k vertices: faces, margin, winding numbers, time
      to make; a cage edit with the made cage vs the sample's hand-made cage vs Mesh Deform bound to
      the made cage (roughness, edge distortion, torn edges, bind).

Exit status 1 when a measurement is not trustworthy (an update that changed nothing, a result still
moving after the timed passes) or our operators fail; a missing operator is a printed note, not a failure.

Usage: python bench/run.py [--quick] [--reps N] [--markdown docs/benchmarks.md] [--only a,b,c,d,p,m,s,w,e]
                           [--zip Z]
"""

from __future__ import annotations

import argparse
import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
#: The parts, in the order they run (suite.run) and appear in the report.
PARTS = ("a", "b", "c", "d", "p", "m", "s", "w", "e")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small meshes, few reps (smoke test)")
    parser.add_argument("--reps", type=int, help="timed repetitions per case (default 15, quick 3)")
    parser.add_argument("--markdown", type=Path, help="also write the tables to this markdown file")
    parser.add_argument("--only", default=",".join(PARTS),
                        help=f"comma list of parts to run ({', '.join(PARTS)})")
    parser.add_argument("--zip", type=Path, help="extension package (default: newest dist/*.zip)")
    ns = parser.parse_args(argv)
    ns.parts = {p.strip() for p in ns.only.split(",") if p.strip()}
    unknown = ns.parts - set(PARTS)
    if unknown:
        parser.error(f"unknown part(s) {sorted(unknown)}: use {', '.join(PARTS)}")
    if ns.reps is not None and ns.reps < 1:
        parser.error("--reps must be at least 1")
    if ns.zip is None:
        built = sorted((ROOT / "dist").glob("affine_deformers-*.zip"), reverse=True)
        ns.zip = built[0] if built else None
    return ns


def main(argv: list[str] | None = None) -> int:
    ns = parse_args(argv)
    # The extension is installed into a throw-away user directory, never into the user's Blender; the
    # variable is read once, when bpy is imported.
    user_dir = tempfile.mkdtemp(prefix="affdef-bench-")
    atexit.register(shutil.rmtree, user_dir, ignore_errors=True)
    os.environ["BLENDER_USER_RESOURCES"] = user_dir
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sys.path.insert(0, str(BENCH))
    import suite

    return suite.run(ns)


if __name__ == "__main__":
    sys.exit(main())
