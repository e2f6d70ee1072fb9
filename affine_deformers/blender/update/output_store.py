"""Where an update writes a deformer's output: the mesh's attributes, or a position carrier — the vertex
positions of a hidden mesh — whichever Blender charges less for (`choose`).

What each costs, measured on bpy 5.0 (`make bench` (w) keeps the rows):

* **Attributes** (`Attribute.data.foreach_set`): a raw copy, ~0 per point, but the write tags every
  component of the mesh, its visibility included, and Blender then re-flushes visibility over the
  whole depsgraph: ~`FLUSH_SECONDS` per object the depsgraph holds, at the next evaluation. Beside
  20,000 objects that is ~95 ms an update; in a small scene nothing.
* **Positions** (`MeshVertex.co` through `vertices.foreach_set("co")`): tags only the carrier's copy
  and geometry, no re-flush; but RNA sets them one vertex at a time, ~`CO_SECONDS` per point.

So an update writes positions when (points written) × CO_SECONDS < (depsgraph objects) ×
FLUSH_SECONDS, with a margin against flipping (`HYSTERESIS`): a 5,000-vertex offset output goes to
positions beside a few hundred objects, a 130,000-vertex motion output stays on attributes until
~10,000. Both give the modifier the same float32 values, read by the same arithmetic (nodes.py),
so the result does not depend on the choice, bit for bit.

A position carrier (one per deformer, `.AffineDeformer <uid>`, a mesh object in no scene, named on our
modifier's "Output Carrier" input) holds, for N points reaching the modifier: offsets, N points then
one stamp point; motions, 4N points — column c of vertex i at c·N + i — then the stamp point, whose x
is the frame stamp (frame_check.py). The group tells the layouts apart by the count (N + 1 or 4N + 1).
It needs the points reaching our modifier to be the mesh's vertices in their order: nothing before
it but modifiers that only move vertices (`MOVES_ONLY`), and a mesh of this file (a library
override's output goes to its carrier's attributes, carrier.py). The store not chosen is emptied
(the carrier's points cleared, or the attributes removed) so the group never reads a stale one.
"""

from __future__ import annotations

import os

import bpy
import numpy as np

from .. import caches
from ..files import carrier_input, nodes, storage
from . import frame_check

#: Whether writing vertex positions tags the mesh for the next evaluation by itself: on Blender 4.2
#: `vertices.foreach_set("co")` leaves the evaluated copy stale, and only a full tag (which
#: re-flushes visibility like an attribute write) makes it seen: no cheaper store there (4.5 and 5.0
#: measured; 4.3 and 4.4 are not tested and count as 4.2).
POSITIONS_TAG_THEMSELVES = bpy.app.version >= (4, 5, 0)
CO_SECONDS = 75e-9
FLUSH_SECONDS = 4.5e-6
#: A store is left for the other only when the other costs less than this fraction of it.
HYSTERESIS = 0.7
MARK = "affine_deformers_positions"  # on a position carrier: the deformer uid it holds the output of
OWNER = "affine_deformers_owner"  # on a position carrier: the object it belongs to (a copy's is not it)
NAME = ".AffineDeformer {}"
#: Modifier types that move vertices and keep their count and order (what a position carrier, read by
#: point index, needs before our modifier). Any other type — a user's Geometry Nodes included — may
#: change the points: the output then stays on attributes, which Blender carries onto new points.
MOVES_ONLY = frozenset({
    "ARMATURE", "CAST", "CLOTH", "CORRECTIVE_SMOOTH", "CURVE", "DISPLACE", "HOOK", "LAPLACIANSMOOTH",
    "LATTICE", "MESH_CACHE", "MESH_DEFORM", "SHRINKWRAP", "SIMPLE_DEFORM", "SMOOTH", "SURFACE_DEFORM",
    "WARP", "WAVE",
})
#: For tests and `make bench`: 'ATTRIBUTES' or 'POSITIONS' forces a store where both are possible
#: (also from the environment, `AFFINE_DEFORMERS_OUTPUT_STORE`, to run a whole test suite on one).
forced: str | None = {"ATTRIBUTES": "ATTRIBUTES", "POSITIONS": "POSITIONS"}.get(
    os.environ.get("AFFINE_DEFORMERS_OUTPUT_STORE", ""))

#: (object session uid, deformer uid) → the store chosen last ('ATTRIBUTES' or 'POSITIONS').
_chosen: dict[tuple[int, str], str] = {}
#: view layer's (scene name, view layer name) → objects in its depsgraph, counted at structural changes.
_objects: dict[tuple[str, str], int] = {}
#: (object session uid, deformer uid) → the store held while a bake captures the output (bake.py).
_pinned: dict[tuple[int, str], str] = {}
#: (object session uid, deformer uid) → the store last written (`switched`).
_written: dict[tuple[int, str], str] = {}


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """Drop the remembered choices (and, at a full forget, the object counts and pins)."""
    caches.drop(_chosen, key)
    caches.drop(_pinned, key)
    caches.drop(_written, key)
    if key is None:
        _objects.clear()


