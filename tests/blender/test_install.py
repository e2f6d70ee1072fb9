"""The built .zip installs and works: in-process on bpy 5.0 and in a subprocess on bpy 4.2 LTS;
register/unregister is clean (no duplicate handlers)."""

from __future__ import annotations

import os
import sys

import addon_utils
import bpy
import pytest

ADDON = "bl_ext.user_default.affine_deformers"
PACKAGE = f"{ADDON}.affine_deformers"


def _our_handlers() -> dict[str, int]:
    counts = {}
    for name in ("frame_change_post", "depsgraph_update_post", "load_post", "render_pre", "render_init"):
        counts[name] = sum(1 for h in getattr(bpy.app.handlers, name)
                           if getattr(h, "__module__", "").startswith(PACKAGE))
    return counts


def test_zip_installs_and_enables_on_this_blender(installed):
    # `make test` runs this suite on bpy 5.0 and again on bpy 4.2 LTS (the manifest's minimum)
    assert bpy.app.version >= (4, 2, 0)
    assert ADDON in {a.module for a in bpy.context.preferences.addons}
    assert PACKAGE + ".blender" in sys.modules
    # the installed copy is the one running, not the working tree
    assert "extensions" in sys.modules[PACKAGE].__file__
    for op in ("affine_probe_deformer_add", "affine_cage_deformer_add", "affine_deformer_bind",
               "affine_deformer_remove", "affine_deformer_apply", "affine_deformer_bake",
               "affine_deformer_unbake", "affine_deformer_probe_add", "affine_deformer_probe_remove"):
        assert hasattr(bpy.ops.object, op), op
    assert "AFFINE_PT_deformers" in dir(bpy.types)
    assert _our_handlers() == {name: 1 for name in _our_handlers()}


def test_disable_enable_leaves_no_duplicate_handlers():
    addon_utils.disable(ADDON, default_set=False)
    try:
        assert not hasattr(bpy.types.Object, "affine_deformers")
        assert set(_our_handlers().values()) == {0}
    finally:
        addon_utils.enable(ADDON, default_set=False)
    addon_utils.enable(ADDON, default_set=False)  # enabling twice must not stack handlers
    assert set(_our_handlers().values()) == {1}
    assert hasattr(bpy.types.Object, "affine_deformers")


LTS_SCRIPT = """
import os, sys, tempfile
os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="affdef_lts_")
import bpy
import numpy as np
assert bpy.app.version[:2] == (4, 2), bpy.app.version_string
assert bpy.ops.extensions.package_install_files(
    filepath=sys.argv[1], repo="user_default", enable_on_install=True) == {"FINISHED"}
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
    return co.reshape(-1, 3)
rest = positions()
probe.location = (0.25, -0.5, 1.0)
moved = positions()
deformer = target.affine_deformers[0]
# one probe, SUM weights: the whole mesh follows the probe exactly
assert deformer.status == "", deformer.status
assert np.abs(moved - rest - np.array([0.25, -0.5, 1.0], np.float32)).max() < 1e-5
probe.rotation_euler.z = 1.0
turned = positions()
assert np.abs(turned - moved).max() > 0.1
# painted weights (read through a temporary Geometry Nodes evaluation) work on 4.2 too
probe.rotation_euler.z = 0.0
target.vertex_groups.new(name="Probe").add(list(range(len(rest))), 0.5, "REPLACE")
deformer.normalize = "NONE"
deformer.weight_mode = "VERTEX_GROUPS"
assert deformer.status == "", deformer.status
half = positions()
assert np.abs(half - rest - 0.5 * np.array([0.25, -0.5, 1.0], np.float32)).max() < 1e-5
# a probe disabled in viewports is evaluated through the modifier's Probes input
probe.hide_viewport = True
probe.location = (0.5, 0.0, 0.0)
assert np.abs(positions() - rest - np.array([0.25, 0.0, 0.0], np.float32)).max() < 1e-5
# the compiled kernel runs from the wheel bundled in the package, which Blender installed into the
# extensions' site-packages
import importlib, zipfile
accel = importlib.import_module("bl_ext.user_default.affine_deformers.affine_deformers.accel")
names = zipfile.ZipFile(sys.argv[1]).namelist()
bundled = any(n.startswith("wheels/affine_deformers_kernel-") for n in names)
if bundled:
    assert accel.active(), accel.backend()
    assert accel.backend().startswith("C kernel (affine_kernel"), accel.backend()
    import affine_deformers_kernel
    assert "extensions" in affine_deformers_kernel.__file__, affine_deformers_kernel.__file__
    assert str(accel._load().path).startswith(affine_deformers_kernel.LIBRARY_DIR), accel._load().path
print("LTS OK", bpy.app.version_string, "kernel:", accel.backend())
"""


def test_zip_installs_and_deforms_on_blender_4_2_lts(extension_zip, tmp_path):
    python = os.environ.get("AFFINE_LTS_PYTHON")
    if not python:
        pytest.skip("AFFINE_LTS_PYTHON is not set (the Makefile's `make test` sets it to .venv42's python)")
    import subprocess

    script = tmp_path / "lts_check.py"
    script.write_text(LTS_SCRIPT)
    env = {k: v for k, v in os.environ.items() if k != "BLENDER_USER_RESOURCES"}
    proc = subprocess.run([python, str(script), str(extension_zip)], capture_output=True, text=True,
                          timeout=300, env=env)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "LTS OK 4.2" in proc.stdout
