"""Bind data and results as mesh attributes, so they are saved in the .blend (never Python globals).

Per deformer with short id `uid`, on the target mesh:
  `.affdef_<uid>_idx<k>`  INT   POINT  k-th influencing control of each vertex   (k < K)
  `.affdef_<uid>_w<k>`    FLOAT POINT  its weight (strength not applied)
  `affdef_<uid>_offset`   FLOAT_VECTOR POINT  deformed − rest, added by our Geometry Nodes modifier
                                              (the fast path: first in the stack, no shape keys), or
  `.affdef_<uid>_m{x,y,z,t}` FLOAT_VECTOR POINT  each vertex's motion x ↦ M x + t as the columns
                                              M e_x, M e_y, M e_z and t, applied by the modifier to
                                              the positions that reach it (nodes.py).
A deformer's output is one of the two forms at a time (the other is removed when it switches).
All reads and writes go through foreach_get/foreach_set on numpy buffers (no loops over vertices).
"""

from __future__ import annotations

import re
import zlib

import bpy
import numpy as np

from ..update.validation import MAX_WEIGHT, values_problem


class StorageError(Exception):
    """Bind data on the mesh is missing or inconsistent (the message says what to do)."""


#: The layout of the bind data in a .blend, versioned apart from the extension (which can change
#: without touching it). 1: written by 0.1.x (no format stamp). 2: weights may use the pooled column
#: (index m, MATH.md §12), a bound topology signature. 3: a bone deformer's weights may use the
#: pooled nodes m … 2m (core.hierarchy.pool_parents). Stamped on each deformer at bind; a deformer
#: of a higher format (bound by a newer add-on) is not evaluated: its status says to update.
FILE_FORMAT = 3
FORMAT_KEY = "file_format"


def file_format(deformer) -> int:
    """The format the deformer's bind data was written in (1 for files from before the stamp)."""
    value = deformer.get(FORMAT_KEY, 1)
    return value if isinstance(value, int) else 1


def stamp_file_format(deformer) -> None:
    deformer[FORMAT_KEY] = FILE_FORMAT


def offset_name(uid: str) -> str:
    return f"affdef_{uid}_offset"


MOTION_SUFFIXES = ("mx", "my", "mz", "mt")


def frame_name(uid: str) -> str:
    """The attribute holding the scene time deformer `uid`'s output was computed for (frame_check.py)."""
    return f".affdef_{uid}_frame"


def motion_names(uid: str) -> tuple[str, str, str, str]:
    """The four motion attributes of deformer `uid`: columns M e_x, M e_y, M e_z and t."""
    return tuple(f".affdef_{uid}_{suffix}" for suffix in MOTION_SUFFIXES)


def index_name(uid: str, k: int) -> str:
    return f".affdef_{uid}_idx{k}"


def weight_name(uid: str, k: int) -> str:
    return f".affdef_{uid}_w{k}"


_ANY_PATTERN = re.compile(r"^\.?affdef_([0-9a-f]+)_")


def uid_of(attribute_name: str) -> str:
    """The deformer id in one of our attribute names ('' for other attributes)."""
    match = _ANY_PATTERN.match(attribute_name)
    return match.group(1) if match else ""


def _bind_pattern(uid: str) -> re.Pattern[str]:
    return re.compile(rf"^\.affdef_{re.escape(uid)}_(idx|w)\d+$")


def _position_attribute(mesh: bpy.types.Mesh) -> bpy.types.Attribute | None:
    attr = mesh.attributes.get("position")
    return attr if attr is not None and attr.data_type == "FLOAT_VECTOR" and attr.domain == "POINT" else None


def read_positions(mesh: bpy.types.Mesh) -> np.ndarray:
    """Rest positions (N, 3) float32, exactly as stored in the mesh."""
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    attr = _position_attribute(mesh)
    # The generic attribute is a plain array copy; MeshVertex.co goes through RNA per item (~40x slower).
    if attr is not None:
        attr.data.foreach_get("vector", co)
    else:
        mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _internal_attribute(mesh: bpy.types.Mesh, name: str, data_type: str, domain: str
                        ) -> bpy.types.Attribute | None:
    attr = mesh.attributes.get(name)
    return attr if attr is not None and attr.data_type == data_type and attr.domain == domain else None