def pin(obj: bpy.types.Object, uid: str, mod: bpy.types.Modifier | None) -> bpy.types.Object | None:
    """Hold deformer `uid`'s output in the store it is in now until `unpin` (a bake's capture reads
    one store for all its frames); returns its position carrier when that is the store."""
    found = carrier_of(obj, mod)
    holding = found is not None and _own(found, obj, uid) and len(found.data.vertices) > 0
    _pinned[obj.session_uid, uid] = "POSITIONS" if holding else "ATTRIBUTES"
    return found if holding else None


def unpin(obj: bpy.types.Object, uid: str) -> None:
    _pinned.pop((obj.session_uid, uid), None)


def switched(obj: bpy.types.Object, uid: str, store: str) -> bool:
    """Record that deformer `uid`'s output is written to `store` now; True when the last write went to
    the other one (what the update remembers of the written values is then about the other store)."""
    key = (obj.session_uid, uid)
    before = _written.get(key)
    _written[key] = store
    return before is not None and before != store


def note(depsgraph: bpy.types.Depsgraph | None) -> None:
    """Count the depsgraph's objects again when objects may have come or gone."""
    if depsgraph is None:
        return
    if depsgraph.id_type_updated("SCENE") or depsgraph.id_type_updated("COLLECTION"):
        _objects.pop(_layer_key(depsgraph), None)


def _layer_key(depsgraph: bpy.types.Depsgraph) -> tuple[str, str]:
    return depsgraph.scene.name_full, depsgraph.view_layer.name


def objects_in(depsgraph: bpy.types.Depsgraph) -> int:
    """The objects of `depsgraph`'s view layer (~0.4 ms at 20,000: counted only after a change)."""
    key = _layer_key(depsgraph)
    count = _objects.get(key)
    if count is None:
        count = _objects[key] = len(depsgraph.view_layer.objects)
    return count


def index_aligned(obj: bpy.types.Object, mod: bpy.types.Modifier | None) -> bool:
    """Whether the points reaching `mod` are `obj`'s mesh's vertices in their order: every enabled
    modifier before it only moves vertices (ours included, and a library override's input ones)."""
    for other in obj.modifiers:
        if other == mod:
            return True
        if not (other.show_viewport or other.show_render):
            continue
        if other.type == "NODES":
            if not (carrier_input.is_input_modifier(other) or nodes.offset_attribute(other)):
                return False
        elif other.type not in MOVES_ONLY:
            return False
    return mod is not None


def choose(obj: bpy.types.Object, uid: str, mod: bpy.types.Modifier | None, path: str,
           depsgraph: bpy.types.Depsgraph) -> str:
    """'POSITIONS' or 'ATTRIBUTES' for deformer `uid`'s output on `obj` this update (module doc)."""
    mesh = obj.data
    if (not POSITIONS_TAG_THEMSELVES or mesh.library is not None or mesh.override_library is not None
            or not nodes.reads_positions(mod) or not index_aligned(obj, mod)):
        return "ATTRIBUTES"
    key = (obj.session_uid, uid)
    if key in _pinned:
        return _pinned[key]
    if forced is not None:
        return forced
    points = (4 if path == "MOTION" else 1) * len(mesh.vertices) + 1
    positions = points * CO_SECONDS
    attributes = objects_in(depsgraph) * FLUSH_SECONDS
    before = _chosen.get(key, "ATTRIBUTES")
    if before == "ATTRIBUTES":
        chosen = "POSITIONS" if positions < HYSTERESIS * attributes else before
    else:
        chosen = "ATTRIBUTES" if attributes < HYSTERESIS * positions else before
    _chosen[key] = chosen
    return chosen


# ------------------------------------------------------------------------------------------ carriers


def carrier_of(obj: bpy.types.Object, mod: bpy.types.Modifier | None) -> bpy.types.Object | None:
    """The position carrier named on our modifier `mod` of `obj` (None: none, or another kind)."""
    found = nodes.carrier_of(mod) if mod is not None else None
    return found if found is not None and found.get(MARK) and found.type == "MESH" else None


def _own(found: bpy.types.Object, obj: bpy.types.Object, uid: str) -> bool:
    """`found` is `obj`'s carrier of deformer `uid` (a copy of `obj`, Shift+D, names its original's)."""
    return found.library is None and found.get(MARK) == uid and found.get(OWNER) == obj


