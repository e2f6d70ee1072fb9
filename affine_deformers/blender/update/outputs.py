"""Where a deformer's result goes: its modifier in the stack, the output path that is exact there,
and the attribute writes (only when the values changed: a write tags the mesh for another update).

OFFSET: v' − v from the rest shape (3 floats per vertex), exact only when the positions reaching the
modifier are the mesh's own; MOTION: each vertex's affine map x ↦ M x + t as four vectors (MATH.md
§11), applied by the modifier to whatever reaches it.
"""

from __future__ import annotations

import bpy
import numpy as np

from ... import accel
from .. import caches
from ..files import carrier_input, nodes, storage
from .result import Result


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """Drop the remembered modifier names (all, or of one (object session uid, deformer uid))."""
    caches.drop(_modifiers, key)


#: (object session uid, deformer uid) → name of the modifier `nodes.find_modifier` found last time.
_modifiers: dict[tuple[int, str], str] = {}


def modifier(obj: bpy.types.Object, uid: str) -> bpy.types.Modifier | None:
    """`nodes.find_modifier(obj, offset attribute of uid)`, trying the modifier found last time first:
    it still counts when it is still ours and still reads this deformer's attribute (the same test
    find_modifier applies), otherwise the stack is searched again. Looked up once per update
    (caches.scoped)."""
    return caches.scoped(("modifier", obj.session_uid, uid), lambda: _find_modifier(obj, uid))


def _find_modifier(obj: bpy.types.Object, uid: str) -> bpy.types.Modifier | None:
    key = (obj.session_uid, uid)
    offset_attr = storage.offset_name(uid)
    name = _modifiers.get(key)
    if name is not None:
        mod = obj.modifiers.get(name)
        if nodes.is_modifier_for(mod, offset_attr):
            return mod
    mod = nodes.find_modifier(obj, offset_attr)
    if mod is None:
        _modifiers.pop(key, None)
        return None
    _modifiers[key] = mod.name
    return mod


#: Modifier types that rebuild the mesh from scratch and drop its point attributes: a deformer after
#: one of them receives no motions (measured on 4.2 and 5.0; Subdivision, Multires, Mirror, Array,
#: Bevel, Solidify, Triangulate, Decimate, Weld, Edge Split, Screw, Wireframe and Boolean keep or
#: interpolate them).
DROPS_ATTRIBUTES = frozenset({"REMESH", "SKIN", "OCEAN"})


def output_path(obj: bpy.types.Object, deformer, rest32: np.ndarray,
                mod: bpy.types.Modifier | None = None) -> tuple[str, str]:
    """('OFFSET' or 'MOTION', error) for the deformer's modifier where it stands in the stack.

    OFFSET (v' − v from the rest shape, 3 floats per vertex) is exact only when the positions that
    reach the modifier are the mesh's own (`rest32`, as stored): no modifier before it is enabled in
    the viewport or in renders, and the mesh has no shape keys, or only its reference key holding
    exactly those positions (a Basis nothing is keyed on yet). Otherwise MOTION: each vertex's affine
    map, applied to whatever reaches the modifier. A modifier before it that drops point attributes is
    an error naming it (the modifier then passes its input through). `mod`: the deformer's modifier
    when the caller has looked it up already."""
    if mod is None:
        mod = modifier(obj, deformer.uid)
    before = []
    for other in obj.modifiers:
        if other == mod:
            break
        # An override's input modifiers (carrier_input.py) only copy outputs: the positions stay.
        if (other.show_viewport or other.show_render) and not carrier_input.is_input_modifier(other):
            before.append(other)
    if not before and keys_keep_rest(obj.data, rest32):
        return "OFFSET", ""
    for other in before:
        if other.type in DROPS_ATTRIBUTES:
            return "MOTION", (f"'{other.name}' rebuilds the mesh before '{mod.name}', which then gets no "
                              f"per-vertex motions: move '{other.name}' below '{mod.name}' in the stack "
                              "(until then the deformer has no effect)")
    return "MOTION", ""


