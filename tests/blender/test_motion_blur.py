"""Motion blur: renders evaluate the scene at shutter subframes, where handler-based add-ons are known to
go stale. Our deformation must move within a frame exactly as a Hook's does for the same motion: the
same subframe positions, and the same blurred image in a Cycles render with motion blur."""

from __future__ import annotations

import math

import bpy
import numpy as np
import pytest


def _animate(obj, start: int = 1, end: int = 9) -> None:
    """A turn and a slide of `obj` between frames start and end, linear in time."""
    obj.rotation_euler = (0.0, 0.0, 0.0)
    obj.location = (0.0, 0.0, 0.0)
    obj.keyframe_insert("rotation_euler", frame=start)
    obj.keyframe_insert("location", frame=start)
    obj.rotation_euler = (0.0, 0.0, math.radians(120.0))
    obj.location = (1.5, 0.0, 0.0)
    obj.keyframe_insert("rotation_euler", frame=end)
    obj.keyframe_insert("location", frame=end)
    action = obj.animation_data.action
    curves = getattr(action, "fcurves", None)
    if curves is None:  # layered actions (Blender 4.4+)
        curves = [c for layer in action.layers for strip in layer.strips
                  for bag in strip.channelbags for c in bag.fcurves]
    for curve in curves:
        for key in curve.keyframe_points:
            key.interpolation = "LINEAR"


def _rig(bl):
    """Two identical bars: ours (three probes under an animated parent, so all move by one motion G(t))
    and a Hook (its empty under an identically animated parent, every vertex assigned)."""
    ours = bl.grid_cube(cuts=6, name="Ours")
    ours.scale = (1.6, 0.4, 0.4)
    probes = [bl.empty(f"P{i}", loc) for i, loc in enumerate(((1.2, 0, 0), (-1.2, 0, 0), (0, 0, 0.6)))]
    bpy.context.view_layer.update()
    bl.add_probe_deformer(ours, probes, normalize="SUM")
    mover = bl.empty("Mover")
    for probe in probes:
        probe.parent = mover
    _animate(mover)

    hooked = bl.grid_cube(cuts=6, name="Hooked")
    hooked.scale = ours.scale
    hook_empty = bl.empty("HookEmpty")
    bpy.context.view_layer.update()
    hook = hooked.modifiers.new("Hook", "HOOK")
    hook.object = hook_empty
    hook.falloff_type = "NONE"
    hook.vertex_indices_set(range(len(hooked.data.vertices)))
    hook.matrix_inverse = hook_empty.matrix_world.inverted() @ hooked.matrix_world
    hook_mover = bl.empty("HookMover")
    hook_empty.parent = hook_mover
    _animate(hook_mover)
    return ours, hooked


def test_subframe_positions_follow_the_motion_like_a_hook(bl):
    ours, hooked = _rig(bl)
    scene = bpy.context.scene
    seen = []
    for frame, subframe in ((5, 0.0), (5, 0.25), (5, 0.5), (4, 0.75), (5, 0.5)):
        scene.frame_set(frame, subframe=subframe)
        got, expected = bl.evaluated_positions(ours), bl.evaluated_positions(hooked)
        assert np.abs(got - expected).max() < 1e-5, (frame, subframe)
        assert ours.affine_deformers[0].status == ""
        seen.append(got.copy())
    assert np.abs(seen[1] - seen[0]).max() > 0.05, "a quarter frame moves the mesh"
    assert np.array_equal(seen[2], seen[4]), "a subframe depends only on itself"


def _render(scene, visible, path, blur: bool) -> np.ndarray:
    for obj in scene.objects:
        if obj.type == "MESH":
            obj.hide_render = obj != visible
    scene.render.use_motion_blur = blur
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(str(path))
    try:
        pixels = np.array(image.pixels[:], dtype=np.float32).reshape(image.size[1], image.size[0], -1)
    finally:
        bpy.data.images.remove(image)
    return pixels[..., :3]


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_cycles_motion_blur_matches_a_hook(bl, tmp_path):
    ours, hooked = _rig(bl)
    hooked.location = ours.location  # rendered one at a time, at the same place
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False
    scene.cycles.seed = 1
    scene.render.resolution_x, scene.render.resolution_y = 96, 64
    scene.render.resolution_percentage = 100
    scene.render.motion_blur_shutter = 1.0
    scene.render.image_settings.file_format = "PNG"
    camera_data = bpy.data.cameras.new("Camera")
    camera_data.type = "ORTHO"
    camera_data.ortho_scale = 6.0
    camera = bpy.data.objects.new("Camera", camera_data)
    scene.collection.objects.link(camera)
    camera.location = (0.6, 0.0, 10.0)
    scene.camera = camera
    world = bpy.data.worlds.new("World")
    world.color = (0.0, 0.0, 0.0)
    scene.world = world
    glow = bpy.data.materials.new("Glow")  # white shapes on black: the blur is the image's grey
    glow.use_nodes = True
    tree = glow.node_tree
    tree.nodes.clear()
    emission = tree.nodes.new("ShaderNodeEmission")
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(emission.outputs[0], output.inputs["Surface"])
    for obj in (ours, hooked):
        obj.data.materials.append(glow)
    scene.frame_set(5)
    blurred_ours = _render(scene, ours, tmp_path / "ours.png", blur=True)
    blurred_hook = _render(scene, hooked, tmp_path / "hook.png", blur=True)
    sharp_hook = _render(scene, hooked, tmp_path / "sharp.png", blur=False)
    assert ours.affine_deformers[0].status == ""
    blur = np.abs(blurred_hook - sharp_hook).mean()
    assert blur > 0.003, "the motion blur shows (a stale subframe would render ours sharp)"
    assert np.abs(blurred_ours - blurred_hook).mean() < 0.1 * blur
