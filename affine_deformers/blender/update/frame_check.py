"""The frame check: a deformer's output knows the scene time it was computed for, and our node group
shows its input (with a warning) at any other time, so a file opened where the add-on does not run
never shows a stale shape.

The update writes, beside the offsets or motions, a FLOAT point attribute `.affdef_<uid>_frame`
holding the same value at every point (storage.frame_name): the scene time of the update
(`scene_time`, what Geometry Nodes' Scene Time node gives as Frame: (frame + subframe) × the time
remapping of Time Stretching), or `STAMP_ALWAYS` when the output is right at every frame
(`right_at_every_frame`).
A constant is used rather than one value because the modifiers before ours (Subdivision, Mirror,
Bevel, …) interpolate point attributes: any point of their output then still holds the stamp, to
the rounding of a weighted mean (`TOLERANCE`, `RELATIVE_TOLERANCE`).

The node group (nodes.py, version 5) reads the stamp at point 0 of the geometry it reads the output
from (`stale_socket`) and compares it with Scene Time: when they differ it passes its input through
(`pass_through_when_stale`) and, where Blender has the Warning node (4.4 on: `HAS_WARNING_NODE`),
says on the modifier why and what to do. Blender 4.2 has no such node: the modifier shows its input
without a message there. A missing stamp (an output written by an older version) is trusted, as
before.

Deciding "right at every frame": the output depends on the controls' poses relative to the target.
When neither the target nor any control, nor any of their parents, has animation data (an action,
drivers or NLA tracks), constraints (object or pose bone) or a rigid body, and no control that is a
mesh (a cage) has modifiers or animated shape keys, nothing changes with time and the stamp is
`STAMP_ALWAYS`. Anything else — including what cannot be known from Python (a driver's expression,
a simulation) — counts as time-dependent: the stamp is the frame, so without the add-on the
modifier warns and shows its input at other frames rather than possibly showing a stale shape.
"""

from __future__ import annotations

import bpy
import numpy as np

from .. import caches
from ..files import storage

#: Blender has the Warning node (4.4 on): the group raises a warning on the modifier.
HAS_WARNING_NODE = hasattr(bpy.types, "GeometryNodeWarning")
#: The stamp of an output that is right at every frame (a float32; any stamp at or below
#: `ALWAYS_BELOW` counts as it).
STAMP_ALWAYS = -3.0e38
ALWAYS_BELOW = -1.0e38
#: |stamp − frame| ≤ TOLERANCE + RELATIVE_TOLERANCE·|frame| counts as the same time: a stamp
#: interpolated by a modifier before ours is off by a few float32 roundings; shutter subframes of
#: motion blur are hundredths of a frame apart or more.
TOLERANCE = 1e-3
RELATIVE_TOLERANCE = 1e-6
WARNING = ("This deformation was computed for another frame and nothing updates it here (the Affine "
           "Deformers add-on is not running, or the rig is linked without a library override): the "
           "modifier shows its input. Install and enable Affine Deformers, make a library override, or "
           "bake the deformer (its panel: Bake) in a file where the add-on runs")

#: (mesh session uid, deformer uid or '' for a position carrier) → the stamp this process last wrote
#: there (float32).
_written: dict[tuple[int, str], np.float32] = {}


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """Drop the remembered stamps (all: undo, redo and file load may restore other values)."""
    if key is None:
        _written.clear()
    else:
        for found in [k for k in _written if k[1] in (key[1], "")]:
            del _written[found]


def scene_time(scene: bpy.types.Scene) -> np.float32:
    """The scene time Geometry Nodes' Scene Time node gives as Frame, in float32 as Blender forms it:
    (frame + subframe) × frame_map_old / frame_map_new (Time Stretching 100 → 50 plays frame 5 at
    time 10; measured on 4.2, 5.0 and 5.3 with a Scene Time node, test_artist_moves.py)."""
    render = scene.render
    remap = np.float32(render.frame_map_old) / np.float32(render.frame_map_new)
    return (np.float32(scene.frame_current) + np.float32(scene.frame_subframe)) * remap


def _animated(block) -> bool:
    data = getattr(block, "animation_data", None)
    return data is not None and (data.action is not None or len(data.drivers) > 0 or len(data.nla_tracks) > 0)


