"""The bone blend's products of passes on the compiled kernel (MATH.md §14): per vertex, the prefix
control's matrix after a product of blended factors, v' = M (F_(P−1) ⋯ F_0 v) + t — the kernel-level
form of core.hierarchy.chain_points / chain_motions, which are its numpy backend.

`Kernel.chain_points_entry` / `chain_motion_entry` (csrc/kernel_chain.c) run on the helper threads
when the backend is active; rows, offsets, out32 and float32 motions follow the vertex entries'
conventions (accel/vertex.py).
"""

from __future__ import annotations

from collections.abc import Hashable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core import hierarchy as _np_hierarchy
from ..core.checks import check_given_out, check_motion_out, check_points, check_rows, check_table
from . import state
from .state import _NO_MOTIONS, _NO_MOTIONS32, _NO_OUT32, _NO_ROWS, _c, _run, _usable
from .vertex import _check_out32, _check_writable

__all__ = ["chain_motions", "chain_points"]

FloatArray = NDArray[np.float64]


def _chain_inputs(
    table: ArrayLike, indices: ArrayLike, values: ArrayLike, prefix: ArrayLike, prefixes: ArrayLike,
    key: Hashable | None,
) -> tuple[FloatArray, NDArray[np.int32], FloatArray, NDArray[np.int32], FloatArray]:
    """Checked table (m, 12), pass indices (P, N, K) in [0, m), values (P, N, K), prefix (N,) in
    [0, m') and prefix matrices (m', 12) for `chain_points` / `chain_motions`. With the key of the
    previous checked call only the shapes are checked (as `vertex._inputs`: the kernel clamps
    indices, so memory stays safe)."""
    tab = check_table(table, 12, "params")
    mats = check_table(prefixes, 12, "prefixes")
    idx = np.asarray(indices)
    val = np.asarray(values, dtype=np.float64)
    pre = np.asarray(prefix)
    if idx.ndim != 3 or idx.shape != val.shape or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"indices and values must be (P, N, K) of one shape, got {idx.shape}, {val.shape}")
    if pre.ndim != 1 or pre.shape[0] != idx.shape[1] or not np.issubdtype(pre.dtype, np.integer):
        raise ValueError(f"prefix must be ({idx.shape[1]},) integers, got {pre.shape} {pre.dtype}")
    if len(mats) == 0:
        raise ValueError("prefixes must have at least one row (the identity)")
    checked = state._state.checked_chain
    if key not in checked:
        if idx.size and (idx.min() < 0 or idx.max() >= tab.shape[0]):
            raise ValueError(f"indices must be in [0, {tab.shape[0]})")
        if pre.size and (pre.min() < 0 or pre.max() >= mats.shape[0]):
            raise ValueError(f"prefix must be in [0, {mats.shape[0]})")
        if not (np.isfinite(val).all() and np.isfinite(mats).all()):
            raise ValueError("values and prefixes must be finite")
        if key is not None:
            checked.add(key)
    if tab.shape[0] == 0:  # no factor to read (P = 0 or K = 0): the kernel still indexes row 0
        tab = np.zeros((1, 12))
    return tab, idx, val, pre, mats


def _chain_layout(indices: NDArray[np.int32], values: FloatArray, prefix: NDArray[np.int32]
                  ) -> _np_hierarchy.ChainLayout:
    """The passes and prefixes as a ChainLayout (what the numpy evaluation reads)."""
    return _np_hierarchy.ChainLayout(prefix, indices, values, np.zeros(1, dtype=np.intp),
                                     np.zeros(0, dtype=np.intp))


