"""One input snapshot per update (blender/update/snapshot.py): every property of a deformer is either
read into it or declared with the reason it need not be, and each declaration is checked by changing the
property. Plus the kind interface: every registered kind implements the whole DeformerKind interface."""

from __future__ import annotations

import importlib
import inspect

import bpy


def _modules(installed):
    load = lambda name: importlib.import_module(f"{installed.package}.blender.{name}")  # noqa: E731
    return load("update.snapshot"), load("props"), load("kinds")


def _rig(bl):
    target = bl.grid_cube(cuts=6)
    probes = [bl.empty("A", (-0.8, 0.0, 0.0)), bl.empty("B", (0.8, 0.0, 0.0))]
    deformer = bl.add_probe_deformer(target, probes, radius=1.5, weight_mode="FALLOFF")
    probes[0].location.x += 0.2
    bpy.context.view_layer.update()
    return target, probes, deformer


def _signature(snapshot, target, deformer):
    return snapshot.take(target, deformer, bpy.context.evaluated_depsgraph_get()).signature()


def test_every_deformer_property_is_read_or_declared(installed):
    snapshot, props, _kinds = _modules(installed)
    names = {p.identifier for p in props.AffineDeformer.bl_rna.properties} - {"rna_type"}
    declared = set(snapshot.SETTINGS) | set(snapshot.DECLARED)
    assert not set(snapshot.SETTINGS) & set(snapshot.DECLARED)
    assert names == declared, (sorted(names - declared), sorted(declared - names))


def _changed(value, prop):
    """Another valid value of an RNA property."""
    if prop.type == "ENUM":
        return next(item.identifier for item in prop.enum_items if item.identifier != value)
    if prop.type == "BOOLEAN":
        return not value
    if prop.type == "INT":
        return value + 1
    return 0.5 * value + 0.1


def test_each_setting_changes_the_signature(bl, installed):
    snapshot, props, _kinds = _modules(installed)
    target, _probes, deformer = _rig(bl)
    rna = props.AffineDeformer.bl_rna.properties
    before = _signature(snapshot, target, deformer)
    assert _signature(snapshot, target, deformer) == before  # nothing changed: the same inputs
    for name in snapshot.SETTINGS:
        old = getattr(deformer, name)
        setattr(deformer, name, _changed(old, rna[name]))
        assert _signature(snapshot, target, deformer) != before, name
        setattr(deformer, name, old)


def test_each_reweighting_property_bumps_the_bind_generation(bl, installed):
    snapshot, props, _kinds = _modules(installed)
    target, _probes, deformer = _rig(bl)
    target.vertex_groups.new(name="Mask").add(list(range(10)), 1.0, "REPLACE")
    cage = bl.grid_cube(cuts=1, size=4.0, name="Cage")
    bpy.context.view_layer.objects.active = target
    cage.select_set(True)
    target.select_set(True)
    assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
    cage_deformer = target.affine_deformers[-1]
    rna = props.AffineDeformer.bl_rna.properties
    values = {"mask_group": "Mask", "weight_mode": "INVERSE_DISTANCE", "half_space": True,
              "cage_weights": "INVERSE_DISTANCE", "normalize": "NONE"}
    reweighting = [n for n, why in snapshot.DECLARED.items() if why.startswith("re-weights")]
    assert len(reweighting) >= 8
    for name in reweighting:
        item = cage_deformer if name in ("half_space", "cage_weights") else deformer
        generation = item.bind_generation
        old = getattr(item, name)
        new = values.get(name)
        if new is None or new == old:
            new = _changed(old, rna[name]) if not isinstance(old, bool) else not old
        setattr(item, name, new)
        assert item.bind_generation > generation, name


def test_what_the_kind_reads_changes_the_signature(bl, installed):
    """'probes' (and, for cages, 'cage' and its rest data) are declared as read by the kind: moving a
    probe's object or re-picking it changes the motions and so the signature."""
    snapshot, _props, _kinds = _modules(installed)
    target, probes, deformer = _rig(bl)
    before = _signature(snapshot, target, deformer)
    probes[1].location.z += 0.3
    bpy.context.view_layer.update()
    moved = _signature(snapshot, target, deformer)
    assert moved != before
    other = bl.empty("C", (0.0, 0.9, 0.0))
    deformer.probes[1].object = other  # re-picking binds the new probe at its pose
    bpy.context.view_layer.update()
    assert _signature(snapshot, target, deformer) != moved


def test_pre_checked_properties_change_the_error(bl, installed):
    snapshot, _props, _kinds = _modules(installed)
    target, _probes, deformer = _rig(bl)
    assert snapshot.take(target, deformer, bpy.context.evaluated_depsgraph_get()).error == ""
    deformer.bound_vertex_count += 1
    assert "vertices" in snapshot.take(target, deformer, bpy.context.evaluated_depsgraph_get()).error
    deformer.bound_vertex_count -= 1
    deformer.bound_flag = False
    assert "Not bound" in snapshot.take(target, deformer, bpy.context.evaluated_depsgraph_get()).error


def test_every_registered_kind_implements_the_interface(installed):
    """Every kind in the registry subclasses DeformerKind with nothing abstract left, has every
    attribute of the interface, and its own properties, classes and add operator are registered."""
    _snapshot, props, kinds = _modules(installed)
    interface = kinds.DeformerKind
    wanted = {n for n, v in vars(interface).items()
              if (inspect.isfunction(v) or isinstance(v, classmethod)) and not n.startswith("_")}
    wanted |= set(interface.__annotations__)
    assert {"properties", "classes", "control_count", "active_control", "paints_groups"} <= wanted
    assert len(kinds.REGISTERED) >= 3
    rna = props.AffineDeformer.bl_rna.properties
    for cls in kinds.REGISTERED:
        assert issubclass(cls, interface) and not cls.__abstractmethods__, cls
        kind = kinds.get(cls.id)
        assert isinstance(kind, cls) and kind.id == kinds.KindId[cls.id]
        missing = sorted(n for n in wanted if not hasattr(kind, n))
        assert not missing, (cls.id, missing)
        for name in cls.properties():
            assert name in rna, (cls.id, name)
        for registered in cls.classes:
            assert registered.is_registered, (cls.id, registered)
        module, name = kinds.add_operator_id(cls.id).split(".")
        assert getattr(getattr(bpy.ops, module), name).get_rna_type() is not None
    assert [item[0] for item in kinds.enum_items()] == [cls.id for cls in kinds.REGISTERED]
