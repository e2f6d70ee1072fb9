"""The installed package runs the compiled kernel (the bundled C library), the preference switches to
numpy and back, and both kernels deform the same (float32 positions: equal to rounding)."""

from __future__ import annotations

import importlib
import zipfile

import bpy
import numpy as np
import pytest

ADDON = "bl_ext.user_default.affine_deformers"


def _modules():
    """(accel, prefs) of the installed package (importable once the session fixture installed it)."""
    return (importlib.import_module(f"{ADDON}.affine_deformers.accel"),
            importlib.import_module(f"{ADDON}.affine_deformers.blender.ui.prefs"))


def _bundles_kernel(zip_path) -> bool:
    return any(n.startswith("wheels/affine_deformers_kernel-") for n in zipfile.ZipFile(zip_path).namelist())


def _positions(obj: bpy.types.Object) -> np.ndarray:
    mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


@pytest.fixture
def rig():
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.mesh.primitive_uv_sphere_add(segments=48, ring_count=24)
    target = bpy.context.active_object
    probes = []
    for i, loc in enumerate(((1, 0, 0), (-1, 0, 0), (0, 0, 1))):
        probe = bpy.data.objects.new(f"P{i}", None)
        probe.location = loc
        bpy.context.scene.collection.objects.link(probe)
        probes.append(probe)
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, *probes]):
        assert bpy.ops.object.affine_probe_deformer_add() == {"FINISHED"}
    yield target, probes
    _modules()[1].preferences().use_compiled_kernel = True


def test_the_package_bundles_the_compiled_kernel_and_uses_it(extension_zip):
    accel, prefs_module = _modules()
    if not _bundles_kernel(extension_zip):
        pytest.skip("package built without wheels (--platform none): numpy kernel only")
    assert accel.active(), accel.backend()
    assert accel.backend().startswith("C kernel (affine_kernel"), accel.backend()
    # The library came from the package's own wheel, installed into the extension's site-packages.
    assert "affine_deformers_kernel" in str(accel._load().path)
    assert prefs_module.preferences().use_compiled_kernel is True


def test_preference_switches_kernel_and_results_agree(rig, extension_zip):
    target, probes = rig
    accel, prefs_module = _modules()
    probes[0].rotation_euler = (0.3, 2.5, -0.4)  # past 90°: the rotation log is exercised
    probes[1].scale = (1.5, 0.7, 1.0)
    probes[2].location = (0.2, 0.1, 1.4)
    compiled = _positions(target)
    prefs = prefs_module.preferences()
    prefs.use_compiled_kernel = False  # the update callback re-evaluates with numpy
    assert accel.backend().startswith("numpy ("), accel.backend()
    assert not accel.active()
    numpy_result = _positions(target)
    assert target.affine_deformers[0].status == ""
    assert np.abs(numpy_result - compiled).max() < 2e-6  # float32 rounding of the same offsets
    # both moved the mesh (a silent no-op would also "agree")
    probes[0].rotation_euler = (0.0, 0.0, 0.0)
    probes[1].scale = (1.0, 1.0, 1.0)
    probes[2].location = (0.0, 0.0, 1.0)
    rest = _positions(target)
    assert np.abs(numpy_result - rest).max() > 0.1
    prefs.use_compiled_kernel = True
    if _bundles_kernel(extension_zip):
        assert accel.active()
    probes[0].rotation_euler = (0.3, 2.5, -0.4)
    probes[1].scale = (1.5, 0.7, 1.0)
    probes[2].location = (0.2, 0.1, 1.4)
    assert np.array_equal(_positions(target), compiled)  # depends only on the inputs, not on history


def test_cage_results_agree_across_kernels_and_depend_only_on_the_inputs(bl, extension_zip):
    """A harmonic cage deformer's per-control path runs in the compiled kernel too (ψ's polar split
    of the moved corners, the node blend): switching to numpy gives the same deformation to float32
    rounding, and back on the compiled kernel the same pose gives the same bits as before, though
    the cage's motion memo was filled by numpy meanwhile."""
    if not _bundles_kernel(extension_zip):
        pytest.skip("package built without wheels (--platform none): numpy kernel only")
    accel, prefs_module = _modules()
    bpy.ops.wm.read_homefile(use_empty=True)
    target = bl.grid_cube(cuts=6, size=1.0, name="Target")
    cage = bl.grid_cube(cuts=2, size=2.4, name="Cage")
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, cage]):
        assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
    deformer = target.affine_deformers[0]
    assert deformer.cage_weights == "HARMONIC" and deformer.status == ""
    vertices = cage.data.vertices
    base = np.array([v.co[:] for v in vertices])
    corner = int(np.argmax(base @ [1.0, 2.0, 3.0]))

    def pose(shift) -> np.ndarray:
        vertices[corner].co = base[corner] + np.asarray(shift)
        cage.data.update()
        bpy.context.view_layer.update()
        return _positions(target)

    rest = _positions(target)
    compiled = pose((0.4, -0.2, 0.5))
    assert np.abs(compiled - rest).max() > 0.02
    prefs = prefs_module.preferences()
    try:
        prefs.use_compiled_kernel = False
        assert not accel.active()
        pose((0.1, 0.1, 0.1))
        numpy_result = pose((0.4, -0.2, 0.5))
        assert deformer.status == ""
        assert np.abs(numpy_result - compiled).max() < 2e-6
    finally:
        prefs.use_compiled_kernel = True
    assert accel.active()
    bpy.context.view_layer.update()
    assert np.array_equal(_positions(target), compiled)
