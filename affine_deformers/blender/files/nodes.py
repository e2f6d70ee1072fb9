"""Geometry Nodes plumbing: the shared "AffineDeformer" node group, one modifier per deformer, and a
throw-away node evaluation that reads painted vertex-group weights without a loop over vertices.

Each deformer is a real entry in the modifier stack: a Geometry Nodes modifier with our group, which
moves the positions that REACH it (shape keys, an Armature or another deformer before it included) by
what the evaluation handler wrote on the mesh, in one of two forms (evaluate.py chooses):

* motion: four FLOAT_VECTOR point attributes holding each vertex's affine map x ↦ M x + t as the
  columns M e_x, M e_y, M e_z and t ("Motion X/Y/Z/T" inputs). The group computes
  x·c_x + y·c_y + z·c_z + t for the incoming position (x, y, z), on the points where the attributes
  exist. Plain vectors rather than one FLOAT4X4 attribute: modifiers that add vertices before ours
  (Subdivision, Multires, Mirror, Array, Bevel, Solidify, …) interpolate or copy vector attributes
  onto the new vertices, so a motion shared by all controls still gives exactly that motion there
  (Subdivision does not interpolate matrix attributes: measured on 4.2 and 5.0);
* offset: one FLOAT_VECTOR attribute v' − v added to the position ("Offset Attribute"), exact only
  when the positions reaching the modifier are the mesh's own (first in the stack, no shape keys): the
  fast path, 3 floats per vertex instead of 12.

An attribute that is missing reads as no change, so a modifier with neither passes its input through.

Version 2 added two inputs that no node reads, "Cage" (Object) and "Probes" (Collection), hidden in
the modifier panel: Geometry Nodes adds a depsgraph relation for every ID set on a modifier's inputs,
used or not, so the controls named there are evaluated whenever the modifier is (see relations.py;
the armature of a bone deformer goes in the collection, whose relation also evaluates its pose).
Version 3 added the motion inputs and nodes. Version 4 added "Output Carrier" (Object, hidden): a
target whose mesh is linked from a library (a library override in a shot file) cannot hold per-frame
attributes, so the handler writes them to a local carrier object instead (carrier.py), one point
per target vertex, and the group reads them from there by point index. A single-value Switch on the
carrier's point count picks one of two copies of the chain, the version-3 chain on the geometry's
own attributes or the same chain sampling the carrier, and only the chosen branch is evaluated: a
local target (no carrier) gets exactly the version-3 result. Groups of older versions (files saved
before) are upgraded in place by `upgrade_group`: the inputs are added and the nodes rebuilt;
modifiers keep their values. A group linked from a library is read-only and is never upgraded: it
is used as it is (see carrier.py for what a version-3 group linked into a shot means).

Version 6 also reads a position carrier on the same input (output_store.py): a mesh of N + 1 or 4N + 1
points (N the points reaching the modifier) holds the offsets or the motion columns as vertex
positions, and its last point the frame stamp; the same arithmetic as on the attributes.

Version 5 checks the frame (frame_check.py): the update stamps its output with the scene time it
was computed for, as a FLOAT point attribute `.affdef_<uid>_frame` (the name derived from the
offset input's by two Replace String nodes, so no modifier needs a new input), or with
`STAMP_ALWAYS` when the output is right at every frame. The group compares the stamp with Scene
Time's frame; when they differ (a file opened where the add-on does not run, at another frame than
it was saved at) it passes its input through and, where Blender has the Warning node (4.4 on),
raises a warning on the modifier saying what to do. A missing stamp (output of an older version)
is trusted as before.
"""

from __future__ import annotations

from collections.abc import Callable

import bpy
import numpy as np

from .. import caches
from ..update import frame_check
from . import modifier_inputs

