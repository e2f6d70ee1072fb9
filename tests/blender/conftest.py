"""Blender-level test set-up: install the BUILT extension .zip into an isolated user directory and drive
it like a user does (operators, frame changes, file save/load), with the bpy module in-process and, for
renders / fresh-process loads / Blender 4.2 LTS, in subprocesses.

BLENDER_USER_RESOURCES must be set before bpy is imported, so this module sets it at import time.
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
USER_DIR = Path(tempfile.mkdtemp(prefix="affdef_user_"))
os.environ["BLENDER_USER_RESOURCES"] = str(USER_DIR)
# Where the deformers write their output (output_store.py): the tests inspect the mesh's attributes,
# so they run on that store unless told otherwise (POSITIONS, or AUTO for the cost model); the
# stores' own tests choose per test.
os.environ.setdefault("AFFINE_DEFORMERS_OUTPUT_STORE", "ATTRIBUTES")

import bpy  # noqa: E402  (must follow BLENDER_USER_RESOURCES)

ADDON = "bl_ext.user_default.affine_deformers"
PACKAGE = f"{ADDON}.affine_deformers"
SUBPROCESS_TIMEOUT = 300


def _package_sources() -> list[Path]:
    files = [ROOT / "__init__.py", ROOT / "blender_manifest.toml", ROOT / "tools" / "build_native.py"]
    # the compiled kernel's C sources go into the package as its wheel's libraries
    return files + sorted((ROOT / "affine_deformers").rglob("*.py")) + sorted((ROOT / "csrc").glob("*.[ch]"))


def _fresh_zip() -> Path:
    """dist/affine_deformers-*.zip when it is newer than every packaged source; else a fresh build in
    a temporary directory (never test stale code, never race other builds writing dist/)."""
    newest = max(p.stat().st_mtime for p in _package_sources() if p.exists())
    built = sorted((ROOT / "dist").glob("affine_deformers-*.zip"))
    if built and built[-1].stat().st_mtime >= newest:
        return built[-1]
    out = Path(tempfile.mkdtemp(prefix="affdef_build_"))
    subprocess.run([sys.executable, str(ROOT / "tools" / "build_extension.py"), "--output-dir", str(out)],
                   check=True, cwd=ROOT, capture_output=True, timeout=SUBPROCESS_TIMEOUT)
    return sorted(out.glob("affine_deformers-*.zip"))[-1]


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "attributes: inspects the mesh-attribute output store directly "
                                       "(skipped on AFFINE_DEFORMERS_OUTPUT_STORE=POSITIONS)")


_SESSION_START = time.monotonic()


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    """Record this suite's counts where `AFFINE_SUITE_RECORD` says (a folder; `make test` sets it), for
    README's table of tested versions (tools/tested_versions.py)."""
    folder = os.environ.get("AFFINE_SUITE_RECORD")
    if not folder:
        return
    stats = terminalreporter.stats
    version = bpy.app.version
    label = os.environ.get("AFFINE_SUITE_LABEL") or f"{version[0]}.{version[1]}"
    record = {
        "label": label,
        "blender": bpy.app.version_string,
        "python": ".".join(map(str, sys.version_info[:3])),
        "passed": len(stats.get("passed", [])),
        "failed": len(stats.get("failed", [])) + len(stats.get("error", [])),
        "skipped": len(stats.get("skipped", [])),
        "seconds": round(time.monotonic() - _SESSION_START, 1),
        "exit": int(exitstatus),
    }
    Path(folder).mkdir(parents=True, exist_ok=True)
    name = "".join(c if c.isalnum() else "_" for c in label)
    (Path(folder) / f"{name}.json").write_text(json.dumps(record), encoding="utf-8")


def pytest_collection_modifyitems(config, items) -> None:
    if os.environ.get("AFFINE_DEFORMERS_OUTPUT_STORE") != "POSITIONS":
        return
    skip = pytest.mark.skip(reason="inspects the attribute store; this run writes to position carriers")
    for item in items:
        if "attributes" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def extension_zip() -> Path:
    return _fresh_zip()


@pytest.fixture(scope="session", autouse=True)
def installed(extension_zip: Path) -> SimpleNamespace:
    """Install + enable the zip once; save the preferences so read_homefile keeps it enabled."""
    result = bpy.ops.extensions.package_install_files(
        filepath=str(extension_zip), repo="user_default", enable_on_install=True)
    assert result == {"FINISHED"}
    assert ADDON in {a.module for a in bpy.context.preferences.addons}
    bpy.ops.wm.save_userpref()
    return SimpleNamespace(
        core=importlib.import_module(f"{PACKAGE}.core"),
        aff3=importlib.import_module(f"{PACKAGE}.core.aff3"),
        deform=importlib.import_module(f"{PACKAGE}.core.deform"),
        evaluate=importlib.import_module(f"{PACKAGE}.blender.update.evaluate"),
        storage=importlib.import_module(f"{PACKAGE}.blender.files.storage"),
        zip=extension_zip,
        addon=ADDON,
        package=PACKAGE,
    )


