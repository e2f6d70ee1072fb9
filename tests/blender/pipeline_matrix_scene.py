"""The Blender side of the pipeline matrix (pipeline_matrix.py): what runs inside the fresh bpy
processes, with the add-on enabled. The plan (a JSON list of bodies, each a kind and the modifiers
around our deformer) comes from pipeline_matrix.py; results go to files it reads back.

- `build_asset`: the asset file, one small rig per body in the collection "Rig", and the reference:
  each body's evaluated mesh at FRAMES, and the same with our modifier switched off (what reaches it,
  passed on through the rest of the stack: what a modifier that cannot deform must show).
- `measure_contexts`: the asset opened locally, appended into a new file, then linked and overridden
  in another new file, which is saved as the shot.
- `measure_reopened`: the shot opened again (a fresh process).
- `measure_render`: a background animation render of the shot (what `blender -b shot.blend -a` runs),
  recording what the render's own depsgraph evaluated at FRAMES.
- `measure_without_addon`: the asset and the shot opened in a process where the add-on is not
  installed (a farm worker without it); the "status" recorded there is the warnings Blender shows on
  our modifiers (frame_check.py: the Warning node, Blender 4.4 on).

Every measurement is the evaluated positions of each body at FRAMES (object space: a body keeps its
place in every context) and its deformer's status, saved as `<label>|<body>|<frame>` entries.
"""

from __future__ import annotations

import json

import bmesh
import bpy
import numpy as np

FRAMES = (1, 12, 24)
#: Contexts visit the frames out of order: a frame must depend on that frame alone.
VISIT = (24, 1, 12)
#: The asset and the shot are saved at a frame none of FRAMES is, so nothing saved is what is measured.
SAVED_AT = 5
SPACING = 7.0
COLUMNS = 7
#: The frame whose render the asset and the shot compare (`measure_render`).
PICTURE_FRAME = 12

# ------------------------------------------------------------------------------------------ the bodies


def _key(owner, frames_values: dict[int, object], path: str) -> None:
    """Key `owner.<path>` to the given value at each frame."""
    for frame, value in frames_values.items():
        setattr(owner, path, value)
        owner.keyframe_insert(path, frame=frame)


def _box_mesh(name: str, weld_seam: bool) -> bpy.types.Mesh:
    """A gridded box (cuts 5 per edge, 218 vertices), x ∈ [-1, 2], y, z ∈ [-1, 1], sheared a little:
    not symmetric about the object's YZ plane, so a Mirror adds real vertices, and one grid line lies
    on that plane, so Mirror's merge has vertices to merge. With `weld_seam` the faces are split along
    the grid line x = 1 (duplicate vertices at one place: what Weld merges) and the vertices sorted
    along x, so Weld's merge shifts the indices of every vertex after the seam."""
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=2.0)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=5, use_grid_fill=True)
    for vert in bm.verts:
        x, y, z = vert.co
        on_plane = abs(x + 1.0 / 3.0) < 1e-4  # becomes x = 0 below: kept exactly on the mirror plane
        vert.co = (0.0 if on_plane else 1.5 * x + 0.5, y + 0.15 * z, z + 0.1 * x * x)
    if weld_seam:
        seam = [e for e in bm.edges if all(abs(v.co.x - 1.0) < 1e-4 for v in e.verts)]
        bmesh.ops.split_edges(bm, edges=seam)
        bm.verts.sort(key=lambda vert: vert.co.x)
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def _skin_armature(rig, name: str, origin) -> bpy.types.Object:
    """An armature of one keyed bone "Skin" along the body, for an Armature modifier before ours."""
    armature = _armature(rig, name, origin, [("Skin", (-1.0, 0.0, 0.0), (2.0, 0.0, 0.0))])
    bone = armature.pose.bones["Skin"]
    bone.rotation_mode = "XYZ"
    _key(bone, {1: (0.0, 0.0, 0.0), 12: (0.3, 0.2, 0.5), 24: (-0.4, 0.1, 0.8)}, "rotation_euler")
    return armature


def _armature(rig, name: str, origin, bones) -> bpy.types.Object:
    """An armature object at `origin` with connected bones (name, head, tail), in the collection."""
    armature = bpy.data.objects.new(name, bpy.data.armatures.new(name))
    armature.location = origin
    rig.objects.link(armature)
    bpy.context.view_layer.objects.active = armature
    bpy.ops.object.mode_set(mode="EDIT")
    parent = None
    for bone_name, head, tail in bones:
        edit_bone = armature.data.edit_bones.new(bone_name)
        edit_bone.head, edit_bone.tail, edit_bone.roll = head, tail, 0.0
        if parent is not None:
            edit_bone.parent, edit_bone.use_connect = parent, True
        parent = edit_bone
    bpy.ops.object.mode_set(mode="OBJECT")
    return armature


