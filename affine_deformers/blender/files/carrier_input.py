"""The input modifier of a library override's deformer: its carrier's output copied onto the mesh at
the top of the stack, so the modifiers before ours carry it as they carry the asset's own.

A deformer of a library override writes its per-frame output to a local carrier object (carrier.py):
one point per vertex of the linked mesh. Our modifier could read it by point index only when the
geometry reaching it still has the mesh's vertices in their order; after a Mirror, a Subdivision
Surface, an Array, a Bevel, a Solidify or a Weld it has more, fewer or other points, and reading by
index tore the mesh. In the asset file the output lives on the mesh, and those modifiers interpolate
or copy it onto the points they make. The override gets exactly that: one Geometry Nodes modifier
per deformer, inserted first in the stack (a local insertion, which a library override keeps at its
place through save and reload on 4.2, 4.5 and 5.0), stores the carrier's attributes on the mesh's
points by index before any other modifier runs. From there on the stack evaluates as in the asset,
bit for bit: our modifier reads the geometry's own attributes (its carrier input stays empty).

The group ("AffineDeformer Input") derives every attribute name from the deformer's offset
attribute name (the motion columns and the frame stamp, storage.py), copies each the carrier holds
and removes each it does not (the linked mesh may hold a stale output saved in the asset, which the
other output form must not meet), and passes its input through when no carrier is named or it has
no points.
"""

from __future__ import annotations

import bpy

from . import modifier_inputs, nodes, storage

GROUP_NAME = "AffineDeformer Input"
GROUP_MARK = "affine_deformers_input"  # custom property identifying the group (value = version)
GROUP_VERSION = 2
#: 1: the copy chain; 2: an attribute is removed only where the geometry has it (Remove Named
#: Attribute warns "Attribute does not exist" on the modifier otherwise, on every working override).
KNOWN_VERSIONS = (1, 2)
MODIFIER_NAME = "{} Input"
#: (suffix of the attribute name in place of "_offset", data type) of every output attribute.
_ATTRIBUTES = (("_offset", "FLOAT_VECTOR"),
               *((f"_{suffix}", "FLOAT_VECTOR") for suffix in storage.MOTION_SUFFIXES),
               ("_frame", "FLOAT"))


def _is_group(ng: bpy.types.NodeTree | None) -> bool:
    """Our input group, of the current or an older version (an older one still copies; see
    `ensure_group`)."""
    return ng is not None and ng.bl_idname == "GeometryNodeTree" and ng.get(GROUP_MARK) in KNOWN_VERSIONS


def ensure_group() -> bpy.types.NodeTree:
    """The input group of this file at the current version: made when missing, rebuilt in place when an
    older version saved it (its modifiers keep their inputs)."""
    found = next((ng for ng in bpy.data.node_groups if _is_group(ng) and nodes.is_editable(ng)), None)
    if found is not None:
        upgrade_group(found)
        return found
    ng = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    ng.is_modifier = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    for name, socket_type, description in (
            (nodes.OFFSET_SOCKET, "NodeSocketString", "The deformer's offset attribute: the names of its "
                                                      "other outputs derive from it (set by the add-on)"),
            (nodes.CARRIER_SOCKET, "NodeSocketObject", "The local object holding the deformer's per-frame "
                                                       "output (set by the add-on)")):
        socket = ng.interface.new_socket(name, in_out="INPUT", socket_type=socket_type)
        socket.description = description
        socket.hide_in_modifier = True
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    _build_nodes(ng)
    ng[GROUP_MARK] = GROUP_VERSION
    return ng


def upgrade_group(ng: bpy.types.NodeTree) -> bool:
    """Rebuild an input group of an older version in place (its modifiers keep their inputs); a linked
    one is left as it is. True when it changed."""
    if not _is_group(ng) or ng.get(GROUP_MARK) == GROUP_VERSION or not nodes.is_editable(ng):
        return False
    ng.nodes.clear()
    _build_nodes(ng)
    ng[GROUP_MARK] = GROUP_VERSION
    return True


