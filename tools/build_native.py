"""Build the compiled kernel (csrc/: SOURCES, one file per concern, compiled into one library) for every
platform, and one wheel per platform.

The kernel is portable C11 loaded with ctypes (affine_deformers/accel/native.py), so one library per
platform serves every Blender and Python from 4.2 on. It is cross-compiled here with zig's clang (the
`ziglang` wheel in the dev venv, `python -m ziglang cc`), which carries the C libraries and SDK stubs of
every target: glibc 2.17 for Linux (loads on every distribution Blender supports), mingw-w64 with the
UCRT for Windows (the DLL needs only system DLLs), macOS 11 on arm64 (Apple M1) and 10.15 on x86-64.
x86-64 platforms also get AVX2 (x86-64-v3) and AVX-512 (x86-64-v4) builds the loader picks from the
CPU's features.
One set of IEEE-strict flags for every build (no -ffast-math, no FP contraction: results must not
depend on the build), symbols hidden except the AK_EXPORT ones (native.EXPORTS), stripped.

Blender installs Python wheels bundled in an extension, picking them by their platform tag; so each
platform's libraries go into a `py3-none-<platform>` wheel of our own, a package
`affine_deformers_kernel/` whose LIBRARY_DIR the loader reads, written here with zipfile (fixed
timestamps and order: the same sources give the same bytes). tools/build_extension.py bundles it.

    python tools/build_native.py                         # this machine's platform (make native)
    python tools/build_native.py --platform all          # all four (make release)

Output: build/native/<platform>/<libraries> and build/native/wheels/<wheel>. zig's cache goes to
build/zig-cache (set ZIG_GLOBAL_CACHE_DIR to share another): the first build of a target also builds
its C library there (minutes for Windows), later ones take a second.
"""

from __future__ import annotations

import argparse
import ast
import base64
import hashlib
import os
import platform as _platform
import subprocess
import sys
import tempfile
import time
import tomllib
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: The C sources compiled into each library, relative to ROOT (no checkout path in the binaries).
SOURCES = tuple(Path("csrc") / name for name in (
    "kernel_threads.c", "kernel_vertex.c", "kernel_chain.c", "kernel_controls.c", "kernel_cage.c",
    "affine_solve.c"))
HEADERS = tuple(Path("csrc") / name for name in (
    "affine_kernel.h", "affine_internal.h", "kernel_math.h", "kernel_map.h"))
NATIVE_PY = ROOT / "affine_deformers" / "accel" / "native.py"
MANIFEST = ROOT / "blender_manifest.toml"
WHEEL_NAME = "affine_deformers_kernel"
#: Every build: C11, IEEE semantics (no contraction into FMAs, no fast-math), position independent,
#: only AK_EXPORT symbols visible, stripped (no symbol table or debug info with build paths).
CFLAGS = ("-std=c11", "-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno",
          "-fvisibility=hidden", "-Wall", "-Wextra", "-s")
#: Each library's own flags, by its position in native.LIBRARY_NAMES: the baseline, then on x86-64
#: AVX2 (x86-64-v3: Haswell, Zen 1 and newer) and AVX-512 (x86-64-v4: Skylake-SP, Zen 4 and newer;
#: 512-bit vectors, which clang does not prefer by default). No FMA contraction in any of them, so
#: every build gives the same bits.
VARIANT_FLAGS = ((), ("-mcpu=x86_64_v3",), ("-mcpu=x86_64_v4", "-mprefer-vector-width=512"))
#: zip entries' time: 1980-01-01, the earliest a zip can hold (reproducible wheels).
ZIP_TIME = (1980, 1, 1, 0, 0, 0)


@dataclass(frozen=True)
class Target:
    zig: str  # zig's -target
    wheel_tag: str  # the wheel's platform tag (compound tags joined by ".")
    x86: bool  # also build the AVX2 and AVX-512 variants
    libs: tuple[str, ...] = ()


TARGETS = {
    "linux_x64": Target("x86_64-linux-gnu.2.17", "manylinux2014_x86_64.manylinux_2_17_x86_64", True,
                        ("-lm",)),
    "windows_x64": Target("x86_64-windows-gnu", "win_amd64", True),
    "macos_arm64": Target("aarch64-macos.11.0", "macosx_11_0_arm64", False),
    "macos_x64": Target("x86_64-macos.10.15", "macosx_10_15_x86_64", True),
}


