"""The two writers of a bake (bake.py runs the job): a PC2 point cache played by a Mesh Cache modifier,
or one keyed shape key per frame.

A writer checks what it needs before anything changes (`__init__`, BakeError), prepares (`begin`),
takes every frame's deformed positions (`add`), swaps its result in (`commit`, returning what
Un-bake needs in the deformer's bake state) or drops what it made (`abort`). `remove_artifacts`
removes a committed bake of either writer (a re-bake, Un-bake).
"""

from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np

from ..files import nodes, storage
from .pc2 import PC2Writer

_KEY_NAME_ROOM = 40  # bytes of the deformer name in key names (63 bytes at most: name + " f" + frame)


class BakeError(Exception):
    """A bake that cannot start or cannot go on; the message is meant for the artist."""


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


class Pc2Target:
    """Frames into a PC2 file; committed as a Mesh Cache modifier (overwrite) directly above the live
    modifier, so modifiers below keep working on the cached shape."""

    mode = "PC2"
    needs_input = False  # the cache holds the deformer's output itself
    above_effect = "are overwritten by the Mesh Cache"

    def __init__(self, obj: bpy.types.Object, deformer, filepath: str) -> None:
        self.object = obj
        self.filepath = bpy.path.ensure_ext(filepath or default_filepath(obj, deformer), ".pc2")
        self.path = resolve_cache_path(self.filepath)
        self._writer: PC2Writer | None = None
        self.modifier = ""

    def begin(self, first_frame: int) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = PC2Writer(self.path, len(self.object.data.vertices), float(first_frame), 1.0)
        except OSError as exc:
            raise BakeError(f"Cannot write the cache '{self.filepath}': {exc.strerror or exc}") from exc

    def add(self, frame: int, deformer_name: str, positions: np.ndarray, _input: np.ndarray | None) -> None:
        self._writer.add(positions)

    def commit(self, deformer, frames: list[int], _previous: dict | None) -> dict:
        """Write the file and add the Mesh Cache modifier; the state entries Un-bake needs."""
        self._writer.commit()
        self._writer = None
        self.modifier = _add_mesh_cache(self.object, deformer, self.filepath, frames[0]).name
        return {"filepath": self.filepath, "modifier": self.modifier, "keys": [], "basis_created": False,
                "action": ""}

    def settle(self, state: dict, deformer_name: str, frames: list[int]) -> None:
        """After the previous bake was removed: nothing to rename."""

    def drop_commit(self) -> None:
        """Take back a commit that failed half way."""
        mod = self.object.modifiers.get(self.modifier)
        if mod is not None:
            self.object.modifiers.remove(mod)

    def describe(self, frames: list[int]) -> str:
        return f"'{self.filepath}'"

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.abort()
            self._writer = None


def _add_mesh_cache(obj: bpy.types.Object, deformer, filepath: str, first_frame: int) -> bpy.types.Modifier:
    live = nodes.find_modifier(obj, storage.offset_name(deformer.uid))
    mod = obj.modifiers.new(name=f"{deformer.name} Bake", type="MESH_CACHE")
    try:
        mod.cache_format = "PC2"
        mod.filepath = filepath
        mod.deform_mode = "OVERWRITE"
        mod.interpolation = "LINEAR"
        # Scene frame f plays sample f - frame_start (sample 0 holds the first baked frame).
        mod.play_mode, mod.time_mode = "SCENE", "FRAME"
        mod.frame_start, mod.frame_scale = float(first_frame), 1.0
        mod.forward_axis, mod.up_axis = "POS_Y", "POS_Z"  # no axis conversion: local space as read
        mod.factor = 1.0
        mod.show_viewport = mod.show_render = True
        modifiers = list(obj.modifiers)
        obj.modifiers.move(modifiers.index(mod), modifiers.index(live))
    except BaseException:
        obj.modifiers.remove(mod)
        raise
    return mod