@pytest.fixture(autouse=True)
def clean_scene(installed):
    """An empty scene per test, with the extension still enabled and registered."""
    bpy.ops.wm.read_homefile(use_empty=True)
    assert ADDON in {a.module for a in bpy.context.preferences.addons}
    assert hasattr(bpy.types.Object, "affine_deformers")
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 20
    scene.frame_set(1)
    yield scene


# ---------------------------------------------------------------------------------------------- helpers


def uv_sphere(segments: int = 32, rings: int = 16, radius: float = 1.0, location=(0.0, 0.0, 0.0)):
    bpy.ops.mesh.primitive_uv_sphere_add(segments=segments, ring_count=rings, radius=radius,
                                         location=location)
    return bpy.context.active_object


def grid_cube(cuts: int = 10, size: float = 2.0, name: str = "Cube"):
    """A cube with `cuts` cuts per edge (6·(cuts+1)² faces), centred at the origin."""
    import bmesh

    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=size)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=cuts, use_grid_fill=True)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def empty(name: str, location=(0.0, 0.0, 0.0)):
    obj = bpy.data.objects.new(name, None)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    return obj


def add_probe_deformer(target, probes, **options):
    """Run the add operator like a script does, then set options (weights recompute live)."""
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, *probes]):
        assert bpy.ops.object.affine_probe_deformer_add() == {"FINISHED"}
    deformer = target.affine_deformers[len(target.affine_deformers) - 1]
    for key, value in options.items():
        setattr(deformer, key, value)
    return deformer


def run_op(op, obj, **kwargs):
    with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj]):
        return op(**kwargs)


def evaluated_positions(obj) -> np.ndarray:
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = obj.evaluated_get(depsgraph).data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def rest_positions(obj) -> np.ndarray:
    co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def dense_weights(obj, deformer) -> np.ndarray:
    """(N, m) weights rebuilt from the stored `.affdef_<uid>_idx<k>` / `_w<k>` attributes; a share
    pooled by the truncation (index m, docs/MATH.md §12) spread over the probes in proportion to their
    weight scales, as the deformer blends it."""
    n, m = len(obj.data.vertices), len(deformer.probes)
    dense = np.zeros((n, m + 1))
    k = 0
    while (a_i := obj.data.attributes.get(f".affdef_{deformer.uid}_idx{k}")) is not None:
        a_w = obj.data.attributes[f".affdef_{deformer.uid}_w{k}"]
        idx = np.empty(n, dtype=np.int32)
        w = np.empty(n, dtype=np.float32)
        a_i.data.foreach_get("value", idx)
        a_w.data.foreach_get("value", w)
        np.add.at(dense, (np.arange(n), idx), w)
        k += 1
    assert k > 0, "no stored weights"
    scales = np.array([item.weight_scale for item in deformer.probes])
    if dense[:, m].any():
        dense[:, :m] += dense[:, m:] * (scales / scales.sum())[None, :]
    return dense[:, :m]


def stored_offsets(target, deformer) -> np.ndarray:
    """A copy of the offsets the deformer last wrote (float32, (N, 3)), wherever they live
    (output_store.py: the mesh's attributes or a position carrier)."""
    store = importlib.import_module(f"{PACKAGE}.blender.update.output_store")
    nodes = importlib.import_module(f"{PACKAGE}.blender.files.nodes")
    mod = nodes.find_modifier(target, f"affdef_{deformer.uid}_offset")
    path, data = store.stored_output(target, deformer.uid, mod)
    assert path == "OFFSET", path
    return data.copy()


def recomputed_offsets(target, deformer) -> np.ndarray:
    """The offsets of a from-scratch evaluation (every cache dropped first): what incremental updates
    must equal exactly."""
    evaluate = importlib.import_module(f"{PACKAGE}.blender.update.evaluate")
    evaluate.forget()
    evaluate.evaluate_object(target, bpy.context.evaluated_depsgraph_get())
    return stored_offsets(target, deformer)