def native_constants() -> dict[str, object]:
    """EXPORTS, PLATFORMS and LIBRARY_NAMES from affine_deformers/accel/native.py, read from its source
    (literals; importing it would import the package and load a library)."""
    wanted = {"EXPORTS", "PLATFORMS", "LIBRARY_NAMES"}
    found = {}
    for node in ast.parse(NATIVE_PY.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.AnnAssign | ast.Assign):
            targets = [node.target] if isinstance(node, ast.AnnAssign) else node.targets
            for target in targets:
                if isinstance(target, ast.Name) and target.id in wanted:
                    found[target.id] = ast.literal_eval(node.value)
    missing = wanted - set(found)
    if missing:
        raise SystemExit(f"{NATIVE_PY.relative_to(ROOT)} does not define {sorted(missing)} as literals")
    if set(found["PLATFORMS"]) != set(TARGETS):
        raise SystemExit(f"native.PLATFORMS {sorted(found['PLATFORMS'])} != this tool's {sorted(TARGETS)}")
    return found


def version() -> str:
    return tomllib.loads(MANIFEST.read_text(encoding="utf-8"))["version"]


def host_platform() -> str:
    """This machine's platform in native.PLATFORMS' spelling ('linux_x64', ...)."""
    machine = _platform.machine().lower()
    arch = {"x86_64": "x64", "amd64": "x64", "arm64": "arm64", "aarch64": "arm64"}.get(machine, machine)
    system = {"linux": "linux", "darwin": "macos", "win32": "windows"}.get(sys.platform, sys.platform)
    return f"{system}_{arch}"


def library_files(platform: str, constants: dict | None = None) -> list[str]:
    """The library file names of `platform`, baseline first (then the x86-64 variants)."""
    constants = constants or native_constants()
    names = constants["LIBRARY_NAMES"]
    suffix = constants["PLATFORMS"][platform]
    return [name + suffix for name in (names if TARGETS[platform].x86 else names[:1])]


def wheel_filename(platform: str, ver: str | None = None) -> str:
    return f"{WHEEL_NAME}-{ver or version()}-py3-none-{TARGETS[platform].wheel_tag}.whl"


def zig_command(platform: str, variant: int, output: Path) -> list[str]:
    target = TARGETS[platform]
    # a dylib records its install name, by default the output path: use a fixed one (reproducible)
    link = [f"-Wl,-install_name,@rpath/{output.name}"] if "-macos" in target.zig else []
    return [sys.executable, "-m", "ziglang", "cc", *CFLAGS, "-target", target.zig,
            *VARIANT_FLAGS[variant], "-o", str(output), *(str(s) for s in SOURCES), *link, *target.libs]


def zig_env() -> dict[str, str]:
    env = dict(os.environ)
    cache = env.setdefault("ZIG_GLOBAL_CACHE_DIR", str(ROOT / "build" / "zig-cache"))
    env.setdefault("ZIG_LOCAL_CACHE_DIR", cache)
    return env


def compile_one(platform: str, name: str, variant: int, dest: Path) -> float:
    """Compile one library into `dest`/name; returns the seconds it took. zig also writes an import
    library (.lib) next to a DLL: compile in a scratch directory and keep the library only, moved into
    place in one step (a process that has the old file loaded keeps its copy)."""
    start = time.perf_counter()
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".affdef_native_", dir=dest) as tmp:
        out = Path(tmp) / name
        proc = subprocess.run(zig_command(platform, variant, out), cwd=ROOT, env=zig_env(),
                              capture_output=True, text=True)
        if proc.returncode != 0 or not out.exists():
            raise SystemExit(f"building {platform}/{name} failed:\n{proc.stdout}{proc.stderr}")
        if proc.stderr.strip():  # warnings (-Wall -Wextra) are shown, not fatal
            print(proc.stderr.rstrip(), file=sys.stderr)
        out.chmod(0o755)
        os.replace(out, dest / name)
    return time.perf_counter() - start


# ----------------------------------------------------------------------------------------------- wheel

INIT_PY = '''"""The compiled kernel of the Affine Deformers Blender extension: its C library for this
platform.

Loaded with ctypes by affine_deformers.accel.native (no Python extension module: the same files serve
every Python). Built by tools/build_native.py from the C sources in csrc/.
"""

import os

LIBRARY_DIR = os.path.dirname(os.path.abspath(__file__))
'''


