"""The compiled kernel's libraries for all four platforms, as built by tools/build_native.py: what can be
checked here of the ones that cannot run here (Windows, macOS), and the wheels they ship in.

For every library (baseline, and AVX2/FMA on x86-64): the file format and architecture (ELF x86-64,
PE32+ x86-64, Mach-O arm64 / x86_64), a shared library; the exported symbols are exactly
`affine_deformers.accel.native.EXPORTS`; it needs nothing beyond the system's C library (glibc 2.17
symbol versions at most; KERNEL32 and the UCRT; libSystem) — read from the headers by
tools/binary_headers.py. The Linux ones are also loaded here. The wheels: names and tags Blender and
pip accept, contents, RECORD hashes, the same bytes when built again.

The session builds all four platforms once, into a temporary directory (the sources as they are now,
never a stale build/). With zig's cache (build/zig-cache) that takes under a second when the sources
have been built before and ~12 s on 2 cores when they changed; the very first build also builds each
target's C library (2.5-4.5 min on 2 cores, mostly the two Windows ones).
"""

from __future__ import annotations

import base64
import csv
import ctypes
import hashlib
import importlib.util
import io
import os
import re
import sys
import time
import zipfile
from pathlib import Path
from types import SimpleNamespace

import pytest
from packaging.tags import sys_tags
from packaging.utils import parse_wheel_filename

from affine_deformers.accel import native

ROOT = Path(__file__).resolve().parents[2]


