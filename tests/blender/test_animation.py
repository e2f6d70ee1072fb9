"""Animated probes: frame_set results match the core on the same inputs and depend only on the frame;
the result survives save + reopen in a fresh process; Cycles renders see every frame's deformation."""

from __future__ import annotations

import math

import bpy
import numpy as np

FRAMES = (1, 10, 20)


def _keyframe(obj, frame: int, location=None, rotation=None, scale=None) -> None:
    for path, value in (("location", location), ("rotation_euler", rotation), ("scale", scale)):
        if value is not None:
            setattr(obj, path, value)
            obj.keyframe_insert(path, frame=frame)


def _animated_scene(bl):
    target = bl.grid_cube(cuts=10)
    probes = [bl.empty("A", (1.2, 0.0, 0.0)), bl.empty("B", (-1.2, 0.0, 0.0)), bl.empty("C", (0.0, 0.0, 1.5))]
    deformer = bl.add_probe_deformer(target, probes, weight_mode="INVERSE_DISTANCE", max_influences=3)
    a, b, c = probes
    _keyframe(a, 1, (1.2, 0, 0), (0, 0, 0), (1, 1, 1))
    _keyframe(a, 10, (1.5, 0.2, 0), (0.0, 0.0, 1.1), (1.3, 1, 1))
    _keyframe(a, 20, (1.2, -0.4, 0.3), (0.4, 0.0, 2.6), (1, 0.7, 1))
    _keyframe(b, 1, (-1.2, 0, 0), (0, 0, 0))
    _keyframe(b, 20, (-1.0, 0, -0.5), (-1.0, 0.3, 0))
    _keyframe(c, 1, scale=(1, 1, 1))
    _keyframe(c, 15, scale=(0.6, 0.6, 1.4))
    return target, probes, deformer


def test_frames_match_the_core_on_the_same_inputs_in_any_order(bl, installed):
    target, probes, deformer = _animated_scene(bl)
    rest = bl.rest_positions(target).astype(np.float64)
    weights = bl.dense_weights(target, deformer)
    assert np.allclose(weights.sum(axis=1), 1.0, atol=1e-6)

    def expected_at(_frame: int) -> np.ndarray:
        pairs = zip(probes, deformer.probes, strict=True)
        A = np.stack([bl.local_motion(target, probe, item.rest_matrix) for probe, item in pairs])
        return installed.deform.deform_points(rest, A, weights)

    results = bl.check_frames_in_any_order(target, deformer, rest, expected_at)
    assert np.abs(results[10] - results[20]).max() > 0.1


def test_save_and_reopen_in_a_fresh_process_gives_identical_positions(bl, tmp_path):
    target, _probes, _deformer = _animated_scene(bl)
    bl.check_frames_survive_reopen(target, FRAMES, tmp_path)


def _render_scene(bl):
    scene = bpy.context.scene
    target = bl.grid_cube(cuts=6)
    target.scale = (2.0, 0.5, 0.5)
    probes = [bl.empty("Left", (-2.0, 0.0, 0.0)), bl.empty("Right", (2.0, 0.0, 0.0))]
    bl.add_probe_deformer(target, probes, weight_mode="INVERSE_DISTANCE")
    right = probes[1]
    for frame, angle in ((1, 0.0), (2, 0.8), (3, 1.6)):
        _keyframe(right, frame, location=(2.0, 0.0, 1.2 * angle), rotation=(0.0, -angle, 0.0))
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.type, camera.data.ortho_scale = "ORTHO", 7.0
    camera.location, camera.rotation_euler = (0.0, -10.0, 0.5), (math.pi / 2, 0.0, 0.0)
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.rotation_euler = (0.6, 0.2, 0.0)
    for obj in (camera, sun):
        scene.collection.objects.link(obj)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.device = 1, "CPU"
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.frame_start, scene.frame_end = 1, 3
    scene.frame_set(3)  # bpy.data holds frame 3: a handler reading it would render frame 3 three times
    return scene


def test_cycles_animation_render_sees_every_frame(bl, tmp_path):
    scene = _render_scene(bl)
    path = tmp_path / "render.blend"
    scene.render.filepath = str(tmp_path / "frame_####")
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bl.run_blender(f"""
        enable_addon()
        bpy.ops.wm.open_mainfile(filepath={str(path)!r}, load_ui=False)
        assert bpy.context.scene.render.use_lock_interface
        bpy.ops.render.render(animation=True)
    """)
    images = []
    for frame in (1, 2, 3):
        image = bpy.data.images.load(str(tmp_path / f"frame_{frame:04d}.png"))
        pixels = np.empty(len(image.pixels), dtype=np.float32)
        image.pixels.foreach_get(pixels)
        images.append(pixels.reshape(32, 32, 4)[..., :3])
    for image in images:
        assert image.std() > 0.02, "blank render"
    for i, j in ((0, 1), (1, 2), (0, 2)):
        assert np.abs(images[i] - images[j]).mean() > 5e-3, f"frames {i + 1} and {j + 1} render alike"
