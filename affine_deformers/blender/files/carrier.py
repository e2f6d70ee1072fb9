"""Deformers on library overrides: the local output carrier, and controls pointed at their overrides.

A shot file links a rig from an asset file and overrides it (Object ▸ Library Override ▸ Make). The
target object becomes a local override, but its mesh stays linked: its attributes are read-only
(writes to linked and override meshes are silently dropped by Blender, and Mesh data is not
overridable, so nothing written there would be saved either). The per-frame output of such a target
goes to a **carrier**: a hidden local mesh object in no scene, one point per target vertex, holding
the same offset / motion attributes the mesh would. An input modifier per deformer, first in the
stack (carrier_input.py), copies them onto the mesh's points before any other modifier runs, so a
Mirror, Subdivision, Array… before ours carries them as in the asset; our modifier then reads the
geometry's own attributes, as on a local target. Shots saved by the previous version named the
carrier on our modifier itself (nodes.py, version 4: read by point index, which tore the mesh after
a modifier that changes the points): `ensure` moves them to the input modifier. Local targets never
get a carrier.

The bind data (weights, rest data) stay on the linked mesh, read-only: everything that would rewrite
them (bind, re-weight, apply, paint) is refused on such a target (addressing.target_problem).

Controls: the deformer's pointers (`probes[].object`, `cage`, `armature`) are overridable, so when
the hierarchy is overridden Blender points them at the controls' overrides and saves that. A shot
overridden while the add-on was disabled (or by an older version) still names the linked controls:
`remap_controls` points them at the override of the same control in the same hierarchy.

An asset saved by a version before 0.2 (a group of version 1 or 2, linked and read-only) has no
motion inputs: its modifier cannot apply what the input modifier copies, and `problem` says what to
do. Groups of version 3 on work.
"""

from __future__ import annotations

import bpy

from .. import binding, kinds
from ..ui.addressing import library_name
from ..update import outputs
from . import carrier_input, nodes, storage

MARK = "affine_deformers_carrier"  # custom property on the carrier objects we own
NAME = ".AffineDeformer Output {}"


def needs_carrier(obj: bpy.types.Object) -> bool:
    """Whether `obj` is a local (or override) mesh object whose mesh is linked from a library or an
    override: its output cannot be written to its mesh."""
    if obj.type != "MESH" or obj.library is not None:
        return False
    mesh = obj.data
    return mesh.library is not None or mesh.override_library is not None


def problem(obj: bpy.types.Object, deformer) -> str:
    """Why deformer `deformer` of `obj` (linked, or needing a carrier) cannot follow its controls
    here, or ''."""
    mod = outputs.modifier(obj, deformer.uid) if deformer.uid else None
    if mod is not None and not (mod.show_viewport or mod.show_render):
        return ""  # muted (e.g. baked in the asset: a Mesh Cache plays instead): nothing is stale
    if obj.library is not None:  # nothing of it is local: no carrier can be named on its modifier
        return (f"'{obj.name}' is linked from '{library_name(obj)}' without a library override: its "
                "deformation cannot update here (an animated one shows its input at frames other than "
                "the one that file was saved at). Make a library override (Object ▸ Library Override ▸ "
                "Make) to animate it, or bake it in that file")
    if mod is None or nodes.has_motion_inputs(mod):
        return ""
    group = mod.node_group
    return (f"'{obj.name}' uses the node group '{group.name}' saved in '{library_name(group)}' by an older "
            "version of Affine Deformers, which cannot show a library override's deformation: open and "
            "save the asset file once with this version of Affine Deformers, or bake it there (until "
            "then the mesh shows the shape saved in the asset)")


