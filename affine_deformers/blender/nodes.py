"""Geometry Nodes plumbing: the shared "AffineDeformer" node group, one modifier per deformer, and a
throw-away node evaluation that reads painted vertex-group weights without a loop over vertices.

The group is Group Input (Geometry, "Offset Attribute": String) → Named Attribute (FLOAT_VECTOR) →
Set Position (Offset) → Group Output, so each deformer is a real entry in the modifier stack that adds
the per-vertex offset attribute written by the evaluation handler; the mesh data keeps the rest shape.
"""

from __future__ import annotations

import bpy
import numpy as np

GROUP_NAME = "AffineDeformer"
GROUP_MARK = "affine_deformers_group"  # custom property identifying our group (value = version)
GROUP_VERSION = 1
OFFSET_SOCKET = "Offset Attribute"
_READER_NAME = ".AffineDeformer VertexGroupReader"
_READER_ATTR = "affdef_tmp_vg{}"


def _is_our_group(ng: bpy.types.NodeTree | None) -> bool:
    return (ng is not None and ng.bl_idname == "GeometryNodeTree" and ng.library is None
            and ng.get(GROUP_MARK) == GROUP_VERSION and offset_socket_identifier(ng) is not None)


def offset_socket_identifier(ng: bpy.types.NodeTree) -> str | None:
    """Identifier of the group's string input that names the offset attribute (e.g. "Socket_1")."""
    for item in ng.interface.items_tree:
        if (getattr(item, "item_type", "") == "SOCKET" and item.in_out == "INPUT"
                and item.name == OFFSET_SOCKET and item.socket_type == "NodeSocketString"):
            return item.identifier
    return None


def find_group() -> bpy.types.NodeTree | None:
    for ng in bpy.data.node_groups:
        if _is_our_group(ng):
            return ng
    return None


def ensure_group() -> bpy.types.NodeTree:
    """The shared node group, created on first use (works on Blender 4.2 and 5.0)."""
    ng = find_group()
    if ng is not None:
        return ng
    ng = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    ng[GROUP_MARK] = GROUP_VERSION
    ng.is_modifier = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket(OFFSET_SOCKET, in_out="INPUT", socket_type="NodeSocketString")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = ng.nodes, ng.links
    group_in = nodes.new("NodeGroupInput")
    group_out = nodes.new("NodeGroupOutput")
    named = nodes.new("GeometryNodeInputNamedAttribute")
    named.data_type = "FLOAT_VECTOR"
    set_pos = nodes.new("GeometryNodeSetPosition")
    group_in.location, named.location = (-400, 0), (-200, -150)
    set_pos.location, group_out.location = (0, 0), (200, 0)
    links.new(group_in.outputs[0], set_pos.inputs["Geometry"])
    links.new(group_in.outputs[1], named.inputs["Name"])
    links.new(named.outputs["Attribute"], set_pos.inputs["Offset"])
    links.new(set_pos.outputs["Geometry"], group_out.inputs[0])
    return ng


def find_modifier(obj: bpy.types.Object, offset_attr: str) -> bpy.types.NodesModifier | None:
    """Our modifier on `obj` that reads `offset_attr`, found by content so user renames don't matter."""
    for mod in obj.modifiers:
        if mod.type != "NODES" or not _is_our_group(mod.node_group):
            continue
        if mod.get(offset_socket_identifier(mod.node_group)) == offset_attr:
            return mod
    return None


def ensure_modifier(obj: bpy.types.Object, offset_attr: str, label: str,
                    show_viewport: bool = True, show_render: bool = True) -> bpy.types.NodesModifier:
    mod = find_modifier(obj, offset_attr)
    if mod is not None:
        return mod
    ng = ensure_group()
    mod = obj.modifiers.new(name=label, type="NODES")
    mod.node_group = ng
    mod[offset_socket_identifier(ng)] = offset_attr
    mod.show_viewport, mod.show_render = show_viewport, show_render
    return mod


def remove_modifier(obj: bpy.types.Object, offset_attr: str) -> None:
    mod = find_modifier(obj, offset_attr)
    if mod is not None:
        obj.modifiers.remove(mod)


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
