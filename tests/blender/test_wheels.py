"""The packages carry the compiled kernel for every Blender they serve, and a kernel that cannot load
falls back to numpy with the reason shown.

* The kernel is a C library (csrc/) in a wheel of ours per platform,
  `affine_deformers_kernel-<version>-py3-none-<platform tag>.whl` (tools/build_native.py): one library
  serves every Python. Blender's OWN wheel filter (`bl_pkg`, from the bpy wheel this suite runs on: 5.0,
  4.5 LTS or 4.2 LTS) picks exactly that platform's wheel for Python 3.11 (Blender 4.2–5.0, run by
  `make test`) and 3.13 (Blender 5.1+, whose cp313 bpy wheels cannot run here: checked, not run) on
  linux-x64, windows-x64, macos-arm64 and macos-x64, and nothing of another platform. The filter reads
  the running Python and `sysconfig.get_platform()`; the tests set both to the target's, then apply
  Blender's de-duplication (`wheel_manager`) as installing does.
* The manifest lists exactly the four wheels tools/build_native.py builds for its version; each built
  package, unpacked as Blender installs it, holds its own platform's wheel with that platform's
  libraries (format and architecture read from their headers).
* A library that does not load (damaged, or a system it cannot run on) leaves the add-on on the numpy
  kernel, with the reason in `accel.backend()` and in the preferences, and the deformation still right.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ADDON = "bl_ext.user_default.affine_deformers"
PACKAGE = f"{ADDON}.affine_deformers"

#: The Pythons of the Blenders the package serves (4.2–5.0: 3.11; 5.1 and newer: 3.13).
PYTHONS = ((3, 11), (3, 13))
#: What `sysconfig.get_platform()` says in Blender's Python on each Blender platform (the filter uses
#: only the architecture of the macOS ones).
SYSCONFIG_PLATFORM = {
    "linux-x64": "linux-x86_64",
    "windows-x64": "win-amd64",
    "macos-arm64": "macosx-11.2-arm64",
    "macos-x64": "macosx-11.2-x86_64",
}
#: What each platform's libraries are (tools/binary_headers.py's names).
LIBRARY_FORMAT = {
    "linux-x64": ("ELF", "x86_64"),
    "windows-x64": ("PE32+", "x86_64"),
    "macos-arm64": ("Mach-O", "arm64"),
    "macos-x64": ("Mach-O", "x86_64"),
}
KERNEL = "affine_deformers_kernel"


def _tool(name: str):
    path = ROOT / "tools" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"affdef_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _build_tool():
    return _tool("build_extension")


def _bl_pkg():
    """(Blender's extension operators module, its wheel manager): the install-time wheel code."""
    return (importlib.import_module("bl_pkg.bl_extension_ops"),
            importlib.import_module("_bpy_internal.extensions.wheel_manager"))


@contextlib.contextmanager
def _as_blender(python: tuple[int, int], platform: str):
    """Run the code inside as if in Blender's Python `python` on `platform` (what the filter reads)."""
    saved = sys.version_info, sysconfig.get_platform
    sys.version_info = (*python, 0, "final", 0)
    sysconfig.get_platform = lambda: SYSCONFIG_PLATFORM[platform]
    try:
        yield
    finally:
        sys.version_info, sysconfig.get_platform = saved


def _installed(wheels: list[str], python: tuple[int, int], platform: str) -> list[str]:
    """The wheels Blender would install from a package listing `wheels` (relative paths as in the
    manifest), by its own filter and de-duplication; the filter alone must already leave nothing to
    de-duplicate."""
    ops, wheel_manager = _bl_pkg()
    with _as_blender(python, platform):
        compatible = ops._extensions_wheel_filter_for_this_system(wheels)
    skip = wheel_manager.wheel_list_deduplicate_as_skip_set([("affine_deformers", compatible)])
    assert not skip, f"more than one wheel of a name for Python {python} on {platform}: {sorted(skip)}"
    return compatible


def _package_manifests() -> dict[str, dict]:
    """platform -> the manifest the build tool writes into that platform's package (no building)."""
    tool = _build_tool()
    text = tool.MANIFEST.read_text(encoding="utf-8")
    manifest = tomllib.loads(text)
    return {target: tomllib.loads(tool.manifest_for(text, target, tool.package_wheels(manifest, target)))
            for target in manifest["platforms"]}


def _kernel_wheel(platform: str) -> str:
    """The manifest path of `platform`'s kernel wheel, as tools/build_native.py names it."""
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text(encoding="utf-8"))
    return "./wheels/" + _tool("build_native").wheel_filename(platform.replace("-", "_"), manifest["version"])


