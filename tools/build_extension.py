"""Validate the manifest and build the extension .zip with the CLI that ships inside the bpy wheel.

The bpy wheel carries Blender's own `blender_ext.py` and the list of valid extension tags
(`_bpy_internal/extensions/tags.py`); using both means the .zip is exactly what Blender's
"Install from Disk" and the extensions platform accept.

The compiled kernel (affine_deformers/accel, numba) is bundled as wheels, which are platform and Python
specific: `blender_manifest.toml` lists every platform's wheels for every Python Blender uses (3.11:
Blender 4.2–5.0, 3.13: 5.1+), and each package holds one platform's, for both Pythons
(`dist/affine_deformers-<version>-<platform>.zip`, see README "Blender versions" for the sizes); Blender
installs the ones matching the running Python. Missing wheels are downloaded from PyPI into `wheels/`
(not in git) once, by exactly the file names the manifest lists (their tags tell pip the Python and
platform); later builds work offline. `--platform none` builds the small all-platform package without
wheels (the numpy kernel only).

    python tools/build_extension.py                      # this machine's platform (make build)
    python tools/build_extension.py --platform all       # every platform in the manifest (a release)
    python tools/build_extension.py --platform none      # no wheels, every platform
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = ROOT / "blender_manifest.toml"
#: What goes into a package (the manifest's exclude patterns keep everything else out of it too).
PACKAGE_FILES = ("__init__.py", "blender_manifest.toml", "README.md")
PACKAGE_DIRS = ("affine_deformers",)
#: `{name}-{version}-cp{py}-{abi}-{platform tags}.whl` (no build tag: the manifest names release wheels).
_WHEEL_NAME = re.compile(
    r"^(?P<name>[A-Za-z0-9_]+)-(?P<version>[^-]+)-cp(?P<py>\d+)-(?P<abi>[^-]+)-(?P<platform>[^-]+)\.whl$"
)


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


def fetch_wheels(paths: list[str]) -> None:
    """Download the manifest's wheels that are not in wheels/ yet (exact file names, no dependencies)."""
    for rel in paths:
        target = ROOT / rel
        if target.exists():
            continue
        match = _WHEEL_NAME.match(target.name)
        if match is None:
            raise SystemExit(f"not a CPython wheel name: {target.name}")
        spec = f"{match['name']}=={match['version']}"
        py = match["py"]
        # The file's own tags: pip then picks exactly that file (a compressed platform tag such as
        # `manylinux2014_x86_64.manylinux_2_17_x86_64` is one --platform per part).
        platforms = [arg for tag in match["platform"].split(".") for arg in ("--platform", tag)]
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run(
                [sys.executable, "-m", "pip", "download", "--disable-pip-version-check", "-q", "--no-deps",
                 "--only-binary=:all:", *platforms, "--implementation", "cp", "--abi", match["abi"],
                 "--python-version", f"{py[0]}.{py[1:]}", "-d", tmp, spec],
                check=True,
            )
            got = Path(tmp) / target.name
            if not got.exists():
                found = ", ".join(p.name for p in Path(tmp).iterdir())
                raise SystemExit(f"PyPI gave {found} for {spec}, the manifest expects {target.name}")
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(got), target)


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
    """The manifest wheels that go into `target`'s package (all its Python versions; None: none)."""
    return [w for w in manifest.get("wheels", []) if target is not None and wheel_platform(w) == target]


def build_one(manifest: dict, text: str, target: str | None, out: Path) -> Path:
    """Stage the package files (and `target`'s wheels) and build one .zip from them."""
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
            shutil.copy2(ROOT / rel, stage / rel)
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
            print(f"no bundled wheels for {wanted}: building the package without the compiled kernel")
            wanted = None
        targets = [wanted]
    out = (ROOT / ns.output_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob(f"{manifest['id']}-*.zip"):
        old.unlink()  # one build's packages only: tests and tools pick "the" package in dist/
    fetch_wheels([w for w in manifest.get("wheels", []) if wheel_platform(w) in targets])
    for target in targets:
        print(f"extension package: {build_one(manifest, text, target, out)}")


if __name__ == "__main__":
    main()