def chain_points(
    points: ArrayLike,
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    prefix: ArrayLike,
    prefixes: ArrayLike,
    rows: ArrayLike | None = None,
    out: FloatArray | None = None,
    *,
    offsets: bool = False,
    out32: NDArray[np.float32] | None = None,
    key: Hashable | None = None,
) -> FloatArray:
    """A product of blends and a matrix per vertex (core.hierarchy): out[v] = M (F_(P−1) ⋯ F_0
    points[v]) + t with F_p = φ(Σ_k values[p, v, k] · params[indices[p, v, k]]) and (M, t) =
    prefixes[prefix[v]] (row-major M, then t; minus points[v] when `offsets`), for every vertex or
    for v in `rows` (the others of `out` left as they are; `out` (N, 3) float64 then required).
    `out32`: as in `deform_points_params_rows`. Each written row is bit-identical to the same row of
    a full call with the same backend; the numpy backend is core.hierarchy.chain_points. `key`: a
    hashable token naming these exact points, indices, values and prefix (as in
    `deform_points_params`): a call with the key of the previous checked call skips re-validating them.
    Inside `batch.collecting` a call with `rows` into a C-contiguous `out` is computed when the batch
    runs (out and out32 must not be read before)."""
    if key in state._state.checked_chain:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            pts = check_points(points)
    else:
        pts = check_points(points)
    tab, idx, val, pre, mats = _chain_inputs(params, indices, values, prefix, prefixes, key)
    if idx.shape[1] != pts.shape[0]:
        raise ValueError(f"indices must have shape (P, {pts.shape[0]}, K), got {idx.shape}")
    sel = None if rows is None else _c(check_rows(rows, pts.shape[0]), np.intp)
    if out is None:
        if sel is not None:
            raise ValueError("out is required with rows")
        out = np.empty(pts.shape)
    check_given_out(out, pts)
    if out32 is not None:
        _check_out32(out32, pts.shape)
    n = pts.shape[0] if sel is None else sel.shape[0]
    p = _c(pts, np.float64)
    dst = out if out.flags.c_contiguous and not np.may_share_memory(out, p) else np.empty_like(p)
    args = (p, _c(tab, np.float64), _c(idx, np.int32), _c(val, np.float64), _c(pre, np.int32),
            _c(mats, np.float64), _NO_ROWS if sel is None else sel, sel is not None, bool(offsets), dst,
            _NO_OUT32 if out32 is None else out32, out32 is not None)
    if _usable() is None or not _run("chain_points_entry", n, *args, defer=dst is out and sel is not None):
        moved = _np_hierarchy.chain_points(p, tab, mats, _chain_layout(idx, val, pre), sel)
        target = slice(None) if sel is None else sel
        dst[target] = moved - p[target] if offsets else moved
        if out32 is not None:
            with np.errstate(over="ignore"):
                out32[target] = dst[target]
    if dst is not out:
        if sel is None:
            np.copyto(out, dst)
        else:
            out[sel] = dst[sel]
    return out


def chain_motions(
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    prefix: ArrayLike,
    prefixes: ArrayLike,
    out: FloatArray | NDArray[np.float32] | None = None,
    *,
    rows: ArrayLike | None = None,
    key: Hashable | None = None,
) -> FloatArray | NDArray[np.float32]:
    """The motions x ↦ M (F_(P−1) ∘ ⋯ ∘ F_0 x) + t of `chain_points` per vertex, in the column form of
    `vertex_motions` (out (4, N, 3) float64 or float32; `rows`: only those written, bit-identical
    to a full call's with the same backend); the numpy backend is core.hierarchy.chain_motions.
    `key`: as in `chain_points` (naming the indices, values and prefix); deferred in a batch as
    `chain_points` is."""
    tab, idx, val, pre, mats = _chain_inputs(params, indices, values, prefix, prefixes, key)
    n = pre.shape[0]
    out = check_motion_out(out, n)
    _check_writable(out)
    sel = None if rows is None else _c(check_rows(rows, n), np.intp)
    dst = out if out.flags.c_contiguous else np.ascontiguousarray(out)
    use32 = dst.dtype == np.float32
    args = (_c(tab, np.float64), _c(idx, np.int32), _c(val, np.float64), _c(pre, np.int32),
            _c(mats, np.float64), _NO_ROWS if sel is None else sel, sel is not None,
            _NO_MOTIONS if use32 else dst, dst if use32 else _NO_MOTIONS32, bool(use32))
    if _usable() is None or not _run("chain_motion_entry", n if sel is None else sel.shape[0], *args,
                                     defer=dst is out and sel is not None):
        motions = _np_hierarchy.chain_motions(tab, mats, _chain_layout(idx, val, pre), sel)
        if sel is None:
            dst[...] = motions
        else:
            dst[:, sel] = motions
    if dst is not out:
        if sel is None:
            np.copyto(out, dst)
        else:
            out[:, sel] = dst[:, sel]
    return out
