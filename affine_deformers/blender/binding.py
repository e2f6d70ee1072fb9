"""Deformer life cycle shared by operators, property updates and scripts: create, bind, re-weight,
remove and apply (the target checks and the lookup of a deformer by stack position or id are
addressing.py's, re-exported here). Kind-specific work (rest data, weights, motions) is delegated to
the deformer's kind (kinds/).
"""

from __future__ import annotations

import contextlib
import itertools
import zlib

import bpy
import numpy as np

from . import caches, kinds
from .files import nodes, relations, storage
from .kinds import BindError
from .tools import weight_preview
from .ui.addressing import (
    deformer_at,
    deformer_index,
    find_uid,
    library_name,
    linked_mesh_problem,
    target_problem,
)
from .update import output_store, registry

__all__ = ["BindError", "apply", "bind", "create", "deformer_at", "deformer_index", "find_uid",
           "linked_mesh_problem", "mask_weights", "rebind_probe_safely", "rebind_safely", "remove",
           "reweight", "reweight_safely", "target_problem"]


_quiet = 0


@contextlib.contextmanager
def quiet():
    """Suspend the property-update side effects (re-weighting, probe rebinding) while operators edit
    a deformer's properties themselves."""
    global _quiet
    _quiet += 1
    try:
        yield
    finally:
        _quiet -= 1


def updates_suspended() -> bool:
    return _quiet > 0


def _kind(deformer):
    kind = kinds.get(deformer.kind)
    if kind is None:
        raise BindError(f"{deformer.kind.title()} deformers are not available in this version")
    return kind


def _new_uid(obj: bpy.types.Object) -> str:
    """A short id for attribute names, derived from the object's name so rebuilt files keep
    the same attribute names; the counter skips ids already used by this object or present on its mesh (a mesh
    shared with another object may carry that object's ids)."""
    used = {d.uid for d in obj.affine_deformers}
    if obj.type == "MESH":
        used |= {storage.uid_of(a.name) for a in obj.data.attributes}
    for k in itertools.count():
        uid = format(zlib.crc32(f"{obj.name}\0{k}".encode()), "08x")
        if uid not in used:
            return uid
    raise AssertionError("unreachable")


def create(obj: bpy.types.Object, kind: str, name: str):
    """Append an unbound deformer item of `kind` to `obj` and make it the active one."""
    deformer = obj.affine_deformers.add()
    registry.add(obj)
    deformer.uid = _new_uid(obj)
    deformer.kind = kind
    deformer.name = name
    obj.affine_deformers_active_index = len(obj.affine_deformers) - 1
    return deformer


def bind(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
         only: list[int] | None = None, rest_from=None) -> None:
    """Make the controls' current poses the rest pose (all controls, or those at indices `only`),
    then compute and store the weights. `rest_from`: a bound deformer of the same kind on another
    object (the source of a copy), whose rest is carried over instead (DeformerKind.adopt_rest),
    where the kind can."""
    problem = target_problem(obj)
    if problem:
        raise BindError(problem)
    if not deformer.uid:  # an item added by a script without the operator
        deformer.uid = _new_uid(obj)
    kind = _kind(deformer)
    # The modifier names the controls first, so the depsgraph evaluates them even when they are
    # disabled in viewports (relations.py) and the rest poses read below are current.
    nodes.ensure_modifier(obj, storage.offset_name(deformer.uid), storage.motion_names(deformer.uid),
                          f"Affine {deformer.name}",
                          bool(deformer.get("stored_show_viewport", True)),
                          bool(deformer.get("stored_show_render", True)))
    if relations.sync(obj, deformer):
        depsgraph.update()
    if rest_from is None or not _adopt_rest(obj, deformer, rest_from, depsgraph):
        kind.store_rest(obj, deformer, depsgraph, only)
    reweight(obj, deformer)


