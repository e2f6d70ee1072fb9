"""Bind data of each deformer as the update uses it: a read-only record read from the mesh once per bind
generation (`BindRecord`), carrying the deformer's last result (result.py) so an update recomputes
only what changed.

The .blend holds the truth (weights as hidden mesh attributes, storage.py); `_bound` is a cache of
it, keyed so that any change of the mesh, the bind or the rest shape rebuilds the entry.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import bpy
import numpy as np

from ... import accel
from ...core import hierarchy
from .. import caches
from ..files import storage
from .result import Result

_bound: dict[tuple[int, str], BindRecord] = {}
_serial = itertools.count(1)


@dataclass
class BindRecord:
    """A deformer's bind data read from the mesh once per bind generation: a cache of the .blend,
    recomputed from it when the key no longer matches, and read-only — nothing outside this class
    assigns its fields (its derived tables are made by its own methods, on first use). Its `result`
    (result.Result) is the last result computed from it, owned by result.py.

    key = (mesh session uid, bind generation, vertex count, control count); `rest32` is checked against
    the mesh on every evaluation (bit for bit, in one compiled pass: accel.same_bits), so edits of the
    rest shape (Edit Mode, Sculpt Mode, scripts) are seen without rebinding. `serial` changes whenever
    the record is rebuilt. `columns`: the parameter rows the weights may index (controls and pooled
    nodes).
    """

    key: tuple
    serial: int
    rest32: np.ndarray  # (N, 3) float32, exactly as stored in the mesh
    points: np.ndarray  # (N, 3) float64
    indices: np.ndarray  # (N, K) int32
    values: np.ndarray  # (N, K) float64, strength not applied
    # the weights index the truncation's pooled nodes past the m controls (MATH.md §12): index m, the
    # pooled control, for probes and cage faces (the blend appends its parameter row, `with_pool`);
    # the nodes m … 2m of core.hierarchy.pool_parents for bones (blend.py `_pooled`)
    pooled: bool = False
    columns: int = 0
    result: Result = field(default_factory=Result)
    _scaled: tuple[float, np.ndarray] | None = field(default=None, repr=False)  # (strength, values·strength)
    # per parameter row: the rows it influences (ptr, rows), and the rows with any weight
    _csr: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    _layout: tuple[tuple, hierarchy.ChainLayout] | None = field(default=None, repr=False)
    _every: np.ndarray | None = field(default=None, repr=False)  # (N,) intp 0 … N − 1
    _reach_at: tuple[float, float, float] | None = field(default=None, repr=False)

    @property
    def proven(self) -> bool:
        """The last result is finite and storable by `core.deform.motion_bound` (result.Result)."""
        return self.result.proven

    def reach(self, strength: float) -> tuple[float, float]:
        """(max |rest point|, max over vertices of Σ_k |w_vk| at `strength`), the inputs of
        core.deform.motion_bound for this bind (kept while the strength is the same)."""
        if self._reach_at is None or self._reach_at[0] != strength:
            radius = float(np.sqrt((self.points ** 2).sum(axis=1)).max(initial=0.0))
            weight_sum = float(np.abs(self.scaled_values(strength)).sum(axis=1).max(initial=0.0))
            self._reach_at = (strength, radius, weight_sum)
        return self._reach_at[1], self._reach_at[2]

    def every_row(self) -> np.ndarray:
        """All vertex indices (N,) intp, as a row list for the kernel's row path (made once)."""
        if self._every is None:
            self._every = np.arange(len(self.points), dtype=np.intp)
        return self._every

    def scaled_values(self, strength: float) -> np.ndarray:
        if self._scaled is None or self._scaled[0] != strength:
            self._scaled = (strength, self.values * strength)
        return self._scaled[1]

    def _rows_by_control(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ptr, rows, weighted): parameter row i's vertices are rows[ptr[i] : ptr[i + 1]], `weighted`
        the vertices with any non-zero weight; built once per record."""
        if self._csr is None:
            m = max(self.columns, int(self.indices.max(initial=-1)) + 1)
            rows, slots = np.nonzero(self.values)
            cols = self.indices[rows, slots]
            order = np.argsort(cols, kind="stable")
            ptr = np.zeros(m + 1, dtype=np.intp)
            np.cumsum(np.bincount(cols, minlength=m), out=ptr[1:])
            self._csr = (ptr, rows[order].astype(np.intp), np.flatnonzero((self.values != 0.0).any(axis=1)))
        return self._csr

    def weighted_rows(self) -> np.ndarray:
        """Sorted vertices with any non-zero weight: all a change of every control can move (the
        others keep φ(0) v = v, their offset exactly 0)."""
        return self._rows_by_control()[2]

    def affected_rows(self, controls: np.ndarray) -> np.ndarray:
        """Sorted vertices with a non-zero weight on any of `controls`: for a few, gathered from
        per-control row lists built once per record (O(affected) plus one boolean pass over the
        vertices); for many, one compiled pass over the weights, or numpy's tagging of the row lists."""
        ptr, rows, weighted = self._rows_by_control()
        if len(controls) == len(ptr) - 1:  # every control (a cage's nodes after any edit): all weighted rows
            return weighted
        if len(controls) == 1:  # one control's rows are already sorted and distinct
            return rows[ptr[controls[0]] : ptr[controls[0] + 1]]
        if len(controls) > 32:  # many controls (cage faces or nodes): no loop over them
            hit = np.zeros(len(ptr) - 1, dtype=bool)
            hit[controls] = True
            compiled = accel.rows_reading(hit, self.indices, self.values)  # one pass, ~6x cheaper
            if compiled is not None:
                return compiled
            # Each row-list entry tagged with its control's flag: one pass over the non-zero weights'
            # entries, 3–7× cheaper than gathering the flags through the (N, K) indices.
            mask = np.zeros(len(self.points), dtype=bool)
            mask[rows[np.repeat(hit, np.diff(ptr))]] = True
            return np.flatnonzero(mask)
        mask = np.zeros(len(self.points), dtype=bool)
        for i in controls:
            mask[rows[ptr[i] : ptr[i + 1]]] = True
        return np.flatnonzero(mask)

    def chain_layout(self, parents: np.ndarray, strength: float) -> hierarchy.ChainLayout:
        """The weights at `strength` laid out down the hierarchy `parents` (core.hierarchy), kept
        while the same parents and strength come back."""
        key = (parents.tobytes(), strength)
        if self._layout is None or self._layout[0] != key:
            self._layout = (key, hierarchy.chain_layout(self.indices, self.scaled_values(strength), parents))
        return self._layout[1]

    def layout_key(self) -> tuple | None:
        """The key of the chain layout made last (None before one): part of the kernel's argument key."""
        return None if self._layout is None else self._layout[0]


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """Drop the cached bind data of one deformer ((object session uid, deformer uid)) or of all."""
    caches.drop(_bound, key)