class ShapeKeyTarget:
    """Frames into relative shape keys: key f holds, relative to the basis, what the deformer adds to
    the shape-key mix at frame f; keyed 1 at its frame and 0 at the neighbouring baked frames."""

    mode = "SHAPE_KEYS"
    needs_input = True  # a key holds output − input (the shape-key mix the deformer deforms)
    above_effect = "now act before the deformation"

    def __init__(self, obj: bpy.types.Object, _deformer, _filepath: str) -> None:
        key = obj.data.shape_keys
        if obj.data.users > 1:
            raise BakeError(f"'{obj.data.name}' is used by {obj.data.users} objects and shape keys "
                            "would deform all of them: make it single-user, or bake to PC2")
        if key is not None and not key.use_relative:
            raise BakeError(f"'{obj.name}' has absolute shape keys: baking adds relative keys, "
                            "switch them to relative or bake to PC2")
        self.object = obj
        self.filepath = ""
        self.keys: list[str] = []
        self.basis_created = False
        self.action_created = ""

    def begin(self, _first_frame: int) -> None:
        if self.object.data.shape_keys is None:
            self.object.shape_key_add(name="Basis", from_mix=False)
            self.basis_created = True

    def add(self, frame: int, deformer_name: str, positions: np.ndarray, inputs: np.ndarray | None) -> None:
        # Relative to the basis, the key adds what the deformer adds to the shape-key mix at this
        # frame, so the other keys (at their values of this frame) plus this one give the output.
        obj = self.object
        basis = np.empty(len(positions) * 3, dtype=np.float32)
        obj.data.shape_keys.reference_key.data.foreach_get("co", basis)
        delta = positions.astype(np.float64) - inputs
        block = obj.shape_key_add(name=_key_name(deformer_name, frame), from_mix=False)
        self.keys.append(block.name)  # Blender appends .001 when the name is taken
        block.value = 0.0
        block.data.foreach_set("co", (basis.reshape(-1, 3) + delta).astype(np.float32).ravel())

    def commit(self, deformer, frames: list[int], previous: dict | None) -> dict:
        """Key the new shape keys (the previous bake, if any, is removed by the caller first: its
        basis and action become this bake's to remove at Un-bake); the state entries Un-bake needs."""
        key = self.object.data.shape_keys
        anim = key.animation_data or key.animation_data_create()
        if anim.action is None:
            anim.action = bpy.data.actions.new(f"{key.name}Action")
            self.action_created = anim.action.name
        _key_frames(key, self.keys, frames)
        if previous is not None and previous.get("mode") == self.mode:
            self.basis_created = self.basis_created or bool(previous.get("basis_created", False))
            self.action_created = self.action_created or previous.get("action", "")
        state = {"filepath": "", "modifier": "", "keys": list(self.keys), "basis_created": self.basis_created,
                 "action": self.action_created}
        self.keys, self.basis_created, self.action_created = [], False, ""  # owned by the bake now
        return state

    def drop_commit(self) -> None:
        """Nothing to take back: keying failed before the keys became the bake's."""

    def settle(self, state: dict, deformer_name: str, frames: list[int]) -> None:
        """After the previous bake was removed: give the new keys the intended names (the previous
        keys held them; the curves follow a rename)."""
        blocks = self.object.data.shape_keys.key_blocks
        keys = state["keys"]
        for i, frame in enumerate(frames):
            wanted = _key_name(deformer_name, frame)
            block = blocks[keys[i]]
            if block.name != wanted and blocks.get(wanted) is None:
                block.name = wanted
                keys[i] = block.name

    def describe(self, frames: list[int]) -> str:
        return f"{len(frames)} shape keys"

    def abort(self) -> None:
        try:
            if self.keys or self.basis_created or self.action_created:
                _remove_keys(self.object, self.keys, self.basis_created, self.action_created)
        finally:
            self.keys, self.basis_created, self.action_created = [], False, ""


TARGETS = {Pc2Target.mode: Pc2Target, ShapeKeyTarget.mode: ShapeKeyTarget}


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


def _absolute(path: str) -> str:
    return os.path.normpath(bpy.path.abspath(path)) if path else ""


def remove_artifacts(obj: bpy.types.Object, state: dict) -> None:
    """Remove what a bake created (the Mesh Cache modifier, or the shape keys); the cache file stays
    on disk: it may be referenced elsewhere (farm jobs, other .blend files)."""
    if state.get("mode") == "PC2":
        # Compared as absolute paths: saving may make the modifier's path relative ("//…").
        path = _absolute(state.get("filepath", ""))
        mod = obj.modifiers.get(state.get("modifier", ""))
        if mod is None or mod.type != "MESH_CACHE" or _absolute(mod.filepath) != path:
            mod = next((m for m in obj.modifiers
                        if m.type == "MESH_CACHE" and _absolute(m.filepath) == path), None)
        if mod is not None:
            obj.modifiers.remove(mod)
    else:
        _remove_keys(obj, list(state.get("keys", [])), bool(state.get("basis_created", False)),
                     state.get("action", ""))