def keys_keep_rest(mesh: bpy.types.Mesh, rest32: np.ndarray) -> bool:
    """Whether the shape keys (if any) leave the mesh's stored positions as they are: none, or only the
    reference key, holding exactly `rest32` (bit for bit)."""
    key = mesh.shape_keys
    if key is None:
        return True
    if len(key.key_blocks) != 1:
        return False
    basis = np.empty(rest32.size, dtype=np.float32)
    key.key_blocks[0].data.foreach_get("co", basis)
    return accel.same_bits(basis.reshape(rest32.shape), rest32)


def write_motions(mesh: bpy.types.Mesh, uid: str, motions: np.ndarray, rows: np.ndarray | None,
                  result: Result | None) -> None:
    """Write `motions` (4, N, 3) float32 to the motion attributes unless they already hold them (as
    `write_offsets`: an incremental result is written when rows changed, a full one when it differs
    from what this process wrote last, or from what the mesh holds when that is unknown), and drop the
    offset attribute, which would add to the motion."""
    if storage.remove_output(mesh, uid, keep="MOTION"):
        mesh.update_tag()
        if result is not None:
            result.forget_written()
    if result is None or (rows is None and not result.knows_motions(motions.shape)):
        stored = storage.read_motions(mesh, uid)  # unknown: read back once, and skip an identical write
        if stored is not None and np.array_equal(stored, motions):
            if result is not None:
                result.note_motions(motions)
            return
    pending = motions if result is None else result.pending_motions(motions, rows)
    if pending is not None:
        storage.write_motions(mesh, uid, pending)


#: The largest magnitude a float32 attribute holds: beyond it a value would be stored as ±inf.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def storable(values: np.ndarray) -> bool:
    """Whether every entry of `values` is finite and within float32 range: two reductions (max and
    min propagate NaN, and ±inf fails the bounds), no temporary array and no BLAS call (whose threads
    wait for cores the kernel's threads hold)."""
    if values.size == 0:
        return True
    return bool(values.max() <= FLOAT32_MAX and values.min() >= -FLOAT32_MAX)


def finite_motions(result: np.ndarray, rows: np.ndarray | None) -> bool:
    """Whether the motions (4, N, 3) are all finite, given that only `rows` changed (see
    `finite_offsets`)."""
    if rows is not None:
        if len(rows) == 0:
            return True
        if 4 * len(rows) < result.shape[1]:
            return storable(np.take(result, rows, axis=1))
    return storable(result)


def finite_offsets(offsets: np.ndarray, rows: np.ndarray | None) -> bool:
    """Whether `offsets` (N, 3) float64 are all finite and storable as float32, given that only `rows`
    (None: any) changed since they were last found so (an incremental result starts from a checked
    one: a failed check drops it, see evaluate.evaluate_deformer)."""
    if rows is not None:
        if len(rows) == 0:
            return True
        if 4 * len(rows) < len(offsets):  # a gather of few rows costs less than a pass over all
            return storable(np.take(offsets, rows, axis=0))
    return storable(offsets)


def write_offsets(mesh: bpy.types.Mesh, uid: str, offsets: np.ndarray, rows: np.ndarray | None,
                  result: Result | None) -> None:
    """Write `offsets` to the offset attribute unless it already holds them (a write tags the mesh,
    which triggers another depsgraph update).

    With the result's copy of the attribute nothing is read back from the mesh (result.Result
    .pending_offsets: an incremental result is written when rows were recomputed, a full one when it
    differs from the copy; the rows are already in the copy, rounded by the kernel). Without a copy
    the attribute is read back once.
    """
    if result is not None and result.knows_offsets(offsets.shape):
        pending = result.pending_offsets(offsets, rows)
        if pending is not None:
            storage.write_offsets_unchecked(mesh, uid, pending)
        return
    fresh = np.array(offsets, dtype=np.float32, order="C")  # always a copy: `offsets` may be a cache's
    storage.write_offsets(mesh, uid, fresh)  # compares with what the mesh holds
    if result is not None:
        result.note_offsets(fresh)