PAIRS = [(python, platform) for python in PYTHONS for platform in SYSCONFIG_PLATFORM]


def test_the_manifest_serves_every_platform_with_the_wheels_the_build_makes():
    assert sorted(_package_manifests()) == sorted(SYSCONFIG_PLATFORM)
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text(encoding="utf-8"))
    assert sorted(manifest["wheels"]) == sorted(_kernel_wheel(p) for p in SYSCONFIG_PLATFORM)
    assert sorted(manifest["wheels"]) == sorted(_build_tool().expected_wheels(manifest))


@pytest.mark.parametrize(("python", "platform"), PAIRS, ids=[f"py{p[0]}.{p[1]}-{t}" for p, t in PAIRS])
def test_blender_picks_the_platforms_kernel_wheel(python, platform):
    package = _package_manifests()[platform]
    assert package["platforms"] == [platform]
    assert package["wheels"] == [_kernel_wheel(platform)]
    assert _installed(package["wheels"], python, platform) == [_kernel_wheel(platform)]
    # the package holds nothing for another platform, and another platform's wheel is not taken here
    for other in SYSCONFIG_PLATFORM:
        if other != platform:
            assert _installed(package["wheels"], python, other) == [], other
            assert _installed([_kernel_wheel(other)], python, platform) == [], other


def _packages_to_check(extension_zip: Path) -> list[Path]:
    """This run's package, plus every package in $AFFINE_PACKAGES_DIR (e.g. the output of
    `tools/build_extension.py --platform all`)."""
    zips = [Path(extension_zip)]
    extra = os.environ.get("AFFINE_PACKAGES_DIR")
    if extra:
        zips += sorted(Path(extra).glob("affine_deformers-*.zip"))
    return zips


def test_built_packages_install_their_platforms_kernel(extension_zip, tmp_path):
    """Each built package, unpacked as Blender installs it: Blender's `pkg_wheel_filter` (which also
    drops wheels missing from the package) gives the one kernel wheel for every Python, and that wheel
    holds the package's platform's libraries (read from their headers), nothing else of note."""
    ops, wheel_manager = _bl_pkg()
    headers = _tool("binary_headers")
    checked = 0
    for package in _packages_to_check(extension_zip):
        repo = tmp_path / package.stem
        with zipfile.ZipFile(package) as zf:
            zf.extractall(repo / "affine_deformers")
            assert not [n for n in zf.namelist() if n.startswith("csrc/")], "C sources in the package"
        manifest = tomllib.loads((repo / "affine_deformers" / "blender_manifest.toml").read_text())
        wheels = manifest.get("wheels", [])
        if not wheels:
            continue  # built with --platform none: the numpy kernel only, by design
        (platform,) = manifest["platforms"]
        assert wheels == [_kernel_wheel(platform)], (package.name, wheels)
        for python in PYTHONS:
            with _as_blender(python, platform):
                found = ops.pkg_wheel_filter("user_default", "affine_deformers", str(repo), wheels)
            assert found is not None, (package.name, python)
            assert not wheel_manager.wheel_list_deduplicate_as_skip_set([found]), found
            (wheel,) = found[1]
            assert Path(wheel).name == Path(_kernel_wheel(platform)).name
        with zipfile.ZipFile(wheel) as zf:
            libraries = [n for n in zf.namelist() if n.startswith(f"{KERNEL}/affine_kernel")]
            assert libraries, zf.namelist()
            for name in libraries:
                (tmp_path / "lib").write_bytes(zf.read(name))
                info = headers.read(tmp_path / "lib")
                assert (info.format, info.arch) == LIBRARY_FORMAT[platform], (package.name, name)
        checked += 1
    if checked == 0:
        pytest.skip("no package with the kernel was built (--platform none)")


# ------------------------------------------------------------------------------- library unusable

#: A stand-in for the bundled wheel's package whose libraries are not libraries (a damaged install, or
#: a file for another system): loading them fails as dlopen/LoadLibrary fail.
FAKE_KERNEL = '''"""A damaged affine_deformers_kernel (tests/blender/test_wheels.py)."""
import os
LIBRARY_DIR = os.path.dirname(os.path.abspath(__file__))
'''

