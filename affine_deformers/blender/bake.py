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
import traceback
from pathlib import Path

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty, StringProperty

from . import binding, evaluate, nodes, relations, storage
from .operators import DeformerIndexed, active_target
from .pc2 import PC2Error, PC2Writer

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


class BakeError(Exception):
    """A bake that cannot start or cannot go on; the message is meant for the artist."""


# --------------------------------------------------------------------------------------- bake state


def bake_state(deformer) -> dict | None:
    """What the last bake of `deformer` created (None when it is not baked): mode, frame range, and
    the Mesh Cache modifier and file, or the shape keys, plus the live modifier's toggles before."""
    state = deformer.get(STATE_KEY)
    return state.to_dict() if state is not None else None


def default_filepath(obj: bpy.types.Object, deformer) -> str:
    """'//<object>_<deformer>.pc2': next to the .blend, so machines sharing the storage resolve it."""
    return f"//{bpy.path.clean_name(obj.name)}_{bpy.path.clean_name(deformer.name)}.pc2"


def resolve_cache_path(filepath: str) -> Path:
    """The absolute path of the cache file `filepath` ('//' = the .blend's folder).

    A relative path in an unsaved file is an error rather than a silent bake into a temporary folder:
    a render farm would never find that file.
    """
    if not filepath:
        raise BakeError("No cache file path given")
    if filepath.startswith("//") and not bpy.data.filepath:
        raise BakeError(f"The cache path '{filepath}' is relative to the .blend file, which is not saved "
                        "yet: save the file first, or give an absolute path")
    path = Path(bpy.path.abspath(filepath))
    if path.is_dir():
        raise BakeError(f"The cache path '{filepath}' is a folder: give a file name ending in .pc2")
    return path


def _find(obj: bpy.types.Object, uid: str):
    """(index, deformer) of the deformer with `uid` on `obj` (items move when others are removed)."""
    for i, item in enumerate(obj.affine_deformers):
        if item.uid == uid:
            return i, item
    raise BakeError(f"The deformer was removed from '{obj.name}' during the bake")


def _live_modifier(obj: bpy.types.Object, deformer) -> bpy.types.Modifier | None:
    return nodes.find_modifier(obj, storage.offset_name(deformer.uid))


def _modifiers_above(obj: bpy.types.Object, modifier: bpy.types.Modifier) -> list[str]:
    """Enabled modifiers above `modifier`: their effect is not in the cache (see module docstring)."""
    names = []
    for mod in obj.modifiers:
        if mod == modifier:
            break
        if mod.show_viewport or mod.show_render:
            names.append(mod.name)
    return names


# ---------------------------------------------------------------------------------- shape key curves


def _key_name(deformer_name: str, frame: int) -> str:
    """'<deformer> f0012', cut on a character boundary so Blender never truncates the frame away."""
    base = deformer_name.encode()[:_KEY_NAME_ROOM].decode(errors="ignore")
    return f"{base} f{frame:04d}"


def _fcurve_collection(key: bpy.types.Key):
    """The F-curves animating `key` (the action's legacy list, or the assigned slot's channelbag on
    Blender 4.4+ layered actions); None when the key is not animated."""
    anim = key.animation_data
    if anim is None or anim.action is None:
        return None
    action = anim.action
    slot = getattr(anim, "action_slot", None)
    if slot is not None:
        from bpy_extras import anim_utils

        getter = getattr(anim_utils, "action_get_channelbag_for_slot", None)
        if getter is not None:
            channelbag = getter(action, slot)
            return channelbag.fcurves if channelbag is not None else None
    return getattr(action, "fcurves", None)


def _value_fcurve(key: bpy.types.Key, data_path: str) -> bpy.types.FCurve:
    anim = key.animation_data
    action = anim.action
    if hasattr(action, "fcurve_ensure_for_datablock"):  # Blender 4.4+: creates layer, strip and slot
        fcurve = action.fcurve_ensure_for_datablock(key, data_path)
    else:
        fcurve = action.fcurves.find(data_path) or action.fcurves.new(data_path)
    fcurve.keyframe_points.clear()
    return fcurve


def _remove_fcurve(key: bpy.types.Key, data_path: str) -> None:
    fcurves = _fcurve_collection(key)
    fcurve = fcurves.find(data_path) if fcurves is not None else None
    if fcurve is not None:
        fcurves.remove(fcurve)


def _action_is_empty(action: bpy.types.Action) -> bool:
    if hasattr(action, "layers"):
        for layer in action.layers:
            for strip in layer.strips:
                if any(len(bag.fcurves) for bag in getattr(strip, "channelbags", ())):
                    return False
    legacy = getattr(action, "fcurves", None)
    return legacy is None or len(legacy) == 0