def _adopt_rest(obj: bpy.types.Object, deformer, source: tuple, depsgraph: bpy.types.Depsgraph) -> bool:
    """`DeformerKind.adopt_rest` from `source` = (its object, its deformer): the rest poses in the world
    are the source's, carried into `obj`'s space by the two objects' current transforms."""
    source_obj, source_deformer = source
    if source_deformer.kind != deformer.kind or not source_deformer.is_bound:
        return False
    def world(o: bpy.types.Object) -> np.ndarray:
        return np.array(o.evaluated_get(depsgraph).matrix_world, dtype=np.float64)

    try:
        relative = np.linalg.solve(world(obj), world(source_obj))
    except np.linalg.LinAlgError:
        return False
    kind = _kind(deformer)
    return bool(np.isfinite(relative).all()) and kind.adopt_rest(source_deformer, deformer, relative)


def mask_weights(obj: bpy.types.Object, deformer) -> tuple[np.ndarray | None, str]:
    """(per-vertex mask (N,) in [0, 1] or None, warning) from the deformer's mask vertex group.

    A missing group masks nothing (like Blender's modifiers) and is reported."""
    name = deformer.mask_group
    if not name:
        return None, ""
    if obj.vertex_groups.get(name) is None:
        return None, f"No vertex group named '{name}': the mask is ignored"
    mask = nodes.vertex_group_weights(obj, [name])[:, 0]
    return np.clip(np.nan_to_num(mask, nan=0.0), 0.0, 1.0), ""


def reweight(obj: bpy.types.Object, deformer) -> None:
    """Recompute the sparse weights from the stored rest data (rest poses are kept) and store them,
    multiplied by the mask vertex group when one is set (painted 0 = the vertex stays put)."""
    problem = target_problem(obj)
    if problem:
        raise BindError(problem)
    mesh = obj.data
    rest = storage.read_positions(mesh).astype(np.float64)
    indices, values, warning = _kind(deformer).sparse_weights(obj, deformer, rest)
    mask, mask_warning = mask_weights(obj, deformer)
    if mask is not None:
        values = values * mask[:, None]
    warning = "; ".join(w for w in (warning, mask_warning) if w)
    storage.write_weights(mesh, deformer.uid, indices, values)
    relations.sync(obj, deformer)  # e.g. a probe was removed
    deformer.bound_vertex_count = len(rest)
    deformer.bound_topology = storage.topology_signature(mesh, rest)
    storage.stamp_file_format(deformer)
    deformer.bound_flag = True
    deformer.bind_warning = warning
    deformer.bind_generation += 1
    if deformer.status != warning:
        deformer.status = warning
    mesh.update_tag()


def reweight_safely(obj: bpy.types.Object, deformer) -> None:
    """`reweight` for property-update callbacks: failures become the deformer's status, never raise."""
    try:
        reweight(obj, deformer)
    except Exception as exc:  # an update callback must not leave the artist with a traceback only
        deformer.status = f"Re-weighting failed: {exc}"


def rebind_probe_safely(obj: bpy.types.Object, deformer, probe_index: int) -> None:
    """Bind one control at its current pose (others keep theirs); failures become the status."""
    try:
        bind(obj, deformer, bpy.context.evaluated_depsgraph_get(), only=[probe_index])
    except Exception as exc:  # see reweight_safely
        deformer.status = f"Binding the new probe failed: {exc}"


def rebind_safely(obj: bpy.types.Object, deformer, what: str) -> None:
    """Bind the whole deformer at the controls' current poses for a property update. A failure leaves
    the deformer unbound (rest shape) with the reason in its status, never raises."""
    try:
        bind(obj, deformer, bpy.context.evaluated_depsgraph_get())
    except Exception as exc:  # see reweight_safely
        deformer.bound_flag = False
        deformer.bind_warning = f"Binding {what} failed: {exc}"
        deformer.status = deformer.bind_warning