def _changes(obj: bpy.types.Object, geometry: bool, seen: set[int]) -> bool:
    """Whether `obj` (or, through its parents, its transform) may change with time; `geometry`: its
    evaluated geometry matters too (a cage, a parent of vertex-parented objects)."""
    while obj is not None and obj.session_uid not in seen:
        seen.add(obj.session_uid)
        if _animated(obj) or len(obj.constraints) or obj.rigid_body is not None:
            return True
        if obj.type == "ARMATURE" and (_animated(obj.data)
                                       or any(len(bone.constraints) for bone in obj.pose.bones)):
            return True
        if geometry and (len(getattr(obj, "modifiers", ())) or _animated(obj.data)
                         or _animated(getattr(obj.data, "shape_keys", None))):
            return True
        geometry = obj.parent_type in {"VERTEX", "VERTEX_3"}
        obj = obj.parent
    return False


def right_at_every_frame(obj: bpy.types.Object, controls: list[bpy.types.Object]) -> bool:
    """Whether the output of a deformer on `obj` with `controls` cannot change with time (module doc)."""
    seen: set[int] = set()
    if _changes(obj, False, seen):
        return False
    return not any(_changes(control, control.type == "MESH", seen) for control in controls)


def stamp(mesh: bpy.types.Mesh, uid: str, value: np.float32) -> None:
    """Make deformer `uid`'s stamp attribute on `mesh` (the target's, or its carrier's) `value`: written
    only when this process did not write that value there last (a write tags the mesh for another
    update)."""
    value = np.float32(value)
    if remembered(mesh, value, uid) and mesh.attributes.get(storage.frame_name(uid)) is not None:
        return
    storage.write_frame(mesh, uid, value)
    remember(mesh, value, uid)


def remembered(mesh: bpy.types.Mesh, value: np.float32, uid: str = "") -> bool:
    """Whether this process wrote stamp `value` on `mesh` last (for deformer `uid`; '' for a position
    carrier, output_store.py)."""
    return _written.get((mesh.session_uid, uid)) == value


def remember(mesh: bpy.types.Mesh, value: np.float32, uid: str = "") -> None:
    _written[(mesh.session_uid, uid)] = np.float32(value)


# ------------------------------------------------------------------------------ the group's nodes


def stamp_name_socket(ng: bpy.types.NodeTree, offset_name: bpy.types.NodeSocket,
                      location: tuple[float, float]) -> bpy.types.NodeSocket:
    """The stamp's attribute name from the offset attribute's ("affdef_<uid>_offset" →
    ".affdef_<uid>_frame", storage.frame_name), so modifiers need no input of their own for it."""
    socket = offset_name
    for i, (find, replace) in enumerate((("affdef_", ".affdef_"), ("_offset", "_frame"))):
        node = ng.nodes.new("FunctionNodeReplaceString")
        node.location = (location[0] + 180 * i, location[1])
        ng.links.new(socket, node.inputs["String"])
        node.inputs["Find"].default_value = find
        node.inputs["Replace"].default_value = replace
        socket = node.outputs[0]
    return socket


def _math(ng: bpy.types.NodeTree, operation: str, a, b=None, c=None, location=(0.0, 0.0)):
    node = ng.nodes.new("ShaderNodeMath")
    node.operation = operation
    node.location = location
    for i, value in enumerate((a, b, c)):
        if isinstance(value, bpy.types.NodeSocket):
            ng.links.new(value, node.inputs[i])
        elif value is not None:
            node.inputs[i].default_value = value
    return node.outputs[0]


def _compare(ng: bpy.types.NodeTree, operation: str, a, b, location) -> bpy.types.NodeSocket:
    node = ng.nodes.new("FunctionNodeCompare")
    node.data_type, node.operation = "FLOAT", operation
    node.location = location
    for socket, value in zip(node.inputs[:2], (a, b), strict=True):
        if isinstance(value, bpy.types.NodeSocket):
            ng.links.new(value, socket)
        else:
            socket.default_value = value
    return node.outputs[0]


def _boolean(ng: bpy.types.NodeTree, operation: str, a, b=None, location=(0.0, 0.0)) -> bpy.types.NodeSocket:
    node = ng.nodes.new("FunctionNodeBooleanMath")
    node.operation = operation
    node.location = location
    ng.links.new(a, node.inputs[0])
    if b is not None:
        ng.links.new(b, node.inputs[1])
    return node.outputs[0]


