"""The bind data's format version, kept apart from the extension's version: stamped at bind, kept
through save and reload, and a deformer bound by a newer add-on (a higher format) is not evaluated —
its status says to update, and the mesh passes through unchanged."""

from __future__ import annotations

import importlib

import bpy
import numpy as np


def test_bind_stamps_the_format_and_a_newer_one_passes_through(bl, installed, tmp_path):
    storage = importlib.import_module(f"{installed.package}.blender.files.storage")
    target = bl.uv_sphere()
    probe = bl.empty("P", (1.2, 0.0, 0.0))
    deformer = bl.add_probe_deformer(target, [probe])
    assert storage.file_format(deformer) == storage.FILE_FORMAT >= 2
    rest = bl.rest_positions(target)
    probe.location.x += 0.5
    bpy.context.view_layer.update()
    moved = bl.evaluated_positions(target)
    assert np.abs(moved - rest).max() > 0.1

    name = target.name
    path = str(tmp_path / "stamped.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    target = bpy.data.objects[name]
    deformer = target.affine_deformers[0]
    assert storage.file_format(deformer) == storage.FILE_FORMAT
    assert deformer.status == ""
    assert np.allclose(bl.evaluated_positions(target), moved, atol=1e-6)

    deformer[storage.FORMAT_KEY] = storage.FILE_FORMAT + 1  # as a newer add-on would have stamped it
    bpy.data.objects["P"].location.x += 0.1
    bpy.context.view_layer.update()
    assert "newer version of Affine Deformers" in deformer.status, deformer.status
    assert "update the add-on" in deformer.status
    assert np.allclose(bl.evaluated_positions(target), rest, atol=1e-6)


def test_a_deformer_without_a_stamp_reads_as_format_1(bl, installed):
    storage = importlib.import_module(f"{installed.package}.blender.files.storage")
    target = bl.uv_sphere()
    deformer = bl.add_probe_deformer(target, [bl.empty("P", (1.2, 0.0, 0.0))])
    del deformer[storage.FORMAT_KEY]  # what 0.1.x wrote
    assert storage.file_format(deformer) == 1
    assert deformer.status == ""