def _tool(name: str):
    spec = importlib.util.spec_from_file_location(f"affdef_{name}", ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


build_native = _tool("build_native")
binary_headers = _tool("binary_headers")

#: What each platform's libraries must be: format, architecture, minimum macOS.
EXPECTED = {
    "linux_x64": ("ELF", "x86_64", None),
    "windows_x64": ("PE32+", "x86_64", None),
    "macos_arm64": ("Mach-O", "arm64", "11.0.0"),
    "macos_x64": ("Mach-O", "x86_64", "10.15.0"),
}
#: The system C library. glibc before 2.34 keeps pthreads in libpthread.so.0 (a C pool would need it).
GLIBC_LIBRARIES = {"libc.so.6", "libm.so.6", "libpthread.so.0"}
GLIBC_BASELINE = (2, 17)
#: KERNEL32 and the Universal CRT (api-ms-win-crt-* forward to ucrtbase.dll; msvcrt.dll is the older CRT
#: every Windows has): no libgcc_s / libwinpthread / vcruntime DLL that would have to be shipped.
WINDOWS_SYSTEM = re.compile(r"^(kernel32\.dll|ucrtbase\.dll|msvcrt\.dll|api-ms-win-crt-[a-z]+-l1-1-0\.dll)$")
MACOS_SYSTEM = {"/usr/lib/libSystem.B.dylib"}
#: zig's Mach-O linker exports the header and the DSO handle it defines in every dylib (Apple's ld keeps
#: them private); data, not code, and two-level namespaces keep them from clashing with anything.
MACHO_LINKER_SYMBOLS = {"_mh_dylib_header", "__dso_handle"}


@pytest.fixture(scope="session")
def built(tmp_path_factory) -> SimpleNamespace:
    """All four platforms built now into a temporary directory: `.wheels` (platform -> its wheel) and
    `.library(platform, name)`."""
    out = tmp_path_factory.mktemp("native")
    start = time.perf_counter()
    wheels = build_native.build(list(build_native.TARGETS), out, os.cpu_count() or 1)
    print(f"tools/build_native.py --platform all: {time.perf_counter() - start:.1f} s")
    return SimpleNamespace(out=out, wheels=wheels, library=lambda platform, name: out / platform / name)


LIBRARIES = [(platform, name) for platform in build_native.TARGETS
             for name in build_native.library_files(platform)]


def test_the_platforms_and_names_are_the_loaders():
    assert set(native.PLATFORMS) == set(build_native.TARGETS) == set(EXPECTED)
    assert native.LIBRARY_NAMES == ("affine_kernel", "affine_kernel_avx2", "affine_kernel_avx512")
    assert len(native.VARIANTS) == len(native.LIBRARY_NAMES) == len(build_native.VARIANT_FLAGS)
    assert len(set(native.EXPORTS)) == len(native.EXPORTS)
    assert all(n.startswith("ak_") for n in native.EXPORTS)
    # the baseline for every platform, the AVX2 and AVX-512 builds on x86-64 only
    assert build_native.library_files("macos_arm64") == ["affine_kernel.dylib"]
    assert build_native.library_files("windows_x64") == ["affine_kernel.dll", "affine_kernel_avx2.dll",
                                                         "affine_kernel_avx512.dll"]


@pytest.mark.parametrize(("platform", "name"), LIBRARIES, ids=[f"{p}/{n}" for p, n in LIBRARIES])
def test_library_format_exports_and_dependencies(built, platform, name):
    path = built.library(platform, name)
    info = binary_headers.read(path)
    fmt, arch, minos = EXPECTED[platform]
    data = path.read_bytes()
    for leak in (str(ROOT), str(built.out), "affdef_native_", "zig-cache", "site-packages/ziglang"):
        assert leak.encode() not in data, leak  # no path of this build: the same bytes anywhere
    assert (info.format, info.arch, info.kind) == (fmt, arch, "shared library"), path
    exports = info.exports - (MACHO_LINKER_SYMBOLS if fmt == "Mach-O" else set())
    assert exports == set(native.EXPORTS), (sorted(exports - set(native.EXPORTS)),
                                            sorted(set(native.EXPORTS) - exports))
    if fmt == "ELF":
        assert set(info.needs) <= GLIBC_LIBRARIES, info.needs
        assert set(info.versions) <= set(info.needs)
        for library, versions in info.versions.items():
            for v in versions:
                match = re.fullmatch(r"GLIBC_(\d+)\.(\d+)(?:\.\d+)?", v)
                assert match, (library, v)  # GLIBC_PRIVATE or another library's versions: no
                assert (int(match[1]), int(match[2])) <= GLIBC_BASELINE, (library, v)
        assert "runpath" not in info.extra and "textrel" not in info.extra, info.extra
    elif fmt == "PE32+":
        assert info.needs and all(WINDOWS_SYSTEM.match(dll.lower()) for dll in info.needs), info.needs
        assert "kernel32.dll" in {dll.lower() for dll in info.needs}
        assert info.extra["unnamed_exports"] == 0 and "delay_loaded" not in info.extra
    else:
        assert info.needs == sorted(MACOS_SYSTEM), info.needs
        assert info.extra["platform"] == "macos" and info.extra["minos"] == minos, info.extra
        assert info.extra["symtab_exports"] == info.exports  # the trie dyld reads and the symbol table
        assert info.extra["install_name"] == f"@rpath/{name}", info.extra  # not the build's path
        assert "runpath" not in info.extra
        # Apple Silicon maps only signed code: the linker's ad-hoc signature must match every page
        if arch == "arm64":
            assert info.extra.get("signature") == "valid", info.extra.get("signature")
        else:
            assert info.extra.get("signature", "valid") == "valid", info.extra["signature"]


@pytest.mark.parametrize("platform", [p for p in build_native.TARGETS if build_native.TARGETS[p].x86])
def test_the_x86_variants_are_other_builds(built, platform):
    """-mcpu=x86_64_v3 / _v4 reached the compiler: the AVX2 and AVX-512 libraries are not the
    baseline's bytes, nor each other's."""
    contents = [built.library(platform, n).read_bytes() for n in build_native.library_files(platform)]
    assert len(contents) == 3 and len(set(contents)) == 3


@pytest.mark.skipif(build_native.host_platform() != "linux_x64",
                    reason="the Linux libraries load on Linux only")
@pytest.mark.parametrize("name", build_native.library_files("linux_x64"))
def test_the_linux_libraries_load_here_with_every_export(built, name):
    """dlopen resolves its dependencies and symbol versions on this machine's glibc (no code of ours
    runs at load: the AVX2 build loads on any CPU)."""
    library = ctypes.CDLL(str(built.library("linux_x64", name)))
    for symbol in native.EXPORTS:
        assert getattr(library, symbol) is not None


def _record(zf: zipfile.ZipFile, dist_info: str) -> dict[str, tuple[str, str]]:
    rows = csv.reader(io.StringIO(zf.read(f"{dist_info}/RECORD").decode("utf-8")))
    return {row[0]: (row[1], row[2]) for row in rows}


@pytest.mark.parametrize("platform", list(build_native.TARGETS))
def test_the_wheel(built, platform):
    wheel = built.wheels[platform]
    version = build_native.version()
    name, wheel_version, build_tag, tags = parse_wheel_filename(wheel.name)
    assert (str(name), str(wheel_version), build_tag) == ("affine-deformers-kernel", version, ())
    assert {(t.interpreter, t.abi) for t in tags} == {("py3", "none")}
    platforms = {t.platform for t in tags}
    assert platforms == set(build_native.TARGETS[platform].wheel_tag.split("."))
    # pip on this machine would install the Linux wheel and no other (the tags sys_tags lists)
    here = {t for t in sys_tags()}
    assert bool(set(tags) & here) == (platform == build_native.host_platform()), platform
    libraries = build_native.library_files(platform)
    dist_info = f"affine_deformers_kernel-{version}.dist-info"
    package = "affine_deformers_kernel"
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        assert names == [f"{package}/__init__.py", *(f"{package}/{n}" for n in libraries),
                         f"{dist_info}/METADATA", f"{dist_info}/WHEEL", f"{dist_info}/RECORD"]
        for n in libraries:
            assert zf.read(f"{package}/{n}") == built.library(platform, n).read_bytes()
        init = zf.read(f"{package}/__init__.py").decode()
        assert "LIBRARY_DIR = os.path.dirname(os.path.abspath(__file__))" in init
        meta = zf.read(f"{dist_info}/WHEEL").decode().splitlines()
        assert "Root-Is-Purelib: false" in meta and "Wheel-Version: 1.0" in meta
        assert sorted(line for line in meta if line.startswith("Tag: ")) == sorted(f"Tag: {t}" for t in tags)
        metadata = zf.read(f"{dist_info}/METADATA").decode().splitlines()
        assert {"Name: affine_deformers_kernel", f"Version: {version}"} <= set(metadata)
        record = _record(zf, dist_info)
        assert set(record) == set(names)
        for member in names:
            if member.endswith("/RECORD"):
                assert record[member] == ("", "")
                continue
            data = zf.read(member)
            digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
            assert record[member] == (f"sha256={digest}", str(len(data))), member
        for info in zf.infolist():
            assert info.date_time == build_native.ZIP_TIME, info


def test_the_wheels_are_reproducible(built, tmp_path):
    """Built again from the same sources: the same bytes (fixed zip times and order, no build paths)."""
    again = build_native.build(list(build_native.TARGETS), tmp_path, 1)
    for platform, wheel in built.wheels.items():
        assert again[platform].name == wheel.name
        assert again[platform].read_bytes() == wheel.read_bytes(), platform