def _record_hash(data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"sha256={digest}"


def _zip_add(zf: zipfile.ZipFile, name: str, data: bytes, executable: bool = False) -> None:
    info = zipfile.ZipInfo(name, date_time=ZIP_TIME)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.create_system = 3  # unix, so the mode bits below are read
    info.external_attr = (0o100755 if executable else 0o100644) << 16
    zf.writestr(info, data, compresslevel=9)


def build_wheel(platform: str, libraries: list[Path], out_dir: Path, ver: str) -> Path:
    """One `py3-none-<tag>` wheel: the package with `platform`'s libraries and its .dist-info."""
    tag = TARGETS[platform].wheel_tag
    dist_info = f"{WHEEL_NAME}-{ver}.dist-info"
    files: list[tuple[str, bytes, bool]] = [(f"{WHEEL_NAME}/__init__.py", INIT_PY.encode(), False)]
    files += [(f"{WHEEL_NAME}/{lib.name}", lib.read_bytes(), True) for lib in libraries]
    metadata = "\n".join([
        "Metadata-Version: 2.1",
        f"Name: {WHEEL_NAME}",
        f"Version: {ver}",
        "Summary: The compiled kernel (a C library loaded with ctypes) of the Affine Deformers Blender"
        " extension",
        "License: GPL-3.0-or-later",
        "Requires-Python: >=3.11",
        "",
    ])
    wheel = "\n".join([
        "Wheel-Version: 1.0",
        "Generator: affine_deformers tools/build_native.py",
        "Root-Is-Purelib: false",
        *(f"Tag: py3-none-{part}" for part in tag.split(".")),
        "",
    ])
    files += [(f"{dist_info}/METADATA", metadata.encode(), False),
              (f"{dist_info}/WHEEL", wheel.encode(), False)]
    record = "".join(f"{name},{_record_hash(data)},{len(data)}\n" for name, data, _x in files)
    record += f"{dist_info}/RECORD,,\n"
    files.append((f"{dist_info}/RECORD", record.encode(), False))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / wheel_filename(platform, ver)
    for old in out_dir.glob(f"{WHEEL_NAME}-*-py3-none-{tag}.whl"):
        old.unlink()  # an older version's wheel for this platform
    partial = path.with_suffix(".whl.part")
    with zipfile.ZipFile(partial, "w") as zf:
        for name, data, executable in files:
            _zip_add(zf, name, data, executable)
    partial.replace(path)
    return path


# ------------------------------------------------------------------------------------------------ main


def build(platforms: list[str], output: Path, jobs: int) -> dict[str, Path]:
    """Compile every library of `platforms` (up to `jobs` zig processes at once) into
    output/<platform>/ and write one wheel each into output/wheels/; returns platform → wheel."""
    constants = native_constants()
    ver = version()
    work = [(p, name, i) for p in platforms for i, name in enumerate(library_files(p, constants))]
    for platform in platforms:  # only this build's files in a platform's directory
        for stale in (output / platform).glob("*"):
            if stale.is_file() and (platform, stale.name) not in {(p, n) for p, n, _a in work}:
                stale.unlink()
    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        times = list(pool.map(lambda w: compile_one(w[0], w[1], w[2], output / w[0]), work))
    for (platform, name, _variant), seconds in zip(work, times, strict=True):
        size = (output / platform / name).stat().st_size
        print(f"  {platform}/{name}: {size / 1024:.0f} KiB, {seconds:.1f} s")
    wheels = {}
    for platform in platforms:
        libraries = [output / platform / name for name in library_files(platform, constants)]
        wheel = wheels[platform] = build_wheel(platform, libraries, output / "wheels", ver)
        print(f"wheel: {wheel} ({wheel.stat().st_size / 1024:.0f} KiB)")
    print(f"built {len(work)} libraries in {time.perf_counter() - start:.1f} s")
    return wheels


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--platform", default="host", choices=[*TARGETS, "all", "host"])
    parser.add_argument("--output", default="build/native", help="output directory (default: build/native)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="zig processes at once")
    ns = parser.parse_args(argv)
    if ns.platform == "all":
        platforms = list(TARGETS)
    elif ns.platform == "host":
        if host_platform() not in TARGETS:
            print(f"no kernel build for this machine ({host_platform()}): nothing to do")
            return
        platforms = [host_platform()]
    else:
        platforms = [ns.platform]
    for path in (*SOURCES, *HEADERS):
        if not (ROOT / path).exists():
            raise SystemExit(f"{path} is missing")
    # The Makefile rebuilds when any file in csrc/ changes: every one must be a listed input.
    unlisted = {p.relative_to(ROOT) for p in (ROOT / "csrc").glob("*.[ch]")} - {*SOURCES, *HEADERS}
    if unlisted:
        raise SystemExit(f"csrc/ files not in this tool's SOURCES or HEADERS: {sorted(map(str, unlisted))}")
    build(platforms, (ROOT / ns.output).resolve(), ns.jobs)


if __name__ == "__main__":
    main()
