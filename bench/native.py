"""Blender's own deformers set up like ours: Hook (smooth falloff), Armature (Preserve Volume), Mesh Deform,
and a chain of bones skinning the target through vertex groups (for the Armature modifier and ours).

Each builder takes a target mesh object that is already in the scene, adds the controls and the modifier(s)
and returns a `Rig`: the object to read back and a `move(i)` that changes one control differently for every
rep index i. Nothing here depends on the Affine Deformers extension.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import bpy
import numpy as np
from common import chain_weights, link_object, rest_positions, wiggle
from mathutils import Vector

# Vertex-group weights are written one distinct value at a time (VertexGroup.add takes a list of
# indices and ONE weight); quantising to this many levels keeps that to a few thousand calls while the
# error (< 1/(2·levels)) is far below anything that could change the timing.
WEIGHT_LEVELS = 4096


@dataclass
class Rig:
    """A deformed object plus the one control the benchmark moves."""

    target: bpy.types.Object
    move: Callable[[int], None]
    setup_seconds: float  # building + binding, not part of the per-update time
    bind_seconds: float | None = None  # the bind step alone, where the method has one


def add_empties(sites: np.ndarray, prefix: str = "Probe") -> list[bpy.types.Object]:
    empties = []
    for i, p in enumerate(sites):
        e = link_object(f"{prefix}.{i:03d}", None)
        e.empty_display_type = "SPHERE"
        e.empty_display_size = 0.1
        e.location = tuple(float(x) for x in p)
        empties.append(e)
    bpy.context.view_layer.update()
    return empties


def move_object(ob: bpy.types.Object) -> Callable[[int], None]:
    """move(i): give `ob` a new small translation + rotation about its rest placement."""
    base = Vector(ob.location)
    base_rot = Vector(ob.rotation_euler)

    def move(i: int) -> None:
        dt, dr = wiggle(i)
        ob.location = base + Vector(dt)
        ob.rotation_euler = base_rot + Vector(dr)

    return move


def move_objects(objects: list[bpy.types.Object]) -> Callable[[int], None]:
    """move(i): give every object of `objects` its own new small translation + rotation."""
    moves = [move_object(ob) for ob in objects]

    def move(i: int) -> None:
        for j, mv in enumerate(moves):
            mv(i * len(moves) + j)

    return move


def hooks(target: bpy.types.Object, empties: list[bpy.types.Object], radius: float) -> Rig:
    """One Hook modifier per Empty, Smooth falloff of `radius`, acting on every vertex."""
    t0 = time.perf_counter()
    everything = range(len(target.data.vertices))
    world_to_local = target.matrix_world.inverted()
    for i, e in enumerate(empties):
        mod = target.modifiers.new(f"Hook.{i:03d}", "HOOK")
        mod.object = e
        # Without assigned vertices (indices or a group) a Hook modifier moves nothing at all.
        mod.vertex_indices_set(everything)
        mod.falloff_type = "SMOOTH"
        mod.falloff_radius = radius
        mod.center = world_to_local @ e.matrix_world.translation
        # Rest pose = identity: the hook applies (hook world matrix) · matrix_inverse.
        mod.matrix_inverse = (world_to_local @ e.matrix_world).inverted()
    bpy.context.view_layer.update()
    return Rig(target, move_object(empties[0]), time.perf_counter() - t0)


def assign_vertex_group(ob: bpy.types.Object, name: str, weights: np.ndarray) -> None:
    """Vertex group `name` with the given per-vertex weights (zeros are left out of the group)."""
    vg = ob.vertex_groups.new(name=name)
    level = np.rint(np.clip(weights, 0.0, 1.0) * WEIGHT_LEVELS).astype(np.int64)
    nz = np.flatnonzero(level)
    if nz.size == 0:
        return
    order = nz[np.argsort(level[nz], kind="stable")]
    values, starts = np.unique(level[order], return_index=True)
    bounds = [*starts.tolist(), order.size]
    for k, value in enumerate(values.tolist()):
        vg.add(order[bounds[k] : bounds[k + 1]].tolist(), value / WEIGHT_LEVELS, "REPLACE")


def armature(
    target: bpy.types.Object, sites: np.ndarray, weights: np.ndarray, preserve_volume: bool = True
) -> Rig:
    """An Armature with one small bone per site, vertex groups from `weights` (N, m), Preserve Volume."""
    t0 = time.perf_counter()
    arm_data = bpy.data.armatures.new("Rig")
    arm = link_object("Rig", arm_data)
    # Edit bones exist only in edit mode, and mode_set acts on the view layer's active object.
    previous_active = bpy.context.view_layer.objects.active
    bpy.context.view_layer.objects.active = arm
    bpy.context.view_layer.update()
    with bpy.context.temp_override(active_object=arm, object=arm, selected_objects=[arm]):
        bpy.ops.object.mode_set(mode="EDIT")
        for i, p in enumerate(sites):
            bone = arm_data.edit_bones.new(f"Bone.{i:03d}")
            head = Vector(tuple(float(x) for x in p))
            bone.head = head
            bone.tail = head + 0.15 * head.normalized() if head.length > 1e-9 else head + Vector((0, 0, 0.15))
        bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.objects.active = previous_active
    for i in range(sites.shape[0]):
        assign_vertex_group(target, f"Bone.{i:03d}", weights[:, i])
    mod = target.modifiers.new("Armature", "ARMATURE")
    mod.object = arm
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    mod.use_deform_preserve_volume = preserve_volume
    bpy.context.view_layer.update()

    pose_bone = arm.pose.bones[0]
    pose_bone.rotation_mode = "XYZ"

    def move(i: int) -> None:
        dt, dr = wiggle(i)
        pose_bone.location = dt
        pose_bone.rotation_euler = dr

    return Rig(target, move, time.perf_counter() - t0)


def bone_chain(target: bpy.types.Object, m: int, with_modifier: bool, preserve_volume: bool = True
               ) -> bpy.types.Object:
    """An armature with a chain of `m` connected bones Chain.000, … up the target's Z axis (−1 to 1, the
    unit sphere's poles) and vertex groups named after them holding `common.chain_weights` of the
    height; with `with_modifier` an Armature modifier (vertex groups, Preserve Volume or not) skins the
    target with it. Returns the armature object."""
    arm_data = bpy.data.armatures.new("Chain")
    arm = link_object("Chain", arm_data)
    previous_active = bpy.context.view_layer.objects.active
    bpy.context.view_layer.objects.active = arm
    bpy.context.view_layer.update()
    heads = np.linspace(-1.0, 1.0, m + 1)
    with bpy.context.temp_override(active_object=arm, object=arm, selected_objects=[arm]):
        bpy.ops.object.mode_set(mode="EDIT")
        parent = None
        for i in range(m):
            bone = arm_data.edit_bones.new(f"Chain.{i:03d}")
            bone.head, bone.tail = (0.0, 0.0, float(heads[i])), (0.0, 0.0, float(heads[i + 1]))
            if parent is not None:
                bone.parent, bone.use_connect = parent, True
            parent = bone
        bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.objects.active = previous_active
    weights = chain_weights(0.5 * (rest_positions(target)[:, 2] + 1.0), m)
    for i in range(m):
        assign_vertex_group(target, f"Chain.{i:03d}", weights[:, i])
    if with_modifier:
        mod = target.modifiers.new("Armature", "ARMATURE")
        mod.object = arm
        mod.use_vertex_groups = True
        mod.use_bone_envelopes = False
        mod.use_deform_preserve_volume = preserve_volume
    for pose_bone in arm.pose.bones:
        pose_bone.rotation_mode = "XYZ"
    bpy.context.view_layer.update()
    return arm


def move_bones(arm: bpy.types.Object, which: list[int]) -> Callable[[int], None]:
    """move(i): give each pose bone of `which` its own new small rotation (the bones are connected, so
    a pose location would be ignored); a bone's children follow it, as in any chain."""
    bones = [arm.pose.bones[k] for k in which]

    def move(i: int) -> None:
        for j, pose_bone in enumerate(bones):
            _, dr = wiggle(i * len(bones) + j)
            pose_bone.rotation_euler = dr

    return move


