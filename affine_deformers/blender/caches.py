"""What the update remembers between calls, and how to forget it.

Every entry is a cache of values recomputable from the .blend (nothing here is bind data): the last
snapshot signature and error of each deformer (evaluate.py), the bind data and last result
(bound.py), the modifier found last (outputs.py), the parameter memo (params.py), the node groups'
input identifiers (nodes.py) and the kinds' own memos. Undo, redo, file load and unregistering drop
them all.
"""

from __future__ import annotations

import bpy

from . import bound, kinds, nodes, outputs, params

#: (object session uid, deformer uid) → signature of the snapshot last written (snapshot.Snapshot).
signatures: dict[tuple[int, str], tuple] = {}
#: (object session uid, deformer uid) → the error of the last update ('' when it deformed).
errors: dict[tuple[int, str], str] = {}


def forget(obj: bpy.types.Object | None = None, uid: str | None = None) -> None:
    """Drop cached state (all, or that of deformer `uid` on `obj`) so the next update recomputes."""
    if obj is None:
        signatures.clear()
        errors.clear()
        bound.forget()
        outputs.forget()
        params.forget()
        kinds.forget()
        nodes.forget()
        return
    key = (obj.session_uid, uid)
    signatures.pop(key, None)
    errors.pop(key, None)
    bound.forget(key)
    outputs.forget(key)
    kinds.forget(key)