FALLBACK_SCRIPT = """
import importlib, sys, types, warnings
import numpy as np
enable_addon()
pkg = "bl_ext.user_default.affine_deformers.affine_deformers"
accel = importlib.import_module(pkg + ".accel")
deform = importlib.import_module(pkg + ".core.deform")
print("BACKEND:", accel.backend())
assert not accel.active()

# the dispatch runs the numpy kernel: the same bits as core's
rng = np.random.default_rng(7)
pts = rng.normal(size=(5000, 3))
params = rng.normal(scale=0.4, size=(4, 12))
idx = rng.integers(0, 4, size=(5000, 3)).astype(np.int32)
val = rng.random((5000, 3))
assert np.array_equal(accel.deform_points_params(pts, params, idx, val),
                      deform.deform_points_params(pts, params, idx, val))

# and a deformer in a scene is right: one probe, so the mesh follows the probe's motion exactly
bpy.ops.mesh.primitive_uv_sphere_add(segments=24, ring_count=12)
target = bpy.context.active_object
probe = bpy.data.objects.new("Probe", None)
bpy.context.scene.collection.objects.link(probe)
with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, probe]):
    assert bpy.ops.object.affine_probe_deformer_add() == {"FINISHED"}
def positions():
    mesh = target.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)
rest = positions()
probe.location = (0.25, -0.5, 1.0)
probe.rotation_euler = (0.3, 1.2, -0.4)
probe.scale = (1.5, 0.8, 1.1)
moved = positions()
A = np.array(probe.matrix_world)
expected = rest @ A[:3, :3].T + A[:3, 3]
assert target.affine_deformers[0].status == "", target.affine_deformers[0].status
err = np.abs(moved - expected).max()
assert err < 1e-5, err
assert np.abs(moved - rest).max() > 0.5

# the add-on preferences show the reason (draw() on a stand-in layout that records the labels)
class Layout:
    def __init__(self):
        self.labels = []
        self.active = True
    def prop(self, *args, **kwargs):
        pass
    def row(self, *args, **kwargs):
        return self
    def label(self, text="", **kwargs):
        self.labels.append(text)
prefs = importlib.import_module(pkg + ".blender.ui.prefs")
layout = Layout()
prefs.AFFINE_AddonPreferences.draw(types.SimpleNamespace(layout=layout), bpy.context)
print("PREFS:", " | ".join(layout.labels))
print("FALLBACK OK", err)
"""


def test_a_library_that_does_not_load_falls_back_to_numpy_with_the_reason(bl, tmp_path):
    """A fresh Blender process whose kernel wheel package holds files that are not libraries: the fake
    package comes first on sys.path, ahead of the bundled wheel Blender installed, and loading its
    library fails as the system's loader does (on Linux: "invalid ELF header")."""
    fake = tmp_path / "fake_site" / KERNEL
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text(FAKE_KERNEL)
    for suffix in (".so", ".dll", ".dylib"):
        for name in ("affine_kernel", "affine_kernel_avx2", "affine_kernel_avx512"):
            (fake / (name + suffix)).write_bytes(b"\0not a shared library\n" * 200)
    path = os.pathsep.join(p for p in (str(fake.parent), os.environ.get("PYTHONPATH", "")) if p)
    # AFFINE_DEFORMERS_ACCEL=1: the compiled kernel is wanted (an outer "0" would hide the failure);
    # no explicit library path either
    env = {"PYTHONPATH": path, "AFFINE_DEFORMERS_ACCEL": "1", "AFFINE_DEFORMERS_KERNEL_LIB": ""}
    proc = bl.run_blender(FALLBACK_SCRIPT, env_extra=env)
    out = proc.stdout.splitlines()
    assert "FALLBACK OK" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]
    reason = "invalid ELF header" if sys.platform.startswith("linux") else "affine_kernel"
    backend = next(line for line in out if line.startswith("BACKEND:")).removeprefix("BACKEND: ")
    assert backend.startswith("numpy (") and reason in backend, backend
    prefs = next(line for line in out if line.startswith("PREFS:"))
    assert reason in prefs, prefs
    print(backend, prefs, sep="\n")
