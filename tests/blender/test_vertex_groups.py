"""Painted weights: vertex groups named after the probes drive the deformation."""

from __future__ import annotations

import bpy
import numpy as np


def test_vertex_group_weights_are_stored_and_drive_the_mesh(bl, installed):
    target = bl.grid_cube(cuts=10)
    rest = bl.rest_positions(target).astype(np.float64)
    top, bottom = bl.empty("Top", (0.0, 0.0, 1.0)), bl.empty("Bottom", (0.0, 0.0, -1.0))
    # paint: "Top" on the upper half (weight grows with z), "Bottom" everywhere at 0.5
    upper = np.flatnonzero(rest[:, 2] > 0.0)
    group = target.vertex_groups.new(name="Top")
    for value in np.unique(np.round(rest[upper, 2], 4)):  # one add() per weight level, not per vertex
        group.add(upper[np.round(rest[upper, 2], 4) == value].tolist(), float(value), "REPLACE")
    target.vertex_groups.new(name="Bottom").add(list(range(len(rest))), 0.5, "REPLACE")

    deformer = bl.add_probe_deformer(target, [top, bottom], weight_mode="VERTEX_GROUPS", normalize="NONE")
    assert deformer.status == ""
    painted = np.zeros((len(rest), 2))
    painted[upper, 0] = np.round(rest[upper, 2], 4)
    painted[:, 1] = 0.5
    stored = bl.dense_weights(target, deformer)
    assert np.abs(stored - painted).max() < 1e-6

    top.location.z = 1.5
    top.rotation_euler.z = 0.6
    got = bl.evaluated_positions(target)
    pairs = zip((top, bottom), deformer.probes, strict=True)
    A = np.stack([bl.local_motion(target, probe, item.rest_matrix) for probe, item in pairs])
    expected = installed.deform.deform_points(rest, A, painted)
    assert np.abs(got - expected).max() < 1e-5
    lower = rest[:, 2] <= 0.0
    assert np.array_equal(got[lower], rest[lower].astype(np.float32)), "unpainted by 'Top': unchanged"
    assert np.abs(got[~lower] - rest[~lower]).max() > 0.2


def test_missing_vertex_group_is_reported(bl):
    target = bl.uv_sphere()
    probes = [bl.empty("Painted"), bl.empty("Unpainted", (0.0, 0.0, 1.0))]
    target.vertex_groups.new(name="Painted").add(list(range(len(target.data.vertices))), 1.0, "REPLACE")
    deformer = bl.add_probe_deformer(target, probes, weight_mode="VERTEX_GROUPS")
    assert "No vertex group named 'Unpainted'" in deformer.status
    probes[1].location.z = 3.0  # no weight: no effect
    assert np.array_equal(bl.evaluated_positions(target), bl.rest_positions(target))
    probes[0].location.x = 0.5
    assert np.abs(bl.evaluated_positions(target) - bl.rest_positions(target) - [0.5, 0, 0]).max() < 1e-5
    assert len(target.modifiers) == 1, "the temporary reader left nothing behind"
    assert not [o for o in bpy.data.objects if o.name.startswith(".affdef")]
    assert not [g for g in bpy.data.node_groups if "VertexGroupReader" in g.name]