GROUP_NAME = "AffineDeformer"
GROUP_MARK = "affine_deformers_group"  # custom property identifying our group (value = version)
GROUP_VERSION = 6
#: 1: Geometry + Offset Attribute; 2: + Cage and Probes; 3: + Motion X/Y/Z/T; 4: + Output Carrier;
#: 5: the frame check (no new input); 6: position carriers on the carrier input (output_store.py)
KNOWN_VERSIONS = (1, 2, 3, 4, 5, 6)
#: The first version that reads a position carrier.
POSITIONS_SINCE = 6
#: Set on a group built with the Warning node (Blender 4.4 on): a group built by an older Blender
#: (the samples are saved by 4.2) is rebuilt where the node exists, so the warning shows there.
WARNS_MARK = "affine_deformers_warns"
OFFSET_SOCKET = "Offset Attribute"
CAGE_SOCKET = "Cage"
PROBES_SOCKET = "Probes"
MOTION_SOCKETS = ("Motion X", "Motion Y", "Motion Z", "Motion T")
CONTROL_SOCKETS = (
    (CAGE_SOCKET, "NodeSocketObject", "The cage of a cage deformer (set by the add-on; only makes the "
                                      "depsgraph evaluate it)"),
    (PROBES_SOCKET, "NodeSocketCollection", "The probes of a probe deformer, or the armature of a bone "
                                            "deformer (set by the add-on; only makes the depsgraph "
                                            "evaluate them)"),
)
_MOTION_INPUTS = tuple(
    (name, "NodeSocketString", f"Point attribute holding the {what} of each vertex's motion (set by the "
                               "add-on)")
    for name, what in zip(MOTION_SOCKETS, ("image of the X axis", "image of the Y axis",
                                           "image of the Z axis", "translation"), strict=True)
)
CARRIER_SOCKET = "Output Carrier"
#: The Switch between the chain on the geometry's own attributes (False) and the carriers' (True).
CARRIER_SWITCH = "Carrier Switch"
_CARRIER_INPUTS = (
    (CARRIER_SOCKET, "NodeSocketObject", "Local object holding this deformer's per-frame output when the "
                                         "target's mesh is linked from a library (set by the add-on)"),
)
#: Inputs added after version 1, in interface order, all managed by the add-on (hidden in the panel).
_MANAGED_INPUTS = CONTROL_SOCKETS + _MOTION_INPUTS + _CARRIER_INPUTS
_READER_NAME = ".AffineDeformer VertexGroupReader"
#: (group session uid, names of its interface items in order) → `_input_identifiers` of it.
_identifier_memo: dict[tuple[int, tuple[str, ...]], dict[tuple[str, str], str]] = {}
_IDENTIFIERS_KEPT = 16
_READER_ATTR = "affdef_tmp_vg{}"


def _is_our_group(ng: bpy.types.NodeTree | None) -> bool:
    """Our group, of the current or an older version (older ones still deform; see upgrade_group)."""
    return _our_offset_identifier(ng) is not None


def offset_attribute(mod: bpy.types.Modifier) -> str:
    """The offset attribute our modifier reads ('' when `mod` is not ours)."""
    identifier = _our_offset_identifier(mod.node_group) if mod.type == "NODES" else None
    value = modifier_inputs.value(mod, identifier)
    return value if isinstance(value, str) else ""


def _our_offset_identifier(ng: bpy.types.NodeTree | None) -> str | None:
    """The offset input's identifier when `ng` is our group (`_is_our_group`), else None."""
    identifiers = _our_identifiers(ng)
    return None if identifiers is None else identifiers[OFFSET_SOCKET, "NodeSocketString"]


def _our_identifiers(ng: bpy.types.NodeTree | None) -> dict[tuple[str, str], str] | None:
    """`_input_identifiers(ng)` when `ng` is our group (marked, with the offset input), else None. A
    group linked from a library counts (the modifier of a library override uses the asset's group),
    read-only: `upgrade_group` leaves it as it is."""
    if (ng is None or ng.bl_idname != "GeometryNodeTree"
            or ng.get(GROUP_MARK) not in KNOWN_VERSIONS):
        return None
    identifiers = _input_identifiers(ng)
    return identifiers if (OFFSET_SOCKET, "NodeSocketString") in identifiers else None


def _input_identifiers(ng: bpy.types.NodeTree) -> dict[tuple[str, str], str]:
    """{(name, socket type): identifier} of the group's inputs (the first of a name and type).

    Every update asks for several, and reading the interface item by item costs ~20 µs through RNA,
    so the map is kept per group and the names of its items in order (one call): adding, removing,
    renaming or reordering items reads it anew. An edit the names do not show (a socket replaced by
    one of the same name, type and place) is seen after the next depsgraph update, whose handler
    forgets the map when a node tree changed; so do undo and file load (caches.forget). Within one
    update the map of a group is looked up once (caches.scoped)."""
    return caches.scoped(("inputs", ng.session_uid), lambda: _read_identifiers(ng))


