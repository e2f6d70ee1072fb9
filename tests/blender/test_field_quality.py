"""The cage field measured against Blender's Mesh Deform (precision 5), in this process, at defaults.

Scenes, edits and metrics are those of `cage_field` (Suzanne subdivided twice in a 384-quad box cage,
and a cylinder in a coarse non-convex "plus" cage; a pulled cage vertex and a 45° twist of the top
half). Our deformer (add operator, defaults: harmonic cage weights), the same deformer with the
inverse-distance option, and Mesh Deform are bound on identical copies and given identical cage
edits; every number is a ratio to Mesh Deform's on the same mesh. Everything Blender-side is done
once per module (Mesh Deform's bind at precision 5 takes seconds), the tests only compare numbers.
Run with -s to see the table.
"""

from __future__ import annotations

import statistics
import time

import bpy
import numpy as np
import pytest

from tests.blender import cage_field as cf

ROUGHNESS_RATIO = 1.5  # ours ≤ this × Mesh Deform's roughness p99
DISPLACEMENT_RATIO = 0.5  # ours ≥ this × Mesh Deform's max |d| (not diluted)
RESIDUAL_RATIO = 1.5  # twisted part: ours ≤ this × Mesh Deform's rigid-fit residual
EXACT = 1e-6  # common affine cage motions: error ≤ this × cage size
BIND_SPEEDUP = 10.0  # Mesh Deform's bind ÷ ours (ours: median of the add operator and two rebinds)

METHODS = ("ours", "idw", "mesh_deform")
SHEAR = np.array([[1.1, 0.45, 0.0], [0.0, 0.9, 0.3], [0.25, 0.0, 1.2]])
SHIFT = np.array([0.3, -0.2, 0.4])


def _rebind(target) -> float:
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        t0 = time.perf_counter()
        assert bpy.ops.object.affine_deformer_bind(index=0) == {"FINISHED"}
        return time.perf_counter() - t0


def _measure_case(case: str) -> dict:
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = cf.build_scene(case)
    rest, edges, cage_rest = scene.rest, scene.edges, scene.cage_rest
    pairs = {name: cf.add_pair(scene, name) for name in METHODS}
    out: dict = {"vertices": len(rest), "faces": len(scene.cage_mesh.polygons)}

    target, cage = pairs["mesh_deform"]
    t0 = time.perf_counter()
    cf.bind_mesh_deform(target, cage)
    out["bind_mesh_deform"] = time.perf_counter() - t0

    target, cage = pairs["ours"]
    t0 = time.perf_counter()
    deformer = cf.bind_ours(target, cage)
    times = [time.perf_counter() - t0, _rebind(target), _rebind(target)]
    out["bind_ours"] = statistics.median(times)
    assert deformer.cage_weights == "HARMONIC" and deformer.status == ""
    cf.bind_ours(*pairs["idw"], cage_weights="INVERSE_DISTANCE")

    for edit in cf.EDITS:
        edited = cf.edited_cage(case, edit, cage_rest)
        for _, cage in pairs.values():
            cf.write_co(cage.data, edited)
        out[edit] = {name: cf.field_metrics(case, edit, rest, cf.evaluated(target), edges, cage_rest)
                     for name, (target, _) in pairs.items()}
        for _, cage in pairs.values():
            cf.write_co(cage.data, cage_rest)

    sheared = cage_rest @ SHEAR.T + SHIFT  # a common affine motion of every cage vertex
    exact = rest @ SHEAR.T + SHIFT
    for _, cage in pairs.values():
        cf.write_co(cage.data, sheared)
    out["affine_error"] = {name: float(np.abs(cf.evaluated(target) - exact).max()) / cf.cage_size(cage_rest)
                           for name, (target, _) in pairs.items()}
    out["affine_motion"] = float(np.abs(exact - rest).max()) / cf.cage_size(cage_rest)
    return out


@pytest.fixture(scope="module")
def measured(installed) -> dict:
    results = {case: _measure_case(case) for case in cf.CASES}
    print()
    for case, r in results.items():
        print(f"{case}: {r['vertices']} vertices, {r['faces']} cage faces; bind ours {r['bind_ours']:.3f} s, "
              f"Mesh Deform {r['bind_mesh_deform']:.3f} s; affine error / size "
              + ", ".join(f"{m} {e:.1e}" for m, e in r["affine_error"].items()))
        for edit in cf.EDITS:
            for metric in r[edit]["mesh_deform"]:
                values = "  ".join(f"{m} {r[edit][m][metric]:.4g}" for m in METHODS)
                print(f"  {edit:5s} {metric:17s} {values}")
    bpy.ops.wm.read_homefile(use_empty=True)
    return results


def test_mesh_deform_fields_have_no_spikes(measured):
    """The reference passes its own seam test (cage_field.spikes): the metric is not tuned to fail."""
    for case in cf.CASES:
        for edit in cf.EDITS:
            assert measured[case][edit]["mesh_deform"]["spikes"] == 0, (case, edit)


@pytest.mark.parametrize("edit", cf.EDITS)
@pytest.mark.parametrize("case", cf.CASES)
def test_cage_edit_is_as_smooth_and_local_as_mesh_deform(measured, case, edit):
    ours, md = measured[case][edit]["ours"], measured[case][edit]["mesh_deform"]
    assert ours["spikes"] == 0
    assert ours["roughness_p99"] <= ROUGHNESS_RATIO * md["roughness_p99"], (ours, md)
    assert ours["max_displacement"] >= DISPLACEMENT_RATIO * md["max_displacement"], (ours, md)
    if edit == "TWIST":
        assert ours["rigid_residual"] <= RESIDUAL_RATIO * md["rigid_residual"], (ours, md)


def test_inverse_distance_option_fails_the_same_measure(measured):
    """The measure can fail: the inverse-distance weights (8 influences, continuous truncation and
    half-space ramp, the 0.1 model made continuous) are still far rougher than Mesh Deform's."""
    idw, md = measured["SUZANNE"]["PULL"]["idw"], measured["SUZANNE"]["PULL"]["mesh_deform"]
    assert idw["roughness_p99"] > 3.0 * md["roughness_p99"], (idw, md)


def test_common_affine_cage_motion_stays_exact(measured):
    for case in cf.CASES:
        error = measured[case]["affine_error"]
        assert error["ours"] <= EXACT and error["idw"] <= EXACT, (case, error)
        assert measured[case]["affine_motion"] > 0.1, "the motion is substantial"


def test_bind_is_ten_times_faster_than_mesh_deform(measured):
    for case in cf.CASES:
        r = measured[case]
        assert BIND_SPEEDUP * r["bind_ours"] <= r["bind_mesh_deform"], (case, r["bind_ours"],
                                                                        r["bind_mesh_deform"])