def _skin_weights(target) -> None:
    """Vertex group "Skin": weight rising along x from 0 to 1, so the Armature modifier bends."""
    group = target.vertex_groups.new(name="Skin")
    for vert in target.data.vertices:
        group.add([vert.index], min(1.0, max(0.0, (vert.co.x + 1.0) / 3.0)), "REPLACE")


def _shape_keys(target) -> None:
    """A "Bulge" shape key (the far end swells and lifts), its value keyed 0, 1, 0.4."""
    target.shape_key_add(name="Basis")
    bulge = target.shape_key_add(name="Bulge", from_mix=False)
    for point in bulge.data:
        x, y, z = point.co
        swell = 1.0 + 0.25 * max(0.0, x)
        point.co = (x, y * swell, z * swell + 0.1 * x)
    _key(bulge, {1: 0.0, 12: 1.0, 24: 0.4}, "value")


def _modifier(target, spec: dict, rig, origin) -> None:
    """Add the modifier `spec` ({"type": ..., "settings": {...}}) at the end of the target's stack."""
    kind = spec["type"]
    mod = target.modifiers.new(kind.title(), kind)
    for name, value in spec.get("settings", {}).items():
        setattr(mod, name, value)
    if kind == "ARMATURE":
        _skin_weights(target)
        mod.object = _skin_armature(rig, target.name + " Skin", origin)


def _probes(rig, name: str, origin) -> list[bpy.types.Object]:
    """Two Empties: one at each end, both keyed (the far one moves, turns and scales)."""
    near = bpy.data.objects.new(name + " P1", None)
    far = bpy.data.objects.new(name + " P2", None)
    for probe in (near, far):
        rig.objects.link(probe)
    x, y, z = origin
    _key(near, {1: (x - 1.5, y, z), 12: (x - 1.6, y + 0.2, z), 24: (x - 1.4, y, z - 0.3)}, "location")
    _key(near, {1: (0.0, 0.0, 0.0), 12: (0.2, 0.0, -0.3), 24: (0.0, 0.3, 0.2)}, "rotation_euler")
    _key(far, {1: (x + 2.5, y, z), 12: (x + 2.8, y + 0.4, z + 1.0), 24: (x + 2.6, y - 0.3, z + 1.8)},
         "location")
    _key(far, {1: (0.0, 0.0, 0.0), 12: (0.0, -0.6, 0.4), 24: (0.3, -1.2, 0.6)}, "rotation_euler")
    _key(far, {1: (1.0, 1.0, 1.0), 12: (1.2, 0.9, 1.1), 24: (0.8, 1.1, 1.0)}, "scale")
    return [near, far]