def _read_identifiers(ng: bpy.types.NodeTree) -> dict[tuple[str, str], str]:
    items = ng.interface.items_tree
    key = (ng.session_uid, tuple(items.keys()))
    found = _identifier_memo.get(key)
    if found is None:
        found = {}
        for item in items:
            if getattr(item, "item_type", "") == "SOCKET" and item.in_out == "INPUT":
                found.setdefault((item.name, item.socket_type), item.identifier)
        _identifier_memo[key] = found
        while len(_identifier_memo) > _IDENTIFIERS_KEPT:
            _identifier_memo.pop(next(iter(_identifier_memo)))
    return found


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """Drop the interface memo (`_input_identifiers`) at a full forget (it is per node group, not per
    deformer)."""
    if key is None:
        _identifier_memo.clear()


def _input_identifier(ng: bpy.types.NodeTree, name: str, socket_type: str) -> str | None:
    return _input_identifiers(ng).get((name, socket_type))


def offset_socket_identifier(ng: bpy.types.NodeTree) -> str | None:
    """Identifier of the group's string input that names the offset attribute (e.g. "Socket_1")."""
    return _input_identifier(ng, OFFSET_SOCKET, "NodeSocketString")


def is_current(ng: bpy.types.NodeTree | None) -> bool:
    """Our group at GROUP_VERSION, with every managed input."""
    identifiers = _our_identifiers(ng)
    return identifiers is not None and _has_managed_inputs(ng, identifiers)


def _has_managed_inputs(ng: bpy.types.NodeTree, identifiers: dict[tuple[str, str], str]) -> bool:
    return (ng.get(GROUP_MARK) == GROUP_VERSION
            and bool(ng.get(WARNS_MARK)) == frame_check.HAS_WARNING_NODE
            and all((name, kind) in identifiers for name, kind, _ in _MANAGED_INPUTS))


def upgrade_group(ng: bpy.types.NodeTree) -> bool:
    """Bring our group of an older version up to GROUP_VERSION in place (versioning of saved files):
    add the missing inputs and rebuild the nodes. Modifiers keep the values of the inputs they had
    (the motion names are set by `set_attribute_names`). True when it changed. A linked (or overridden)
    group is never changed: its data is the library's, and an edit would not be saved."""
    if not _is_our_group(ng) or is_current(ng) or not is_editable(ng):
        return False
    for name, socket_type, description in _MANAGED_INPUTS:
        if _input_identifier(ng, name, socket_type) is None:
            socket = ng.interface.new_socket(name, in_out="INPUT", socket_type=socket_type)
            socket.description = description
            socket.hide_in_modifier = True  # managed by the add-on: a hand-picked value would go stale
    _build_nodes(ng)
    ng[GROUP_MARK] = GROUP_VERSION
    ng[WARNS_MARK] = frame_check.HAS_WARNING_NODE
    return True


def is_editable(ng: bpy.types.NodeTree) -> bool:
    """Whether the group belongs to this file (not linked from a library, nor a library override)."""
    return ng.library is None and ng.override_library is None