def _ints(mesh: bpy.types.Mesh, attribute: tuple[str, str, str], items: bpy.types.bpy_prop_collection,
          prop: str, size: int) -> np.ndarray:
    """(size,) int32 from the generic attribute (name, data type, domain) when the mesh has it, a
    plain array copy, else from the RNA property `prop` of `items`, which goes item by item (~50×
    slower)."""
    out = np.empty(size, dtype=np.int32)
    attr = _internal_attribute(mesh, *attribute)
    if attr is not None:
        attr.data.foreach_get("value", out)
    else:
        items.foreach_get(prop, out)
    return out


def corner_vertices(mesh: bpy.types.Mesh) -> np.ndarray:
    """Each face corner's vertex index (L,) int32 (MeshLoop.vertex_index)."""
    return _ints(mesh, (".corner_vert", "INT", "CORNER"), mesh.loops, "vertex_index", len(mesh.loops))


def edge_vertices(mesh: bpy.types.Mesh) -> np.ndarray:
    """Each edge's two vertex indices, flat (2E,) int32 (MeshEdge.vertices)."""
    return _ints(mesh, (".edge_verts", "INT32_2D", "EDGE"), mesh.edges, "vertices", 2 * len(mesh.edges))


def face_corners(mesh: bpy.types.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(loop_start (F,), loop_total (F,)) int32 of the faces. The faces' corners are consecutive
    (Blender stores one offsets array, start_f = offset_f and total_f = offset_{f+1} − offset_f), so
    the totals follow from the starts and one RNA read suffices."""
    start = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_start", start)
    total = np.diff(start, append=np.int32(len(mesh.loops))).astype(np.int32, copy=False)
    return start, total


def write_positions(mesh: bpy.types.Mesh, positions: np.ndarray) -> None:
    flat = np.ascontiguousarray(positions, dtype=np.float32).ravel()
    attr = _position_attribute(mesh)
    if attr is not None:
        attr.data.foreach_set("vector", flat)
    else:
        mesh.vertices.foreach_set("co", flat)
    mesh.update()


def topology_signature(mesh: bpy.types.Mesh, positions: np.ndarray) -> str:
    """'<connectivity crc>:<positions crc>' — CRC-32s of the edges' and corners' vertex indices (with
    the counts) and of the rest positions (N, 3) float32. Bind weights belong to vertex indices:
    deleting one vertex and adding another keeps the vertex count but renumbers the vertices, which
    changes both; an edit of the shape alone, or of the faces alone, changes one (see
    evaluate._check_vertices)."""
    edges, corners = edge_vertices(mesh), corner_vertices(mesh)
    counts = np.array([len(mesh.edges), len(mesh.loops), len(mesh.polygons)], dtype=np.int64)
    connectivity = zlib.crc32(corners.tobytes(), zlib.crc32(edges.tobytes(), zlib.crc32(counts.tobytes())))
    shape = zlib.crc32(np.ascontiguousarray(positions, dtype=np.float32).tobytes())
    return f"{connectivity:08x}:{shape:08x}"


def _point_attribute(mesh: bpy.types.Mesh, name: str, data_type: str) -> bpy.types.Attribute:
    """The attribute `name` with the given type on the POINT domain, (re)created when it is not."""
    attr = mesh.attributes.get(name)
    if attr is not None and (attr.data_type != data_type or attr.domain != "POINT"):
        mesh.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = mesh.attributes.new(name, data_type, "POINT")
    return attr


def remove_bind_data(mesh: bpy.types.Mesh, uid: str) -> None:
    """Remove the weight attributes of deformer `uid` (the offset attribute stays)."""
    pattern = _bind_pattern(uid)
    for name in [a.name for a in mesh.attributes if pattern.match(a.name)]:
        mesh.attributes.remove(mesh.attributes[name])


def remove_all(mesh: bpy.types.Mesh, uid: str) -> None:
    """Remove every attribute of deformer `uid`, its output included: the mesh shows the rest shape."""
    remove_bind_data(mesh, uid)
    remove_output(mesh, uid)
    stamp = mesh.attributes.get(frame_name(uid))
    if stamp is not None:
        mesh.attributes.remove(stamp)
    mesh.update_tag()


def remove_output(mesh: bpy.types.Mesh, uid: str, keep: str = "") -> bool:
    """Remove deformer `uid`'s output attributes (offset and motion), except the form `keep`
    ('OFFSET' or 'MOTION'); True when something was removed (the caller tags the mesh)."""
    names = [] if keep == "MOTION" else list(motion_names(uid))
    if keep != "OFFSET":
        names.append(offset_name(uid))
    removed = False
    for name in names:
        attr = mesh.attributes.get(name)
        if attr is not None:
            mesh.attributes.remove(attr)
            removed = True
    return removed


def copy_bind_data(mesh: bpy.types.Mesh, uid: str, new_uid: str) -> None:
    """Copy deformer `uid`'s weight attributes to the names of `new_uid` (a deformer given a new id)."""
    remove_bind_data(mesh, new_uid)
    n = len(mesh.vertices)
    k = 0
    while (a_i := mesh.attributes.get(index_name(uid, k))) is not None:
        a_w = mesh.attributes.get(weight_name(uid, k))
        if a_w is None:
            break
        column_i = np.empty(n, dtype=np.int32)
        column_w = np.empty(n, dtype=np.float32)
        a_i.data.foreach_get("value", column_i)
        a_w.data.foreach_get("value", column_w)
        _point_attribute(mesh, index_name(new_uid, k), "INT").data.foreach_set("value", column_i)
        _point_attribute(mesh, weight_name(new_uid, k), "FLOAT").data.foreach_set("value", column_w)
        k += 1


def write_weights(mesh: bpy.types.Mesh, uid: str, indices: np.ndarray, values: np.ndarray) -> None:
    """Store sparse weights: indices (N, K) int, values (N, K) (stored as float32)."""
    n = len(mesh.vertices)
    if indices.shape != values.shape or indices.ndim != 2 or indices.shape[0] != n:
        raise StorageError(f"weights of shape {indices.shape} do not match {n} vertices")
    remove_bind_data(mesh, uid)
    for k in range(indices.shape[1]):
        column_i = np.ascontiguousarray(indices[:, k], dtype=np.int32)
        column_w = np.ascontiguousarray(values[:, k], dtype=np.float32)
        _point_attribute(mesh, index_name(uid, k), "INT").data.foreach_set("value", column_i)
        _point_attribute(mesh, weight_name(uid, k), "FLOAT").data.foreach_set("value", column_w)


def read_weights(mesh: bpy.types.Mesh, uid: str, n_controls: int) -> tuple[np.ndarray, np.ndarray]:
    """Sparse weights (indices (N, K) int32, values (N, K) float64) checked as bind data: each
    column a pair of POINT attributes (INT, FLOAT), every index in [0, n_controls), every weight a
    finite number in [0, validation.MAX_WEIGHT]; StorageError naming the damaged attribute."""
    n = len(mesh.vertices)
    columns_i, columns_w = [], []
    k = 0
    while (a_i := mesh.attributes.get(index_name(uid, k))) is not None:
        a_w = mesh.attributes.get(weight_name(uid, k))
        problem = _column_problem(a_i, "INT") or (f"'{weight_name(uid, k)}' is missing" if a_w is None
                                                  else _column_problem(a_w, "FLOAT"))
        if problem:
            raise StorageError(f"weight attributes are damaged ({problem}): rebind the deformer")
        column_i = np.empty(n, dtype=np.int32)
        column_w = np.empty(n, dtype=np.float32)
        a_i.data.foreach_get("value", column_i)
        a_w.data.foreach_get("value", column_w)
        problem = values_problem(f"'{index_name(uid, k)}'", column_i, 0, max(n_controls, 1) - 1, "vertex")
        if problem:
            raise StorageError(f"weights refer to controls that no longer exist ({problem}): "
                               "rebind the deformer")
        problem = values_problem(f"'{weight_name(uid, k)}'", column_w, 0.0, MAX_WEIGHT, "vertex")
        if problem:
            raise StorageError(f"weight attributes are damaged ({problem}): rebind the deformer")
        columns_i.append(column_i)
        columns_w.append(column_w)
        k += 1
    if k == 0:
        raise StorageError("no bind data on the mesh: rebind the deformer")
    return np.stack(columns_i, axis=1), np.stack(columns_w, axis=1).astype(np.float64)


def _column_problem(attribute: bpy.types.Attribute, data_type: str) -> str:
    """Why a stored weight column's attribute is not of `data_type` on the POINT domain ('' if it is)."""
    if attribute.data_type == data_type and attribute.domain == "POINT":
        return ""
    return (f"'{attribute.name}' is {attribute.data_type} on the {attribute.domain} domain, not "
            f"{data_type} on POINT")


def read_offsets(mesh: bpy.types.Mesh, uid: str) -> np.ndarray | None:
    attr = mesh.attributes.get(offset_name(uid))
    if attr is None or attr.data_type != "FLOAT_VECTOR" or attr.domain != "POINT":
        return None
    out = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    attr.data.foreach_get("vector", out)
    return out.reshape(-1, 3)


def write_offsets(mesh: bpy.types.Mesh, uid: str, offsets: np.ndarray) -> bool:
    """Write offsets (N, 3) when they differ from the stored ones; True when something was written.

    Skipping identical writes matters: a write tags the mesh, which triggers another depsgraph update.
    """
    offsets = np.ascontiguousarray(offsets, dtype=np.float32)
    current = read_offsets(mesh, uid)
    if current is not None and current.shape == offsets.shape and np.array_equal(current, offsets):
        return False
    write_offsets_unchecked(mesh, uid, offsets)
    return True


def write_offsets_unchecked(mesh: bpy.types.Mesh, uid: str, offsets: np.ndarray) -> None:
    """Write offsets (N, 3) float32 C-contiguous (the caller knows they differ from the stored ones),
    creating the attribute if needed, and tag the mesh."""
    shape = (len(mesh.vertices), 3)
    if offsets.dtype != np.float32 or not offsets.flags.c_contiguous or offsets.shape != shape:
        raise StorageError(f"offsets must be C-contiguous float32 of shape ({len(mesh.vertices)}, 3)")
    _point_attribute(mesh, offset_name(uid), "FLOAT_VECTOR").data.foreach_set("vector", offsets.ravel())
    mesh.update_tag()


def read_motions(mesh: bpy.types.Mesh, uid: str) -> np.ndarray | None:
    """The stored motions (4, N, 3) float32 (columns M e_x, M e_y, M e_z, t), or None when any of the
    four attributes is missing or of another type."""
    n = len(mesh.vertices)
    out = np.empty((4, n, 3), dtype=np.float32)
    for column, name in zip(out, motion_names(uid), strict=True):
        attr = mesh.attributes.get(name)
        if attr is None or attr.data_type != "FLOAT_VECTOR" or attr.domain != "POINT":
            return None
        attr.data.foreach_get("vector", column.reshape(-1))
    return out


def write_motions(mesh: bpy.types.Mesh, uid: str, motions: np.ndarray) -> None:
    """Write motions (4, N, 3) float32 C-contiguous into the four motion attributes (created when
    needed) and tag the mesh. The caller knows they differ from the stored ones."""
    shape = (4, len(mesh.vertices), 3)
    if motions.dtype != np.float32 or not motions.flags.c_contiguous or motions.shape != shape:
        raise StorageError(f"motions must be C-contiguous float32 of shape {shape}")
    for column, name in zip(motions, motion_names(uid), strict=True):
        _point_attribute(mesh, name, "FLOAT_VECTOR").data.foreach_set("vector", column.reshape(-1))
    mesh.update_tag()


def write_frame(mesh: bpy.types.Mesh, uid: str, value: float) -> None:
    """Write `value` at every point of deformer `uid`'s frame stamp (frame_check.py) and tag the mesh."""
    _point_attribute(mesh, frame_name(uid), "FLOAT").data.foreach_set(
        "value", np.full(len(mesh.vertices), value, dtype=np.float32))
    mesh.update_tag()
