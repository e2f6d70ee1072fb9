"""(w) The write paths tried for a deformer's per-frame output, each as a floor: a handler that only
writes a changing offset for every vertex (nothing read, nothing computed) and a minimal Geometry Nodes
modifier that adds it, so the rows show what Blender charges for each way of handing data to a
modifier — the choice made in output_store.py and read_ahead.py stays visible.

Paths (each written ahead of the frame's evaluation, in frame_change_pre, unless it says after):
mesh attribute (after: what every frame cost before read-ahead; and ahead); position carrier
(`vertices.foreach_set("co")` on a hidden mesh read by Object Info + Sample Index; after and ahead);
a carrier's attribute; a float image read by Image Texture (Closest); a legacy curve's points.
Two scenes: a ~5,000-vertex mesh beside 5,000 other objects (the visibility re-flush dominates) and a
~80,000-vertex mesh alone (the per-point cost of the write dominates). Nothing here uses the add-on.
"""

from __future__ import annotations

import importlib
import time
import traceback

import bpy
import common
import native
import numpy as np
import ours
from common import Samples, Table, fmt_ms, fmt_ratio

FRAMES = 16
IMAGE_WIDTH = 1024


def _group(name: str) -> tuple[bpy.types.NodeTree, bpy.types.Node, bpy.types.Node]:
    """A modifier group with a Geometry and an Object input; returns (group, input node, Set Position)."""
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.is_modifier = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Carrier", in_out="INPUT", socket_type="NodeSocketObject")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    group_in, group_out = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    move = ng.nodes.new("GeometryNodeSetPosition")
    ng.links.new(group_in.outputs[0], move.inputs["Geometry"])
    ng.links.new(move.outputs[0], group_out.inputs[0])
    return ng, group_in, move


def _sampled(ng, group_in, move, value_node_output) -> None:
    """Offset = the carrier's `value` at the same point index (Object Info + Sample Index)."""
    info = ng.nodes.new("GeometryNodeObjectInfo")
    info.transform_space = "ORIGINAL"
    ng.links.new(group_in.outputs[1], info.inputs["Object"])
    sample = ng.nodes.new("GeometryNodeSampleIndex")
    sample.data_type, sample.domain = "FLOAT_VECTOR", "POINT"
    ng.links.new(info.outputs["Geometry"], sample.inputs["Geometry"])
    ng.links.new(value_node_output, sample.inputs["Value"])
    ng.links.new(ng.nodes.new("GeometryNodeInputIndex").outputs[0], sample.inputs["Index"])
    ng.links.new(sample.outputs[0], move.inputs["Offset"])


def _named(ng, name: str):
    node = ng.nodes.new("GeometryNodeInputNamedAttribute")
    node.data_type = "FLOAT_VECTOR"
    node.inputs["Name"].default_value = name
    return node.outputs["Attribute"]


def _modifier(target, ng, carrier=None) -> None:
    mod = target.modifiers.new("Floor", "NODES")
    mod.node_group = ng
    if carrier is not None:
        inputs = importlib.import_module(f"{ours.INNER}.blender.files.modifier_inputs")
        inputs.set_value(mod, "Socket_1", carrier)
        mod.node_group = ng  # re-assigned: the relation to the carrier is built


def _values(n: int, scene) -> np.ndarray:
    return np.full((n, 3), 1e-3 * (scene.frame_current % 7 + 1), dtype=np.float32)


def _mesh_attribute(target, n):
    ng, _group_in, move = _group("Floor attribute")
    ng.links.new(_named(ng, "floor"), move.inputs["Offset"])
    _modifier(target, ng)
    target.data.attributes.new("floor", "FLOAT_VECTOR", "POINT")
    def write(scene):
        target.data.attributes["floor"].data.foreach_set("vector", _values(n, scene).ravel())
        target.data.update_tag()  # as the add-on does: Blender 4.2 does not tag on the write itself

    return write


def _positions(target, n):
    ng, group_in, move = _group("Floor positions")
    _sampled(ng, group_in, move, ng.nodes.new("GeometryNodeInputPosition").outputs[0])
    mesh = bpy.data.meshes.new(".Floor carrier")
    mesh.vertices.add(n)
    _modifier(target, ng, bpy.data.objects.new(".Floor carrier", mesh))
    return lambda scene: mesh.vertices.foreach_set("co", _values(n, scene).ravel())


def _carrier_attribute(target, n):
    ng, group_in, move = _group("Floor carrier attribute")
    _sampled(ng, group_in, move, _named(ng, "floor"))
    mesh = bpy.data.meshes.new(".Floor carrier")
    mesh.vertices.add(n)
    mesh.attributes.new("floor", "FLOAT_VECTOR", "POINT")
    _modifier(target, ng, bpy.data.objects.new(".Floor carrier", mesh))
    return lambda scene: mesh.attributes["floor"].data.foreach_set("vector", _values(n, scene).ravel())


