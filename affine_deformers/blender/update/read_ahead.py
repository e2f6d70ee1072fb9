"""Read-ahead: each deformer's frame computed and written before Blender evaluates the frame, so a frame
costs one evaluation of the scene instead of two.

The update used to run after the frame's evaluation (frame_change_post): its writes made Blender
evaluate the frame again — beside thousands of objects a second walk of the whole graph. Now, in
frame_change_pre (the scene is at the new frame, nothing evaluated yet), a hidden helper scene
(`HELPER`, one collection holding nothing but the controls of the scene's deformers: probes, cages,
armatures) is set to the same time and evaluated: its depsgraph evaluates those controls and what
they depend on — parents, constraints' targets, drivers' sources — and none of the artist's other
objects (~0.1 ms beside 20,000 of them). The update runs against it (evaluate.run with `read=`),
writes the outputs, and the frame's own evaluation applies them.

frame_change_post then runs the usual update against the frame's own depsgraph: it reads the controls
again, and when their exact bits give the signature written in pre (caches.signatures) there is
nothing to do. Where the helper cannot reproduce a control bit for bit — a simulation, a control
hidden in viewports, a driver reading the deformed mesh, a target that moves (its transform is read
from the frame's original data, which holds the previous frame) — the signatures differ and the post
update writes as before: one more evaluation, never a wrong frame. A deformer whose read-ahead fails
in any way (an error, a control not evaluated) is left to the post update untouched: no status, no
write.

Not read ahead: renders (their frames are evaluated by the render's own depsgraph, maybe on another
thread; they keep the post update), and frames changed on another thread. The helper scene is removed
before every save (save_pre) and made again at the next frame change, so saved files never hold it;
controls are linked into it only while they are in the artist's scene, and checks that ask whether a
control is in a scene ignore it (`is_helper`).
"""

from __future__ import annotations

import os
import threading

import bpy

from .. import caches, kinds
from ..kinds.transforms import HELPER_MARK as MARK
from . import output_store, registry

HELPER = ".AffineDeformers Read-ahead"
#: What reading a deformer's controls twice costs (once ahead, once to check after the frame) against
#: what the evaluation it saves costs per object of the scene (measured: `make bench` (w), (m)):
#: reading ahead pays only where objects × WALK_SECONDS > deformers × READ_SECONDS — a deformed mesh
#: beside a few hundred objects, not a crowd of deformed props in a small scene.
READ_SECONDS = 150e-6
WALK_SECONDS = 2e-6
#: Off with `AFFINE_DEFORMERS_READ_AHEAD=0` (every frame then updates after its evaluation, as before),
#: on whatever the scene's size with `always` (`AFFINE_DEFORMERS_READ_AHEAD=always`): for comparisons
#: in tests and `make bench`, and to run a whole test suite read ahead.
enabled = os.environ.get("AFFINE_DEFORMERS_READ_AHEAD", "1") != "0"
always = os.environ.get("AFFINE_DEFORMERS_READ_AHEAD") == "always"

#: The helper scene's controls last linked (session uids), so the collection changes only when they do.
_linked: set[int] = set()


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """At a full forget (load, undo, redo) the helper's collection is looked at again."""
    if key is None:
        _linked.clear()


def is_helper(scene: bpy.types.Scene | None) -> bool:
    return scene is not None and bool(scene.get(MARK))


def _helper(create: bool) -> bpy.types.Scene | None:
    found = bpy.data.scenes.get(HELPER)
    if found is not None and found.get(MARK) and found.library is None:
        return found
    if not create:
        return None
    found = bpy.data.scenes.new(HELPER)
    found[MARK] = True
    _linked.clear()
    return found


def remove() -> None:
    """Remove the helper scene (before a save: saved files never hold it)."""
    found = _helper(create=False)
    _linked.clear()
    if found is not None and bpy.context.scene != found:
        bpy.data.scenes.remove(found)


def _controls(scene: bpy.types.Scene, objects: list[bpy.types.Object]) -> dict[int, bpy.types.Object]:
    """The controls of `objects`' bound deformers that `scene` holds, by session uid."""
    found = {}
    members = scene.objects
    for obj in objects:
        for deformer in obj.affine_deformers:
            kind = kinds.get(deformer.kind)
            if kind is None or not deformer.is_bound:
                continue
            for control in kind.controls(obj, deformer):
                if members.get(control.name) == control:
                    found[control.session_uid] = control
    return found


def _sync(helper: bpy.types.Scene, controls: dict[int, bpy.types.Object]) -> None:
    """Make the helper's collection hold exactly `controls`."""
    if set(controls) == _linked:
        return
    collection = helper.collection
    for obj in list(collection.objects):
        if obj.session_uid not in controls:
            collection.objects.unlink(obj)
    for uid, obj in controls.items():
        if uid not in _linked and collection.objects.get(obj.name) != obj:
            collection.objects.link(obj)
    _linked.clear()
    _linked.update(controls)


def frame_depsgraph(scene: bpy.types.Scene,
                    given: bpy.types.Depsgraph | None) -> bpy.types.Depsgraph | None:
    """The depsgraph about to evaluate `scene`'s new frame: the one frame_change_pre was given (a
    render's), else the context view layer's, taken without evaluating it (`ViewLayer.depsgraph`);
    None for a scene other than the context's."""
    if given is not None:
        return given
    context = bpy.context
    if getattr(context, "scene", None) != scene or getattr(context, "view_layer", None) is None:
        return None
    return context.view_layer.depsgraph


def depsgraph(scene: bpy.types.Scene,
              frame_depsgraph: bpy.types.Depsgraph | None) -> bpy.types.Depsgraph | None:
    """The helper's depsgraph evaluated at `scene`'s time, holding the controls of `scene`'s deformers;
    None when this frame is not read ahead (a render, another thread, no deformer, the helper itself)."""
    if (not enabled or frame_depsgraph is None or frame_depsgraph.mode == "RENDER" or is_helper(scene)
            or threading.current_thread() is not threading.main_thread()):
        return None
    objects = registry.in_scene(scene)
    if not objects:
        return None
    deformers = sum(len(obj.affine_deformers) for obj in objects)
    if not always and output_store.objects_in(frame_depsgraph) * WALK_SECONDS <= deformers * READ_SECONDS:
        return None
    controls = _controls(scene, objects)
    if not controls:
        return None
    helper = _helper(create=True)
    _sync(helper, controls)
    render, source = helper.render, scene.render
    if (render.fps, render.fps_base, render.frame_map_old, render.frame_map_new) != (
            source.fps, source.fps_base, source.frame_map_old, source.frame_map_new):
        render.fps, render.fps_base = source.fps, source.fps_base  # drivers read time in seconds
        render.frame_map_old, render.frame_map_new = source.frame_map_old, source.frame_map_new
    helper.frame_set(scene.frame_current, subframe=scene.frame_subframe)
    return helper.view_layers[0].depsgraph
