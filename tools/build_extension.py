"""Validate the manifest and build the extension .zip with the CLI that ships inside the bpy wheel.

The bpy wheel carries Blender's own `blender_ext.py` and the list of valid extension tags
(`_bpy_internal/extensions/tags.py`); using both means the .zip is exactly what Blender's
"Install from Disk" and the extensions platform accept.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def bpy_scripts_dir() -> Path:
    """The `<bpy>/<version>/scripts` folder of the installed bpy wheel (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        sys.exit("bpy is not installed in this interpreter; run `make venv` first")
    base = Path(next(iter(spec.submodule_search_locations)))
    candidates = sorted(base.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not candidates:
        sys.exit(f"blender_ext.py not found under {base}")
    return candidates[-1].parents[3]


def run_cli(*args: str) -> None:
    scripts = bpy_scripts_dir()
    cli = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    cmd = [sys.executable, str(cli), *args, f"--valid-tags={tags}"]
    subprocess.run(cmd, check=True, cwd=ROOT)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--output-dir", default="dist")
    ns = parser.parse_args()
    out = (ROOT / ns.output_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_cli("validate", str(ROOT))
    run_cli("build", "--source-dir", str(ROOT), "--output-dir", str(out))
    zips = sorted(out.glob("affine_deformers-*.zip"))
    print(f"extension package: {zips[-1] if zips else '(missing)'}")


if __name__ == "__main__":
    main()