def remove(obj: bpy.types.Object, index: int) -> None:
    """Remove deformer `index`: its modifier, its mesh attributes and the item (rest shape back).
    Refused (BindError) on a library override, before anything changes: the item and the modifier
    come from the library, and an override cannot remove either."""
    deformer = deformer_at(obj, index)
    if obj.override_library is not None and obj.library is None:
        raise BindError(
            f"'{obj.name}' is a library override: its deformer '{deformer.name}' comes from library "
            f"'{library_name(obj)}' and cannot be removed here. Turn it off instead (its Viewport and "
            "Render toggles are kept in the override), or remove it in that file")
    uid = deformer.uid
    weight_preview.release(obj, deformer)  # the deformer takes its weight preview with it
    output_store.remove_carrier(obj, nodes.find_modifier(obj, storage.offset_name(uid)))
    relations.remove_modifier(obj, uid)
    if obj.type == "MESH" and obj.data.library is None:
        storage.remove_all(obj.data, uid)
    obj.affine_deformers.remove(index)
    obj.affine_deformers_active_index = max(0, min(obj.affine_deformers_active_index,
                                                   len(obj.affine_deformers) - 1))
    caches.forget(obj, uid)


def apply(obj: bpy.types.Object, index: int) -> None:
    """Write the deformer's current effect on the mesh's own shape into the mesh (its stored output
    applied to the rest positions: what its modifier gives when it is first in the stack, as Blender's
    Apply does for a modifier that is not first), then remove the deformer. The caller evaluates the
    deformer first so the output is current."""
    problem = target_problem(obj)
    if problem:
        raise BindError(problem)
    mesh = obj.data
    if mesh.shape_keys is not None:
        raise BindError(f"'{mesh.name}' has shape keys: apply is not supported (remove them or bake)")
    if mesh.users > 1:
        raise BindError(f"'{mesh.name}' is used by {mesh.users} objects: make it single-user first")
    deformer = deformer_at(obj, index)
    deformed = output_store.deformed_positions(obj, deformer.uid, nodes.find_modifier(
        obj, storage.offset_name(deformer.uid)))
    remove(obj, index)
    if deformed is not None:
        storage.write_positions(mesh, deformed)


def sharing_objects(obj: bpy.types.Object) -> list[bpy.types.Object]:
    """Other local objects using `obj`'s mesh (linked duplicates), O(objects) only when it is shared."""
    mesh = obj.data
    if obj.type != "MESH" or mesh is None or mesh.users <= 1:
        return []
    return [other for other in bpy.data.objects
            if other.data == mesh and other != obj and other.library is None]


def separate_shared_ids(obj: bpy.types.Object) -> list[str]:
    """Give `obj`'s deformers that share their id with a deformer of a linked duplicate (another object
    using the same mesh: Alt+D copies the deformers and their modifiers) an id of their own, so the two
    objects never read or write each other's attributes on the shared mesh. The object whose name
    comes first keeps the id; the other's bind data is copied to its new id, so its shape is the same.
    Returns the names of the deformers that got a new id."""
    others = sharing_objects(obj)
    if not others or obj.library is not None or obj.data.library is not None:
        return []
    renamed = []
    for deformer in obj.affine_deformers:
        uid = deformer.uid
        holders = [o for o in others if any(d.uid == uid for d in o.affine_deformers)]
        if not uid or not holders or min(o.name_full for o in holders) > obj.name_full:
            continue
        new_uid = _new_uid(obj)
        mesh = obj.data
        storage.copy_bind_data(mesh, uid, new_uid)
        mod = nodes.find_modifier(obj, storage.offset_name(uid))
        deformer.uid = new_uid
        if mod is not None:
            nodes.set_offset_name(mod, storage.offset_name(new_uid))
            nodes.set_motion_names(mod, storage.motion_names(new_uid))
        relations.sync(obj, deformer)
        caches.forget(obj, uid)
        renamed.append(deformer.name)
    return renamed
