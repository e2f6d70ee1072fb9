"""The deformer kinds, registered in one place.

A kind is one module in this package with a class implementing `base.DeformerKind` (rest data,
weights, current motions, controls, panel part, caches). Adding a kind = its file plus its class in
`REGISTERED`; `AffineDeformer.kind`'s items, `KindId`, the panel, relations, binding and the update
pipeline then know it. Kinds never import the update pipeline, binding, properties or panels (the
package has no import cycle: tests/blender/test_structure.py walks the imports).
"""

from __future__ import annotations

import enum

from .base import BindError, Chain, ChannelTurns, DeformerKind, Motions
from .bone import BoneKind
from .cage import CageKind
from .probe import ProbeKind

__all__ = ["KINDS", "REGISTERED", "BindError", "Chain", "ChannelTurns", "DeformerKind", "KindId", "Motions",
           "add_operator_id", "enum_items", "forget", "get"]

#: Every kind, in the order the interface lists them (the first is the default). Append new kinds at
#: the end: a .blend stores a deformer's kind as its position here.
REGISTERED: tuple[type[DeformerKind], ...] = (ProbeKind, CageKind, BoneKind)

KINDS: dict[str, DeformerKind] = {cls.id: cls() for cls in REGISTERED}

#: The kind ids as an enum (KindId.PROBE == "PROBE"): what `AffineDeformer.kind` holds.
KindId = enum.StrEnum("KindId", {cls.id: cls.id for cls in REGISTERED})


def get(kind_id: str) -> DeformerKind | None:
    """The kind registered as `kind_id`, or None (a file saved by a version with more kinds)."""
    return KINDS.get(kind_id)


def enum_items() -> list[tuple[str, str, str, str, int]]:
    """Items of the `kind` EnumProperty: (id, label, description, icon, number)."""
    return [(cls.id, cls.label, cls.description, cls.icon, i) for i, cls in enumerate(REGISTERED)]


def add_operator_id(kind_id: str) -> str:
    """The bl_idname of the add operator of kind `kind_id` (operators.add_operator makes it)."""
    return f"object.affine_{kind_id.lower()}_deformer_add"


def forget(key: tuple[int, str] | None = None) -> None:
    """Drop every kind's caches for one deformer ((target session_uid, uid)) or for all."""
    for kind in KINDS.values():
        kind.forget(key)
