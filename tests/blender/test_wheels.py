"""The packages carry a compiled kernel for every Blender they serve, and a kernel that cannot load falls
back to numpy with the reason shown.

* Blender's OWN wheel filter (`bl_pkg`, from the bpy wheel this suite runs on: 5.0, 4.5 LTS or 4.2 LTS)
  picks exactly one numba and one llvmlite for every (Python, platform) pair: Python 3.11 (Blender
  4.2–5.0, run by `make test`) and 3.13 (Blender 5.1+, whose cp313 bpy wheels cannot run here: checked,
  not run) × linux-x64, windows-x64, macos-arm64, macos-x64. The filter reads the running Python and
  `sysconfig.get_platform()`; the tests set both to the target's, then apply Blender's de-duplication
  (`wheel_manager`, which keeps the newest wheel of a name) as installing does.
* A numba that fails to import (its import-time check rejects the numpy it finds: "Numba needs NumPy
  2.1 or less") leaves the add-on on the numpy kernel, with the reason in `accel.backend()` and in the
  preferences, and the deformation still right.
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
from collections import Counter
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[2]
ADDON = "bl_ext.user_default.affine_deformers"
PACKAGE = f"{ADDON}.affine_deformers"

#: The Pythons of the Blenders the package serves, and the numpy those Blenders come with (bpy wheels on
#: PyPI: 4.2–5.0 require numpy>=1.26,<2.0 and bundle 1.26.4; 5.1–5.3 require numpy>=2.2,<3.0).
PYTHONS = {(3, 11): ("1.26.4",), (3, 13): ("2.2.0", "2.3.5")}
#: What `sysconfig.get_platform()` says in Blender's Python on each Blender platform (the filter uses
#: only the architecture of the macOS ones).
SYSCONFIG_PLATFORM = {
    "linux-x64": "linux-x86_64",
    "windows-x64": "win-amd64",
    "macos-arm64": "macosx-11.2-arm64",
    "macos-x64": "macosx-11.2-x86_64",
}
KERNEL = {"numba", "llvmlite"}


def _build_tool():
    path = ROOT / "tools" / "build_extension.py"
    spec = importlib.util.spec_from_file_location("affdef_build_extension", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
    de-duplicate (no second numba for one Python in a package)."""
    ops, wheel_manager = _bl_pkg()
    with _as_blender(python, platform):
        compatible = ops._extensions_wheel_filter_for_this_system(wheels)
    skip = wheel_manager.wheel_list_deduplicate_as_skip_set([("affine_deformers", compatible)])
    assert not skip, f"more than one wheel of a name for Python {python} on {platform}: {sorted(skip)}"
    return compatible


def _dist(wheel: str) -> tuple[str, str, str]:
    """(name, version, python tag) of a wheel file name."""
    name, version, python_tag, _abi, _platform = Path(wheel).name[: -len(".whl")].split("-")
    return name, version, python_tag


def _check_one_pair(chosen: list[str], python: tuple[int, int]) -> dict[str, str]:
    names = Counter(_dist(w)[0] for w in chosen)
    assert names == Counter(KERNEL), f"Blender would install {chosen}"
    for wheel in chosen:
        assert _dist(wheel)[2] == f"cp{python[0]}{python[1]}", wheel
    return {_dist(w)[0]: w for w in chosen}


def _package_manifests() -> dict[str, dict]:
    """platform -> the manifest the build tool writes into that platform's package (no building)."""
    tool = _build_tool()
    text = tool.MANIFEST.read_text(encoding="utf-8")
    manifest = tomllib.loads(text)
    return {target: tomllib.loads(tool.manifest_for(text, target, tool.package_wheels(manifest, target)))
            for target in manifest["platforms"]}


PAIRS = [(python, platform) for python in PYTHONS for platform in SYSCONFIG_PLATFORM]


def test_the_manifest_serves_every_platform():
    assert sorted(_package_manifests()) == sorted(SYSCONFIG_PLATFORM)


@pytest.mark.parametrize(("python", "platform"), PAIRS, ids=[f"py{p[0]}.{p[1]}-{t}" for p, t in PAIRS])
def test_blender_picks_one_numba_and_one_llvmlite(python, platform):
    package = _package_manifests()[platform]
    assert package["platforms"] == [platform]
    _check_one_pair(_installed(package["wheels"], python, platform), python)
    # and the package holds nothing for another platform
    for other in SYSCONFIG_PLATFORM:
        if other != platform:
            assert _installed(package["wheels"], python, other) == [], other


