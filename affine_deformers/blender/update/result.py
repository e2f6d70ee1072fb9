"""The last result of a deformer's update, owned by this module: what an incremental update reuses, and
what the output store holds. Nothing outside assigns its fields; the update asks it what it needs.

A result is computed from the bind record (bound.BindRecord: rest points, weights) and the blend
parameters of the controls. Every vertex's result depends only on its own rest position, its weights
and the parameters of its controls (the kernel's rows are independent of how vertices are grouped),
so recomputing only the vertices that read a control whose parameters changed bitwise equals a full
recompute bit for bit — under the same state (path, strength, branch rule, kernel backend:
snapshot.Snapshot.result_state). `Result` keeps that state, the parameters (and a hierarchy's prefix
matrices) and the arrays (float64 offsets or float32 motions), and what the store holds now
(`written`: float32 offsets; `motions_written`), so an identical write is skipped without reading
the store back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Result:
    """The last result of one deformer (see the module docstring); fields are read by the update and
    assigned only by the methods below."""

    state: tuple | None = None  # what `params` and the arrays were computed with
    params: np.ndarray | None = None  # (m, 12) blend parameters of the last result
    prefixes: np.ndarray | None = None  # (m + 1, 12) a hierarchy's prefix matrices (bones)
    offsets: np.ndarray | None = None  # (N, 3) float64 the last offsets
    motions: np.ndarray | None = None  # (4, N, 3) float32 the last motions
    written: np.ndarray | None = None  # (N, 3) float32 the offsets the store holds (None: unknown)
    motions_written: np.ndarray | None = None  # (4, N, 3) float32 the motions the store holds
    proven: bool = False  # the last result is finite and storable (core.deform.motion_bound)

    # ---------------------------------------------------------------------- incremental updates

    def changed_controls(self, state: tuple, params: np.ndarray, *, motions: bool,
                         prefixes: np.ndarray | None = None) -> np.ndarray | None:
        """The parameter rows (controls, pooled nodes) that differ bitwise from the last result's — in
        `params` or, for a hierarchy, in `prefixes` — or None when the last result cannot be reused
        (none of that form: `motions` or offsets, another state, another shape). The Preserve Shape
        pass asks for motions under the offset path's state: only a kept array of the asked form
        counts."""
        previous = self.motions if motions else self.offsets
        if (previous is None or self.state != state or self.params is None
                or self.params.shape != params.shape or (prefixes is not None and self.prefixes is None)):
            return None
        changed = (params.view(np.int64) != self.params.view(np.int64)).any(axis=1)
        if prefixes is not None:
            changed |= (prefixes[:-1].view(np.int64) != self.prefixes[:-1].view(np.int64)).any(axis=1)
        return np.flatnonzero(changed)

    def keep(self, state: tuple, params: np.ndarray, *, offsets: np.ndarray | None = None,
             motions: np.ndarray | None = None, prefixes: np.ndarray | None = None) -> None:
        """A full recompute's result becomes the one to reuse."""
        self.state, self.params, self.prefixes = state, params, prefixes
        self.offsets, self.motions = offsets, motions

    def advance(self, params: np.ndarray, prefixes: np.ndarray | None = None) -> None:
        """Rows were recomputed in place (the arrays are the same): the parameters are now these."""
        self.params = params
        if prefixes is not None:
            self.prefixes = prefixes

    def prove(self, proven: bool) -> None:
        self.proven = proven

    def forget(self) -> None:
        """No result to reuse (the next update computes every vertex); the store's content is still
        known."""
        self.state = self.params = self.offsets = self.motions = self.prefixes = None
        self.proven = False

    # ------------------------------------------------------------------------------ the store

    def forget_written(self, motions_only: bool = False) -> None:
        """What the store holds is unknown (another store was written, an attribute removed, an error
        written without the result)."""
        self.motions_written = None
        if not motions_only:
            self.written = None

    def offsets_buffer(self, shape: tuple) -> np.ndarray | None:
        """The copy of the stored offsets the kernel rounds recomputed rows into (`out32`), when it
        is one of `shape`."""
        written = self.written
        return written if written is not None and written.shape == shape else None

    def knows_offsets(self, shape: tuple) -> bool:
        return self.offsets_buffer(shape) is not None

    def pending_offsets(self, offsets: np.ndarray, rows: np.ndarray | None) -> np.ndarray | None:
        """The float32 offsets to write, or None when the store holds them already: an incremental
        result's rows are already in the copy (the kernel rounded them into it), a full result is
        compared with it; an unknown content is written (the store is not read back here)."""
        if self.knows_offsets(offsets.shape):
            if rows is not None and len(rows) == 0:
                return None
            if rows is None:
                fresh = offsets.astype(np.float32)
                if np.array_equal(self.written, fresh):
                    return None
                self.written = fresh
            return self.written
        fresh = np.array(offsets, dtype=np.float32, order="C")
        self.written = fresh
        return fresh

    def note_offsets(self, written: np.ndarray) -> None:
        """The store holds these float32 offsets now (it was compared or written by the caller)."""
        self.written = written

    def knows_motions(self, shape: tuple) -> bool:
        return self.motions_written is not None and self.motions_written.shape == shape

    def pending_motions(self, motions: np.ndarray, rows: np.ndarray | None) -> np.ndarray | None:
        """The motions (4, N, 3) float32 to write, or None when the store holds them already (as
        `pending_offsets`)."""
        known = self.motions_written
        if self.knows_motions(motions.shape):
            if rows is not None and len(rows) == 0 and known is motions:
                return None
            if rows is None and known is not motions and np.array_equal(known, motions):
                if self.motions is motions:
                    self.motions = known  # one array: later incremental updates write into it
                return None
        self.motions_written = motions
        return motions

    def note_motions(self, written: np.ndarray) -> None:
        self.motions_written = written