def _build_nodes(ng: bpy.types.NodeTree) -> None:
    """(Re)create the group's nodes: the chain on the geometry's own attributes, the same chain on the
    carrier's attributes sampled by point index, the chain on a position carrier's points (offset or
    motion layout, output_store.py), and single-value Switches between them on the carrier's point
    count (lazy: only the chosen chain runs, see the module doc); then the frame check."""
    nodes, links = ng.nodes, ng.links
    nodes.clear()
    group_in = nodes.new("NodeGroupInput")
    group_out = nodes.new("NodeGroupOutput")
    group_in.location, group_out.location = (-1100, 0), (1300, 0)
    info = nodes.new("GeometryNodeObjectInfo")
    info.transform_space = "ORIGINAL"  # the carrier's own data, wherever the object stands
    info.location = (-900, -900)
    links.new(group_in.outputs[CARRIER_SOCKET], info.inputs["Object"])
    carrier = info.outputs["Geometry"]
    count = _point_count(ng, carrier, (-700, -1100))
    points = _point_count(ng, group_in.outputs[0], (-700, -1250))
    # FLOAT comparisons: a point count is exact in float32 far beyond any mesh.
    has_points = _compare(ng, "GREATER_THAN", count, 0.5, (-500, -1100))
    layout = _math(ng, "SUBTRACT", count, 1.0, (-500, -1250))  # a position carrier's data points
    as_offsets = _compare(ng, "EQUAL", layout, points, (-300, -1250))
    as_motions = _compare(ng, "EQUAL", layout, _math(ng, "MULTIPLY", points, 4.0, (-500, -1400)),
                          (-300, -1400))
    index = nodes.new("GeometryNodeInputIndex")
    index.location = (-900, -1200)
    own = _build_chain(ng, group_in, _attribute_reader(ng, None, None), 0)
    sampled = _build_chain(ng, group_in, _attribute_reader(ng, carrier, index.outputs[0]), -1400)
    at = index.outputs[0]
    offsets = _build_chain(ng, group_in, _position_reader(ng, carrier, at, points, False), -2800)
    motions = _build_chain(ng, group_in, _position_reader(ng, carrier, at, points, True), -4200)
    positions = _switch(ng, "GEOMETRY", as_offsets, _switch(ng, "GEOMETRY", as_motions, sampled, motions,
                                                            (500, -1800)), offsets, (600, -1600))
    deformed = _switch(ng, "GEOMETRY", has_points, own, positions, (700, 0), name=CARRIER_SWITCH)
    stamp_name = frame_check.stamp_name_socket(ng, group_in.outputs[OFFSET_SOCKET], (-900, 500))
    own_stale = frame_check.stale_socket(ng, group_in.outputs[0], stamp_name, (-500, 700))
    carrier_stale = frame_check.stale_socket(ng, carrier, stamp_name, (-500, 900))
    positions_stale = frame_check.stale_point_socket(ng, carrier, layout, (-500, 1100))
    in_positions = _boolean(ng, "OR", as_offsets, as_motions, (-100, 1100))
    carrier_stale = _switch(ng, "BOOLEAN", in_positions, carrier_stale, positions_stale, (0, 1000))
    stale = _switch(ng, "BOOLEAN", has_points, own_stale, carrier_stale, (100, 700))
    shown = frame_check.pass_through_when_stale(ng, stale, group_in.outputs[0], deformed, (900, 300))
    links.new(shown, group_out.inputs[0])


def _point_count(ng: bpy.types.NodeTree, geometry: bpy.types.NodeSocket,
                 location: tuple[float, float]) -> bpy.types.NodeSocket:
    node = ng.nodes.new("GeometryNodeAttributeDomainSize")
    node.component = "MESH"
    node.location = location
    ng.links.new(geometry, node.inputs[0])
    return node.outputs["Point Count"]


def _operands(ng: bpy.types.NodeTree, node: bpy.types.Node, values) -> None:
    for socket, value in zip(node.inputs, values, strict=False):
        if isinstance(value, bpy.types.NodeSocket):
            ng.links.new(value, socket)
        else:
            socket.default_value = value


def _compare(ng: bpy.types.NodeTree, operation: str, a, b, location) -> bpy.types.NodeSocket:
    """A FLOAT Compare node (its A and B are the node's first two inputs)."""
    node = ng.nodes.new("FunctionNodeCompare")
    node.data_type, node.operation = "FLOAT", operation
    node.location = location
    _operands(ng, node, (a, b))
    if operation == "EQUAL":
        node.inputs["Epsilon"].default_value = 0.0  # counts are whole numbers
    return node.outputs[0]


def _math(ng: bpy.types.NodeTree, operation: str, a, b, location) -> bpy.types.NodeSocket:
    """A FLOAT Math node `operation` of a and b (sockets or numbers)."""
    node = ng.nodes.new("ShaderNodeMath")
    node.operation = operation
    node.location = location
    _operands(ng, node, (a, b))
    return node.outputs[0]


def _boolean(ng: bpy.types.NodeTree, operation: str, a, b, location) -> bpy.types.NodeSocket:
    node = ng.nodes.new("FunctionNodeBooleanMath")
    node.operation = operation
    node.location = location
    _operands(ng, node, (a, b))
    return node.outputs[0]


def _switch(ng: bpy.types.NodeTree, input_type: str, condition: bpy.types.NodeSocket,
            false: bpy.types.NodeSocket, true: bpy.types.NodeSocket,
            location: tuple[float, float], name: str = "") -> bpy.types.NodeSocket:
    """A Switch node of `input_type` giving `true` when `condition`, else `false` (lazy: only the
    chosen input is evaluated); `name`: the node's name, for one that tests look up."""
    node = ng.nodes.new("GeometryNodeSwitch")
    if name:
        node.name = name
    node.input_type = input_type
    node.location = location
    ng.links.new(condition, node.inputs["Switch"])
    ng.links.new(false, node.inputs["False"])
    ng.links.new(true, node.inputs["True"])
    return node.outputs[0]