def _name_socket(ng: bpy.types.NodeTree, offset_name: bpy.types.NodeSocket, suffix: str,
                 location: tuple[float, float]) -> bpy.types.NodeSocket:
    """The attribute name with `suffix` in place of "_offset" (and hidden: a leading dot) — the names of
    storage.motion_names and storage.frame_name; the offset attribute's own name for "_offset"."""
    if suffix == "_offset":
        return offset_name
    socket = offset_name
    for i, (find, replace) in enumerate((("affdef_", ".affdef_"), ("_offset", suffix))):
        node = ng.nodes.new("FunctionNodeReplaceString")
        node.location = (location[0] + 180 * i, location[1])
        ng.links.new(socket, node.inputs["String"])
        node.inputs["Find"].default_value, node.inputs["Replace"].default_value = find, replace
        socket = node.outputs[0]
    return socket


def _copy(ng: bpy.types.NodeTree, geometry: bpy.types.NodeSocket, carrier: bpy.types.NodeSocket,
          index: bpy.types.NodeSocket, name: bpy.types.NodeSocket, data_type: str,
          location: tuple[float, float]) -> bpy.types.NodeSocket:
    """`geometry` with the carrier's point attribute `name` stored by point index when the carrier has
    it, else with any attribute of that name removed."""
    x, y = location
    named = ng.nodes.new("GeometryNodeInputNamedAttribute")
    named.data_type = data_type
    named.location = (x, y)
    ng.links.new(name, named.inputs["Name"])
    exists = ng.nodes.new("GeometryNodeSampleIndex")  # a single value: no index field linked
    exists.data_type, exists.domain = "BOOLEAN", "POINT"
    exists.location = (x + 180, y + 80)
    ng.links.new(carrier, exists.inputs["Geometry"])
    ng.links.new(named.outputs["Exists"], exists.inputs["Value"])
    value = ng.nodes.new("GeometryNodeSampleIndex")
    value.data_type, value.domain = data_type, "POINT"
    value.location = (x + 180, y - 80)
    ng.links.new(carrier, value.inputs["Geometry"])
    ng.links.new(named.outputs["Attribute"], value.inputs["Value"])
    ng.links.new(index, value.inputs["Index"])
    store = ng.nodes.new("GeometryNodeStoreNamedAttribute")
    store.data_type, store.domain = data_type, "POINT"
    store.location = (x + 360, y - 80)
    ng.links.new(geometry, store.inputs["Geometry"])
    ng.links.new(name, store.inputs["Name"])
    ng.links.new(value.outputs[0], store.inputs["Value"])
    remove = ng.nodes.new("GeometryNodeRemoveAttribute")
    remove.location = (x + 360, y + 80)
    ng.links.new(geometry, remove.inputs["Geometry"])
    ng.links.new(name, remove.inputs["Name"])
    # Remove only what is there: Remove Named Attribute warns on the modifier when it finds nothing, and
    # the lazy Switch does not evaluate it then.
    here = ng.nodes.new("GeometryNodeSampleIndex")  # a single value: does the geometry have it?
    here.data_type, here.domain = "BOOLEAN", "POINT"
    here.location = (x + 180, y + 240)
    ng.links.new(geometry, here.inputs["Geometry"])
    ng.links.new(named.outputs["Exists"], here.inputs["Value"])
    removed = _geometry_switch(ng, here.outputs[0], geometry, remove.outputs[0], (x + 450, y + 160))
    return _geometry_switch(ng, exists.outputs[0], removed, store.outputs[0], (x + 540, y))