def local_motion(target, probe, rest_matrix) -> np.ndarray:
    """A = C · C_rest⁻¹ with C = target_world⁻¹ · probe_world, independently of the add-on (float64)."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    tw = np.array(target.evaluated_get(depsgraph).matrix_world, dtype=np.float64)
    pw = np.array(probe.evaluated_get(depsgraph).matrix_world, dtype=np.float64)
    current = np.linalg.inv(tw) @ pw
    return current @ np.linalg.inv(np.array(rest_matrix, dtype=np.float64).reshape(4, 4))


def run_blender(script: str, python: str | None = None, env_extra: dict | None = None,
                timeout: float = SUBPROCESS_TIMEOUT) -> subprocess.CompletedProcess:
    """Run `script` in a fresh bpy process (default: this interpreter, the shared user directory where
    the extension is installed). The script must enable the add-on itself (`enable_addon()` prelude)."""
    prelude = textwrap.dedent(f"""
        import bpy
        import addon_utils
        def enable_addon():
            mod = addon_utils.enable({ADDON!r}, default_set=True)
            assert mod is not None and hasattr(bpy.types.Object, "affine_deformers"), "add-on not enabled"
    """)
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(USER_DIR), **(env_extra or {})}
    proc = subprocess.run([python or sys.executable, "-c", prelude + textwrap.dedent(script)],
                          env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise AssertionError(f"subprocess failed ({proc.returncode}):\n"
                             f"{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return proc


def check_frames_in_any_order(target, deformer, rest: np.ndarray, expected_at) -> dict:
    """Visit frames 20, 1, 10, 20: at each the evaluated positions match `expected_at(frame)` (an
    independent computation) to 1e-5, a revisited frame gives the same bits (a frame depends only on
    that frame), the status stays clean, and frame 1 (the bind pose) is the rest shape. Returns the
    positions per frame."""
    results = {}
    for frame in (20, 1, 10, 20):
        bpy.context.scene.frame_set(frame)
        got = evaluated_positions(target)
        expected = expected_at(frame)
        assert np.abs(got - expected).max() < 1e-5, f"frame {frame}"
        if frame in results:
            assert np.array_equal(results[frame], got), "the result at a frame depends only on that frame"
        results[frame] = got.copy()
        assert deformer.status == ""
    assert np.array_equal(results[1], rest.astype(np.float32)), "frame 1 is the bind pose"
    return results


def check_frames_survive_reopen(target, frames, tmp_path: Path) -> None:
    """Positions at `frames` evaluated here equal those of the saved file reopened in a fresh process
    (bind data and offsets live in the .blend), and the file opens showing what was saved."""
    expected = {}
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        expected[frame] = evaluated_positions(target).copy()
    bpy.context.scene.frame_set(10)
    path = tmp_path / "reopened.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    got = reopened_positions(path, target.name, (20, 1, 10), tmp_path / "positions.npz")
    assert str(got["status"]) == ""
    assert np.array_equal(got["opened"], expected[10]), "offsets saved in the .blend"
    for frame in frames:
        assert np.array_equal(got[str(frame)], expected[frame]), f"frame {frame}"


def reopened_positions(path: Path, object_name: str, frames, out: Path) -> dict:
    """Open `path` in a fresh bpy process and return the evaluated positions of `object_name` right
    after opening ("opened") and after frame_set(f) for each frame (str(f)), plus its first
    deformer's status ("status")."""
    run_blender(f"""
        import numpy as np
        enable_addon()
        bpy.ops.wm.open_mainfile(filepath={str(path)!r}, load_ui=False)
        target = bpy.data.objects[{object_name!r}]
        def positions():
            mesh = target.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
            co = np.empty(len(mesh.vertices) * 3, np.float32)
            mesh.vertices.foreach_get("co", co)
            return co.reshape(-1, 3)
        result = {{"opened": positions()}}
        for frame in {list(frames)!r}:
            bpy.context.scene.frame_set(frame)
            result[str(frame)] = positions()
        result["status"] = np.array(target.affine_deformers[0].status)
        np.savez({str(out)!r}, **result)
    """)
    return dict(np.load(out))


@pytest.fixture
def asset(tmp_path_factory, bl) -> dict[str, str]:
    """The rig asset of test_overrides.py (a probe, a cage and a bone deformer with keyed controls in a
    collection "Rig"; its file, reference positions and render), built once per session."""
    from tests.blender.test_overrides import build_asset  # its scripts live with the override tests

    return build_asset(tmp_path_factory, bl)


@pytest.fixture
def bl() -> SimpleNamespace:
    """Helper functions for driving Blender in tests."""
    return SimpleNamespace(
        uv_sphere=uv_sphere, grid_cube=grid_cube, empty=empty, add_probe_deformer=add_probe_deformer,
        run_op=run_op, evaluated_positions=evaluated_positions, rest_positions=rest_positions,
        dense_weights=dense_weights, local_motion=local_motion, run_blender=run_blender,
        reopened_positions=reopened_positions, stored_offsets=stored_offsets,
        check_frames_in_any_order=check_frames_in_any_order,
        check_frames_survive_reopen=check_frames_survive_reopen,
        recomputed_offsets=recomputed_offsets,
    )