#: A reader of the chain's inputs: (the group input naming the attribute, motion column 0…3 or None
#: for the offset, node location) → (value, exists) sockets.
Reader = Callable[[bpy.types.NodeSocket, int | None, tuple[float, float]],
                  tuple[bpy.types.NodeSocket, bpy.types.NodeSocket]]


def _attribute_reader(ng: bpy.types.NodeTree, carrier: bpy.types.NodeSocket | None,
                      index: bpy.types.NodeSocket | None) -> Reader:
    """The vector attribute named by the input: on the evaluated geometry itself (carrier None), or on
    the carrier geometry at the same point index."""
    nodes, links = ng.nodes, ng.links

    def read(name: bpy.types.NodeSocket, _column: int | None, location: tuple[float, float]):
        named = nodes.new("GeometryNodeInputNamedAttribute")
        named.data_type = "FLOAT_VECTOR"
        named.location = location
        links.new(name, named.inputs["Name"])
        if carrier is None:
            return named.outputs["Attribute"], named.outputs["Exists"]
        sampled = []
        for data_type, output, dy in (("FLOAT_VECTOR", "Attribute", 0), ("BOOLEAN", "Exists", -60)):
            node = nodes.new("GeometryNodeSampleIndex")
            node.data_type, node.domain = data_type, "POINT"
            node.location = (location[0] + 150, location[1] + dy)
            links.new(carrier, node.inputs["Geometry"])
            links.new(named.outputs[output], node.inputs["Value"])
            links.new(index, node.inputs["Index"])
            sampled.append(node.outputs[0])
        return sampled[0], sampled[1]

    return read


def _position_reader(ng: bpy.types.NodeTree, carrier: bpy.types.NodeSocket, index: bpy.types.NodeSocket,
                     points: bpy.types.NodeSocket, motions: bool) -> Reader:
    """A position carrier's points (output_store.py): the offsets at the point's own index, or motion
    column c at index c·N + index (N: the points reaching the modifier); the other form reads as
    missing, exactly as an absent attribute does on the chain of the geometry's own attributes."""
    nodes, links = ng.nodes, ng.links

    def read(_name: bpy.types.NodeSocket, column: int | None, location: tuple[float, float]):
        exists = nodes.new("FunctionNodeInputBool")
        exists.boolean = motions == (column is not None)
        exists.location = (location[0], location[1] - 80)
        if not exists.boolean:
            zero = nodes.new("FunctionNodeInputVector")
            zero.location = location
            return zero.outputs[0], exists.outputs[0]
        at = index
        if column:  # N·c + index: whole numbers, exact in float32 below 2^24
            node = nodes.new("ShaderNodeMath")
            node.operation = "MULTIPLY_ADD"
            node.location = (location[0] + 80, location[1] - 120)
            _operands(ng, node, (points, float(column), index))
            at = node.outputs[0]
        sample = nodes.new("GeometryNodeSampleIndex")
        sample.data_type, sample.domain = "FLOAT_VECTOR", "POINT"
        sample.location = (location[0] + 150, location[1])
        position = nodes.new("GeometryNodeInputPosition")
        position.location = (location[0], location[1] - 40)
        links.new(carrier, sample.inputs["Geometry"])
        links.new(position.outputs[0], sample.inputs["Value"])
        links.new(at, sample.inputs["Index"])
        return sample.outputs[0], exists.outputs[0]

    return read


