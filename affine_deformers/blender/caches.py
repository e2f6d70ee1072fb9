"""What the Blender layer remembers between updates, and the one way to forget it.

Every module-level memo of the Blender layer registers the function that clears it, next to the memo
(`register`, used as a decorator): `clear(key)` drops what it holds for one deformer (key = (object
session uid, deformer uid)) or, with None, everything. `forget` calls them all: undo, redo, file load
and unregistering forget everything; removing a deformer or giving it a new id forgets that deformer.
Every entry is a cache of values recomputable from the .blend (nothing here is bind data), so
forgetting only costs a recomputation. tests/blender/test_caches.py finds every module-level container
of blender/ from the source and checks that `forget()` empties it.

This module imports nothing of the add-on (every layer registers into it). It holds the update's own
memo: the signature and the error of each deformer's last update (evaluate.py), and the lookups one
update makes once (`update_scope`, `scoped`).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from typing import Any

import bpy

Key = tuple[int, str]
Clear = Callable[[Key | None], None]

#: The registered clear functions by qualified name (a reloaded module replaces its own).
_clears: dict[str, Clear] = {}


def register(clear: Clear) -> Clear:
    """Register `clear(key)`, which drops a memo's entries of one deformer (or all, with None);
    returns it, so it can decorate the function."""
    _clears[f"{clear.__module__}.{clear.__qualname__}"] = clear
    return clear


def drop(memo: dict, key: Key | None) -> None:
    """The usual clear of a memo keyed by deformer: its entry for `key`, or everything for None."""
    if key is None:
        memo.clear()
    else:
        memo.pop(key, None)


def forget(obj: bpy.types.Object | None = None, uid: str | None = None) -> None:
    """Drop cached state (all, or that of deformer `uid` on `obj`) so the next update recomputes."""
    key = None if obj is None else (obj.session_uid, uid)
    for clear in list(_clears.values()):
        clear(key)


#: (object session uid, deformer uid) → signature of the snapshot last written (snapshot.Snapshot).
signatures: dict[Key, tuple] = {}
#: (object session uid, deformer uid) → the error of the last update ('' when it deformed).
errors: dict[Key, str] = {}


@register
def _forget_updates(key: Key | None) -> None:
    drop(signatures, key)
    drop(errors, key)


#: Lookups valid for the update running now (`update_scope`), None between updates.
_scope: dict[Hashable, Any] | None = None


@contextmanager
def update_scope() -> Iterator[None]:
    """Within the block (one update: evaluate.run, evaluate_object) `scoped` lookups are made once:
    a deformer's modifier, a node group's inputs — what each step of an update would otherwise ask
    the RNA again. Nothing an update does changes them (it writes outputs, stamps and statuses; it
    adds no modifier and edits no group). Nested blocks share the outer one."""
    global _scope
    outer = _scope
    if outer is None:
        _scope = {}
    try:
        yield
    finally:
        if outer is None:
            _scope = None


def scoped(key: Hashable, compute: Callable[[], Any]) -> Any:
    """`compute()`, made once per `update_scope` for `key` (every time outside one)."""
    scope = _scope
    if scope is None:
        return compute()
    try:
        return scope[key]
    except KeyError:
        value = scope[key] = compute()
        return value