def ensure_carrier(obj: bpy.types.Object, uid: str, mod: bpy.types.Modifier,
                   create: bool) -> bpy.types.Object | None:
    """Deformer `uid`'s position carrier, named on `mod` (made when missing and `create`: never during
    a render frame, which may create no ID)."""
    found = carrier_of(obj, mod)
    if found is not None and _own(found, obj, uid):
        return found
    if not create:
        return None
    name = NAME.format(uid)
    found = bpy.data.objects.new(name, bpy.data.meshes.new(name))
    found[MARK], found[OWNER] = uid, obj
    nodes.set_carrier(mod, found)
    return found


def empty_carrier(obj: bpy.types.Object, mod: bpy.types.Modifier | None) -> bool:
    """Clear the points of the position carrier on `mod`, so the group reads the mesh's own attributes
    again (a copy's carrier, still its original's, is let go instead); True when it held points."""
    found = carrier_of(obj, mod)
    if found is None or found.library is not None:
        return False
    if found.get(OWNER) != obj:
        nodes.set_carrier(mod, None)
        return True
    if not len(found.data.vertices):
        return False
    found.data.clear_geometry()
    return True


def remove_carrier(obj: bpy.types.Object, mod: bpy.types.Modifier | None) -> None:
    """Delete `obj`'s position carrier on `mod` with its mesh (the deformer is removed)."""
    found = carrier_of(obj, mod)
    if found is None or found.library is not None or found.get(OWNER) != obj:
        return
    mesh = found.data
    bpy.data.objects.remove(found)
    if mesh.users == 0:
        bpy.data.meshes.remove(mesh)


def stored_output(obj: bpy.types.Object, uid: str, mod: bpy.types.Modifier | None
                  ) -> tuple[str, np.ndarray] | None:
    """('OFFSET', (N, 3)) or ('MOTION', (4, N, 3)) float32: deformer `uid`'s output where it lives
    now (its position carrier, else the mesh's attributes); None without one."""
    mesh = obj.data
    found = carrier_of(obj, mod)
    n = len(mesh.vertices)
    if found is not None and len(found.data.vertices) in (n + 1, 4 * n + 1):
        points = found.data.vertices
        flat = np.empty(len(points) * 3, dtype=np.float32)
        points.foreach_get("co", flat)
        data = flat.reshape(-1, 3)[:-1]
        return ("OFFSET", data) if len(data) == n else ("MOTION", data.reshape(4, n, 3))
    motions = storage.read_motions(mesh, uid)
    if motions is not None:
        return "MOTION", motions
    offsets = storage.read_offsets(mesh, uid)
    return None if offsets is None or offsets.shape != (n, 3) else ("OFFSET", offsets)


def deformed_positions(obj: bpy.types.Object, uid: str,
                       mod: bpy.types.Modifier | None) -> np.ndarray | None:
    """The mesh's rest positions moved by deformer `uid`'s stored output, float32 (N, 3), as its modifier
    computes them when it is first in the stack (Apply); None without an output."""
    found = stored_output(obj, uid, mod)
    if found is None:
        return None
    path, data = found
    rest = storage.read_positions(obj.data)
    if path == "OFFSET":
        return rest + data
    x, y, z = (rest[:, i : i + 1] for i in range(3))
    return x * data[0] + y * data[1] + z * data[2] + data[3]


class PositionStore:
    """Writes an output into a position carrier's mesh (layout in the module doc). `written` is what
    it holds, kept by the update (result.Result) to skip identical writes."""

    def __init__(self, mesh: bpy.types.Mesh) -> None:
        self.mesh = mesh

    def write(self, data: np.ndarray, stamp: float) -> None:
        """Write `data` ((N, 3) offsets or (4, N, 3) motions, float32) and the stamp point."""
        flat = np.empty((data.size // 3 + 1, 3), dtype=np.float32)
        flat[:-1] = data.reshape(-1, 3)
        flat[-1] = (stamp, 0.0, 0.0)
        mesh = self.mesh
        if len(mesh.vertices) != len(flat):
            mesh.clear_geometry()
            mesh.vertices.add(len(flat))
        mesh.vertices.foreach_set("co", flat.ravel())
        frame_check.remember(mesh, np.float32(stamp))

    def stamp(self, value: float) -> None:
        """Only the stamp point (the data are right at this time too)."""
        mesh = self.mesh
        if len(mesh.vertices) and not frame_check.remembered(mesh, np.float32(value)):
            mesh.vertices[len(mesh.vertices) - 1].co = (value, 0.0, 0.0)
            frame_check.remember(mesh, np.float32(value))


def drop_attributes(mesh: bpy.types.Mesh, uid: str) -> bool:
    """Remove deformer `uid`'s output attributes from `mesh` (its output now lives in a carrier); True
    when there were any."""
    removed = storage.remove_output(mesh, uid)
    stamp = mesh.attributes.get(storage.frame_name(uid))
    if stamp is not None:
        mesh.attributes.remove(stamp)
        removed = True
    if removed:
        mesh.update_tag()
    return removed
