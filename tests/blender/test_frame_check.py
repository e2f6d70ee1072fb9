"""The frame check (frame_check.py): the output is stamped with the scene time it was computed for,
and a file opened where the add-on does not run shows the modifier's input at any other frame — with
a warning on the modifier where Blender has the Warning node (4.4 on), without one on 4.2 — never a
stale shape. Outputs that are right at every frame (nothing animated) are stamped so and keep
deforming; baked and disabled deformers are not flagged; enabling the add-on plays again."""

from __future__ import annotations

import importlib
import json

import bpy
import numpy as np

from tests.blender.conftest import PACKAGE
from tests.blender.test_animation import _animated_scene
from tests.blender.test_artist_moves import blender_scene_time


def _frame_check(installed):
    return importlib.import_module(f"{installed.package}.blender.update.frame_check")


def _stamp(obj, deformer) -> np.ndarray:
    """The output's stamp: the mesh's attribute (every point), or a position carrier's last point."""
    nodes = importlib.import_module(f"{PACKAGE}.blender.files.nodes")
    mod = next((m for m in obj.modifiers if m.type == "NODES"), None)
    carrier = nodes.carrier_of(mod) if mod is not None else None
    if carrier is not None and carrier.get("affine_deformers_positions") and len(carrier.data.vertices):
        return np.array([carrier.data.vertices[len(carrier.data.vertices) - 1].co.x], np.float32)
    values = np.empty(len(obj.data.vertices), np.float32)
    obj.data.attributes[f".affdef_{deformer.uid}_frame"].data.foreach_get("value", values)
    return values


def test_the_stamp_is_the_scene_time_or_every_frame(bl, installed):
    check = _frame_check(installed)
    target, probes, deformer = _animated_scene(bl)
    scene = bpy.context.scene
    for frame, subframe in ((7, 0.0), (3, 0.25), (12, 0.5)):
        scene.frame_set(frame, subframe=subframe)
        assert deformer.status == ""
        stamp = _stamp(target, deformer)
        assert np.all(stamp == np.float32(frame + subframe)), (frame, subframe, stamp[:3])
    scene.render.frame_map_old, scene.render.frame_map_new = 100, 50  # Time Stretching: frame 10 at time 20
    scene.frame_set(10)
    assert np.all(_stamp(target, deformer) == blender_scene_time()) and blender_scene_time() == 20.0
    scene.render.frame_map_old = scene.render.frame_map_new = 100

    still = bl.grid_cube(cuts=3, name="Still")
    still.location.x = 6.0
    still_probes = [bl.empty("S1", (7.0, 0, 0)), bl.empty("S2", (5.0, 0, 0))]
    still_deformer = bl.add_probe_deformer(still, still_probes)
    still_probes[0].location.z += 0.4
    scene.frame_set(4)
    assert np.all(_stamp(still, still_deformer) == np.float32(check.STAMP_ALWAYS)), "nothing animated"
    still_probes[1].parent = probes[0]  # now its pose follows an animated object
    scene.frame_set(5)
    assert np.all(_stamp(still, still_deformer) == np.float32(5.0))


def test_every_stack_position_plays_as_before_with_the_check(bl):
    """The group's check passes the deformation through at the frame it was written for: subdivided
    after ours, ours after a Mirror and a Subdivision (motions interpolated with the stamp)."""
    target, _probes, deformer = _animated_scene(bl)
    mirror = target.modifiers.new("Mirror", "MIRROR")
    subsurf = target.modifiers.new("Subdivision", "SUBSURF")
    ours = next(m for m in target.modifiers if m.type == "NODES")
    target.modifiers.move(list(target.modifiers).index(ours), 2)
    assert [m.name for m in target.modifiers] == [mirror.name, subsurf.name, ours.name]
    scene = bpy.context.scene
    scene.frame_set(1)
    rest = bl.evaluated_positions(target).copy()
    scene.frame_set(15)
    moved = bl.evaluated_positions(target)
    assert deformer.status == "" and len(moved) > 4 * len(target.data.vertices)
    assert np.abs(moved - rest).max() > 0.2, "every vertex the modifiers before ours made is deformed"


_SAVE = """
enable_addon()
{build}
scene = bpy.context.scene
results = {{}}
for frame in (10, 30):
    scene.frame_set(frame)
    results[frame] = {{name: positions(bpy.data.objects[name]).tolist() for name in NAMES}}
scene.frame_set(10)
bpy.ops.wm.save_as_mainfile(filepath={path!r})
json.dump(results, open({out!r}, "w"))
"""

