"""Validate the manifest and build the extension .zip with the CLI that ships inside the bpy wheel.

The bpy wheel carries Blender's own `blender_ext.py` and the list of valid extension tags
(`_bpy_internal/extensions/tags.py`); using both means the .zip is exactly what Blender's
"Install from Disk" and the extensions platform accept.

The compiled kernel (the C sources in csrc/, loaded by affine_deformers/accel/native.py) is bundled as
a wheel of our own per platform, `affine_deformers_kernel-<version>-py3-none-<platform tag>.whl`, built
by tools/build_native.py into build/native/wheels/ (this script runs it for the platforms it packages:
a second when nothing changed). One library serves every Python, so every Blender from 4.2 on.
`blender_manifest.toml` lists the four platforms' wheels of the current version (checked here against
what was built), and each package holds its own platform's only
(`dist/affine_deformers-<version>-<platform>.zip`, its size printed as it is built); Blender
installs it by its platform tag. `--platform none` builds the small all-platform package without the
kernel (the numpy kernel only).

    python tools/build_extension.py                      # this machine's platform (make build)
    python tools/build_extension.py --platform all       # every platform in the manifest (a release)
    python tools/build_extension.py --platform none      # no wheels, every platform
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = ROOT / "blender_manifest.toml"
#: What goes into a package (the manifest's exclude patterns keep everything else out of it too).
PACKAGE_FILES = ("__init__.py", "blender_manifest.toml", "README.md")
PACKAGE_DIRS = ("affine_deformers",)
#: Where tools/build_native.py writes the libraries and wheels (make native / make release).
NATIVE_OUT = ROOT / "build" / "native"


def bpy_scripts_dir() -> Path:
    """The `<bpy>/<version>/scripts` folder of the installed bpy wheel (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        sys.exit("bpy is not installed in this interpreter: run `make venv` and use .venv/bin/python "
                 "(e.g. `.venv/bin/python tools/build_extension.py --platform none`); nothing was changed")
    base = Path(next(iter(spec.submodule_search_locations)))
    candidates = sorted(base.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not candidates:
        sys.exit(f"blender_ext.py not found under {base}")
    return candidates[-1].parents[3]


def run_cli(*args: str, cwd: Path = ROOT) -> None:
    scripts = bpy_scripts_dir()
    cli = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    cmd = [sys.executable, str(cli), *args, f"--valid-tags={tags}"]
    subprocess.run(cmd, check=True, cwd=cwd)


def host_platform() -> str:
    """Blender's name for this machine's platform ('linux-x64', 'macos-arm64', ...)."""
    machine = platform.machine().lower()
    arch = {"x86_64": "x64", "amd64": "x64", "arm64": "arm64", "aarch64": "arm64"}.get(machine, machine)
    system = {"linux": "linux", "darwin": "macos", "win32": "windows"}.get(sys.platform, sys.platform)
    return f"{system}-{arch}"


def wheel_platform(path: str) -> str:
    """The Blender platform a manifest wheel path is for (from the platform tag in its file name)."""
    name = Path(path).name
    if "win_amd64" in name:
        return "windows-x64"
    if "macosx" in name:
        return "macos-arm64" if "arm64" in name else "macos-x64"
    if "linux" in name and "x86_64" in name:
        return "linux-x64"
    raise SystemExit(f"cannot tell the platform of wheel {name}")


def build_native() -> ModuleType:
    """tools/build_native.py as a module."""
    spec = importlib.util.spec_from_file_location("affdef_build_native", ROOT / "tools" / "build_native.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def expected_wheels(manifest: dict) -> list[str]:
    """The manifest paths of the kernel wheels tools/build_native.py makes for the manifest's platforms
    and version."""
    native = build_native()
    return [f"./wheels/{native.wheel_filename(p.replace('-', '_'), manifest['version'])}"
            for p in manifest.get("platforms", [])]


def kernel_wheels(manifest: dict, targets: list[str | None]) -> dict[str, Path]:
    """Build the kernel of the packaged platforms into build/native (from zig's cache in about a
    second when nothing changed) and check the manifest lists exactly the wheels built for its
    platforms and version: Blender platform -> the built wheel."""
    listed, expected = manifest.get("wheels", []), expected_wheels(manifest)
    if sorted(listed) != sorted(expected):
        raise SystemExit("blender_manifest.toml `wheels` must list the kernel wheels tools/build_native.py "
                         "builds for its platforms and version:\n  " + "\n  ".join(expected)
                         + "\nit lists:\n  " + "\n  ".join(listed))
    platforms = [t for t in targets if t is not None]
    if not platforms:
        return {}
    if importlib.util.find_spec("ziglang") is None:
        return built_kernel_wheels(manifest, platforms)
    built = build_native().build([t.replace("-", "_") for t in platforms], NATIVE_OUT, os.cpu_count() or 1)
    wheels = {}
    for target in platforms:
        wheel = built[target.replace("-", "_")]
        if [Path(w).name for w in package_wheels(manifest, target)] != [wheel.name]:
            raise SystemExit(f"built {wheel.name}; the manifest lists {package_wheels(manifest, target)}")
        wheels[target] = wheel
    return wheels


def built_kernel_wheels(manifest: dict, platforms: list[str]) -> dict[str, Path]:
    """Without zig in this interpreter (e.g. the Blender 4.2 venv running its suite): the wheels
    `make native` / `make release` built, which must be there and not older than the C sources."""
    native = build_native()
    newest = max((ROOT / p).stat().st_mtime for p in (*native.SOURCES, *native.HEADERS))
    wheels = {}
    for target in platforms:
        (rel,) = package_wheels(manifest, target)
        wheel = NATIVE_OUT / "wheels" / Path(rel).name
        if not wheel.exists() or wheel.stat().st_mtime < newest:
            raise SystemExit(f"{wheel} is {'stale' if wheel.exists() else 'missing'} and this Python has no "
                             f"ziglang to build it: run `make native` (or `make release`) first")
        wheels[target] = wheel
    return wheels


def manifest_for(text: str, target: str | None, wheels: list[str]) -> str:
    """The manifest text for one package: its platform and its wheels only (None: neither)."""
    text = re.sub(r"(?ms)^wheels\s*=\s*\[.*?\]\s*\n", "", text)
    text = re.sub(r"(?m)^platforms\s*=\s*\[.*?\]\s*\n", "", text)
    lines = []
    if target is not None:
        lines.append(f'platforms = ["{target}"]')
        lines.append("wheels = [" + ", ".join(f'"{w}"' for w in wheels) + "]")
    extra = "\n".join(lines) + "\n" if lines else ""
    head, sep, tail = text.partition("\n[build]")
    return head.rstrip("\n") + "\n" + extra + sep + tail


def package_wheels(manifest: dict, target: str | None) -> list[str]:
    """The manifest wheels that go into `target`'s package (its kernel wheel; None: none)."""
    return [w for w in manifest.get("wheels", []) if target is not None and wheel_platform(w) == target]


def build_one(manifest: dict, text: str, target: str | None, out: Path, built: dict[str, Path]) -> Path:
    """Stage the package files (and `target`'s kernel wheel, from `built`) and build one .zip from them."""
    wheels = package_wheels(manifest, target)
    suffix = "" if target is None else "-" + target.replace("-", "_")
    zip_path = out / f"{manifest['id']}-{manifest['version']}{suffix}.zip"
    with tempfile.TemporaryDirectory(prefix="affdef_stage_") as tmp:
        stage = Path(tmp)
        for name in PACKAGE_FILES:
            shutil.copy2(ROOT / name, stage / name)
        for name in PACKAGE_DIRS:
            shutil.copytree(ROOT / name, stage / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        (stage / "blender_manifest.toml").write_text(manifest_for(text, target, wheels), encoding="utf-8")
        for rel in wheels:
            (stage / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(built[target], stage / rel)
        run_cli("validate", str(stage))
        run_cli("build", "--source-dir", str(stage), "--output-filepath", str(zip_path))
    return zip_path


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--output-dir", default="dist")
    parser.add_argument("--platform", default="host",
                        help="host (default), all, none, or a Blender platform such as linux-x64")
    ns = parser.parse_args()
    text = MANIFEST.read_text(encoding="utf-8")
    manifest = tomllib.loads(text)
    declared = manifest.get("platforms", [])
    if ns.platform == "all":
        targets: list[str | None] = list(declared)
    elif ns.platform == "none":
        targets = [None]
    else:
        wanted = host_platform() if ns.platform == "host" else ns.platform
        if wanted not in declared:
            print(f"no kernel build for {wanted}: building the package without the compiled kernel")
            wanted = None
        targets = [wanted]
    bpy_scripts_dir()  # exits with the fix when this interpreter has no bpy, before anything is deleted
    out = (ROOT / ns.output_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob(f"{manifest['id']}-*.zip"):
        old.unlink()  # one build's packages only: tests and tools pick "the" package in dist/
    built = kernel_wheels(manifest, targets)
    for target in targets:
        print(f"extension package: {build_one(manifest, text, target, out, built)}")


if __name__ == "__main__":
    main()