def _key_pulses(frames: list[int]) -> list[list[tuple[float, float]]]:
    """Keyframes (frame, value) of each baked key: 1 at its frame, 0 at the neighbouring baked frames.
    The first and last keys get no outer zero, so constant extrapolation holds them outside the range."""
    out = []
    for i, frame in enumerate(frames):
        points = [(float(frame), 1.0)]
        if i > 0:
            points.insert(0, (float(frames[i - 1]), 0.0))
        if i + 1 < len(frames):
            points.append((float(frames[i + 1]), 0.0))
        out.append(points)
    return out


def _key_frames(key: bpy.types.Key, names: list[str], frames: list[int]) -> None:
    for name, points in zip(names, _key_pulses(frames), strict=True):
        fcurve = _value_fcurve(key, key.key_blocks[name].path_from_id("value"))
        fcurve.keyframe_points.add(len(points))
        fcurve.keyframe_points.foreach_set("co", np.array(points, dtype=np.float32).ravel())
        for point in fcurve.keyframe_points:  # ≤ 3 points per key
            point.interpolation = "LINEAR"
        fcurve.extrapolation = "CONSTANT"
        fcurve.update()


def _remove_keys(obj: bpy.types.Object, names: list[str], basis_created: bool, action_name: str) -> None:
    """Remove the shape keys `names` and their curves; then the basis and the action when the bake
    created them and nothing else uses them."""
    key = obj.data.shape_keys
    if key is None:
        return
    for name in names:
        block = key.key_blocks.get(name)
        if block is None:
            continue
        _remove_fcurve(key, block.path_from_id("value"))  # removing a key leaves its curve behind
        obj.shape_key_remove(block)
    key = obj.data.shape_keys
    action = bpy.data.actions.get(action_name) if action_name else None
    if action is not None and _action_is_empty(action):
        if key is not None and key.animation_data is not None and key.animation_data.action == action:
            key.animation_data.action = None
        if action.users == 0:
            bpy.data.actions.remove(action)
    if basis_created and key is not None and len(key.key_blocks) == 1:
        obj.shape_key_clear()


def _remove_artifacts(obj: bpy.types.Object, state: dict) -> None:
    """Remove what a bake created (the Mesh Cache modifier, or the shape keys); the cache file stays
    on disk: it may be referenced elsewhere (farm jobs, other .blend files)."""
    if state.get("mode") == "PC2":
        mod = obj.modifiers.get(state.get("modifier", ""))
        if mod is None or mod.type != "MESH_CACHE" or mod.filepath != state.get("filepath"):
            mod = next((m for m in obj.modifiers
                        if m.type == "MESH_CACHE" and m.filepath == state.get("filepath")), None)
        if mod is not None:
            obj.modifiers.remove(mod)
    else:
        _remove_keys(obj, list(state.get("keys", [])), bool(state.get("basis_created", False)),
                     state.get("action", ""))


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
        try:
            self.object = self._stand_in(scene, obj)
            capture = nodes.ensure_modifier(self.object, offset_attr, motion_attrs, "Capture")
            # Keeps the controls evaluated while the live modifier is muted (a re-bake).
            relations.copy_controls(nodes.find_modifier(obj, offset_attr), capture)
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
        for stand_in in (self.object, self.input):
            if stand_in is not None:
                bpy.data.objects.remove(stand_in, do_unlink=True)
        self.object = self.input = None


# ------------------------------------------------------------------------------------------------ job


