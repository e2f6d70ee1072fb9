"""The application handlers: frame changes, depsgraph updates, file load, undo / redo, render start.

All are @persistent and never let an exception escape (a bug must not take Blender down); the
updates they start are guarded against re-entrancy (evaluate.run: an update writes mesh attributes,
which triggers another depsgraph update).
"""

from __future__ import annotations

import traceback

import bpy
from bpy.app.handlers import persistent

from .. import caches
from ..files import carrier, copies, instances, nodes, relations
from ..kinds import transforms
from . import evaluate, read_ahead, registry

_syncing = False  # relations.sync_scene is running (its depsgraph.update() calls this handler again)


@persistent
def on_frame_change_pre(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None = None) -> None:
    """Read the new frame's controls ahead and write the outputs before Blender evaluates it
    (read_ahead.py); what cannot be read ahead is left to on_frame_change_post."""
    if read_ahead.is_helper(scene) or evaluate.running():
        return
    try:
        frame = read_ahead.frame_depsgraph(scene, depsgraph)
        read = read_ahead.depsgraph(scene, frame)
        if read is not None:
            evaluate.run(scene, frame, read=read)
    except Exception:
        traceback.print_exc()
    finally:
        transforms.take_resync()  # asked for ahead of the frame: the update after it asks again


@persistent
def on_frame_change_post(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None = None) -> None:
    if read_ahead.is_helper(scene):
        return
    evaluate.run(scene, depsgraph)
    if transforms.take_resync():
        _sync(scene, depsgraph)
        evaluate.run(scene, depsgraph)


@persistent
def on_depsgraph_update_post(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None = None) -> None:
    if _syncing or read_ahead.is_helper(scene):
        return
    try:
        # Before `_sync`, which may evaluate again: the depsgraph then lists that pass's updates only
        # (an appended rig whose node group `_sync` upgraded was never registered, and never updated).
        registry.note(depsgraph)
        scene_changed = False
        for update in depsgraph.updates if depsgraph is not None else ():
            # Visibility, collection and view layer changes all list the scene; moving a control does not.
            scene_changed = scene_changed or isinstance(update.id, bpy.types.Scene)
            if isinstance(update.id, bpy.types.NodeTree):
                nodes.forget()  # a group's interface may have changed in a way its item names do not show
        if scene_changed:
            _sync(scene, depsgraph)
        if depsgraph is not None and not evaluate.running():
            copies.handle(depsgraph)  # Copy to Selected / Copy Modifiers copy a modifier alone
    except Exception:
        traceback.print_exc()
    evaluate.run(scene, depsgraph)
    if transforms.take_resync():
        _sync(scene, depsgraph)
        evaluate.run(scene, depsgraph)


def _sync(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None) -> None:
    """relations.sync_scene; when a relation changed, evaluate `depsgraph` again (a control named just
    now was not evaluated in this pass, and may have moved) — not a render's, whose relations were
    synced when it started (on_render_start)."""
    global _syncing
    if _syncing or depsgraph is None:
        return
    _syncing = True
    try:
        if relations.sync_scene(scene) and depsgraph.mode != "RENDER":
            depsgraph.update()
    except Exception:
        traceback.print_exc()
    finally:
        _syncing = False


@persistent
def on_load_post(*_args) -> None:
    caches.forget()
    try:
        relations.upgrade_all()  # versioning: node groups and control inputs of older files
    except Exception:
        traceback.print_exc()
    try:
        # Library overrides: controls still naming linked objects (overridden without the add-on),
        # and the output carriers of targets whose mesh is linked (carrier.py).
        if carrier.remap_controls():
            relations.upgrade_all()  # the modifiers name the overridden controls too
        carrier.ensure_all()
        instances.report(bpy.context.scene)  # linked instances without override cannot play: say so
    except Exception:
        traceback.print_exc()
    try:
        if bpy.context.scene is not None:
            evaluate.run(bpy.context.scene, bpy.context.evaluated_depsgraph_get())
    except Exception:
        traceback.print_exc()


@persistent
def on_save_pre(*_args) -> None:
    try:
        read_ahead.remove()  # helper data never goes into a saved file
    except Exception:
        traceback.print_exc()


@persistent
def on_undo_redo(*_args) -> None:
    # Undo restores mesh attributes and transforms together; cached signatures may describe neither.
    caches.forget()


@persistent
def on_render_start(scene: bpy.types.Scene, *_args) -> None:
    # Handlers write mesh data during renders: the interface must be locked or Blender may crash.
    try:
        if not scene.render.use_lock_interface:
            scene.render.use_lock_interface = True
    except Exception:
        traceback.print_exc()
    try:
        carrier.ensure_all(scene)  # no ID may be made during a render frame: make the carriers now
        instances.report(scene)
    except Exception:
        traceback.print_exc()
    try:
        relations.sync_scene(scene)  # before the render depsgraph is built: controls hidden in renders
    except Exception:
        traceback.print_exc()


HANDLERS = (
    ("frame_change_pre", on_frame_change_pre),
    ("frame_change_post", on_frame_change_post),
    ("save_pre", on_save_pre),
    ("depsgraph_update_post", on_depsgraph_update_post),
    ("load_post", on_load_post),
    ("undo_post", on_undo_redo),
    ("redo_post", on_undo_redo),
    ("render_init", on_render_start),
    ("render_pre", on_render_start),
)


def register_handlers() -> None:
    unregister_handlers()
    for name, func in HANDLERS:
        getattr(bpy.app.handlers, name).append(func)


def unregister_handlers() -> None:
    # Match by qualified name too: after a reload the old function objects are different objects.
    ours = {(f.__module__, f.__name__) for _, f in HANDLERS}
    for name, _func in HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        stale = [h for h in handlers if (getattr(h, "__module__", ""), getattr(h, "__name__", "")) in ours]
        for h in stale:
            handlers.remove(h)
    caches.forget()