def _image(target, n):
    height = (n + IMAGE_WIDTH - 1) // IMAGE_WIDTH
    image = bpy.data.images.new(".Floor image", IMAGE_WIDTH, height, alpha=True, float_buffer=True)
    image.colorspace_settings.name = "Non-Color"
    image.alpha_mode = "CHANNEL_PACKED"
    ng, _group_in, move = _group("Floor image")
    texture = ng.nodes.new("GeometryNodeImageTexture")
    texture.interpolation, texture.extension = "Closest", "EXTEND"
    texture.inputs["Image"].default_value = image

    def math(operation, a, b):
        node = ng.nodes.new("ShaderNodeMath")
        node.operation = operation
        for socket, value in zip(node.inputs, (a, b), strict=False):
            if isinstance(value, bpy.types.NodeSocket):
                ng.links.new(value, socket)
            else:
                socket.default_value = value
        return node.outputs[0]

    index = ng.nodes.new("GeometryNodeInputIndex").outputs[0]
    u = math("DIVIDE", math("ADD", math("FLOORED_MODULO", index, IMAGE_WIDTH), 0.5), IMAGE_WIDTH)
    v = math("DIVIDE", math("ADD", math("FLOOR", math("DIVIDE", index, IMAGE_WIDTH), 0), 0.5), height)
    uv = ng.nodes.new("ShaderNodeCombineXYZ")
    ng.links.new(u, uv.inputs[0])
    ng.links.new(v, uv.inputs[1])
    ng.links.new(uv.outputs[0], texture.inputs["Vector"])
    ng.links.new(texture.outputs["Color"], move.inputs["Offset"])
    _modifier(target, ng)
    pixels = np.ones((IMAGE_WIDTH * height, 4), dtype=np.float32)

    def write(scene):
        pixels[:n, :3] = _values(n, scene)
        image.pixels.foreach_set(pixels.ravel())
        image.update_tag()  # without a tag the modifier does not see the change

    return write


def _curve(target, n):
    ng, group_in, move = _group("Floor curve")
    _sampled(ng, group_in, move, ng.nodes.new("GeometryNodeInputPosition").outputs[0])
    curve = bpy.data.curves.new(".Floor curve", "CURVE")
    curve.dimensions = "3D"
    spline = curve.splines.new("POLY")
    spline.points.add(n - 1)
    _modifier(target, ng, bpy.data.objects.new(".Floor curve", curve))
    points = np.ones((n, 4), dtype=np.float32)

    def write(scene):
        points[:, :3] = _values(n, scene)
        spline.points.foreach_set("co", points.ravel())

    return write


PATHS = (
    ("mesh attribute, after the frame", _mesh_attribute, "post"),
    ("mesh attribute, ahead", _mesh_attribute, "pre"),
    ("position carrier, after the frame", _positions, "post"),
    ("position carrier, ahead", _positions, "pre"),
    ("a carrier's attribute, ahead", _carrier_attribute, "pre"),
    ("float image (Image Texture), ahead", _image, "pre"),
    ("legacy curve points, ahead", _curve, "pre"),
)


def _floor(n_target: int, others: int, make, phase: str | None) -> Samples:
    """Seconds per frame of frame_set + settle with `make`'s writer run in frame_change_`phase`
    (None: Hooks on 4 keyed Empties instead)."""
    scene = bpy.context.scene
    if others:
        crowd = bpy.data.collections.new("Others")
        scene.collection.children.link(crowd)
        for i in range(others):
            crowd.objects.link(bpy.data.objects.new(f"Other.{i:05d}", None))
    target = common.sphere_object("Target", n_target)
    empties = native.add_empties(common.probe_sites(4))
    for j, empty in enumerate(empties):
        for frame in range(1, FRAMES + 1):
            empty.location.z = 0.05 * np.sin(frame + j)
            empty.keyframe_insert("location", frame=frame)
    handlers = []
    if phase is None:
        native.hooks(target, empties, 1.0)
    else:
        write = make(target, len(target.data.vertices))

        def handler(scn, _depsgraph=None):
            write(scn)

        handlers = getattr(bpy.app.handlers, f"frame_change_{phase}")
        handlers.append(handler)
    try:
        for frame in (1, 2, 1):
            scene.frame_set(frame)
            common.settle()
        out = Samples()
        before = common.evaluated_positions(target)
        for frame in range(2, FRAMES + 1):
            t0 = time.perf_counter()
            scene.frame_set(frame)
            common.settle()
            out.seconds.append(time.perf_counter() - t0)
            now = common.evaluated_positions(target)
            if phase is not None and np.array_equal(now, before):
                out.stale += 1
            before = now
        return out
    finally:
        if phase is not None:
            handlers.remove(handler)


def part_w_paths(plan, report) -> None:
    cases = ((plan.w_verts, plan.w_others[-2] if len(plan.w_others) > 1 else 0), (plan.w_paths_verts, 0))
    table = Table("(w) write paths, each as a floor: a handler that only writes an offset for every vertex "
                  f"({FRAMES} frames)", ["scene", "path", "per frame", "÷ Hooks", "check"])
    for n_target, others in cases:
        label = f"~{n_target:,} vertices beside {others:,} objects"
        print(f"(w) write paths: {label}", flush=True)
        rows = []
        for name, make, phase in (("Hook ×4 (nothing written)", None, None), *PATHS):
            try:
                samples = _floor(n_target, others, make, phase)
                rows.append((name, samples))
                print(f"  {name:<40} {fmt_ms(samples.median):>9}", flush=True)
            except Exception as exc:  # one broken path must not hide the others
                traceback.print_exc()
                report.problems.append(f"(w) write path {name}: {type(exc).__name__}: {exc}")
            finally:
                common.clear_scene()
        hooks = rows[0][1] if rows else None
        for name, samples in rows:
            ratio = fmt_ratio(samples.median, hooks.median) if hooks is not None else "—"
            check = f"{samples.stale} stale" if samples.stale else ""
            if samples.stale:  # a finding, not a broken measurement: the path does not work here
                report.notes.append(f"(w) write path {name}: {samples.stale} frames changed nothing on "
                                    f"Blender {bpy.app.version_string}: the write is not seen")
            table.add(label, name, fmt_ms(samples.median), ratio, check)
    table.notes.append("ahead: written in frame_change_pre, applied by the frame's own evaluation; after: "
                       "written in frame_change_post, applied by a second evaluation (settle)")
    report.tables.append(table)
