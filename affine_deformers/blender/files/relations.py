"""Depsgraph relations from a deformed mesh to its controls (cage, probes, armature).

Blender evaluates an object only when it is visible or something visible depends on it, and nothing
made the target depend on its controls: a cage, probe or armature disabled in viewports (or in
renders) kept a stale evaluated copy, so the deformer read old transforms, shapes and poses, or had to
refuse. Each deformer's modifier now names its controls on the shared group's inputs
(nodes.CAGE_SOCKET, an Object; nodes.PROBES_SOCKET, a Collection). Geometry Nodes adds a depsgraph
relation for every ID set on a modifier's inputs, whether or not a node reads it (object: transform,
and geometry when it has a geometry component; collection: its geometry, which waits for each
member's transform, geometry and instancing), so while the modifier is enabled the controls are
evaluated with the target, in the viewport and in renders.

An armature's pose is neither its transform nor geometry (it has no geometry component): named on
the Object input, a disabled armature kept a stale pose. Its instancing waits for its whole pose, so
the Collection input evaluates it: an armature goes in the collection (`object_input_evaluates`).

The probes (or armature) of a deformer are held by a collection of its own, named PROBES_NAME, marked
with PROBES_MARK and linked to no scene (the Collection input is the only way to name a changing
number of objects on one shared node group). `sync` keeps it and the inputs in step with the
deformer; it is called at bind / re-weight, when a control is picked or cleared, and for every
deformer when a file is loaded (which also upgrades node groups saved by older versions, see
nodes.upgrade_group, and moves an armature an older version named on the Object input).

Only controls the depsgraph would not evaluate anyway are named (`evaluated_anyway`). A relation
also re-evaluates the target whenever a named control moves, before our handler has written the
new result: the target's stack ran twice per update, once with stale data. A control enabled in
viewports and renders in every view layer that holds the target is evaluated without one. Its
visibility can change later: every depsgraph update that lists a Scene (visibility and collection
changes do) re-runs `sync_scene`, and so does every render start; visibility that is animated or
driven counts as disabled, since a frame change re-syncs nothing.
"""

from __future__ import annotations

import bpy

from .. import kinds
from . import carrier_input, nodes, storage

PROBES_NAME = ".AffineDeformer Probes"
PROBES_MARK = "affine_deformers_probes"  # custom property on the probe collections we own


def _is_ours(collection: bpy.types.Collection | None) -> bool:
    return collection is not None and collection.library is None and bool(collection.get(PROBES_MARK))


HIDE_PATHS = frozenset({"hide_viewport", "hide_render"})


def evaluated_anyway(target: bpy.types.Object, control: bpy.types.Object) -> bool:
    """Whether every depsgraph that evaluates `target` (viewport and render, each view layer of each
    scene holding it) evaluates `control` without a relation: the control is enabled in both (the eye
    icon only hides: hidden objects are still evaluated) on some path of collections that is neither
    excluded nor disabled, in each of those view layers, and its visibility is not animated."""
    if control.hide_viewport or control.hide_render or _visibility_animated(control):
        return False
    scenes = target.users_scene
    return bool(scenes) and all(_enabled_under(layer.layer_collection, control)
                                for scene in scenes for layer in scene.view_layers)


def _enabled_under(layer: bpy.types.LayerCollection, control: bpy.types.Object) -> bool:
    collection = layer.collection
    if layer.exclude or collection.hide_viewport or collection.hide_render:
        return False
    if collection.objects.get(control.name) == control:
        return True
    return any(_enabled_under(child, control) for child in layer.children)


def _visibility_animated(obj: bpy.types.Object) -> bool:
    """Whether an F-curve or driver of `obj` (its action, its NLA strips' actions) writes a hide flag."""
    anim = obj.animation_data
    if anim is None:
        return False
    if any(d.data_path in HIDE_PATHS for d in anim.drivers):
        return True
    actions = [anim.action] + [strip.action for track in anim.nla_tracks for strip in track.strips]
    return any(fc.data_path in HIDE_PATHS for action in actions if action is not None
               for fc in _fcurves(action))


def _fcurves(action: bpy.types.Action) -> list:
    """Every F-curve of `action`: its channel bags' on layered actions (Blender 4.4+; the only kind
    in 5.0), `action.fcurves` before."""
    layers = getattr(action, "layers", None)
    if layers is None:
        return list(action.fcurves)
    curves = [fc for layer in layers for strip in layer.strips
              for bag in getattr(strip, "channelbags", ()) for fc in bag.fcurves]
    legacy = getattr(action, "fcurves", None)  # 4.4–4.5 still show the first slot's curves here
    return curves + (list(legacy) if legacy is not None and not curves else [])


def object_input_evaluates(control: bpy.types.Object) -> bool:
    """Whether naming `control` on the Object input makes the depsgraph evaluate all a kind reads of
    it: not for an armature, whose pose only the Collection input evaluates (see the module doc;
    measured on 4.2, 4.5 and 5.0, and kept by tests/blender/test_pipeline_files.py)."""
    return control.type != "ARMATURE"


def _wanted(obj: bpy.types.Object, deformer) -> tuple[bpy.types.Object | None, list[bpy.types.Object]]:
    """(object, collection members) the deformer's modifier should name: a kind with one control
    object (a cage) names it on the Object input, others (probes) and armatures
    (`object_input_evaluates`) go in the collection; the target itself never, nor controls the
    depsgraph evaluates anyway."""
    kind = kinds.get(deformer.kind)
    controls = kind.controls(obj, deformer) if kind is not None else []
    controls = [control for control in controls if not evaluated_anyway(obj, control)]
    if kind is not None and kind.single_control and all(map(object_input_evaluates, controls)):
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


def drop_if_unused(collection: bpy.types.Collection | None) -> None:
    """Remove `collection` when it is one of our probe collections and nothing uses it any more."""
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
        drop_if_unused(old_collection)
    return changed or (collection is not None and set(collection.objects) != held)


def remove_modifier(obj: bpy.types.Object, uid: str) -> None:
    """Remove deformer `uid`'s modifier, and its probe collection once nothing uses it."""
    mod = nodes.find_modifier(obj, storage.offset_name(uid))
    if mod is None:
        return
    _cage, collection = nodes.controls(mod)
    nodes.remove_modifier(obj, mod)
    drop_if_unused(collection)


def copy_controls(source: bpy.types.NodesModifier | None, target: bpy.types.NodesModifier) -> None:
    """Give `target` (e.g. the bake's stand-in modifier) the control inputs of `source`, so the
    controls are evaluated with it even while `source` is muted."""
    if source is not None:
        nodes.set_controls(target, *nodes.controls(source))


def sync_scene(scene: bpy.types.Scene) -> bool:
    """`sync` every local deformer of the scene's meshes (visibility may have changed); True when a
    relation changed."""
    changed = False
    for obj in scene.objects:
        if obj.type == "MESH" and obj.library is None and len(obj.affine_deformers):
            for deformer in obj.affine_deformers:
                changed = sync(obj, deformer) or changed
    return changed


def upgrade_all() -> None:
    """Upgrade our node groups and sync every local deformer (a file was loaded or the add-on enabled).
    Writes nothing when everything is current."""
    for ng in list(bpy.data.node_groups):
        nodes.upgrade_group(ng)
        carrier_input.upgrade_group(ng)
    for obj in bpy.data.objects:
        if obj.library is not None or obj.type != "MESH":
            continue
        for deformer in obj.affine_deformers:
            sync(obj, deformer)
