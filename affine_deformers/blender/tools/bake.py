"""Bake a deformer into data Blender plays without the add-on: a PC2 point cache read by a Mesh Cache
modifier, or one keyed shape key per frame. For render farms and Alembic / USD exports.

What is captured: the deformer applied to the mesh's shape-key mix at frame f (its output where it is
first in the stack after the shape keys): positions read from an evaluated mesh (a hidden temporary
object sharing the target's mesh, showing its shape-key mix and carrying only a copy of the deformer's
Geometry Nodes modifier), so modifiers above and below ours never leak into the cache, and the user's
modifier stack is never toggled. A previous shape-key bake of the same deformer is muted meanwhile.

How it replaces the live deformer (which is muted, not deleted, so Un-bake can bring it back):
- PC2: a Mesh Cache modifier (overwrite mode) inserted directly above the muted modifier. Modifiers
  below keep working on the cached shape exactly as they worked on the live one; the shape keys'
  effect at each frame is part of the cache. Enabled modifiers above are overwritten by the cache:
  the bake warns and names them.
- Shape keys: key f holds, relative to the basis, what the deformer adds to the shape-key mix at frame
  f (a second hidden object without modifiers gives the mix), so the other keys at their values of
  frame f plus key f give the output exactly; its value is 1 at frame f and 0 at the neighbouring
  baked frames, linear in between (motion blur sees a linear blend of consecutive frames), and the
  first and last keys hold outside the baked range. Enabled modifiers above ours now act on the
  baked shape instead of before the deformation: warned.

Safety: the result does not change until every frame is captured (new keys stay at 0 until then). A
failure or Esc mid-bake drops the temporary file / keys; the modifiers, shape keys, cache file and
frame stay as they were.
"""

from __future__ import annotations

import contextlib
import json
import traceback

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty, StringProperty

from .. import binding
from ..files import carrier, carrier_input, nodes, relations, storage
from ..ui.addressing import DeformerIndexed, active_target
from ..update import evaluate, output_store
from .bake_targets import TARGETS, BakeError, default_filepath, remove_artifacts, resolve_cache_path
from .pc2 import PC2Error

__all__ = ["CLASSES", "MODES", "BakeError", "BakeJob", "bake_state", "default_filepath", "resolve_cache_path",
           "unbake"]