def _geometry_switch(ng: bpy.types.NodeTree, condition: bpy.types.NodeSocket, false: bpy.types.NodeSocket,
                     true: bpy.types.NodeSocket, location: tuple[float, float]) -> bpy.types.NodeSocket:
    switch = ng.nodes.new("GeometryNodeSwitch")
    switch.input_type = "GEOMETRY"
    switch.location = location
    ng.links.new(condition, switch.inputs["Switch"])
    ng.links.new(false, switch.inputs["False"])
    ng.links.new(true, switch.inputs["True"])
    return switch.outputs[0]


def _build_nodes(ng: bpy.types.NodeTree) -> None:
    """The copy chain of every output attribute, run only when the carrier has points."""
    group_in, group_out = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    group_in.location = (-900, 0)
    info = ng.nodes.new("GeometryNodeObjectInfo")
    info.transform_space = "ORIGINAL"  # only the carrier's attributes are read
    info.location = (-700, -300)
    ng.links.new(group_in.outputs[nodes.CARRIER_SOCKET], info.inputs["Object"])
    carrier = info.outputs["Geometry"]
    index = ng.nodes.new("GeometryNodeInputIndex")
    index.location = (-700, -450)
    geometry = group_in.outputs[0]
    for i, (suffix, data_type) in enumerate(_ATTRIBUTES):
        name = _name_socket(ng, group_in.outputs[nodes.OFFSET_SOCKET], suffix, (-700, 300 * i))
        geometry = _copy(ng, geometry, carrier, index.outputs[0], name, data_type, (-300, 300 * i))
    size = ng.nodes.new("GeometryNodeAttributeDomainSize")
    size.component = "MESH"
    size.location = (-500, -600)
    ng.links.new(carrier, size.inputs[0])
    has_points = ng.nodes.new("FunctionNodeCompare")
    has_points.data_type, has_points.operation = "FLOAT", "GREATER_THAN"
    has_points.location = (-300, -600)
    ng.links.new(size.outputs["Point Count"], has_points.inputs[0])
    has_points.inputs[1].default_value = 0.5
    shown = _geometry_switch(ng, has_points.outputs[0], group_in.outputs[0], geometry, (500, 0))
    group_out.location = (700, 0)
    ng.links.new(shown, group_out.inputs[0])


def is_input_modifier(mod: bpy.types.Modifier) -> bool:
    return mod.type == "NODES" and _is_group(mod.node_group)


def offset_of(mod: bpy.types.Modifier) -> str:
    """The offset attribute an input modifier copies for ('' when `mod` is not one)."""
    if not is_input_modifier(mod):
        return ""
    identifier = nodes.offset_socket_identifier(mod.node_group)
    value = modifier_inputs.value(mod, identifier)
    return value if isinstance(value, str) else ""


def ensure_modifier(obj: bpy.types.Object, offset_attr: str, carrier: bpy.types.Object,
                    label: str) -> bpy.types.NodesModifier:
    """The input modifier of the deformer whose offset attribute is `offset_attr` on `obj`, first in the
    stack, naming `carrier` (made, moved and set when needed)."""
    mod = next((m for m in obj.modifiers if offset_of(m) == offset_attr), None)
    if mod is None:
        ng = ensure_group()
        mod = obj.modifiers.new(name=MODIFIER_NAME.format(label), type="NODES")
        mod.node_group = ng
        modifier_inputs.set_value(mod, nodes.offset_socket_identifier(ng), offset_attr)
        mod.show_expanded = False
    if obj.modifiers[0] != mod:
        obj.modifiers.move(list(obj.modifiers).index(mod), 0)
    nodes.set_carrier(mod, carrier)
    return mod


def remove_stale(obj: bpy.types.Object, offset_attrs: set[str]) -> None:
    """Remove the input modifiers on `obj` of deformers that are gone (not in `offset_attrs`)."""
    for mod in [m for m in obj.modifiers if is_input_modifier(m) and offset_of(m) not in offset_attrs]:
        if not mod.is_override_data:  # only our local insertions; anything from the library stays
            nodes.remove_modifier(obj, mod)