_BUILD = """
import json
import numpy as np
NAMES = ("Animated", "Still", "Muted")
def positions(obj):
    mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)
def rig(name, x, animated):
    bpy.ops.mesh.primitive_cube_add(location=(x, 0, 0))
    body = bpy.context.active_object
    body.name = name
    body.modifiers.new("Subdivision", "SUBSURF")
    probes = []
    for i, dx in enumerate((-1.0, 1.0)):
        probe = bpy.data.objects.new(f"{name}P{i}", None)
        probe.location = (x + dx, 0, 0)
        bpy.context.scene.collection.objects.link(probe)
        probes.append(probe)
    bpy.context.view_layer.update()
    with bpy.context.temp_override(active_object=body, object=body, selected_objects=[body, *probes]):
        assert bpy.ops.object.affine_probe_deformer_add() == {"FINISHED"}
    moved = probes[1]
    if animated:
        moved.keyframe_insert("location", frame=1)
        moved.location.z += 1.5
        moved.rotation_euler.x = 0.8
        moved.keyframe_insert("location", frame=40)
        moved.keyframe_insert("rotation_euler", frame=40)
    else:
        moved.location.z += 0.8
    return body
bpy.ops.wm.read_homefile(use_empty=True)
rig("Animated", 0.0, True)
rig("Still", 4.0, False)
muted = rig("Muted", 8.0, True)
"""

_OPEN_WITHOUT = """
import json
import numpy as np
{positions}
bpy.ops.wm.open_mainfile(filepath={path!r}, load_ui=False)
assert not hasattr(bpy.types.Object, "affine_deformers"), "the add-on must not run here"
scene = bpy.context.scene
results = {{}}
for frame in (10, 30):
    scene.frame_set(frame)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for name in NAMES:
        obj = bpy.data.objects[name]
        mod = next(m for m in obj.modifiers if m.type == "NODES")
        warnings = [w.message for w in getattr(mod, "node_warnings", ())]
        results[f"{{name}}/{{frame}}"] = {{"positions": positions(obj).tolist(), "warnings": warnings}}
# The add-on installed and enabled afterwards plays correctly at the next update.
bpy.ops.extensions.package_install_files(filepath={zip!r}, repo="user_default", enable_on_install=True)
scene.frame_set(30)
results["enabled"] = {{name: positions(bpy.data.objects[name]).tolist() for name in NAMES}}
json.dump(results, open({out!r}, "w"))
"""


def test_a_file_opened_without_the_addon_shows_the_input_and_says_why(bl, installed, tmp_path):
    path, saved, opened = tmp_path / "rig.blend", tmp_path / "saved.json", tmp_path / "opened.json"
    positions = _BUILD.split("bpy.ops.wm.read_homefile")[0]
    bl.run_blender(_SAVE.format(build=_BUILD + """
for mod in muted.modifiers:
    if mod.type == "NODES":
        mod.show_viewport = mod.show_render = False
""", path=str(path), out=str(saved)))
    empty_user = tmp_path / "no_addon"
    empty_user.mkdir()
    bl.run_blender(_OPEN_WITHOUT.format(positions=positions, path=str(path), out=str(opened),
                                        zip=str(installed.zip)),
                   env_extra={"BLENDER_USER_RESOURCES": str(empty_user)})
    reference = json.loads(saved.read_text())
    got = json.loads(opened.read_text())
    warns = _frame_check(installed).HAS_WARNING_NODE

    def error(name, frame, against):
        return float(np.abs(np.array(got[f"{name}/{frame}"]["positions"]) - np.array(against)).max())

    base = {name: np.array(got[f"{name}/10"]["positions"]) for name in ("Animated", "Still", "Muted")}
    # At the frame it was saved at, the file shows what was saved.
    assert error("Animated", 10, reference["10"]["Animated"]) == 0.0
    assert got["Animated/10"]["warnings"] == []
    # At another frame: the modifier's input (the subdivided rest), never the stale frame-10 shape.
    animated_30 = np.array(got["Animated/30"]["positions"])
    input_shape = np.array(reference["10"]["Muted"])  # a muted deformer shows its input
    assert np.abs(animated_30 - np.array(reference["10"]["Animated"])).max() > 0.1, "not the stale shape"
    assert np.array_equal(animated_30, input_shape)
    stale_warning = [w for w in got["Animated/30"]["warnings"]
                     if "add-on is not running" in w and "Install and enable" in w and "bake" in w]
    assert len(stale_warning) == (1 if warns else 0), got["Animated/30"]["warnings"]
    # Right at every frame: deforms at every frame, no warning; muted: its input, no warning.
    assert error("Still", 30, reference["30"]["Still"]) == 0.0 and got["Still/30"]["warnings"] == []
    assert np.array_equal(base["Still"], np.array(reference["10"]["Still"]))
    assert got["Muted/30"]["warnings"] == [] and error("Muted", 30, reference["30"]["Muted"]) == 0.0
    # Enabled again: the next update plays frame 30 as the rig does.
    for name in ("Animated", "Still"):
        assert np.abs(np.array(got["enabled"][name]) - np.array(reference["30"][name])).max() < 1e-6, name
    print("frame-30 warnings without the add-on:", got["Animated/30"]["warnings"])
