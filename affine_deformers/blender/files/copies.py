"""Modifiers of ours copied without their deformer (Copy to Selected, Copy Modifiers / Ctrl+L).

A deformer is its item in `Object.affine_deformers` plus bind data on its mesh; its Geometry Nodes
modifier only applies what the handler writes. Blender's copy operators copy the modifier alone (their
poll refuses only Hook and Collision modifiers, and an add-on cannot hook it), which left a modifier
that does nothing on the target and no word. The depsgraph handler sees the copied-to object updated
and finds there a modifier of ours reading the attributes of a deformer that lives on another object
(with another mesh). On a mesh that can carry a deformer the copy is **adopted**: a deformer item of
the source's kind with its controls and settings and an id of its own, the modifier repointed at it,
bound to its own mesh at the source's rest poses (carried over by the two objects' transforms), so a
copy made while the rig is posed deforms as the source does. The bind waits for a timer (`bind_adopted`):
painted weights are read by evaluating a depsgraph, which a depsgraph handler must not do. Anywhere
else (not a mesh, linked data) the copy is removed, and the console says why.
"""

from __future__ import annotations

import traceback

import bpy

from .. import binding, kinds
from . import nodes, relations, storage

ADOPTED = "affine_deformers_adopted_from"  # ID property on an adopted item until it is bound
ADOPTED_UID = "affine_deformers_adopted_uid"  # … and the source deformer's uid, whose rest it takes
#: Deformer properties an adopted item does not copy: its identity, bind results and viewport state.
_NOT_COPIED = frozenset({"rna_type", "name", "uid", "kind", "bound_flag", "is_bound", "status",
                         "bind_warning", "bound_vertex_count", "bound_topology", "bind_generation",
                         "show_weights", "show_viewport", "show_render"})


def _owner(uid: str, obj: bpy.types.Object) -> tuple[bpy.types.Object, object] | None:
    """(object, deformer) holding deformer `uid` when it is not on `obj` nor on an object sharing
    its mesh (a linked duplicate, the bake's stand-in: no copy), else None."""
    data = obj.data
    found = None
    for other in bpy.data.objects:
        if other == obj:
            continue
        deformer = next((d for d in other.affine_deformers if d.uid == uid), None)
        if deformer is None:
            continue
        if data is not None and other.data == data:
            return None
        found = found or (other, deformer)
    return found


def dead_copies(obj: bpy.types.Object) -> list[tuple[bpy.types.Modifier, bpy.types.Object, object]]:
    """(modifier, source object, source deformer) of the modifiers of ours on `obj` copied without
    their deformer."""
    if obj.library is not None or obj.override_library is not None:
        return []
    own = {d.uid for d in getattr(obj, "affine_deformers", ())}
    found = []
    for mod in obj.modifiers:
        uid = storage.uid_of(nodes.offset_attribute(mod))
        if uid and uid not in own:
            source = _owner(uid, obj)
            if source is not None:
                found.append((mod, *source))
    return found


def _copy_properties(source, target, skipped: frozenset[str] = frozenset({"rna_type"})) -> None:
    """Copy the RNA properties of `source` to `target` (same type), items of collections included;
    pointers only to IDs (controls). A property that refuses the value keeps its default."""
    for prop in source.bl_rna.properties:
        name = prop.identifier
        if name in skipped:
            continue
        try:
            if prop.type == "COLLECTION":
                items = getattr(target, name)
                items.clear()
                for item in getattr(source, name):
                    _copy_properties(item, items.add())
            elif prop.type == "POINTER":
                value = getattr(source, name)
                if value is None or isinstance(value, bpy.types.ID):
                    setattr(target, name, value)
            elif not prop.is_readonly:
                value = getattr(source, name)
                setattr(target, name, tuple(value) if getattr(prop, "is_array", False) else value)
        except (AttributeError, TypeError, ValueError):
            continue


def _adopt(obj: bpy.types.Object, mod: bpy.types.Modifier, source: bpy.types.Object, deformer) -> str:
    """Give the copied `mod` a deformer item of its own on `obj` (bound later by `bind_adopted`)."""
    with binding.quiet():  # copying controls and weight options must not rebind or re-weight now
        new = binding.create(obj, deformer.kind, deformer.name)
        _copy_properties(deformer, new, _NOT_COPIED)
        new[ADOPTED] = source.name
        new[ADOPTED_UID] = deformer.uid
        # The status of an unbound deformer shows its bind warning: "Not bound: press Bind (…)".
        new.bind_warning = f"copied from '{source.name}', binds to this mesh at the next idle moment"
    nodes.set_offset_name(mod, storage.offset_name(new.uid))
    nodes.set_motion_names(mod, storage.motion_names(new.uid))
    if not bpy.app.timers.is_registered(bind_adopted):
        bpy.app.timers.register(bind_adopted, first_interval=0.0)
    return (f"'{mod.name}' copied to '{obj.name}' from '{source.name}': a deformer of its own, bound to "
            "its mesh")


def handle(depsgraph: bpy.types.Depsgraph) -> list[str]:
    """Adopt or remove the dead copies on the objects `depsgraph` just updated; returns (and
    prints) what was done."""
    messages = []
    for update in depsgraph.updates:
        obj = update.id.original if isinstance(update.id, bpy.types.Object) else None
        if obj is None or obj.library is not None or obj.mode == "EDIT":
            continue  # in Edit Mode the copy waits: it is adopted once the object is back in Object Mode
        for mod, source, deformer in dead_copies(obj):
            problem = binding.target_problem(obj)
            if not problem and kinds.get(deformer.kind) is None:
                problem = f"deformer kind '{deformer.kind}' is not available"
            if not problem:
                messages.append(_adopt(obj, mod, source, deformer))
                continue
            name = mod.name
            _cage, collection = nodes.controls(mod)
            nodes.remove_modifier(obj, mod)
            relations.drop_if_unused(collection)
            messages.append(f"Removed '{name}' copied to '{obj.name}' from '{source.name}': an affine "
                            f"deformer cannot be copied there ({problem})")
    for message in messages:
        print(f"Affine Deformers: {message}")
    return messages


def _source(name: str, uid: str | None) -> tuple | None:
    """(object, deformer) the adopted copy came from, when both are still there."""
    obj = bpy.data.objects.get(name)
    deformer = next((d for d in obj.affine_deformers if d.uid == uid), None) if obj and uid else None
    return (obj, deformer) if deformer is not None else None


def bind_adopted() -> None:
    """Bind every adopted deformer at its source's rest poses (a timer: outside the depsgraph
    handler). A failure leaves it unbound with the reason in its status. Returns None (no repeat)."""
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        for obj in bpy.data.objects:
            if obj.library is not None:
                continue
            for deformer in obj.affine_deformers:
                source = deformer.get(ADOPTED)
                if source is None:
                    continue
                uid = deformer.get(ADOPTED_UID)
                del deformer[ADOPTED]
                if uid is not None:
                    del deformer[ADOPTED_UID]
                try:  # at the source's rest, so the copy deforms as the source does (issue 57)
                    binding.bind(obj, deformer, depsgraph, rest_from=_source(source, uid))
                    deformer.status = deformer.bind_warning
                except Exception as exc:  # the item stays, unbound, saying why
                    deformer.status = f"Copied from '{source}': binding failed ({exc}): press Bind"
    except Exception:
        traceback.print_exc()
    return None