def _build_chain(ng: bpy.types.NodeTree, group_in: bpy.types.Node, read: Reader,
                 y: float) -> bpy.types.NodeSocket:
    """position' = Σ_c x_c·(Motion c) + Motion T where the motion exists, then + Offset (see the module
    doc), the inputs read by `read`; returns the resulting geometry socket. On the geometry's own
    attributes these are the nodes of version 3, so local targets get its results bit for bit, and
    every reader feeds the same arithmetic."""
    nodes, links = ng.nodes, ng.links
    position = nodes.new("GeometryNodeInputPosition")
    position.location = (-700, y + 250)
    separate = nodes.new("ShaderNodeSeparateXYZ")
    separate.location = (-500, y + 250)
    links.new(position.outputs[0], separate.inputs[0])
    columns = [read(group_in.outputs[name], i, (-700, y - 150 * i)) for i, name in enumerate(MOTION_SOCKETS)]
    total = None
    for i, ((value, _exists), coordinate) in enumerate(zip(columns[:3], separate.outputs, strict=True)):
        scale = nodes.new("ShaderNodeVectorMath")
        scale.operation = "SCALE"
        scale.location = (-300, y - 150 * i)
        links.new(value, scale.inputs[0])
        links.new(coordinate, scale.inputs["Scale"])
        if total is None:
            total = scale
        else:
            total = _vector_add(ng, total.outputs[0], scale.outputs[0], (-100, y - 150 * i))
    total = _vector_add(ng, total.outputs[0], columns[3][0], (100, y - 300))
    moved = nodes.new("GeometryNodeSetPosition")
    moved.location = (300, y)
    links.new(group_in.outputs[0], moved.inputs["Geometry"])
    links.new(columns[3][1], moved.inputs["Selection"])
    links.new(total.outputs[0], moved.inputs["Position"])
    offset, _exists = read(group_in.outputs[OFFSET_SOCKET], None, (100, y + 250))
    shifted = nodes.new("GeometryNodeSetPosition")
    shifted.location = (500, y)
    links.new(moved.outputs["Geometry"], shifted.inputs["Geometry"])
    links.new(offset, shifted.inputs["Offset"])
    return shifted.outputs["Geometry"]


def _vector_add(ng: bpy.types.NodeTree, a: bpy.types.NodeSocket, b: bpy.types.NodeSocket,
                location: tuple[float, float]) -> bpy.types.Node:
    node = ng.nodes.new("ShaderNodeVectorMath")
    node.operation = "ADD"
    node.location = location
    ng.links.new(a, node.inputs[0])
    ng.links.new(b, node.inputs[1])
    return node


def find_group() -> bpy.types.NodeTree | None:
    """Our group in this file, preferring one at the current version (a linked one cannot be upgraded,
    and a modifier added here must not depend on what a library holds)."""
    ours = [ng for ng in bpy.data.node_groups if is_editable(ng) and _is_our_group(ng)]
    return next((ng for ng in ours if is_current(ng)), ours[0] if ours else None)


def ensure_group() -> bpy.types.NodeTree:
    """The shared node group at the current version, created or upgraded on first use (works on Blender
    4.2 and 5.0)."""
    ng = find_group()
    if ng is not None:
        upgrade_group(ng)
        return ng
    ng = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    ng[GROUP_MARK] = 1
    ng.is_modifier = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket(OFFSET_SOCKET, in_out="INPUT", socket_type="NodeSocketString")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    upgrade_group(ng)  # one code path for the later inputs and the nodes, new or saved by an older version
    return ng


def find_modifier(obj: bpy.types.Object, offset_attr: str) -> bpy.types.NodesModifier | None:
    """Our modifier on `obj` that reads `offset_attr`, found by content so user renames don't matter."""
    for mod in obj.modifiers:
        if is_modifier_for(mod, offset_attr):
            return mod
    return None


def is_modifier_for(mod: bpy.types.Modifier | None, offset_attr: str) -> bool:
    """`mod` is a Geometry Nodes modifier with our group that reads `offset_attr`."""
    if mod is None or mod.type != "NODES":
        return False
    identifier = _our_offset_identifier(mod.node_group)
    return identifier is not None and modifier_inputs.value(mod, identifier) == offset_attr


def ensure_modifier(obj: bpy.types.Object, offset_attr: str, motion_attrs: tuple[str, ...], label: str,
                    show_viewport: bool = True, show_render: bool = True) -> bpy.types.NodesModifier:
    """Our modifier reading `offset_attr` on `obj` (found, or added at the bottom of the stack), with
    its motion inputs naming `motion_attrs` (storage.motion_names)."""
    mod = find_modifier(obj, offset_attr)
    if mod is None:
        ng = ensure_group()
        mod = obj.modifiers.new(name=label, type="NODES")
        mod.node_group = ng
        modifier_inputs.set_value(mod, offset_socket_identifier(ng), offset_attr)
        mod.show_viewport, mod.show_render = show_viewport, show_render
    set_motion_names(mod, motion_attrs)
    return mod