def move_cage_vertex(cage: bpy.types.Object, index: int = 0) -> Callable[[int], None]:
    """move(i): push one cage vertex to a new spot near its rest position."""
    me = cage.data
    base = Vector(me.vertices[index].co)

    def move(i: int) -> None:
        dt, _ = wiggle(i)
        me.vertices[index].co = base + 2.0 * Vector(dt)
        me.update()

    return move


def mesh_deform(target: bpy.types.Object, cage: bpy.types.Object, precision: int = 5) -> Rig:
    """Mesh Deform bound to `cage` at `precision`; `bind_seconds` is the bind operator alone."""
    t0 = time.perf_counter()
    mod = target.modifiers.new("MeshDeform", "MESH_DEFORM")
    mod.object = cage
    mod.precision = precision
    bpy.context.view_layer.update()
    tb = time.perf_counter()
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        result = bpy.ops.object.meshdeform_bind(modifier=mod.name)
    bpy.context.view_layer.update()
    bind = time.perf_counter() - tb
    if "FINISHED" not in result or not mod.is_bound:
        raise RuntimeError(f"Mesh Deform bind did not finish ({result}, is_bound={mod.is_bound})")
    return Rig(target, move_cage_vertex(cage), time.perf_counter() - t0, bind_seconds=bind)