def stale_socket(ng: bpy.types.NodeTree, geometry: bpy.types.NodeSocket, name: bpy.types.NodeSocket,
                 location: tuple[float, float]) -> bpy.types.NodeSocket:
    """A single boolean: `geometry` holds a stamp attribute named `name` (read at point 0) that is
    neither `STAMP_ALWAYS` nor the scene time (a NaN stamp is stale too)."""
    x, y = location
    named = ng.nodes.new("GeometryNodeInputNamedAttribute")
    named.data_type = "FLOAT"
    named.location = (x, y)
    ng.links.new(name, named.inputs["Name"])
    sampled = []
    for i, (data_type, output) in enumerate((("FLOAT", "Attribute"), ("BOOLEAN", "Exists"))):
        node = ng.nodes.new("GeometryNodeSampleIndex")
        node.data_type, node.domain = data_type, "POINT"
        node.location = (x + 180, y - 80 * i)
        ng.links.new(geometry, node.inputs["Geometry"])
        ng.links.new(named.outputs[output], node.inputs["Value"])
        node.inputs["Index"].default_value = 0
        sampled.append(node.outputs[0])
    fresh = _fresh(ng, sampled[0], (x + 360, y))
    return _boolean(ng, "NIMPLY", sampled[1], fresh, (x + 1080, y))  # exists and not fresh


def stale_point_socket(ng: bpy.types.NodeTree, geometry: bpy.types.NodeSocket, index: bpy.types.NodeSocket,
                       location: tuple[float, float]) -> bpy.types.NodeSocket:
    """A single boolean: the x of point `index` of `geometry` (a position carrier's stamp point,
    output_store.py) is neither `STAMP_ALWAYS` nor the scene time."""
    x, y = location
    position = ng.nodes.new("GeometryNodeInputPosition")
    position.location = (x, y)
    separate = ng.nodes.new("ShaderNodeSeparateXYZ")
    separate.location = (x + 80, y)
    ng.links.new(position.outputs[0], separate.inputs[0])
    node = ng.nodes.new("GeometryNodeSampleIndex")
    node.data_type, node.domain = "FLOAT", "POINT"
    node.location = (x + 180, y)
    ng.links.new(geometry, node.inputs["Geometry"])
    ng.links.new(separate.outputs[0], node.inputs["Value"])
    ng.links.new(index, node.inputs["Index"])
    fresh = _fresh(ng, node.outputs[0], (x + 360, y))
    return _boolean(ng, "NOT", fresh, None, (x + 1080, y))


def _fresh(ng: bpy.types.NodeTree, value: bpy.types.NodeSocket,
           location: tuple[float, float]) -> bpy.types.NodeSocket:
    """A single boolean: the stamp `value` is `STAMP_ALWAYS` or the scene time (within the tolerance);
    False for NaN."""
    x, y = location
    time = ng.nodes.new("GeometryNodeInputSceneTime")
    time.location = (x - 180, y + 120)
    frame = time.outputs["Frame"]
    difference = _math(ng, "ABSOLUTE", _math(ng, "SUBTRACT", value, frame, location=(x, y + 60)),
                       location=(x + 180, y + 60))
    allowed = _math(ng, "MULTIPLY_ADD", _math(ng, "ABSOLUTE", frame, location=(x, y + 180)),
                    RELATIVE_TOLERANCE, TOLERANCE, location=(x + 180, y + 180))
    same = _compare(ng, "LESS_EQUAL", difference, allowed, (x + 360, y + 120))
    always = _compare(ng, "LESS_EQUAL", value, ALWAYS_BELOW, (x + 360, y - 40))
    return _boolean(ng, "OR", same, always, (x + 540, y + 60))


def pass_through_when_stale(ng: bpy.types.NodeTree, stale: bpy.types.NodeSocket,
                            geometry: bpy.types.NodeSocket, deformed: bpy.types.NodeSocket,
                            location: tuple[float, float]) -> bpy.types.NodeSocket:
    """`geometry` (the modifier's input) when `stale`, else `deformed`; with the Warning node, the
    switch reads the node's output, so the warning is raised exactly when the input is shown."""
    x, y = location
    if HAS_WARNING_NODE:
        warning = ng.nodes.new("GeometryNodeWarning")
        warning.warning_type = "WARNING"
        warning.location = (x - 200, y + 150)
        ng.links.new(stale, warning.inputs["Show"])
        warning.inputs["Message"].default_value = WARNING
        stale = warning.outputs[0]
    switch = ng.nodes.new("GeometryNodeSwitch")
    switch.input_type = "GEOMETRY"
    switch.location = (x, y)
    ng.links.new(stale, switch.inputs["Switch"])
    ng.links.new(deformed, switch.inputs["False"])
    ng.links.new(geometry, switch.inputs["True"])
    return switch.outputs[0]
