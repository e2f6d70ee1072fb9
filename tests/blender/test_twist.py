"""Twists past 180° (MATH.md §8): a probe keyed through several turns twists continuously, by the
angle of its own rotation channels, the same in every rotation mode, and frame f is computed from frame
f alone (a fresh process jumping to f, or a render farm rendering only f, gives the same result).

The scene: an elliptic tube along Z (elliptic, so a full turn of a cross-section is visible in a
render), a probe at its top, FALLOFF weights without normalisation (the top follows the probe, the
bottom has weight 0 and stays). A probe turning by θ about the tube's axis through its own origin then
moves each vertex by exactly v' = Rz(w_v·θ)·v (w_v its weight), which the tests check to 1e-4.

The same rule for a cage object turned by its own rotation channels (the cage deformer applies the
object's motion G after the blend, at strength s as φ(s·ψ(G))): a cage keyed 0 → 720° at s = 0.5
turns the whole target by s·θ about the cage's origin, continuously.
"""

from __future__ import annotations

import itertools
import math

import bpy
import numpy as np
import pytest
from bpy_extras import anim_utils

HEIGHT = 4.0
SEGMENTS, RINGS = 24, 33
SEMI_AXES = (0.6, 0.25)
LAST_FRAME = 73  # 0° at frame 1 → 720° at frame 73: 10° per frame, 360° at frame 37