def cached(obj: bpy.types.Object, deformer) -> BindRecord | None:
    """The cached entry of `deformer` on `obj`, if any (not checked against the mesh)."""
    return _bound.get((obj.session_uid, deformer.uid))


def bind_data(obj: bpy.types.Object, deformer, n_controls: int, pool: int = 0) -> BindRecord:
    """The cached bind data of `deformer`, re-read when the bind generation, mesh, vertex or control
    count changed or the rest positions differ from the cached ones. `pool`: how many pooled nodes
    past the controls its weights may point at (MATH.md §12): 1 for the pooled control of a flat set
    (index n_controls), n_controls + 1 for a hierarchy's (core.hierarchy.pool_parents). Raises
    storage.StorageError."""
    mesh = obj.data
    rest = storage.read_positions(mesh)
    key = (mesh.session_uid, deformer.bind_generation, len(rest), n_controls)
    cache_key = (obj.session_uid, deformer.uid)
    bound = _bound.get(cache_key)
    if bound is not None and bound.key == key and accel.same_bits(bound.rest32, rest):
        return bound
    _bound.pop(cache_key, None)
    _check_vertices(mesh, deformer, rest)
    indices, values = storage.read_weights(mesh, deformer.uid, n_controls + pool)
    pooled = bool(pool and indices.size and int(indices.max()) >= n_controls)
    bound = BindRecord(key, next(_serial), rest, rest.astype(np.float64), indices, values, pooled=pooled,
                       columns=n_controls + pool)
    _bound[cache_key] = bound
    return bound


def _check_vertices(mesh: bpy.types.Mesh, deformer, rest32: np.ndarray) -> None:
    """Raise StorageError when the mesh's vertices are no longer the ones the weights were bound to.

    Compared with the signature stored at bind (storage.topology_signature): a change of the shape
    alone (Edit / Sculpt Mode moves) or of the connectivity alone (faces added or deleted, vertices in
    place) keeps the vertices and is accepted — the stored signature follows it; both at once, as
    deleting one vertex and adding another gives, means the indices were renumbered. Called only
    when the rest positions differ from the cached ones (or on the first read), so updates pay nothing.
    """
    stored = deformer.bound_topology
    if not stored:  # file format 1 (0.1.x) stored no signature
        return
    now = storage.topology_signature(mesh, rest32)
    if now == stored:
        return
    connectivity, shape = stored.split(":")
    connectivity_now, shape_now = now.split(":")
    if connectivity != connectivity_now and shape != shape_now:
        raise storage.StorageError("The mesh's vertices changed since bind (deleted and added?): the "
                                   "topology changed, rebind the deformer")
    deformer.bound_topology = now
