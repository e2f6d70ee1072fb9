"""Depsgraph relations from a deformed mesh to its controls (cage, probes).

Blender evaluates an object only when it is visible or something visible depends on it, and nothing
made the target depend on its controls: a cage or probe disabled in viewports (or in renders) kept a
stale evaluated copy, so the deformer read old transforms and shapes, or had to refuse. Each
deformer's modifier now names its controls on the shared group's inputs (nodes.CAGE_SOCKET, an
Object; nodes.PROBES_SOCKET, a Collection). Geometry Nodes adds a depsgraph relation for every ID set
on a modifier's inputs, whether or not a node reads it (object: transform and geometry; collection:
its objects' transforms and geometry), so while the modifier is enabled the controls are evaluated
with the target, in the viewport and in renders.

The probes of a deformer are held by a collection of its own, named PROBES_NAME, marked with
PROBES_MARK and linked to no scene (the Collection input is the only way to name a changing number of
objects on one shared node group). `sync` keeps it and the inputs in step with the deformer; it is
called at bind / re-weight, when a control is picked or cleared, and for every deformer when a file is
loaded (which also upgrades node groups saved by older versions, see nodes.upgrade_group).
"""

from __future__ import annotations

import bpy

from . import kinds, nodes, storage

PROBES_NAME = ".AffineDeformer Probes"
PROBES_MARK = "affine_deformers_probes"  # custom property on the probe collections we own


def _is_ours(collection: bpy.types.Collection | None) -> bool:
    return collection is not None and collection.library is None and bool(collection.get(PROBES_MARK))


def _wanted(obj: bpy.types.Object, deformer) -> tuple[bpy.types.Object | None, list[bpy.types.Object]]:
    """(object, collection members) the deformer's modifier should name: a kind with one control
    object (a cage) names it on the Object input, others (probes) put theirs in the collection; the
    target itself never."""
    kind = kinds.get(deformer.kind)
    controls = kind.controls(obj, deformer) if kind is not None else []
    if kind is not None and kind.single_control:
        return (controls[0] if controls else None), []
    return None, controls


def _probe_collection(current: bpy.types.Collection | None,
                      probes: list[bpy.types.Object]) -> bpy.types.Collection | None:
    """A collection of ours holding exactly `probes` (None when there are none): `current` when it is
    ours and no other modifier uses it (a duplicated object shares its modifier's collection until
    either is synced), else a new one."""
    if not probes:
        return None
    collection = current if _is_ours(current) and current.users <= 1 else None
    if collection is None:
        collection = bpy.data.collections.new(PROBES_NAME)
        collection[PROBES_MARK] = True
    held = set(collection.objects)
    wanted = set(probes)
    # Linking and unlinking objects tags the depsgraph relations by itself.
    for probe in held - wanted:
        collection.objects.unlink(probe)
    for probe in wanted - held:
        collection.objects.link(probe)
    return collection


def _drop_if_unused(collection: bpy.types.Collection | None) -> None:
    if _is_ours(collection) and collection.users == 0:
        bpy.data.collections.remove(collection)


def sync(obj: bpy.types.Object, deformer) -> bool:
    """Name the deformer's current controls on its modifier (nothing to do without one). True when
    the relations changed (the caller may then want a freshly evaluated depsgraph)."""
    mod = nodes.find_modifier(obj, storage.offset_name(deformer.uid)) if deformer.uid else None
    if mod is None:
        return False
    cage, probes = _wanted(obj, deformer)
    _old_cage, old_collection = nodes.controls(mod)
    held = set(old_collection.objects) if old_collection is not None else set()
    collection = _probe_collection(old_collection, probes)
    changed = nodes.set_controls(mod, cage, collection)
    changed = nodes.set_motion_names(mod, storage.motion_names(deformer.uid)) or changed
    if old_collection is not None and old_collection != collection:
        _drop_if_unused(old_collection)
    return changed or (collection is not None and set(collection.objects) != held)


def remove_modifier(obj: bpy.types.Object, uid: str) -> None:
    """Remove deformer `uid`'s modifier, and its probe collection once nothing uses it."""
    mod = nodes.find_modifier(obj, storage.offset_name(uid))
    if mod is None:
        return
    _cage, collection = nodes.controls(mod)
    obj.modifiers.remove(mod)
    _drop_if_unused(collection)


def copy_controls(source: bpy.types.NodesModifier | None, target: bpy.types.NodesModifier) -> None:
    """Give `target` (e.g. the bake's stand-in modifier) the control inputs of `source`, so the
    controls are evaluated with it even while `source` is muted."""
    if source is not None:
        nodes.set_controls(target, *nodes.controls(source))


def upgrade_all() -> None:
    """Upgrade our node groups and sync every local deformer (a file was loaded or the add-on enabled).
    Writes nothing when everything is current."""
    for ng in list(bpy.data.node_groups):
        nodes.upgrade_group(ng)
    for obj in bpy.data.objects:
        if obj.library is not None or obj.type != "MESH":
            continue
        for deformer in obj.affine_deformers:
            sync(obj, deformer)
