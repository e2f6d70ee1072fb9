"""Linked rigs that are only instanced (a collection linked from an asset file and shown by an Empty,
without a library override): nothing of them is local, so no per-frame output can be written for them
(carrier.py needs a local override to name its carrier on): their meshes show the shape saved in the
asset file at the frame it was saved at and, when the rig is animated, their modifiers' input at other
frames (frame_check.py), while the linked controls play. They are found here so the artist is told what to do:
the console at file load and render start, the panel of the instancing Empty."""

from __future__ import annotations

import bpy

from ..ui.addressing import library_name
from . import nodes


def deformed_linked(collection: bpy.types.Collection) -> list[bpy.types.Object]:
    """The linked mesh objects in `collection` and its children with a deformer whose modifier is
    enabled (a deformer baked in the asset is muted, and its Mesh Cache or shape keys play here)."""
    return [obj for obj in collection.all_objects
            if obj.type == "MESH" and obj.library is not None and len(obj.affine_deformers)
            and any(nodes.offset_attribute(mod) and (mod.show_viewport or mod.show_render)
                    for mod in obj.modifiers)]


def instance_message(obj: bpy.types.Object) -> str:
    """What to do about `obj` when it instances a linked collection holding deformed meshes, else ''."""
    collection = obj.instance_collection if obj.instance_type == "COLLECTION" else None
    if collection is None or collection.library is None:
        return ""
    found = deformed_linked(collection)
    if not found:
        return ""
    names = ", ".join(f"'{o.name}'" for o in found[:4]) + (", …" if len(found) > 4 else "")
    return (f"'{obj.name}' instances '{collection.name}' from '{library_name(collection)}': {names} carry "
            "affine deformers, which cannot update in a linked instance (an animated one shows its input "
            "at frames other than the one that file was saved at). Make a library override (Object ▸ "
            "Library Override ▸ Make) to animate them, or bake them in that file")


def report(scene: bpy.types.Scene | None) -> list[str]:
    """Print (and return) the message of every such instance in `scene` (at load and render start)."""
    messages = []
    for obj in scene.objects if scene is not None else ():
        message = instance_message(obj)
        if message:
            print(f"Affine Deformers: {message}")
            messages.append(message)
    return messages