def remove_modifier(obj: bpy.types.Object, mod: bpy.types.NodesModifier) -> None:
    """Remove a modifier of ours, emptying its ID inputs first: Blender 5.2 and 5.3 keep the users of
    the IDs a removed modifier named (measured on 5.2.4 and 5.3.0), so a probe collection or a carrier
    would look used after its deformer is gone."""
    ng = mod.node_group
    if ng is not None:
        for (_name, socket_type), identifier in _input_identifiers(ng).items():
            if socket_type in ("NodeSocketObject", "NodeSocketCollection"):
                modifier_inputs.set_value(mod, identifier, None)
    obj.modifiers.remove(mod)


def set_motion_names(mod: bpy.types.NodesModifier, motion_attrs: tuple[str, ...]) -> bool:
    """Name the four motion attributes on our modifier's inputs, upgrading its group first when needed.
    True when something changed (the modifier is then tagged for re-evaluation)."""
    ng = mod.node_group
    changed = upgrade_group(ng)
    if changed:
        mod.node_group = ng  # let the modifier pick up the new inputs before they are set
    for name, value in zip(MOTION_SOCKETS, motion_attrs, strict=True):
        identifier = _input_identifier(ng, name, "NodeSocketString")
        changed = modifier_inputs.set_value(mod, identifier, value) or changed
    if changed:
        mod.node_group = ng  # assigning an input does not tag the modifier; re-assigning does
    return changed


def set_offset_name(mod: bpy.types.NodesModifier, offset_attr: str) -> None:
    """Point our modifier at another offset attribute (a deformer that got a new id)."""
    ng = mod.node_group
    modifier_inputs.set_value(mod, offset_socket_identifier(ng), offset_attr)
    mod.node_group = ng


def controls(mod: bpy.types.NodesModifier) -> tuple[bpy.types.Object | None, bpy.types.Collection | None]:
    """(cage, probe collection) named on our modifier's control inputs (None, None before version 2)."""
    identifiers = _our_identifiers(mod.node_group)
    keys = [(name, socket_type) for name, socket_type, _ in CONTROL_SOCKETS]
    if identifiers is None or not all(key in identifiers for key in keys):  # a linked group may be old
        return None, None
    cage = modifier_inputs.value(mod, identifiers[keys[0]])
    probes = modifier_inputs.value(mod, identifiers[keys[1]])
    return (cage if isinstance(cage, bpy.types.Object) else None,
            probes if isinstance(probes, bpy.types.Collection) else None)


def set_controls(mod: bpy.types.NodesModifier, cage: bpy.types.Object | None,
                 probes: bpy.types.Collection | None) -> bool:
    """Name `cage` and `probes` (None = nothing) on our modifier's control inputs, upgrading its group
    first when needed, and have the depsgraph rebuild its relations. True when something changed."""
    ng = mod.node_group
    changed = upgrade_group(ng)
    if changed:
        mod.node_group = ng  # let the modifier pick up the new inputs before they are set
    for (name, socket_type, _), value in zip(CONTROL_SOCKETS, (cage, probes), strict=True):
        identifier = _input_identifier(ng, name, socket_type)
        changed = modifier_inputs.set_value(mod, identifier, value) or changed
    if changed:
        # Assigning an input does not tag the depsgraph relations; re-assigning the group does.
        mod.node_group = ng
    return changed


def reads_positions(mod: bpy.types.NodesModifier | None) -> bool:
    """Whether our modifier's group reads a position carrier named on its carrier input (version 6 on;
    a group of an older version, linked from a library or not upgraded yet, does not)."""
    ng = mod.node_group if mod is not None else None
    version = ng.get(GROUP_MARK) if ng is not None else None
    return (isinstance(version, int) and version >= POSITIONS_SINCE
            and _input_identifier(ng, CARRIER_SOCKET, "NodeSocketObject") is not None)


def has_motion_inputs(mod: bpy.types.NodesModifier) -> bool:
    """Whether our modifier's group applies motions (version 3 on; a group linked from an asset saved
    by an older version may not, and cannot be upgraded here)."""
    ng = mod.node_group
    return ng is not None and all(_input_identifier(ng, name, "NodeSocketString") is not None
                                  for name in MOTION_SOCKETS)


def carrier_of(mod: bpy.types.NodesModifier) -> bpy.types.Object | None:
    """The object named on the carrier input of a modifier of ours (the deformer's, or its input
    modifier: carrier_input.py); None: none, or no such input."""
    ng = mod.node_group
    identifier = _input_identifier(ng, CARRIER_SOCKET, "NodeSocketObject") if ng is not None else None
    value = modifier_inputs.value(mod, identifier)
    return value if isinstance(value, bpy.types.Object) else None