MODES = [
    ("PC2", "Point Cache (PC2)",
     "Write a PC2 file played by a Mesh Cache modifier placed where the deformer was"),
    ("SHAPE_KEYS", "Shape Keys", "One shape key per frame, keyed to 1 at its frame and 0 at its neighbours"),
]
STATE_KEY = "affdef_bake"  # ID property on the deformer item: what the bake created, for Un-bake
# Blender 4.5+ warns when '//' is given to a path property that does not declare it understands it.
_PATH_OPTIONS = {"SKIP_SAVE"} | ({"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 5, 0) else set())
CAPTURE_NAME = ".affdef_bake_capture"
PRINT_EVERY = 10  # background mode: one progress line per this many frames
MAX_FRAME = 1048574  # Blender's MAXFRAME
_KEY_NAME_ROOM = 40  # bytes of the deformer name in key names (63 bytes at most: name + " f" + frame)


# --------------------------------------------------------------------------------------- bake state


def bake_state(deformer) -> dict | None:
    """What the last bake of `deformer` created (None when it is not baked): mode, frame range, and
    the Mesh Cache modifier and file, or the shape keys, plus the live modifier's toggles before."""
    state = deformer.get(STATE_KEY)
    if state is not None:
        return state.to_dict()
    # On a library override an ID property of a library item is not saved; the overridable copy is.
    record = getattr(deformer, "bake_record", "")
    try:
        return json.loads(record) if record else None
    except ValueError:
        return None


def _deformer_at(obj: bpy.types.Object | None, index: int, pc2_on_override: bool = False):
    """Deformer `index` of `obj`, which must be an editable mesh (BakeError saying why not). With
    `pc2_on_override`, a library override whose mesh is linked may bake to (or un-bake) PC2: the
    capture reads the live modifier's carrier, and the Mesh Cache modifier and the muted toggles are
    kept in the override. Shape keys would have to be added to the linked mesh: refused."""
    linked = binding.linked_mesh_problem(obj, "bake it") if obj is not None and obj.type == "MESH" else ""
    if linked and pc2_on_override and obj.override_library is not None and obj.library is None:
        problem = "" if binding.target_problem(obj) == binding.linked_mesh_problem(obj) else \
            binding.target_problem(obj)
    else:
        problem = linked or binding.target_problem(obj)
    if problem:
        raise BakeError(problem)
    try:
        return binding.deformer_at(obj, index)
    except LookupError as exc:
        raise BakeError(str(exc)) from None


def _find(obj: bpy.types.Object, uid: str):
    """(index, deformer) of the deformer with `uid` on `obj` (items move when others are removed)."""
    try:
        return binding.find_uid(obj, uid)
    except LookupError:
        raise BakeError(f"The deformer was removed from '{obj.name}' during the bake") from None


def _live_modifier(obj: bpy.types.Object, deformer) -> bpy.types.Modifier | None:
    return nodes.find_modifier(obj, storage.offset_name(deformer.uid))


def _modifiers_above(obj: bpy.types.Object, modifier: bpy.types.Modifier) -> list[str]:
    """Enabled modifiers above `modifier`: their effect is not in the cache (see module docstring)."""
    names = []
    for mod in obj.modifiers:
        if mod == modifier:
            break
        if (mod.show_viewport or mod.show_render) and not carrier_input.is_input_modifier(mod):
            names.append(mod.name)
    return names


# -------------------------------------------------------------------------------------------- capture


class _Capture:
    """Hidden objects sharing the target's mesh and showing its shape-key mix: one carries only a copy
    of the deformer's modifier (its evaluated positions are the deformer applied to the shape keys'
    result, with no other modifier), the other, when `with_input`, carries nothing (the deformer's
    input). The user's own object and stack are never touched."""

    def __init__(self, scene: bpy.types.Scene, obj: bpy.types.Object, uid: str, with_input: bool) -> None:
        offset_attr, motion_attrs = storage.offset_name(uid), storage.motion_names(uid)
        self.count = len(obj.data.vertices)
        self.object = self.input = None
        self._pinned: tuple[bpy.types.Object, str] | None = None
        try:
            self.object = self._stand_in(scene, obj)
            capture = nodes.ensure_modifier(self.object, offset_attr, motion_attrs, "Capture")
            # Keeps the controls evaluated while the live modifier is muted (a re-bake); synced
            # first: a visibility change since the last depsgraph update may need a relation now.
            relations.sync(obj, _find(obj, uid)[1])
            relations.copy_controls(nodes.find_modifier(obj, offset_attr), capture)
            # A library override's output is on its carrier, not on the mesh: made now if no update
            # has written it yet, so the capture reads the same carrier from the first frame.
            found = carrier.ensure(obj) if carrier.needs_carrier(obj) else None
            if found is None:
                # The live output stays in the store it is in (output_store.py) while the capture
                # reads it: a position carrier is named on the capture too.
                found = output_store.pin(obj, uid, nodes.find_modifier(obj, offset_attr))
                self._pinned = (obj, uid)
            if found is not None:
                nodes.set_carrier(capture, found)
            if with_input:
                self.input = self._stand_in(scene, obj)
        except BaseException:
            self.remove()
            raise

    @staticmethod
    def _stand_in(scene: bpy.types.Scene, obj: bpy.types.Object) -> bpy.types.Object:
        stand_in = bpy.data.objects.new(CAPTURE_NAME, obj.data)
        stand_in.show_only_shape_key = False
        stand_in.hide_render = True
        scene.collection.objects.link(stand_in)
        # Hidden objects are still evaluated; this only keeps the stand-in out of the artist's view.
        with contextlib.suppress(RuntimeError):  # not in the context's view layer: stays visible
            stand_in.hide_set(True)
        return stand_in

    def positions(self, depsgraph: bpy.types.Depsgraph) -> np.ndarray:
        """The deformer's output: evaluated positions (N, 3) float32 in the target's local space."""
        return self._read(self.object, depsgraph)

    def input_positions(self, depsgraph: bpy.types.Depsgraph) -> np.ndarray:
        """The shape-key mix the deformer deforms (needs `with_input`)."""
        return self._read(self.input, depsgraph)

    def _read(self, stand_in: bpy.types.Object, depsgraph: bpy.types.Depsgraph) -> np.ndarray:
        mesh = stand_in.evaluated_get(depsgraph).data
        if len(mesh.vertices) != self.count:
            raise BakeError(f"The evaluated mesh has {len(mesh.vertices)} vertices, expected {self.count}")
        return storage.read_positions(mesh)

    def remove(self) -> None:
        if self._pinned is not None:
            output_store.unpin(*self._pinned)
            self._pinned = None
        for stand_in in (self.object, self.input):
            if stand_in is not None:
                bpy.data.objects.remove(stand_in, do_unlink=True)
        self.object = self.input = None


# ------------------------------------------------------------------------------------------------ job


class BakeJob:
    """One bake, in steps so that an operator can run it to the end or one frame per timer tick; the
    mode's writer (bake_targets) does what differs between a PC2 cache and shape keys.

    `BakeJob(...)` only validates (raises BakeError, changes nothing); `begin` creates the temporary
    capture object and the cache / basis; `step` bakes one frame; `commit` swaps the result in;
    `abort` drops everything the job created; `finish` (always) removes the capture object and
    restores the frame.
    """

    def __init__(self, context: bpy.types.Context, obj: bpy.types.Object | None, index: int, mode: str,
                 frame_start: int, frame_end: int, filepath: str) -> None:
        deformer = _deformer_at(obj, index, pc2_on_override=mode.upper() == "PC2")
        if not deformer.is_bound:
            raise BakeError(f"'{deformer.name}' is not bound: bind it before baking")
        live = _live_modifier(obj, deformer)
        if live is None:
            raise BakeError(f"The modifier of '{deformer.name}' was removed or applied: rebind it first")
        if len(obj.data.vertices) != deformer.bound_vertex_count:
            raise BakeError(f"'{obj.name}' has {len(obj.data.vertices)} vertices but '{deformer.name}' was "
                            f"bound with {deformer.bound_vertex_count}: rebind it first")
        if frame_end < frame_start:
            raise BakeError(f"Bad frame range {frame_start}..{frame_end}: the end comes before the start")
        scene = context.scene
        if scene is None or scene.objects.get(obj.name) != obj:
            raise BakeError(f"'{obj.name}' is not in the current scene")
        target = TARGETS.get(mode.upper())
        if target is None:
            raise BakeError(f"Unknown bake mode '{mode}'")
        self.target = target(obj, deformer, filepath)
        self.mode, self.filepath = self.target.mode, self.target.filepath
        self.warnings: list[str] = []
        above = _modifiers_above(obj, live)
        if above:
            self.warnings.append(f"Modifiers above '{live.name}' ({', '.join(above)}) "
                                 f"{self.target.above_effect}: move the deformer to the top of the stack "
                                 "for an exact bake")
        self.object, self.uid, self.scene = obj, deformer.uid, scene
        self.frames = list(range(frame_start, frame_end + 1))
        self.done = 0
        self._capture: _Capture | None = None
        self._frame = (scene.frame_current, scene.frame_subframe)
        self._muted: list[str] = []  # keys of a previous shape-key bake, muted while capturing
        self._shape_view = (obj.active_shape_key_index, obj.show_only_shape_key)

    @property
    def total(self) -> int:
        return len(self.frames)

    def label(self) -> str:
        return f"'{self.object.name}' / '{_find(self.object, self.uid)[1].name}'"

    def begin(self) -> None:
        obj = self.object
        self.target.begin(self.frames[0])
        self._capture = _Capture(self.scene, obj, self.uid, with_input=self.target.needs_input)
        # A previous shape-key bake of this deformer must not be part of the shape-key mix captured
        # now: muted while baking (commit removes those keys; abort un-mutes them).
        previous = bake_state(_find(obj, self.uid)[1]) or {}
        blocks = obj.data.shape_keys.key_blocks if obj.data.shape_keys is not None else {}
        for name in previous.get("keys", []) if previous.get("mode") == "SHAPE_KEYS" else []:
            block = blocks.get(name)
            if block is not None and not block.mute:
                block.mute = True
                self._muted.append(name)

    def step(self, context: bpy.types.Context) -> bool:
        """Bake the next frame; True while frames remain."""
        frame = self.frames[self.done]
        self.scene.frame_set(frame)
        obj = self.object
        _index, deformer = _find(obj, self.uid)
        evaluate.evaluate_deformer(obj, deformer, context.evaluated_depsgraph_get())
        # Only errors stop the bake; warnings (a missing vertex group, collapsed cage faces) still
        # deform, and the bake captures what the live deformer shows.
        error = evaluate.blocking_error(obj, deformer)
        if error:
            raise BakeError(f"Frame {frame}: {error}")
        depsgraph = context.evaluated_depsgraph_get()
        positions = self._capture.positions(depsgraph)
        if not np.all(np.isfinite(positions)):
            raise BakeError(f"Frame {frame}: the deformed positions are not finite")
        inputs = self._capture.input_positions(depsgraph) if self.target.needs_input else None
        self.target.add(frame, deformer.name, positions, inputs)
        self.done += 1
        return self.done < self.total

    def commit(self) -> str:
        """Swap the bake in (replacing a previous bake of this deformer) and mute the live modifier.
        Returns a summary for the report."""
        obj = self.object
        _index, deformer = _find(obj, self.uid)
        previous = bake_state(deformer)
        try:
            state = self.target.commit(deformer, self.frames, previous)
        except BaseException:
            self.target.drop_commit()
            raise
        if previous is not None:
            remove_artifacts(obj, previous)
            self.target.settle(state, deformer.name, self.frames)
        live_flags = ((previous["show_viewport"], previous["show_render"]) if previous is not None
                      else (deformer.show_viewport, deformer.show_render))
        deformer.show_viewport = deformer.show_render = False
        if STATE_KEY in deformer:  # a re-bake: never assign over an ID property of another shape
            del deformer[STATE_KEY]
        record = {
            "mode": self.mode, "frame_start": self.frames[0], "frame_end": self.frames[-1], **state,
            "show_viewport": bool(live_flags[0]), "show_render": bool(live_flags[1]),
        }
        deformer[STATE_KEY] = record
        if obj.override_library is not None:  # the ID property is not saved with an override
            deformer.bake_record = json.dumps(bake_state(deformer))
        return (f"Baked '{deformer.name}' on '{obj.name}', frames {self.frames[0]}..{self.frames[-1]}, "
                f"to {self.target.describe(self.frames)}")

    def abort(self) -> None:
        """Drop what the job created; the object and the cache path keep what they had."""
        self.target.abort()

    def finish(self) -> None:
        """Always called last: remove the capture object, restore the shape key view and the frame."""
        try:
            if self._capture is not None:
                self._capture.remove()
                self._capture = None
        finally:
            obj = self.object
            key = obj.data.shape_keys
            for name in self._muted:  # those commit did not remove (an abort) come back as they were
                block = key.key_blocks.get(name) if key is not None else None
                if block is not None:
                    block.mute = False
            self._muted = []
            index, only = self._shape_view
            obj.active_shape_key_index = min(index, max(len(key.key_blocks) - 1, 0)) if key else 0
            obj.show_only_shape_key = only
            frame, subframe = self._frame
            self.scene.frame_set(frame, subframe=subframe)


def unbake(obj: bpy.types.Object, index: int) -> str:
    """Remove the bake of deformer `index` (Mesh Cache modifier or shape keys; the .pc2 file stays on
    disk) and give the live modifier back its toggles from before the bake. Returns a summary."""
    deformer = _deformer_at(obj, index, pc2_on_override=True)
    state = bake_state(deformer)
    if state is None:
        raise BakeError(f"'{deformer.name}' is not baked")
    if state.get("mode") != "PC2":
        _deformer_at(obj, index)  # shape keys live on the mesh: refused when it is linked
    if state.get("mode") == "SHAPE_KEYS" and obj.data.users > 1:
        raise BakeError(f"'{obj.data.name}' is used by {obj.data.users} objects: removing the baked "
                        "shape keys would change all of them; make it single-user first")
    remove_artifacts(obj, state)
    deformer.show_viewport = bool(state.get("show_viewport", True))
    deformer.show_render = bool(state.get("show_render", True))
    if STATE_KEY in deformer:
        del deformer[STATE_KEY]
    if deformer.bake_record:
        deformer.bake_record = ""
    evaluate.forget(obj, deformer.uid)
    return f"Un-baked '{deformer.name}' on '{obj.name}': the live deformer is back"


# ------------------------------------------------------------------------------------------ operators


class AFFINE_OT_deformer_bake(DeformerIndexed, bpy.types.Operator):
    """Bake the deformer over a frame range into a PC2 cache (Mesh Cache modifier) or shape keys, so
    renders and exports work without the add-on. The live deformer is muted, not deleted (Esc cancels)"""

    bl_idname = "object.affine_deformer_bake"
    bl_label = "Bake Affine Deformer"

    mode: EnumProperty(name="Bake To", items=MODES, default="PC2")
    frame_start: IntProperty(
        name="Start", default=1, min=-MAX_FRAME, max=MAX_FRAME, options={"SKIP_SAVE"},
        description="First frame to bake (default: the scene's start)")
    frame_end: IntProperty(
        name="End", default=250, min=-MAX_FRAME, max=MAX_FRAME, options={"SKIP_SAVE"},
        description="Last frame to bake (default: the scene's end)")
    filepath: StringProperty(
        name="Cache File", subtype="FILE_PATH", default="", options=_PATH_OPTIONS,
        description="PC2 file ('//' = next to the .blend; empty: //<object>_<deformer>.pc2)")

    _job = None  # the running BakeJob (modal); not annotated: annotations are RNA properties here
    _timer = None

    def _make_job(self, context: bpy.types.Context) -> BakeJob | None:
        scene = context.scene
        if scene is not None:
            if not self.properties.is_property_set("frame_start"):
                self.frame_start = scene.frame_start
            if not self.properties.is_property_set("frame_end"):
                self.frame_end = scene.frame_end
        try:
            job = BakeJob(context, active_target(context), self.index, self.mode, self.frame_start,
                          self.frame_end, self.filepath)
        except BakeError as exc:
            self.report({"ERROR"}, str(exc))
            return None
        self.filepath = job.filepath
        return job

    def _fail(self, job: BakeJob, exc: BaseException | None) -> None:
        """Undo the job's work; `exc` None means the artist cancelled."""
        try:
            job.abort()
        finally:
            job.finish()
        if exc is None:
            self.report({"WARNING"}, "Bake cancelled: nothing changed")
        elif isinstance(exc, BakeError | PC2Error):
            self.report({"ERROR"}, f"Bake failed, nothing changed: {exc}")
        else:
            traceback.print_exc()
            self.report({"ERROR"}, f"Bake failed, nothing changed ({type(exc).__name__}: {exc})")

    def _done(self, context: bpy.types.Context, job: BakeJob) -> set[str]:
        summary = job.commit()
        job.finish()
        evaluate.forget(job.object, job.uid)
        for warning in job.warnings:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary)
        return {"FINISHED"}

    def _progress(self, context: bpy.types.Context, job: BakeJob) -> None:
        if bpy.app.background:
            if job.done % PRINT_EVERY == 0 or job.done == job.total:
                print(f"Affine Deformers: baking {job.label()}: frame {job.frames[job.done - 1]} "
                      f"({job.done}/{job.total})", flush=True)
        else:
            context.window_manager.progress_update(job.done)

    def execute(self, context: bpy.types.Context) -> set[str]:
        job = self._make_job(context)
        if job is None:
            return {"CANCELLED"}
        wm = context.window_manager
        show_progress = not bpy.app.background and wm is not None
        if show_progress:
            wm.progress_begin(0, job.total)
        try:
            job.begin()
            while True:
                more = job.step(context)
                self._progress(context, job)
                if not more:
                    break
            return self._done(context, job)
        except Exception as exc:
            self._fail(job, exc)
            return {"CANCELLED"}
        except BaseException:  # KeyboardInterrupt in a background bake: clean up, then stop
            try:
                job.abort()
            finally:
                job.finish()
            raise
        finally:
            if show_progress:
                wm.progress_end()

    def invoke(self, context: bpy.types.Context, _event: bpy.types.Event) -> set[str]:
        if bpy.app.background or context.window is None:
            return self.execute(context)
        job = self._make_job(context)
        if job is None:
            return {"CANCELLED"}
        try:
            job.begin()
        except Exception as exc:
            self._fail(job, exc)
            return {"CANCELLED"}
        self._job = job
        wm = context.window_manager
        wm.progress_begin(0, job.total)
        self._timer = wm.event_timer_add(0.001, window=context.window)
        wm.modal_handler_add(self)
        self.report({"INFO"}, f"Baking {job.total} frames (Esc cancels)")
        return {"RUNNING_MODAL"}

    def _stop_modal(self, context: bpy.types.Context) -> None:
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        self._job = None

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            self._stop_modal(context)
            self._fail(job, None)
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"RUNNING_MODAL"}  # the scene must not change under the bake: swallow other input
        try:
            more = job.step(context)
            self._progress(context, job)
            if more:
                return {"RUNNING_MODAL"}
            self._stop_modal(context)
            return self._done(context, job)
        except Exception as exc:
            self._stop_modal(context)
            self._fail(job, exc)
            return {"CANCELLED"}

    def cancel(self, context: bpy.types.Context) -> None:
        # Blender ends the modal (file load, window closed): leave the object as it was.
        job = self._job
        self._stop_modal(context)
        if job is not None:
            try:
                job.abort()
            finally:
                job.finish()


class AFFINE_OT_deformer_unbake(DeformerIndexed, bpy.types.Operator):
    """Remove the bake (Mesh Cache modifier or baked shape keys; the cache file stays on disk) and turn
    the live deformer back on"""

    bl_idname = "object.affine_deformer_unbake"
    bl_label = "Un-bake Affine Deformer"


    def execute(self, context: bpy.types.Context) -> set[str]:
        obj = active_target(context)
        try:
            summary = unbake(obj, self.index)
        except BakeError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        evaluate.evaluate_object(obj, context.evaluated_depsgraph_get())
        self.report({"INFO"}, summary)
        return {"FINISHED"}


CLASSES = (AFFINE_OT_deformer_bake, AFFINE_OT_deformer_unbake)