class BakeJob:
    """One bake, in steps so that an operator can run it to the end or one frame per timer tick.

    `BakeJob(...)` only validates (raises BakeError, changes nothing); `begin` creates the temporary
    capture object and the cache / basis; `step` bakes one frame; `commit` swaps the result in;
    `abort` drops everything the job created; `finish` (always) removes the capture object and
    restores the frame.
    """

    def __init__(self, context: bpy.types.Context, obj: bpy.types.Object | None, index: int, mode: str,
                 frame_start: int, frame_end: int, filepath: str) -> None:
        problem = binding.target_problem(obj)
        if problem:
            raise BakeError(problem)
        if not 0 <= index < len(obj.affine_deformers):
            raise BakeError(f"'{obj.name}' has no affine deformer #{index} "
                            f"(it has {len(obj.affine_deformers)})")
        deformer = obj.affine_deformers[index]
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
        mode = mode.upper()
        if mode not in {m[0] for m in MODES}:
            raise BakeError(f"Unknown bake mode '{mode}'")
        key = obj.data.shape_keys
        self.warnings: list[str] = []
        self.path: Path | None = None
        self.filepath = ""
        if mode == "PC2":
            self.filepath = bpy.path.ensure_ext(filepath or default_filepath(obj, deformer), ".pc2")
            self.path = resolve_cache_path(self.filepath)
        else:
            if obj.data.users > 1:
                raise BakeError(f"'{obj.data.name}' is used by {obj.data.users} objects and shape keys "
                                "would deform all of them: make it single-user, or bake to PC2")
            if key is not None and not key.use_relative:
                raise BakeError(f"'{obj.name}' has absolute shape keys: baking adds relative keys, "
                                "switch them to relative or bake to PC2")
        above = _modifiers_above(obj, live)
        if above:
            effect = ("are overwritten by the Mesh Cache" if mode == "PC2"
                      else "now act before the deformation")
            self.warnings.append(f"Modifiers above '{live.name}' ({', '.join(above)}) {effect}: "
                                 "move the deformer to the top of the stack for an exact bake")
        self.object, self.uid, self.mode, self.scene = obj, deformer.uid, mode, scene
        self.frames = list(range(frame_start, frame_end + 1))
        self.done = 0
        self.keys: list[str] = []
        self.basis_created = False
        self.action_created = ""
        self._capture: _Capture | None = None
        self._writer: PC2Writer | None = None
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
        if self.mode == "PC2":
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._writer = PC2Writer(self.path, len(obj.data.vertices), float(self.frames[0]), 1.0)
            except OSError as exc:
                raise BakeError(f"Cannot write the cache '{self.filepath}': {exc.strerror or exc}") from exc
        elif obj.data.shape_keys is None:
            obj.shape_key_add(name="Basis", from_mix=False)
            self.basis_created = True
        self._capture = _Capture(self.scene, obj, self.uid, with_input=self.mode == "SHAPE_KEYS")
        # A previous shape-key bake of this deformer must not be part of the shape-key mix captured
        # now: muted while baking (commit removes those keys; abort un-mutes them).
        previous = bake_state(_find(obj, self.uid)[1])
        blocks = obj.data.shape_keys.key_blocks if obj.data.shape_keys is not None else {}
        for name in (previous or {}).get("keys", []) if (previous or {}).get("mode") == "SHAPE_KEYS" else []:
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
        if self._writer is not None:
            self._writer.add(positions)
        else:
            # Relative to the basis, the key adds what the deformer adds to the shape-key mix at this
            # frame, so the other keys (at their values of this frame) plus this one give the output.
            key = obj.data.shape_keys
            basis = np.empty(len(positions) * 3, dtype=np.float32)
            key.reference_key.data.foreach_get("co", basis)
            delta = positions.astype(np.float64) - self._capture.input_positions(depsgraph)
            block = obj.shape_key_add(name=_key_name(deformer.name, frame), from_mix=False)
            self.keys.append(block.name)  # Blender appends .001 when the name is taken
            block.value = 0.0
            block.data.foreach_set("co", (basis.reshape(-1, 3) + delta).astype(np.float32).ravel())
        self.done += 1
        return self.done < self.total

    def commit(self) -> str:
        """Swap the bake in (replacing a previous bake of this deformer) and mute the live modifier.
        Returns a summary for the report."""
        obj = self.object
        _index, deformer = _find(obj, self.uid)
        previous = bake_state(deformer)
        created_mod = None
        try:
            if self.mode == "PC2":
                self._writer.commit()
                self._writer = None
                created_mod = self._add_mesh_cache(deformer)
            else:
                key = obj.data.shape_keys
                anim = key.animation_data or key.animation_data_create()
                if anim.action is None:
                    anim.action = bpy.data.actions.new(f"{key.name}Action")
                    self.action_created = anim.action.name
                _key_frames(key, self.keys, self.frames)
        except BaseException:
            if created_mod is not None:
                obj.modifiers.remove(created_mod)
            raise
        if previous is not None:
            _remove_artifacts(obj, previous)
            if self.mode == "SHAPE_KEYS" and previous.get("mode") == "SHAPE_KEYS":
                # The basis and action the first bake created are this bake's to remove at un-bake.
                self.basis_created = self.basis_created or bool(previous.get("basis_created", False))
                self.action_created = self.action_created or previous.get("action", "")
            if self.mode == "SHAPE_KEYS":
                # A previous bake held the names: give the new keys the intended ones (curves follow).
                for i, frame in enumerate(self.frames):
                    wanted = _key_name(deformer.name, frame)
                    block = obj.data.shape_keys.key_blocks[self.keys[i]]
                    if block.name != wanted and obj.data.shape_keys.key_blocks.get(wanted) is None:
                        block.name = wanted
                        self.keys[i] = block.name
        live_flags = ((previous["show_viewport"], previous["show_render"]) if previous is not None
                      else (deformer.show_viewport, deformer.show_render))
        deformer.show_viewport = deformer.show_render = False
        if STATE_KEY in deformer:  # a re-bake: never assign over an ID property of another shape
            del deformer[STATE_KEY]
        deformer[STATE_KEY] = {
            "mode": self.mode, "frame_start": self.frames[0], "frame_end": self.frames[-1],
            "filepath": self.filepath, "modifier": created_mod.name if created_mod is not None else "",
            "keys": list(self.keys), "basis_created": self.basis_created,
            "action": self.action_created, "show_viewport": bool(live_flags[0]),
            "show_render": bool(live_flags[1]),
        }
        self.keys, self.basis_created, self.action_created = [], False, ""  # owned by the bake now
        where = f"'{self.filepath}'" if self.mode == "PC2" else f"{self.total} shape keys"
        return (f"Baked '{deformer.name}' on '{obj.name}', frames {self.frames[0]}..{self.frames[-1]}, "
                f"to {where}")

    def _add_mesh_cache(self, deformer) -> bpy.types.Modifier:
        obj = self.object
        live = _live_modifier(obj, deformer)
        mod = obj.modifiers.new(name=f"{deformer.name} Bake", type="MESH_CACHE")
        try:
            mod.cache_format = "PC2"
            mod.filepath = self.filepath
            mod.deform_mode = "OVERWRITE"
            mod.interpolation = "LINEAR"
            # Scene frame f plays sample f - frame_start (sample 0 holds the first baked frame).
            mod.play_mode, mod.time_mode = "SCENE", "FRAME"
            mod.frame_start, mod.frame_scale = float(self.frames[0]), 1.0
            mod.forward_axis, mod.up_axis = "POS_Y", "POS_Z"  # no axis conversion: local space as read
            mod.factor = 1.0
            mod.show_viewport = mod.show_render = True
            modifiers = list(obj.modifiers)
            obj.modifiers.move(modifiers.index(mod), modifiers.index(live))
        except BaseException:
            obj.modifiers.remove(mod)
            raise
        return mod

    def abort(self) -> None:
        """Drop what the job created; the object and the cache path keep what they had."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None
        try:
            if self.keys or self.basis_created or self.action_created:
                _remove_keys(self.object, self.keys, self.basis_created, self.action_created)
        finally:
            self.keys, self.basis_created, self.action_created = [], False, ""

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
    problem = binding.target_problem(obj)
    if problem:
        raise BakeError(problem)
    if not 0 <= index < len(obj.affine_deformers):
        raise BakeError(f"'{obj.name}' has no affine deformer #{index}")
    deformer = obj.affine_deformers[index]
    state = bake_state(deformer)
    if state is None:
        raise BakeError(f"'{deformer.name}' is not baked")
    if state.get("mode") == "SHAPE_KEYS" and obj.data.users > 1:
        raise BakeError(f"'{obj.data.name}' is used by {obj.data.users} objects: removing the baked "
                        "shape keys would change all of them; make it single-user first")
    _remove_artifacts(obj, state)
    deformer.show_viewport = bool(state.get("show_viewport", True))
    deformer.show_render = bool(state.get("show_render", True))
    del deformer[STATE_KEY]
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


# ---------------------------------------------------------------------------------------------- panel


def draw_bake(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """The Bake section of the deformer panel."""
    state = bake_state(deformer)
    col = layout.column(align=True)
    if state is None:
        row = col.row(align=True)
        op = row.operator(AFFINE_OT_deformer_bake.bl_idname, text="Bake PC2", icon="FILE_CACHE")
        op.index, op.mode = index, "PC2"
        op = row.operator(AFFINE_OT_deformer_bake.bl_idname, text="Bake Shape Keys", icon="SHAPEKEY_DATA")
        op.index, op.mode = index, "SHAPE_KEYS"
        return
    what = state.get("filepath") if state.get("mode") == "PC2" else "shape keys"
    col.label(text=f"Baked to {what}, frames {state.get('frame_start')}..{state.get('frame_end')}",
              icon="FILE_CACHE")
    if deformer.show_viewport or deformer.show_render:
        col.label(text="The live deformer is on too: the motion is applied twice", icon="ERROR")
    row = col.row(align=True)
    op = row.operator(AFFINE_OT_deformer_bake.bl_idname, text="Re-bake", icon="FILE_REFRESH")
    op.index, op.mode = index, state.get("mode", "PC2")
    if state.get("mode") == "PC2":
        op.filepath = state.get("filepath", "")
    row.operator(AFFINE_OT_deformer_unbake.bl_idname, text="Un-bake", icon="X").index = index