def tube(name: str = "Tube", segments: int = SEGMENTS, rings: int = RINGS):
    """Open elliptic tube, z from 0 to HEIGHT, `rings` rings of `segments` vertices."""
    angle = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    z = np.linspace(0.0, HEIGHT, rings)
    ring = np.stack([SEMI_AXES[0] * np.cos(angle), SEMI_AXES[1] * np.sin(angle)], axis=1)
    co = np.column_stack([np.tile(ring, (rings, 1)), np.repeat(z, segments)])
    faces = [(r * segments + s, r * segments + (s + 1) % segments,
              (r + 1) * segments + (s + 1) % segments, (r + 1) * segments + s)
             for r in range(rings - 1) for s in range(segments)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(co.tolist(), [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def rotate_z(points: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Each row of `points` turned about the z axis by its own angle."""
    c, s = np.cos(angles), np.sin(angles)
    x, y = points[:, 0], points[:, 1]
    return np.column_stack([c * x - s * y, s * x + c * y, points[:, 2]])


def twist_scene(bl, rotation_mode: str = "XYZ", rest_rotation=None):
    """The tube with a probe at its top, bound; returns (target, probe, deformer, weights (N,))."""
    target = tube()
    probe = bl.empty("Twister", (0.0, 0.0, HEIGHT))
    probe.rotation_mode = rotation_mode
    if rest_rotation is not None:
        channel = {"QUATERNION": "rotation_quaternion", "AXIS_ANGLE": "rotation_axis_angle"}
        setattr(probe, channel.get(rotation_mode, "rotation_euler"), rest_rotation)
    deformer = bl.add_probe_deformer(target, [probe], weight_mode="FALLOFF", radius=HEIGHT, normalize="NONE")
    assert deformer.status == "" and deformer.branch_rule == "CHANNELS"
    weights = bl.dense_weights(target, deformer)[:, 0]
    bottom = bl.rest_positions(target)[:, 2] == 0.0
    assert np.all(weights[bottom] == 0.0) and weights.max() > 0.9
    return target, probe, deformer, weights


def key_linear_spin(probe, degrees: float = 720.0) -> None:
    """rotation_euler.z keyed 0° at frame 1 and `degrees` at LAST_FRAME, LINEAR interpolation."""
    for frame, angle in ((1, 0.0), (LAST_FRAME, math.radians(degrees))):
        probe.rotation_euler.z = angle
        probe.keyframe_insert("rotation_euler", index=2, frame=frame)
    animation = probe.animation_data
    if hasattr(animation.action, "fcurves"):  # Blender < 4.4: legacy actions
        fcurves = animation.action.fcurves
    else:
        fcurves = anim_utils.action_get_channelbag_for_slot(animation.action, animation.action_slot).fcurves
    for fcurve in fcurves:
        for point in fcurve.keyframe_points:
            point.interpolation = "LINEAR"


def step_frames(bl, target, frames) -> dict[int, np.ndarray]:
    out = {}
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        out[frame] = bl.evaluated_positions(target).astype(np.float64)
    return out


def max_jump_ratio(positions: dict[int, np.ndarray]) -> float:
    """Max over vertices and consecutive frames of a vertex's motion / its median per-frame motion
    (medians below 1e-4 count as 1e-4, so a static vertex that jumps counts too)."""
    frames = sorted(positions)
    steps = np.stack([np.linalg.norm(positions[b] - positions[a], axis=1)
                      for a, b in itertools.pairwise(frames)])
    median = np.maximum(np.median(steps, axis=0), 1e-4)
    return float((steps / median).max())


# ------------------------------------------------------------------------------------- continuity


def test_euler_spin_to_720_is_continuous_and_keeps_full_turns(bl):
    target, probe, deformer, w = twist_scene(bl)
    key_linear_spin(probe)
    rest = bl.rest_positions(target).astype(np.float64)
    got = step_frames(bl, target, range(1, LAST_FRAME + 1))
    assert deformer.status == ""

    assert max_jump_ratio(got) <= 3.0, "a vertex jumps between consecutive frames"
    for frame in (1, 10, 19, 20, 28, 37, 55, 73):
        theta = math.radians(10.0 * (frame - 1))
        np.testing.assert_allclose(got[frame], rotate_z(rest, w * theta), atol=1e-4, err_msg=f"frame {frame}")
    # 360° is a full twist (mid-height turned by w·360°), not the rest shape; 720° is not 360°.
    assert np.abs(got[37] - rest).max() > 0.3
    assert np.abs(got[73] - got[37]).max() > 0.3


def test_shortest_rule_reproduces_the_flip(bl):
    target, probe, deformer, w = twist_scene(bl)
    key_linear_spin(probe)
    deformer.branch_rule = "SHORTEST"
    rest = bl.rest_positions(target).astype(np.float64)
    got = step_frames(bl, target, range(1, LAST_FRAME + 1))
    assert max_jump_ratio(got) > 10.0, "the principal log flips at 180°"
    np.testing.assert_allclose(got[28], rotate_z(rest, w * math.radians(-90.0)), atol=1e-4)  # 270° → −90°
    np.testing.assert_allclose(got[37], rest, atol=1e-4)  # 360° reads as the rest pose
    # Switching back follows the channels again at the same frame (the option is live).
    deformer.branch_rule = "CHANNELS"
    bpy.context.scene.frame_set(28)
    np.testing.assert_allclose(bl.evaluated_positions(target), rotate_z(rest, w * math.radians(270.0)),
                               atol=1e-4)


# ------------------------------------------------------------------------------------- rotation modes


def _set_turn(probe, degrees: float, rest_rotation) -> None:
    """Turn the probe by `degrees` about world z on top of its rest rotation, through its own channels."""
    mode = probe.rotation_mode
    a = math.radians(degrees)
    if mode == "QUATERNION":
        w0, x0, y0, z0 = rest_rotation  # q_z(a) ⊗ q_rest, continuing the path from the rest quaternion
        c, s = math.cos(a / 2), math.sin(a / 2)
        probe.rotation_quaternion = (c * w0 - s * z0, c * x0 - s * y0, c * y0 + s * x0, c * z0 + s * w0)
    elif mode == "AXIS_ANGLE":
        angle, *axis = rest_rotation
        probe.rotation_axis_angle = (angle + a, *axis)
    else:
        probe.rotation_euler = (rest_rotation[0], rest_rotation[1], rest_rotation[2] + a)


@pytest.mark.parametrize(
    ("mode", "rest_rotation", "turns"),
    [
        ("XYZ", (0.3, -0.2, 0.5), (200.0, 300.0, 400.0, 720.0, -500.0)),
        ("AXIS_ANGLE", (0.5, 0.0, 0.0, 1.0), (200.0, 300.0, 400.0, 720.0, -500.0)),
        # A quaternion holds at most one turn (q and −q): read along the straight path from the rest one.
        ("QUATERNION", (math.cos(0.4), 0.6 * math.sin(0.4), 0.0, 0.8 * math.sin(0.4)),
         (200.0, 300.0, -330.0)),
    ],
)
def test_every_rotation_mode_gives_the_same_twist(bl, mode, rest_rotation, turns):
    target, probe, deformer, w = twist_scene(bl, mode, rest_rotation)
    rest = bl.rest_positions(target).astype(np.float64)
    for degrees in turns:
        _set_turn(probe, degrees, rest_rotation)
        got = bl.evaluated_positions(target)
        np.testing.assert_allclose(got, rotate_z(rest, w * math.radians(degrees)), atol=1e-4,
                                   err_msg=f"{mode} {degrees}°")
        assert deformer.status == ""


def test_rotation_mode_changed_since_bind_counts_turns_from_the_converted_rest(bl):
    target, probe, deformer, w = twist_scene(bl, "XYZ")
    rest = bl.rest_positions(target).astype(np.float64)

    def check(degrees: float) -> None:
        np.testing.assert_allclose(bl.evaluated_positions(target), rotate_z(rest, w * math.radians(degrees)),
                                   atol=1e-4, err_msg=f"{probe.rotation_mode} {degrees}°")
        assert deformer.status == ""

    probe.rotation_euler.z = math.radians(400.0)
    check(400.0)
    probe.rotation_mode = "ZYX"  # Blender keeps the Euler turns across an order switch
    check(400.0)
    probe.rotation_mode = "AXIS_ANGLE"
    probe.rotation_axis_angle = (math.radians(650.0), 0.0, 0.0, 1.0)  # keyed in the new mode
    check(650.0)
    probe.rotation_mode = "QUATERNION"
    half = math.radians(300.0) / 2
    probe.rotation_quaternion = (math.cos(half), 0.0, 0.0, math.sin(half))
    check(300.0)


def test_channels_turn_in_the_parent_frame_and_parent_turns_take_the_nearest_branch(bl):
    """The target lies along world X; the probe's parent (scaled, turned) maps the probe's Y channel
    onto the target's axis, so turning that channel by 400° twists the tube by 400°. The parent then
    adds 30° about the same axis: 430° in total, the branch nearest the channels' 400°."""
    target = tube()
    target.location, target.rotation_euler = (1.0, 2.0, 3.0), (0.0, math.pi / 2, 0.0)  # local z = world x
    parent = bl.empty("Parent", (1.0 + HEIGHT, 2.0, 3.0))  # the tube's top
    parent.rotation_mode = "ZYX"  # x outermost: its X channel turns about world x
    parent.rotation_euler = (0.0, 0.0, -math.pi / 2)  # the parent's y axis is world x
    parent.scale = (2.0, 2.0, 2.0)
    child = bl.empty("Child")
    child.parent = parent
    child.rotation_euler = (0.3, 0.0, 0.0)  # a rest tilt inside the Y turn (x is innermost in XYZ)
    bpy.context.view_layer.update()
    deformer = bl.add_probe_deformer(target, [child], weight_mode="FALLOFF", radius=HEIGHT, normalize="NONE")
    w = bl.dense_weights(target, deformer)[:, 0]
    rest = bl.rest_positions(target).astype(np.float64)
    assert w.max() > 0.9

    child.rotation_euler.y = math.radians(400.0)
    np.testing.assert_allclose(bl.evaluated_positions(target), rotate_z(rest, w * math.radians(400.0)),
                               atol=1e-4)
    parent.rotation_euler.x = math.radians(30.0)
    np.testing.assert_allclose(bl.evaluated_positions(target), rotate_z(rest, w * math.radians(430.0)),
                               atol=1e-4)
    assert deformer.status == ""
    deformer.branch_rule = "SHORTEST"  # 430° = 70° the short way
    np.testing.assert_allclose(bl.evaluated_positions(target), rotate_z(rest, w * math.radians(70.0)),
                               atol=1e-4)


# ------------------------------------------------------------------------------------- frame independence


def _render_setup(scene, path) -> None:
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.type, camera.data.ortho_scale = "ORTHO", 5.0
    camera.location, camera.rotation_euler = (0.0, -10.0, HEIGHT / 2), (math.pi / 2, 0.0, 0.0)
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.rotation_euler = (0.7, 0.3, 0.2)
    for obj in (camera, sun):
        scene.collection.objects.link(obj)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.device, scene.cycles.seed = 1, "CPU", 0
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(path)


def _image(path) -> np.ndarray:
    image = bpy.data.images.load(str(path))
    pixels = np.empty(len(image.pixels), dtype=np.float32)
    image.pixels.foreach_get(pixels)
    bpy.data.images.remove(image)
    return pixels.reshape(32, 32, 4)[..., :3]


def test_frame_37_in_a_fresh_process_and_a_single_frame_render_match_stepping(bl, tmp_path):
    target, probe, _deformer, w = twist_scene(bl)
    key_linear_spin(probe)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, LAST_FRAME
    _render_setup(scene, tmp_path / "unused_")
    rest = bl.rest_positions(target).astype(np.float64)

    stepped = step_frames(bl, target, range(1, 38))[37]
    np.testing.assert_allclose(stepped, rotate_z(rest, w * 2.0 * math.pi), atol=1e-4)
    scene.render.filepath = str(tmp_path / "stepped_37.png")
    bpy.ops.render.render(write_still=True)
    scene.frame_set(1)
    scene.render.filepath = str(tmp_path / "rest_1.png")
    bpy.ops.render.render(write_still=True)

    path = tmp_path / "twist.blend"
    scene.render.filepath = str(tmp_path / "farm_####")
    bpy.ops.wm.save_as_mainfile(filepath=str(path))  # saved at frame 1: the file holds rest offsets
    out = tmp_path / "fresh.npy"
    bl.run_blender(f"""
        import numpy as np
        enable_addon()
        bpy.ops.wm.open_mainfile(filepath={str(path)!r}, load_ui=False)
        scene = bpy.context.scene
        scene.frame_set(37)
        mesh = bpy.data.objects["Tube"].evaluated_get(bpy.context.evaluated_depsgraph_get()).data
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        np.save({str(out)!r}, co.reshape(-1, 3))
        # What `blender -b twist.blend -f 37` does: render one frame of a file saved elsewhere in time.
        bpy.ops.wm.open_mainfile(filepath={str(path)!r}, load_ui=False)
        scene = bpy.context.scene
        scene.frame_start = scene.frame_end = 37
        bpy.ops.render.render(animation=True)
    """)
    fresh = np.load(out).astype(np.float64)
    assert np.abs(fresh - stepped).max() <= 1e-5

    stepped_img, farm_img = _image(tmp_path / "stepped_37.png"), _image(tmp_path / "farm_0037.png")
    rest_img = _image(tmp_path / "rest_1.png")
    assert stepped_img.std() > 0.02, "blank render"
    assert np.abs(rest_img - stepped_img).mean() > 0.01, "the full twist must show in the render"
    assert np.abs(farm_img - stepped_img).max() <= 2.0 / 255.0


def test_channels_too_large_to_unwrap_give_a_clear_status_and_the_rest_shape(bl):
    target, probe, deformer, w = twist_scene(bl)
    rest = bl.rest_positions(target).astype(np.float64)
    probe.rotation_euler.z = 1e6  # ~160000 turns: more than the unwrap will sample
    got = bl.evaluated_positions(target)
    assert "too many turns" in deformer.status
    assert np.array_equal(got, rest.astype(np.float32)), "the mesh shows its rest shape"
    deformer.branch_rule = "SHORTEST"  # needs no unwrap: deforms again
    angle = math.remainder(1e6, 2.0 * math.pi)
    np.testing.assert_allclose(bl.evaluated_positions(target), rotate_z(rest, w * angle), atol=1e-3)
    assert deformer.status == ""


# ------------------------------------------------------------------------------------- cage objects


CAGE_ORIGIN = (0.3, -0.2, 0.1)


def cage_twist_scene(bl, strength: float = 0.5):
    """A cube (turned and moved, so the target's space is not the world's) inside a box cage whose
    origin is off the cube's centre; the cage's rotation_euler.z keyed 0 → 720° over frames 1..73.
    Returns (target, cage, deformer)."""
    target = bl.grid_cube(cuts=4, size=2.0, name="Target")
    target.location, target.rotation_euler = (0.2, 0.1, -0.3), (0.4, 0.0, 0.0)
    cage = bl.grid_cube(cuts=1, size=3.6, name="CageBox")
    cage.location = CAGE_ORIGIN
    bpy.context.view_layer.update()
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target, cage]):
        assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
    deformer = target.affine_deformers[0]
    deformer.strength = strength
    assert deformer.status == "" and deformer.branch_rule == "CHANNELS"
    key_linear_spin(cage)
    bpy.context.scene.frame_set(1)
    return target, cage, deformer


def world_points(target, local: np.ndarray) -> np.ndarray:
    matrix = np.array(target.matrix_world, dtype=np.float64)
    return local.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]


def cage_turn(points_world: np.ndarray, degrees: float) -> np.ndarray:
    """World points turned about the vertical axis through the cage's origin."""
    centre = np.array(CAGE_ORIGIN)
    return rotate_z(points_world - centre, np.full(len(points_world), math.radians(degrees))) + centre


def test_cage_object_spun_to_720_at_half_strength_turns_continuously_to_360(bl):
    target, _cage, deformer = cage_twist_scene(bl)
    rest = world_points(target, bl.rest_positions(target))
    got = {f: world_points(target, p) for f, p in step_frames(bl, target, range(1, LAST_FRAME + 1)).items()}
    assert deformer.status == ""
    assert max_jump_ratio(got) <= 3.0, "a vertex jumps between consecutive frames"
    for frame in (1, 10, 19, 20, 28, 37, 55, 73):
        half_turn = 0.5 * 10.0 * (frame - 1)
        np.testing.assert_allclose(got[frame], cage_turn(rest, half_turn), atol=1e-4,
                                   err_msg=f"frame {frame}")
    assert np.abs(got[37] - rest).max() > 0.3, "360° at half strength is a half turn, not the rest pose"
    assert np.abs(got[73] - rest).max() < 1e-4, "720° at half strength is a full turn"


def test_cage_object_shortest_rule_flips_and_files_without_rest_channels_fall_back_to_it(bl):
    target, cage, deformer = cage_twist_scene(bl)
    deformer.branch_rule = "SHORTEST"
    rest = world_points(target, bl.rest_positions(target))
    got = {f: world_points(target, p) for f, p in step_frames(bl, target, range(1, LAST_FRAME + 1)).items()}
    assert max_jump_ratio(got) > 10.0, "the principal log flips at 180°"
    np.testing.assert_allclose(got[28], cage_turn(rest, -45.0), atol=1e-4)  # 270° → −90°, halved
    np.testing.assert_allclose(got[37], rest, atol=1e-4)  # 360° reads as the rest pose

    bpy.context.scene.frame_set(37)
    deformer.branch_rule = "CHANNELS"  # live: the same frame follows the channels again
    np.testing.assert_allclose(world_points(target, bl.evaluated_positions(target)), cage_turn(rest, 180.0),
                               atol=1e-4)
    deformer.strength = 1.0  # at full strength the branch does not matter: exactly the cage's motion
    np.testing.assert_allclose(world_points(target, bl.evaluated_positions(target)), cage_turn(rest, 360.0),
                               atol=1e-5)
    deformer.strength = 0.5
    # A cage bound before the rest channels were stored has no reference: the shortest way is taken.
    assert deformer.is_property_set("cage_rest_rotation")
    deformer.property_unset("cage_rest_rotation")
    bpy.context.scene.frame_set(28)
    np.testing.assert_allclose(world_points(target, bl.evaluated_positions(target)), cage_turn(rest, -45.0),
                               atol=1e-4)
    assert deformer.status == ""
    # Channels beyond what the unwrap follows: a clear status and the rest shape, not a wrong turn.
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    cage.animation_data_clear()
    cage.rotation_euler.z = 1e6
    assert np.array_equal(bl.evaluated_positions(target), bl.rest_positions(target))
    assert "The motion of cage 'CageBox' cannot be blended" in deformer.status
    assert "too many turns" in deformer.status


def test_cage_object_turn_at_frame_37_in_a_fresh_process_matches_stepping(bl, tmp_path):
    target, _cage, _deformer = cage_twist_scene(bl)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, LAST_FRAME
    stepped = step_frames(bl, target, range(1, 38))[37]
    scene.frame_set(1)
    path = tmp_path / "cage_twist.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))  # saved at frame 1: the file holds rest offsets
    out = tmp_path / "fresh.npy"
    bl.run_blender(f"""
        import numpy as np
        enable_addon()
        bpy.ops.wm.open_mainfile(filepath={str(path)!r}, load_ui=False)
        bpy.context.scene.frame_set(37)
        target = bpy.data.objects["Target"]
        assert target.affine_deformers[0].status == "", target.affine_deformers[0].status
        mesh = target.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        np.save({str(out)!r}, co.reshape(-1, 3))
    """)
    fresh = np.load(out).astype(np.float64)
    assert np.abs(fresh - stepped).max() <= 1e-5
    assert np.abs(stepped - bl.rest_positions(target)).max() > 0.3
