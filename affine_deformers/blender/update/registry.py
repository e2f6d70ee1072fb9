"""The objects that carry deformers, kept current so that an update's work scales with the deformers,
not with the scene.

Scanning every object of a scene at every update cost ~12 ms at 20,000 objects, with no deformer
anywhere. The registry holds the objects with at least one deformer item instead, by session uid:

* filled by one scan of `bpy.data.objects` the first time it is asked after a file load, undo or redo
  (caches.forget drops it: every Python reference may be stale then) or registration;
* grown where objects with deformers appear: our own add operators and the adoption of copied
  modifiers call `add`; objects that arrive otherwise (append, link, library overrides, Shift+D,
  paste, a script) are added to the scene, which tags the scene or a collection, and `note` then
  looks at the depsgraph's updated objects — a frame change or a move of a control tags neither,
  so playback and drags never iterate the updates;
* shrunk lazily: `targets` drops objects that were deleted or whose last deformer was removed.
"""

from __future__ import annotations

import bpy

from .. import caches

#: session uid → object carrying at least one deformer item (None: not scanned since the last forget).
_objects: dict[int, bpy.types.Object] | None = None


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """Drop the registry at a full forget (file load, undo, redo, unregistering): the next `targets`
    scans again. Forgetting one deformer keeps it (its object is still there)."""
    global _objects
    if key is None:
        _objects = None


def _carries(obj: bpy.types.Object) -> bool:
    return len(getattr(obj, "affine_deformers", ())) > 0


def _scan() -> dict[int, bpy.types.Object]:
    return {obj.session_uid: obj for obj in bpy.data.objects if _carries(obj)}


def add(obj: bpy.types.Object) -> None:
    """Register `obj`, which now carries a deformer."""
    if _objects is not None:
        _objects[obj.session_uid] = obj


def note(depsgraph: bpy.types.Depsgraph | None) -> None:
    """Register the objects with deformers among `depsgraph`'s updates when objects may have been added
    (the scene or a collection changed)."""
    if _objects is None or depsgraph is None:
        return
    if not (depsgraph.id_type_updated("SCENE") or depsgraph.id_type_updated("COLLECTION")):
        return
    for update in depsgraph.updates:
        found = update.id
        if isinstance(found, bpy.types.Object):
            obj = found.original
            if obj.session_uid not in _objects and _carries(obj):
                _objects[obj.session_uid] = obj


def targets() -> list[bpy.types.Object]:
    """Every object carrying a deformer (scanning once after a forget), deleted objects and objects
    without deformers dropped."""
    global _objects
    if _objects is None:
        _objects = _scan()
    found = []
    for uid, obj in list(_objects.items()):
        try:
            alive = obj.session_uid == uid and _carries(obj)
        except ReferenceError:  # deleted since
            alive = False
        if alive:
            found.append(obj)
        else:
            del _objects[uid]
    return found


def in_scene(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """The registered objects that `scene` holds (a hash lookup each, not a pass over the scene)."""
    objects = scene.objects
    return [obj for obj in targets() if objects.get(obj.name_full) == obj or objects.get(obj.name) == obj]
