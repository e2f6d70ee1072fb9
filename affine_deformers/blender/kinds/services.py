"""What the Blender layer above the kinds does for them, and the property updates built on it.

The kinds sit below binding, relations, the update and the weight preview — which all dispatch to
them — so a kind cannot import those modules. Yet a kind's properties re-weight or rebind the
deformer when they are edited, and its operators bind, re-weight and evaluate. The layer above hands
the kinds an implementation of `Services` once, when the add-on is imported (blender/kind_services.py calls
`provide`); `services()` returns it. The property update callbacks every kind's properties use (and
the deformer's common ones, props.py) are defined here on top of it.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Protocol

import bpy


class Services(Protocol):
    """What kinds may ask of the layer above them (each method is the function of that name in
    binding.py, relations.py, evaluate.py or weight_preview.py; see blender/kind_services.py)."""

    def quiet(self) -> AbstractContextManager[None]:
        """Suspend the property-update side effects while an operator edits a deformer itself."""

    def updates_suspended(self) -> bool:
        """Whether `quiet` is in effect."""

    def create(self, obj: bpy.types.Object, kind_id: str, name: str):
        """Append an unbound deformer item of `kind_id` to `obj` (the active one) and return it."""

    def bind(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
             only: list[int] | None = None) -> None:
        """Bind (all controls, or those at `only`); BindError / ValueError when it cannot."""

    def reweight(self, obj: bpy.types.Object, deformer) -> None:
        """Recompute the weights from the stored rest data; BindError / ValueError when it cannot."""

    def remove(self, obj: bpy.types.Object, index: int) -> None:
        """Remove deformer `index` of `obj` with its modifier and stored data."""

    def sync(self, obj: bpy.types.Object, deformer) -> bool:
        """Name the deformer's controls on its modifier; True when that changed."""

    def evaluate(self, obj: bpy.types.Object, depsgraph: bpy.types.Depsgraph) -> list[str]:
        """Update every deformer of `obj` now; their statuses."""

    def reweight_safely(self, obj: bpy.types.Object, deformer) -> None:
        """`reweight` whose failure becomes the deformer's status."""

    def rebind_safely(self, obj: bpy.types.Object, deformer, what: str) -> None:
        """`bind` whose failure leaves the deformer unbound with the reason (naming `what`)."""

    def rebind_control_safely(self, obj: bpy.types.Object, deformer, index: int) -> None:
        """Bind control `index` at its current pose; a failure becomes the deformer's status."""

    def preview_option(self, deformer) -> None:
        """A weight preview option (or the active control) changed: redraw the preview."""


_provided: Services | None = None


def provide(implementation: Services) -> None:
    """Hand the kinds the layer above's implementation (blender/kind_services.py, at import)."""
    global _provided
    _provided = implementation


def services() -> Services:
    """The implementation given to `provide` (RuntimeError when the add-on did not give one)."""
    if _provided is None:
        raise RuntimeError("The add-on's services were not provided (import affine_deformers.blender)")
    return _provided


# ---------------------------------------------------------------------------------- property updates

#: A control item's path: 'affine_deformers[i].<collection>[j]'.
_ITEM_PATH = re.compile(r"(.+)\.\w+\[(\d+)\]")


def owner(item) -> tuple[bpy.types.Object, object, int] | None:
    """The object and deformer holding a control item (a probe, a bone), and the item's index
    (property groups do not know their parent)."""
    obj = item.id_data
    if not isinstance(obj, bpy.types.Object):
        return None
    match = _ITEM_PATH.fullmatch(item.path_from_id())
    if match is None:
        return None
    return obj, obj.path_resolve(match[1]), int(match[2])


def reweight(deformer) -> None:
    """Re-weight a bound deformer after one of its weight options changed (not while an operator
    edits it: `Services.quiet`); a failure becomes its status."""
    obj = deformer.id_data
    provided = services()
    if provided.updates_suspended():
        return
    if deformer.is_bound and isinstance(obj, bpy.types.Object):
        provided.reweight_safely(obj, deformer)


def on_weight_option(self, _context: bpy.types.Context) -> None:
    """Update of a deformer option that re-weights (declared `REWEIGHTS`)."""
    reweight(self)


def on_item_weight_option(self, _context: bpy.types.Context) -> None:
    """Update of a control item's option that re-weights its deformer (a weight scale)."""
    found = owner(self)
    if found is not None:
        reweight(found[1])


def on_preview_option(self, _context: bpy.types.Context) -> None:
    """Update of a weight preview option or of the active control: the preview follows."""
    services().preview_option(self)


def control_picker(kind_id: str, field: str, what: str) -> Callable[[object, bpy.types.Context], None]:
    """The update of the deformer property `field` that picks a kind's control object (a cage, an
    armature). A deformer of kind `kind_id` bound before binds the new pick — also when the last pick
    failed to bind, so the status speaks of `what` (the new pick), not of the object picked before;
    otherwise the relations follow (a cleared pick is no longer evaluated for it)."""

    def update(self, _context: bpy.types.Context) -> None:
        obj = self.id_data
        provided = services()
        if provided.updates_suspended() or not isinstance(obj, bpy.types.Object) or self.kind != kind_id:
            return
        if getattr(self, field) is not None and (self.is_bound or self.bind_generation > 0):
            provided.rebind_safely(obj, self, what)
        else:
            provided.sync(obj, self)

    return update


def search_vertex_groups(self, _context: bpy.types.Context, _text: str) -> list[str]:
    """`search` of a property naming one of the target's vertex groups."""
    obj = self.id_data
    return [g.name for g in obj.vertex_groups] if isinstance(obj, bpy.types.Object) else []
