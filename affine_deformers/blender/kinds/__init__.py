"""The deformer kinds, registered in one place.

A kind is a class implementing `base.DeformerKind` (rest data, weights, current motions, controls,
its own properties, classes and panel part, what the weight tools need of it), in its own module of
this package. Adding a kind = its file plus the class in `REGISTERED` (imported above it):
`AffineDeformer.kind`'s items and the kind's properties on it, `KindId`, registration, the add
operator, the panel, relations, binding, the weight tools and the update pipeline then know it. Kinds
never import the update pipeline, binding, properties or panels; what they need of those comes
through `services` (the package has no import cycle: tests/core/test_package_structure.py walks the
imports).
"""

from __future__ import annotations

import enum

from .base import BindError, Chain, ChannelTurns, DeformerKind, KindProperty, Motions
from .bone import BoneKind
from .cage import CageKind
from .probe import ProbeKind

__all__ = ["CLASSES", "KINDS", "REGISTERED", "BindError", "Chain", "ChannelTurns", "DeformerKind", "KindId",
           "KindProperty", "Motions", "add_operator_id", "declared", "enum_items", "get", "properties"]

#: Every kind, in the order the interface lists them (the first is the default). Append new kinds at
#: the end: a .blend stores a deformer's kind as its position here.
REGISTERED: tuple[type[DeformerKind], ...] = (ProbeKind, CageKind, BoneKind)

KINDS: dict[str, DeformerKind] = {cls.id: cls() for cls in REGISTERED}

#: The kind ids as an enum (KindId.PROBE == "PROBE"): what `AffineDeformer.kind` holds.
KindId = enum.StrEnum("KindId", {cls.id: cls.id for cls in REGISTERED})

#: The bpy classes of every kind, registered before the deformer's property group (props.py), which
#: refers to the kinds' control item groups.
CLASSES: tuple[type, ...] = tuple(c for cls in REGISTERED for c in cls.classes)


def get(kind_id: str) -> DeformerKind | None:
    """The kind registered as `kind_id`, or None (a file saved by a version with more kinds)."""
    return KINDS.get(kind_id)


def enum_items() -> list[tuple[str, str, str, str, int]]:
    """Items of the `kind` EnumProperty: (id, label, description, icon, number)."""
    return [(cls.id, cls.label, cls.description, cls.icon, i) for i, cls in enumerate(REGISTERED)]


def add_operator_id(kind_id: str) -> str:
    """The bl_idname of the add operator of kind `kind_id` (operators.add_operator makes it)."""
    return f"object.affine_{kind_id.lower()}_deformer_add"


def properties() -> dict[str, KindProperty]:
    """Every kind's own properties of the deformer, by name (ValueError when two kinds claim one)."""
    found: dict[str, KindProperty] = {}
    for cls in REGISTERED:
        for name, prop in cls.properties().items():
            if name in found:
                raise ValueError(f"Deformer property '{name}' is claimed by two kinds")
            found[name] = prop
    return found


def declared() -> dict[str, str]:
    """Why the update need not read each kind's property itself (part of snapshot.DECLARED)."""
    return {name: prop.declared for name, prop in properties().items()}
