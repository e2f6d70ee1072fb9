"""Reading several deformers of one kind in one batch (DeformerKind.prefetch).

A kind that supports it splits its `current_motions` in three: `read` (its controls from the
evaluated depsgraph, memo lookups; Motions at once for a problem found there), `fill` (the rows that
missed the memo, for a list of readings in one stacked computation) and `finish` (the Motions of a
reading whose rows are known). `Batch` runs them for one deformer or for many, and keeps what a
prefetch read for the same update's `current_motions` (same depsgraph) until `drop`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import bpy

from .base import Motions


class Batch:
    """`read` / `fill` / `finish` of one kind (see the module docstring); readings carry `obj` and
    `deformer`."""

    def __init__(self, read: Callable[[bpy.types.Object, Any, bpy.types.Depsgraph], Any],
                 fill: Callable[[list], None], finish: Callable[[Any], Motions]) -> None:
        self._read, self._fill, self._finish = read, fill, finish
        #: (object session uid, deformer uid) -> (depsgraph, motions) read by `prefetch`
        self._kept: dict[tuple[int, str], tuple[bpy.types.Depsgraph, Motions]] = {}

    def current(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Motions:
        """The deformer's motions: those `prefetch` read for this update, else read now."""
        found = self._kept.pop((obj.session_uid, deformer.uid), None)
        if found is not None and found[0] is depsgraph:
            return found[1]
        reading = self._read(obj, deformer, depsgraph)
        if isinstance(reading, Motions):
            return reading
        self._fill([reading])
        return self._finish(reading)

    def prefetch(self, pairs: list[tuple[bpy.types.Object, Any]],
                 depsgraph: bpy.types.Depsgraph) -> list[tuple[Any, Motions]]:
        """Read every (object, deformer) pair, fill the rows of all in one batch, keep the motions
        without an error for `current`; returns (deformer, motions) of those kept."""
        readings = [r for r in (self._read(obj, deformer, depsgraph) for obj, deformer in pairs)
                    if not isinstance(r, Motions)]
        self._fill(readings)
        out = []
        for reading in readings:
            motions = self._finish(reading)
            if not motions.error:
                self._kept[(reading.obj.session_uid, reading.deformer.uid)] = (depsgraph, motions)
                out.append((reading.deformer, motions))
        return out

    def drop(self) -> None:
        """Forget what `prefetch` kept (the end of the update, or any cache forget)."""
        self._kept.clear()


def keep_rows(memo: dict, limit: int, misses: list[tuple[Any, tuple]], computed: list) -> None:
    """Store each computed row under its miss's key in `memo` (cleared first when it would outgrow
    `limit`) and in its reading's `rows` at the miss's slot; a miss is (reading, (slot, key, ...)).
    The readings' rows are then complete."""
    if len(memo) + len(misses) > limit:
        memo.clear()
    for (reading, (slot, key, *_)), row in zip(misses, computed, strict=True):
        memo[key] = reading.rows[slot] = row
    for reading, _miss in misses:
        reading.misses = []


class BatchedKind:
    """Mixin (before DeformerKind) for a kind whose motions are read through a `Batch`: its
    `current_motions`, `prefetch` and `drop_prefetched`. The kind's module sets `batch` once its read /
    fill / finish are defined."""

    batch: Batch

    def current_motions(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Motions:
        return self.batch.current(obj, deformer, depsgraph)

    def prefetch(self, pairs: list[tuple[bpy.types.Object, Any]],
                 depsgraph: bpy.types.Depsgraph) -> list[tuple[Any, Motions]]:
        """Every listed deformer's controls read and the rows of all that moved computed in one
        batch (`Batch.prefetch`)."""
        return self.batch.prefetch(pairs, depsgraph)

    def drop_prefetched(self) -> None:
        self.batch.drop()