def _cage(rig, name: str, origin) -> list[bpy.types.Object]:
    """A box cage around the body: the object keyed (turns, scales) and a shape key pulling its far
    end up and out, keyed 0, 1, 0.5. Hidden in renders, as riggers hide cages."""
    mesh = bpy.data.meshes.new(name + " Cage")
    corners = [(x, y, z) for x in (-1.4, 2.4) for y in (-1.4, 1.4) for z in (-1.4, 1.4)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh.from_pydata(corners, [], faces)
    cage = bpy.data.objects.new(name + " Cage", mesh)
    cage.location, cage.display_type, cage.hide_render = origin, "WIRE", True
    rig.objects.link(cage)
    cage.shape_key_add(name="Basis")
    pull = cage.shape_key_add(name="Pull", from_mix=False)
    for point in pull.data:
        if point.co.x > 0:
            point.co = (point.co.x + 0.6, point.co.y * 1.2, point.co.z + 0.8)
    _key(pull, {1: 0.0, 12: 1.0, 24: 0.5}, "value")
    _key(cage, {1: (0.0, 0.0, 0.0), 12: (0.3, 0.0, 0.4), 24: (0.0, -0.2, 0.7)}, "rotation_euler")
    _key(cage, {1: (1.0, 1.0, 1.0), 12: (1.1, 0.9, 1.0), 24: (0.9, 1.2, 1.1)}, "scale")
    return [cage]


def _bones(rig, name: str, origin) -> list[bpy.types.Object]:
    """An armature of two connected bones along the body, both keyed (weights by distance)."""
    chain = [("B0", (-1.0, 0.0, 0.0), (0.5, 0.0, 0.0)), ("B1", (0.5, 0.0, 0.0), (2.0, 0.0, 0.0))]
    armature = _armature(rig, name + " Arm", origin, chain)
    for bone_name, poses in (("B0", {1: (0.0, 0.0, 0.0), 12: (0.0, 0.2, 0.1), 24: (0.2, 0.0, -0.2)}),
                             ("B1", {1: (0.0, 0.0, 0.0), 12: (0.4, 0.0, 0.9), 24: (0.8, 0.3, 1.4)})):
        bone = armature.pose.bones[bone_name]
        bone.rotation_mode = "XYZ"
        _key(bone, poses, "rotation_euler")
    return [armature]


CONTROLS = {"probe": _probes, "cage": _cage, "bone": _bones}


def _add_deformer(kind: str, target, controls) -> None:
    """Our add operator, as a script runs it (the target active, its controls selected)."""
    with bpy.context.temp_override(active_object=target, object=target,
                                   selected_objects=[target, *controls]):
        operator = getattr(bpy.ops.object, f"affine_{kind}_deformer_add")
        assert operator() == {"FINISHED"}, (kind, target.name)


def build_body(rig, index: int, body: dict) -> None:
    """One rig of the plan: the body (a box) with the modifiers before ours, its shape keys, its
    controls keyed at FRAMES, our deformer bound at frame 1, and the modifiers after ours."""
    origin = (SPACING * (index % COLUMNS), SPACING * (index // COLUMNS), 0.0)
    target = bpy.data.objects.new(body["name"], _box_mesh(body["name"], body.get("weld_seam", False)))
    target.location = origin
    rig.objects.link(target)
    if body.get("shape_keys"):
        _shape_keys(target)
    for spec in body.get("before", ()):
        _modifier(target, spec, rig, origin)
    controls = CONTROLS[body["kind"]](rig, body["name"], origin)
    bpy.context.scene.frame_set(1)  # bind at the first keyed pose
    _add_deformer(body["kind"], target, controls)
    if body.get("preserve_shape"):
        target.affine_deformers[0].preserve_shape = True
    for spec in body.get("after", ()):
        _modifier(target, spec, rig, origin)


# ------------------------------------------------------------------------------------------ measuring


def positions(obj, depsgraph=None) -> np.ndarray:
    """The evaluated vertex positions of `obj` in `depsgraph` (default: the context's), object space."""
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    mesh = obj.evaluated_get(depsgraph).data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def status(obj) -> str:
    """The deformer's status ('' when it deforms without complaint); more than one: all of them."""
    return " / ".join(d.status for d in obj.affine_deformers if d.status)


class Record:
    """Positions and statuses of each body at each frame, under labels, saved for the parent process."""

    def __init__(self) -> None:
        self.positions: dict[str, np.ndarray] = {}
        self.statuses: dict[str, str] = {}

    def add(self, label: str, name: str, frame: int, obj, depsgraph=None) -> None:
        key = f"{label}|{name}|{frame}"
        self.positions[key] = positions(obj, depsgraph)
        self.statuses[key] = status(obj)
        self.statuses[f"{WARNINGS}|{key}"] = node_warnings(obj)

    def measure(self, label: str, names, get, frames=VISIT) -> None:
        """Visit `frames` and record every body (`get(name)`: its object in this context)."""
        scene = bpy.context.scene
        for frame in frames:
            scene.frame_set(frame)
            for name in names:
                self.add(label, name, frame, get(name))

    def save(self, out: str) -> None:
        np.savez(out + ".npz", **self.positions)
        with open(out + ".json", "w") as file:
            json.dump(self.statuses, file)


#: The prefix of the keys under which `Record.add` keeps the warnings on a body's modifiers.
WARNINGS = "warnings"


def node_warnings(obj) -> str:
    """The warnings Blender shows on any Geometry Nodes modifier of `obj` (`node_warnings`: 4.3 on),
    ours, our input modifiers' and the artist's alike."""
    found = [w.message for mod in obj.modifiers if mod.type == "NODES"
             for w in getattr(mod, "node_warnings", ())]
    return " / ".join(dict.fromkeys(found))


def ours(obj) -> list[bpy.types.Modifier]:
    """The Geometry Nodes modifiers of our deformers on `obj`."""
    return [m for m in obj.modifiers
            if m.type == "NODES" and m.node_group is not None and "affine_deformers_group" in m.node_group]


def _stage(scene, render_out: str) -> None:
    """A top orthographic camera over all the rigs and a sun; a tiny Cycles render of 1 sample (the
    same in the asset and the shot, so their pictures compare); frames 1 to 24, which `-a` renders."""
    stage = bpy.data.collections.new("Stage")
    scene.collection.children.link(stage)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.type, camera.data.ortho_scale = "ORTHO", SPACING * (COLUMNS + 1)
    camera.location = (SPACING * (COLUMNS - 1) / 2, SPACING * (COLUMNS - 1) / 2, 30.0)
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.rotation_euler = (0.6, 0.2, 0.0)
    for obj in (camera, sun):
        stage.objects.link(obj)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.device = 1, "CPU"
    scene.render.resolution_x = scene.render.resolution_y = 96
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.frame_start, scene.frame_end, scene.frame_step = 1, 24, 1
    scene.render.filepath = render_out


# ------------------------------------------------------------------------------------------ processes


def build_asset(plan_json: str, asset: str, out: str, render_out: str) -> None:
    """Build the asset from the plan, save it at SAVED_AT, record the reference ("asset", and "input":
    our modifiers off), the vertex counts and the Blender version (`out` + "_meta.json"), and render
    PICTURE_FRAME to `render_out` + "asset.png"."""
    plan = json.loads(plan_json)
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    rig = bpy.data.collections.new("Rig")
    scene.collection.children.link(rig)
    for index, body in enumerate(plan):
        build_body(rig, index, body)
    _stage(scene, render_out + "shot_")
    names = [body["name"] for body in plan]
    record = Record()
    record.measure("asset", names, bpy.data.objects.__getitem__, FRAMES)
    scene.frame_set(SAVED_AT)
    bpy.ops.wm.save_as_mainfile(filepath=asset)
    counts = {name: _counts(bpy.data.objects[name]) for name in names}
    meta = {"blender": bpy.app.version_string, "counts": counts}
    with open(out + "_meta.json", "w") as file:
        json.dump(meta, file)
    _render_still(scene, PICTURE_FRAME, render_out + "asset.png")
    for name in names:
        for mod in ours(bpy.data.objects[name]):
            mod.show_viewport = False
    record.measure("input", names, bpy.data.objects.__getitem__, FRAMES)
    record.save(out)


def _counts(obj) -> tuple[int, int]:
    """The body's vertex count: its mesh's, and what reaches our modifier (ours and what follows off)."""
    mods = list(obj.modifiers)
    after = mods[mods.index(ours(obj)[0]):]
    for mod in after:
        mod.show_viewport = False
    counts = len(obj.data.vertices), len(positions(obj))
    for mod in after:
        mod.show_viewport = True
    return counts


def _render_still(scene, frame: int, path: str) -> None:
    scene.frame_set(frame)
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)


def _override(name: str) -> bpy.types.Object:
    """The local override of the rig's object `name`."""
    found = [obj for obj in bpy.data.objects if obj.name == name and obj.library is None]
    assert len(found) == 1 and found[0].override_library is not None, (name, found)
    return found[0]


def _link_and_override(asset: str) -> None:
    """Link the collection "Rig" and override it, as Object ▸ Library Override ▸ Make does on an
    instance of it."""
    scene = bpy.context.scene
    with bpy.data.libraries.load(asset, link=True) as (_source, linked):
        linked.collections = ["Rig"]
    instance = bpy.data.objects.new("RigInstance", None)
    instance.instance_type, instance.instance_collection = "COLLECTION", linked.collections[0]
    scene.collection.objects.link(instance)
    linked.collections[0].override_hierarchy_create(scene, bpy.context.view_layer, reference=instance)
    bpy.data.objects.remove(instance)


def measure_contexts(plan_json: str, asset: str, shot: str, out: str, render_out: str) -> None:
    """Local (the asset opened), appended (File ▸ Append of "Rig" into a new file) and linked and
    overridden (a new file; saved at SAVED_AT as the shot, with the stage of the asset)."""
    names = [body["name"] for body in json.loads(plan_json)]
    record = Record()
    bpy.ops.wm.open_mainfile(filepath=asset, load_ui=False)
    record.measure("local", names, bpy.data.objects.__getitem__)
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.wm.append(directory=asset + "/Collection/", filename="Rig") == {"FINISHED"}
    record.measure("appended", names, bpy.data.objects.__getitem__)
    bpy.ops.wm.read_homefile(use_empty=True)
    _link_and_override(asset)
    record.measure("overridden", names, _override)
    scene = bpy.context.scene
    _stage(scene, render_out + "shot_")
    scene.frame_set(SAVED_AT)
    bpy.ops.wm.save_as_mainfile(filepath=shot)
    record.save(out)


def measure_reopened(plan_json: str, shot: str, out: str) -> None:
    """The shot opened in this fresh process."""
    names = [body["name"] for body in json.loads(plan_json)]
    record = Record()
    bpy.ops.wm.open_mainfile(filepath=shot, load_ui=False)
    record.measure("reopened", names, _override)
    record.save(out)


def measure_render(plan_json: str, shot: str, out: str, asset_picture: str) -> None:
    """A background animation render of the shot, as `blender -b shot.blend -a` runs it (frames 1 to
    24, Cycles), recording what the render evaluated at FRAMES (`RenderCapture`), and how its picture
    of PICTURE_FRAME differs from the asset's (`out` + "_picture.json")."""
    names = [body["name"] for body in json.loads(plan_json)]
    bpy.ops.wm.open_mainfile(filepath=shot, load_ui=False)
    capture = RenderCapture(names)
    handlers = bpy.app.handlers.frame_change_post
    handlers.append(capture)  # after the add-on's handler, which writes the deformations
    try:
        assert any(getattr(h, "__name__", "") == "on_frame_change_post" for h in handlers[:-1]), handlers[:]
        assert bpy.ops.render.render(animation=True) == {"FINISHED"}
    finally:
        handlers.remove(capture)  # bpy 4.2 crashes at exit on a handler left behind
    assert sorted(capture.frames) == sorted(FRAMES), capture.frames
    capture.record.save(out)
    shot_picture = _pixels(bpy.context.scene.render.frame_path(frame=PICTURE_FRAME))
    asset = _pixels(asset_picture)
    difference = np.abs(shot_picture - asset)
    with open(out + "_picture.json", "w") as file:
        json.dump({"frame": PICTURE_FRAME, "max": float(difference.max()),
                   "pixels": int((difference.max(axis=1) > 0).sum()), "blank": bool(asset.std() < 0.01)},
                  file)


def _warnings(obj) -> str:
    """The warnings on `obj`'s modifiers of ours (`NodesModifier.node_warnings`: Blender 4.3 on), for
    a process without the add-on, where no deformer status exists."""
    found = [w.message for mod in ours(obj) for w in getattr(mod, "node_warnings", ())]
    return " / ".join(dict.fromkeys(found))


def measure_without_addon(plan_json: str, asset: str, shot: str, out: str) -> None:
    """The asset ("asset without add-on") and the shot ("shot without add-on") opened where the add-on
    is not installed: nothing updates the deformations; frames other than SAVED_AT must show each
    modifier's input, with the warning where Blender has the Warning node."""
    assert not hasattr(bpy.types.Object, "affine_deformers"), "the add-on must not run here"
    names = [body["name"] for body in json.loads(plan_json)]
    record = Record()
    for label, path, get in (("bare_asset", asset, lambda name: bpy.data.objects[name]),
                             ("bare_shot", shot, _override)):
        bpy.ops.wm.open_mainfile(filepath=path, load_ui=False)
        scene = bpy.context.scene
        for frame in VISIT:
            scene.frame_set(frame)
            for name in names:
                key = f"{label}|{name}|{frame}"
                record.positions[key] = positions(get(name))
                record.statuses[key] = _warnings(get(name))
    record.save(out)


def _pixels(path: str) -> np.ndarray:
    """A picture's RGBA pixels, (n, 4) float32."""
    image = bpy.data.images.load(path)
    pixels = np.empty(len(image.pixels), np.float32)
    image.pixels.foreach_get(pixels)
    bpy.data.images.remove(image)
    return pixels.reshape(-1, 4)


class RenderCapture:
    """A frame_change_post handler that records the bodies as a render evaluates them.

    During a render frame Blender evaluates the render's depsgraph, runs the frame_change_post
    handlers (the add-on's writes the deformations then), and evaluates again what they changed
    before the engine renders; no handler runs between that second pass and the engine. So this one,
    after the add-on's, runs that pass itself (`depsgraph.update()`; Blender's own then finds nothing
    left to do) and reads the evaluated meshes. Checked on Blender 5.0 and 4.2 when this was written,
    on overridden rigs both right and torn, at 384 × 384 pixels: the pictures rendered with and
    without it are bit for bit the same, and the captured meshes, rebuilt as plain meshes and
    rendered alone, give the live render's picture bit for bit (the state before the update does
    not: up to 830 pixels differ)."""

    def __init__(self, names) -> None:
        self.names = list(names)
        self.record = Record()
        self.frames: list[int] = []
        self.__name__ = "pipeline_matrix_render_capture"  # handler lists show names

    def __call__(self, scene, depsgraph=None) -> None:
        if depsgraph is None or depsgraph.mode != "RENDER" or scene.frame_current not in FRAMES:
            return
        depsgraph.update()
        self.frames.append(scene.frame_current)
        for name in self.names:
            self.record.add("render", name, scene.frame_current, _override(name), depsgraph)
