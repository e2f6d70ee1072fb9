"""Explicit hooks around the update: what other parts of the add-on do next to it, kept out of it.

The update (evaluate.py) computes and writes deformations and knows nothing of the interface. Work
that belongs beside it — the weight tools' bookkeeping: renamed probes' groups, leaving Weight Paint
mode, the weight preview, the probes' states — registers here and runs at two points:

* `before_object` hooks run with an object before its deformers are evaluated;
* `inputs_read` hooks run with (object, deformer, snapshot, depsgraph) once a deformer's inputs are
  read (snapshot.take), whether or not its output then changes.

A hook must never raise (it runs inside depsgraph handlers). This module imports nothing of the
add-on; registration happens when the registering module is imported (weight_groups.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import bpy

if TYPE_CHECKING:
    from .snapshot import Snapshot

BeforeObject = Callable[[bpy.types.Object], None]
InputsRead = Callable[[bpy.types.Object, object, "Snapshot", bpy.types.Depsgraph], None]

#: The hooks by qualified name (a reloaded module replaces its own), in registration order.
_before_object: dict[str, BeforeObject] = {}
_inputs_read: dict[str, InputsRead] = {}


def _name(hook: Callable) -> str:
    return f"{hook.__module__}.{hook.__qualname__}"


def before_object(hook: BeforeObject) -> BeforeObject:
    """Register `hook(obj)`, run before the deformers of `obj` are evaluated (a decorator)."""
    _before_object[_name(hook)] = hook
    return hook


def inputs_read(hook: InputsRead) -> InputsRead:
    """Register `hook(obj, deformer, snapshot, depsgraph)`, run once a deformer's inputs are read."""
    _inputs_read[_name(hook)] = hook
    return hook


def run_before_object(obj: bpy.types.Object) -> None:
    """Run the `before_object` hooks for `obj`."""
    for hook in list(_before_object.values()):
        hook(obj)


def run_inputs_read(obj: bpy.types.Object, deformer, snapshot: Snapshot,
                    depsgraph: bpy.types.Depsgraph) -> None:
    """Run the `inputs_read` hooks for one deformer's snapshot."""
    for hook in list(_inputs_read.values()):
        hook(obj, deformer, snapshot, depsgraph)