def test_one_numba_version_for_every_blender_and_the_dev_venv_tests_it():
    """One numba/llvmlite release in every package (so the numba and LLVM the kernel is tested with on
    Python 3.11 are those the 3.13 wheels carry), and it is the one tools/requirements-dev.txt pins, so
    `make test-core` tests the numba that ships."""
    versions = {_dist(w)[:2] for m in _package_manifests().values() for w in m["wheels"]}
    by_name = {name: {v for n, v in versions if n == name} for name in KERNEL}
    assert all(len(v) == 1 for v in by_name.values()), by_name
    pins = {}
    for line in (ROOT / "tools" / "requirements-dev.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            req = Requirement(line)
            pins[req.name] = str(req.specifier)
    for name in KERNEL:
        assert pins.get(name) == f"=={next(iter(by_name[name]))}", (name, pins.get(name), by_name[name])


def _packages_to_check(extension_zip: Path) -> list[Path]:
    """This run's package, plus every package in $AFFINE_PACKAGES_DIR (e.g. the output of
    `tools/build_extension.py --platform all`)."""
    zips = [Path(extension_zip)]
    extra = os.environ.get("AFFINE_PACKAGES_DIR")
    if extra:
        zips += sorted(Path(extra).glob("affine_deformers-*.zip"))
    return zips


def _metadata(wheel: Path) -> list[str]:
    with zipfile.ZipFile(wheel) as zf:
        name = next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
        return zf.read(name).decode("utf-8").splitlines()


def _requires(wheel: Path) -> dict[str, Requirement]:
    reqs = [Requirement(line.split(":", 1)[1].strip()) for line in _metadata(wheel)
            if line.startswith("Requires-Dist:")]
    return {r.name: r for r in reqs if not r.marker}


def test_built_packages_install_a_consistent_kernel_for_each_python(extension_zip, tmp_path):
    """Each built package, unpacked as Blender installs it: Blender's `pkg_wheel_filter` (which also
    drops wheels missing from the package) gives one numba and one llvmlite per Python, that numba's
    llvmlite requirement holds, and its numpy range admits the numpy of the Blenders with that Python."""
    ops, wheel_manager = _bl_pkg()
    checked = 0
    for package in _packages_to_check(extension_zip):
        repo = tmp_path / package.stem
        with zipfile.ZipFile(package) as zf:
            zf.extractall(repo / "affine_deformers")
        manifest = tomllib.loads((repo / "affine_deformers" / "blender_manifest.toml").read_text())
        wheels = manifest.get("wheels", [])
        if not wheels:
            continue  # built with --platform none: the numpy kernel only, by design
        (platform,) = manifest["platforms"]
        for python, numpys in PYTHONS.items():
            with _as_blender(python, platform):
                found = ops.pkg_wheel_filter("user_default", "affine_deformers", str(repo), wheels)
            assert found is not None, (package.name, python)
            assert not wheel_manager.wheel_list_deduplicate_as_skip_set([found]), found
            chosen = _check_one_pair(found[1], python)
            numba, llvmlite = Path(chosen["numba"]), Path(chosen["llvmlite"])
            requires = _requires(numba)
            assert requires["llvmlite"].specifier.contains(Version(_dist(llvmlite.name)[1]), prereleases=True)
            for numpy in numpys:
                assert requires["numpy"].specifier.contains(numpy), (package.name, python, numpy)
            checked += 1
    if checked == 0:
        pytest.skip("no package with wheels was built (--platform none)")


# ------------------------------------------------------------------------------------ numba unusable

FAKE_NUMBA = '''raise ImportError("Numba needs NumPy 2.1 or less. Got NumPy 2.3.")\n'''

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
prefs = importlib.import_module(pkg + ".blender.prefs")
layout = Layout()
prefs.AFFINE_AddonPreferences.draw(types.SimpleNamespace(layout=layout), bpy.context)
print("PREFS:", " | ".join(layout.labels))
print("FALLBACK OK", err)
"""


def test_numba_that_fails_to_import_falls_back_to_numpy_with_the_reason(bl, tmp_path):
    """A fresh Blender process whose `import numba` fails as numba's own import-time check does when it
    meets a numpy newer than it supports (numba 0.62 raises 'Numba needs NumPy 2.3 or less' on a
    Blender whose numpy is newer): the fake package comes first on sys.path, ahead of the bundled wheels
    and of the venv's numba."""
    fake = tmp_path / "fake_site"
    (fake / "numba").mkdir(parents=True)
    (fake / "numba" / "__init__.py").write_text(FAKE_NUMBA)
    path = os.pathsep.join(p for p in (str(fake), os.environ.get("PYTHONPATH", "")) if p)
    # AFFINE_DEFORMERS_ACCEL=1: the compiled kernel is wanted (an outer "0" would hide the failure)
    proc = bl.run_blender(FALLBACK_SCRIPT, env_extra={"PYTHONPATH": path, "AFFINE_DEFORMERS_ACCEL": "1"})
    out = proc.stdout.splitlines()
    assert "FALLBACK OK" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]
    reason = "Numba needs NumPy 2.1 or less. Got NumPy 2.3."
    backend = next(line for line in out if line.startswith("BACKEND:")).removeprefix("BACKEND: ")
    assert backend.startswith("numpy (") and reason in backend, backend
    prefs = next(line for line in out if line.startswith("PREFS:"))
    assert reason in prefs, prefs
    print(backend, prefs, sep="\n")