def set_carrier(mod: bpy.types.NodesModifier, carrier: bpy.types.Object | None) -> bool:
    """Name `carrier` (None: nothing) on the carrier input of a modifier of ours; False when its group
    has none."""
    ng = mod.node_group
    identifier = _input_identifier(ng, CARRIER_SOCKET, "NodeSocketObject") if ng is not None else None
    if identifier is None:
        return False
    if modifier_inputs.set_value(mod, identifier, carrier):
        mod.node_group = ng  # assigning an input does not tag the relations; re-assigning does
    return True


def _reader_group(names: list[str]) -> bpy.types.NodeTree:
    """Group storing each named vertex group as a plain FLOAT point attribute (readable by foreach_get)."""
    ng = bpy.data.node_groups.new(_READER_NAME, "GeometryNodeTree")
    ng.is_modifier = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    group_in, group_out = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    geometry = group_in.outputs[0]
    for i, name in enumerate(names):
        named = ng.nodes.new("GeometryNodeInputNamedAttribute")
        named.data_type = "FLOAT"
        named.inputs["Name"].default_value = name
        store = ng.nodes.new("GeometryNodeStoreNamedAttribute")
        store.data_type, store.domain = "FLOAT", "POINT"
        store.inputs["Name"].default_value = _READER_ATTR.format(i)
        ng.links.new(geometry, store.inputs["Geometry"])
        ng.links.new(named.outputs["Attribute"], store.inputs["Value"])
        geometry = store.outputs["Geometry"]
    ng.links.new(geometry, group_out.inputs[0])
    return ng


def vertex_group_weights(obj: bpy.types.Object, names: list[str]) -> np.ndarray:
    """Painted weights (N, len(names)) float64 of the vertex groups `names` on the rest mesh of `obj`.

    Vectorised: a temporary object shares the mesh (vertex groups live on the mesh), carries only a
    Geometry Nodes modifier that stores each group as a named point attribute, and is evaluated once.
    A missing group reads as zeros. Everything temporary is removed again, also on failure.
    """
    mesh = obj.data
    n = len(mesh.vertices)
    out = np.zeros((n, len(names)), dtype=np.float64)
    if not names or n == 0:
        return out
    scene = bpy.context.scene if bpy.context.scene is not None else obj.users_scene[0]
    ng = _reader_group(names)
    tmp = bpy.data.objects.new(".affdef_vertex_group_reader", mesh)
    try:
        tmp.modifiers.new("reader", "NODES").node_group = ng
        scene.collection.objects.link(tmp)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        evaluated = tmp.evaluated_get(depsgraph).data
        if len(evaluated.vertices) != n:
            raise RuntimeError("vertex group reader changed the vertex count")
        column = np.empty(n, dtype=np.float32)
        for i in range(len(names)):
            evaluated.attributes[_READER_ATTR.format(i)].data.foreach_get("value", column)
            out[:, i] = column
    finally:
        bpy.data.objects.remove(tmp, do_unlink=True)
        bpy.data.node_groups.remove(ng)
    return out


def evaluates(obj: bpy.types.Object, attr: str, control: bpy.types.Object,
              depsgraph: bpy.types.Depsgraph) -> bool:
    """Whether `depsgraph` evaluates `control` because a modifier of ours that is enabled in its mode
    (viewport or render) reads the offset attribute `attr` and names `control` on its inputs."""
    return control in named_controls(obj, attr, depsgraph)


def named_controls(obj: bpy.types.Object, attr: str, depsgraph: bpy.types.Depsgraph) -> set:
    """The controls that modifiers of ours enabled in `depsgraph`'s mode (viewport or render) and
    reading the offset attribute `attr` name on their inputs: the target's own, and the one of
    another object sharing its mesh (the bake's stand-in, which keeps the controls evaluated while a
    baked deformer's modifier is muted)."""
    flag = "show_render" if depsgraph.mode == "RENDER" else "show_viewport"
    named: set = set()

    def add(host: bpy.types.Object) -> None:
        mod = find_modifier(host, attr)
        if mod is None or not getattr(mod, flag):
            return
        cage, collection = controls(mod)
        if cage is not None:
            named.add(cage)
        if collection is not None:
            named.update(collection.objects)

    add(obj)
    mesh = obj.data
    if obj.type == "MESH" and mesh.users > 1:
        for other in bpy.data.objects:
            if other.data == mesh and other != obj:
                add(other)
    return named
