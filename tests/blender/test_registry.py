"""The registry of deformed objects (registry.py): an update visits the objects that carry deformers,
not every object of the scene, and objects that arrive by append, duplication or a script are
updated at the very next frame change; deleted ones are dropped without a trace."""

from __future__ import annotations

import importlib
import statistics
import time

import bpy
import numpy as np


def _modules(installed):
    return (importlib.import_module(f"{installed.package}.blender.update.registry"),
            importlib.import_module(f"{installed.package}.blender.update.evaluate"))


def _rig(bl, name: str, x: float = 0.0):
    body = bl.grid_cube(cuts=3, name=name)
    body.location.x = x
    probes = [bl.empty(f"{name}A", (x + 1.5, 0, 0)), bl.empty(f"{name}B", (x - 1.5, 0, 0))]
    bpy.context.view_layer.update()
    bl.add_probe_deformer(body, probes)
    mover = probes[0]
    mover.keyframe_insert("location", frame=1)
    mover.location.z += 1.0
    mover.keyframe_insert("location", frame=10)
    return body


def test_an_update_costs_nothing_per_object_without_a_deformer(bl, installed):
    registry, evaluate = _modules(installed)
    scene = bpy.context.scene
    crowd = bpy.data.collections.new("Crowd")
    scene.collection.children.link(crowd)
    for i in range(20000):
        crowd.objects.link(bpy.data.objects.new(f"E{i}", None))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluate.run(scene, depsgraph)  # the one scan after the file was read

    def seconds() -> float:
        start = time.perf_counter()
        evaluate.run(scene, depsgraph)
        return time.perf_counter() - start

    idle = statistics.median(seconds() for _ in range(30))
    assert registry.targets() == []
    # A pass over 20,000 objects took ~12 ms; the update must not depend on them.
    assert idle < 1e-3, f"an update without deformers took {idle * 1e3:.2f} ms beside 20,000 objects"


def test_objects_that_arrive_are_updated_at_the_next_frame(bl, installed, tmp_path):
    registry, _evaluate = _modules(installed)
    scene = bpy.context.scene
    body = _rig(bl, "Body")
    path = tmp_path / "asset.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.frame_set(1)
    assert registry.targets() == []
    with bpy.data.libraries.load(str(path), link=False) as (_src, dst):
        dst.objects = ["Body", "BodyA", "BodyB"]
    for obj in dst.objects:
        scene.collection.objects.link(obj)
    scene.frame_set(10)  # no other update in between: the frame change itself must find it
    body = bpy.data.objects["Body"]
    rest = bl.rest_positions(body)
    assert body in registry.targets() and body.affine_deformers[0].status == ""
    assert np.abs(bl.evaluated_positions(body) - rest).max() > 0.3, "appended and deformed"

    copy = body.copy()  # a script's duplicate: a new object with a deformer item, nothing else
    copy.location.x = 6.0
    scene.collection.objects.link(copy)
    scene.frame_set(5)
    assert copy in registry.targets()
    assert copy.affine_deformers[0].status == "" and np.abs(bl.evaluated_positions(copy) - rest).max() > 0.1

    bpy.data.objects.remove(copy)  # deleted: dropped, nothing raised
    scene.frame_set(7)
    assert len(registry.targets()) == 1 and body.affine_deformers[0].status == ""