def ensure(obj: bpy.types.Object, create: bool = True) -> bpy.types.Object | None:
    """The carrier of `obj`, with one point per vertex of its mesh, named on the input modifier of
    every deformer of `obj` (carrier_input.py) — made, resized and set up when missing and `create`;
    without `create` nothing is changed, and None is returned unless all is in place (a render frame
    may create no ID and edit no stack). None when `obj` has no modifier of ours."""
    mods = {storage.offset_name(d.uid): mod for d in obj.affine_deformers if d.uid
            for mod in [outputs.modifier(obj, d.uid)] if mod is not None}
    if not mods:
        return None
    inputs = [m for m in obj.modifiers if carrier_input.offset_of(m) in mods]
    found = next((c for c in map(nodes.carrier_of, inputs + list(mods.values())) if c is not None), None)
    if found is not None and _shared(found, obj):
        found = None  # a copy of the object (Shift+D of an override) names its original's carrier
    count = len(obj.data.vertices)
    if not create:
        ready = (found is not None and found.library is None and found.type == "MESH" and found.get(MARK)
                 and len(found.data.vertices) == count and len(inputs) == len(mods)
                 and all(nodes.carrier_of(m) == found for m in inputs))
        return found if ready else None
    if found is None or found.library is not None or found.type != "MESH" or not found.get(MARK):
        name = NAME.format(obj.name)
        found = bpy.data.objects.new(name, bpy.data.meshes.new(name))
        found[MARK] = True
    if len(found.data.vertices) != count:
        old = found.data
        mesh = bpy.data.meshes.new(old.name)
        mesh.vertices.add(count)  # the points' positions are never read, only their attributes
        found.data = mesh
        if old.users == 0:
            bpy.data.meshes.remove(old)
    carrier_input.remove_stale(obj, set(mods))
    for offset_attr, mod in mods.items():
        carrier_input.ensure_modifier(obj, offset_attr, found, mod.name)
        nodes.set_carrier(mod, None)  # read the geometry's own attributes, which the input copied
    return found


def _shared(found: bpy.types.Object, obj: bpy.types.Object) -> bool:
    """Whether another object with deformers names `found` on a modifier too (a copy of `obj`; the
    bake's stand-in, which has no deformers, reads it on purpose). Its users are the modifiers naming
    it, so the scan runs only when it has more users than `obj` has naming modifiers."""
    own = sum(nodes.carrier_of(mod) == found for mod in obj.modifiers if mod.type == "NODES")
    if found.users <= own:
        return False
    return any(nodes.carrier_of(mod) == found for other in bpy.data.objects
               if other != obj and len(other.affine_deformers)
               for mod in other.modifiers if mod.type == "NODES")


def output_mesh(obj: bpy.types.Object, create: bool = True) -> bpy.types.Mesh | None:
    """Where the output of `obj`'s deformers goes: its own mesh, or its carrier's when it needs one
    (None when that carrier does not exist and may not be made now, e.g. during a render frame)."""
    if not needs_carrier(obj):
        return obj.data
    found = ensure(obj, create)
    return found.data if found is not None else None


def ensure_all(scene: bpy.types.Scene | None = None) -> None:
    """Make the carriers the targets of `scene` (default: every object) need, before a render (no ID
    is created while a render runs) or after a file is loaded."""
    objects = scene.objects if scene is not None else bpy.data.objects
    for obj in objects:
        if len(obj.affine_deformers) and needs_carrier(obj):
            ensure(obj)


def _control_fields(deformer) -> list[tuple]:
    """(owner, property name) of every control pointer of the deformer's kind that is set."""
    kind = kinds.get(deformer.kind)
    return [] if kind is None else kind.control_pointers(deformer)


def _root(override: bpy.types.IDOverrideLibrary) -> int:
    """The session uid of an override's hierarchy root (two overrides of one rig are two hierarchies)."""
    root = override.hierarchy_root
    return root.session_uid if root is not None else 0


def remap_controls(objects=None) -> int:
    """Point every control of an override's deformers that names a linked object at that object's
    override in the same override hierarchy (a shot overridden while the add-on was disabled). Returns
    how many pointers changed."""
    objects = list(bpy.data.objects if objects is None else objects)
    overrides = {}
    for cand in bpy.data.objects:
        ol = cand.override_library
        if cand.library is None and ol is not None and ol.reference is not None:
            overrides[(ol.reference.session_uid, _root(ol))] = cand
    if not overrides:
        return 0
    changed = 0
    with binding.quiet():  # a picked control rebinds (control_picker): this is not a pick
        for obj in objects:
            ol = obj.override_library
            if obj.library is not None or ol is None:
                continue
            for deformer in obj.affine_deformers:
                for owner, name in _control_fields(deformer):
                    control = getattr(owner, name)
                    if control.library is None:
                        continue
                    found = overrides.get((control.session_uid, _root(ol)))
                    if found is not None:
                        setattr(owner, name, found)
                        changed += 1
    return changed
