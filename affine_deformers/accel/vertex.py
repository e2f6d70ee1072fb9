"""The per-vertex map on the compiled kernel: core.deform's `deform_points_params`,
`deform_points_params_rows` and `vertex_motions` (their contract — arguments, checks, messages,
results — is core.deform's; here only what the compiled path adds), and the passes over the bind
weights and positions the incremental update makes (`rows_reading`, `same_bits`).

Each entry runs `Kernel.deform_points_entry` / `motion_params` (csrc/kernel_vertex.c) on the helper
threads when the backend is active, and core.deform's function otherwise or when the entry fails on
its first call. The results agree with numpy's to ~1e-15 relative (polynomial transcendentals, see
csrc/kernel_math.h); within one backend every row is bit-identical whichever call, thread count or
row subset computes it.
"""

from __future__ import annotations

from collections.abc import Hashable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core import deform as _np_kernel
from ..core.checks import (
    check_deform_args,
    check_given_out,
    check_motion_args,
    check_motion_out,
    check_out,
    check_rows,
    check_table,
    identity_motions,
    unchanged,
)
from . import state
from .state import _FAILED, _NO_MOTIONS, _NO_MOTIONS32, _NO_OUT32, _NO_ROWS, _c, _entry_call, _run, _usable

__all__ = [
    "deform_points_params",
    "deform_points_params_rows",
    "linear_maps",
    "rows_reading",
    "same_bits",
    "vertex_motions",
]

FloatArray = NDArray[np.float64]


# ----------------------------------------------------------------------------------------------
# arguments: core.deform's checks, skipped for a key the caller vouches for


def _inputs(
    points: ArrayLike, params: ArrayLike, indices: ArrayLike, values: ArrayLike, key: Hashable | None
) -> tuple[FloatArray, FloatArray, NDArray[np.integer], FloatArray]:
    """Checked points, table, indices and values (`check_deform_args`). With a key seen before, only
    the shapes are checked (the caller vouches for the contents; the kernel clamps indices, so memory
    stays safe)."""
    checked = state._state.checked
    if key in checked:
        table = check_table(params, 12, "params")
        pts = np.asarray(points, dtype=np.float64)
        idx = np.asarray(indices)
        val = np.asarray(values, dtype=np.float64)
        if (
            pts.ndim == 2
            and pts.shape[1] == 3
            and idx.shape == val.shape
            and idx.ndim == 2
            and idx.shape[0] == pts.shape[0]
            and np.issubdtype(idx.dtype, np.integer)
        ):
            return pts, table, idx, val
        checked.discard(key)
    pts, table, idx, val = check_deform_args(points, params, indices, values)
    if key is not None:
        checked.add(key)
    return pts, table, idx, val


def _weights_inputs(
    params: ArrayLike, indices: ArrayLike, values: ArrayLike, key: Hashable | None
) -> tuple[FloatArray, NDArray[np.integer], FloatArray]:
    """Checked table, indices and values (no points: `vertex_motions`; `check_motion_args`). With a
    key of an earlier checked call (with or without points) only the shapes are checked, as in
    `_inputs`."""
    current = state._state
    if key in current.checked or key in current.checked_weights:
        table = check_table(params, 12, "params")
        idx = np.asarray(indices)
        val = np.asarray(values, dtype=np.float64)
        if idx.ndim == 2 and idx.shape == val.shape and np.issubdtype(idx.dtype, np.integer):
            return table, idx, val
    table, idx, val = check_motion_args(params, indices, values)
    if key is not None:
        current.checked_weights.add(key)
    return table, idx, val


def _check_writable(out: np.ndarray) -> None:
    if not out.flags.writeable:
        raise ValueError("out must be writable")


def _check_out32(out32: object, shape: tuple[int, ...]) -> None:
    """`out32`, the float32 copy the rows entries also write: (N, 3) float32, C-contiguous, writable."""
    if (
        not isinstance(out32, np.ndarray)
        or out32.dtype != np.float32
        or out32.shape != shape
        or not out32.flags.c_contiguous
        or not out32.flags.writeable
    ):
        raise ValueError(f"out32 must be a writable C-contiguous float32 array of shape {shape}")


# ----------------------------------------------------------------------------------------------
# entries


def deform_points_params(
    points: ArrayLike,
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    out: FloatArray | None = None,
    *,
    key: Hashable | None = None,
) -> FloatArray:
    """`core.deform.deform_points_params` (the contract) on the compiled kernel when it is active.
    `key` here skips re-validating the points, indices and values of a checked call with that key.
    `out` must be writable."""
    def numpy() -> FloatArray:
        return _np_kernel.deform_points_params(points, params, indices, values, out, key=key)

    if _usable() is None:
        return numpy()
    pts, table, idx, val = _inputs(points, params, indices, values, key)
    out = check_out(out, pts)
    _check_writable(out)
    if not table.any():  # every control at rest (also m = 0)
        return unchanged(pts, out)
    p = _c(pts, np.float64)
    dst = out if out.flags.c_contiguous else np.empty_like(p)
    # A chunk reads its points before writing its results, so out may be points itself — but not a
    # different view of the same memory.
    if np.may_share_memory(dst, p) and not (
        dst.__array_interface__["data"][0] == p.__array_interface__["data"][0] and dst.strides == p.strides
    ):
        p = p.copy()
    args = (p, _c(table, np.float64), _c(idx, np.int32), _c(val, np.float64), _NO_ROWS, False, False, dst,
            _NO_OUT32, False)
    if not _run("deform_points_entry", p.shape[0], *args):
        return numpy()
    if dst is not out:
        np.copyto(out, dst)
    return out


def deform_points_params_rows(
    points: ArrayLike,
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    rows: ArrayLike,
    out: FloatArray,
    *,
    offsets: bool = False,
    key: Hashable | None = None,
    out32: NDArray[np.float32] | None = None,
) -> FloatArray:
    """`core.deform.deform_points_params_rows` (the contract) on the compiled kernel when it is
    active; each written row is bit-identical to the same row of `deform_points_params` with the same
    backend. `key` as in `deform_points_params`. `out32`: an optional (N, 3) float32 C-contiguous
    array that also gets out[v] rounded to float32 (bit for bit what out.astype(np.float32) holds
    there) for v in rows, and nothing elsewhere: a float32 copy of `out` is kept up to date without
    converting the whole array.

    Inside `batch.collecting` the rows are computed when the batch runs (out and out32 must not be
    read before), unless `out` is not C-contiguous.
    """
    if out32 is not None:
        _check_out32(out32, np.shape(out))
        if np.may_share_memory(out32, out):
            raise ValueError("out32 must not share memory with out")
    if _usable() is None:
        return _numpy_rows(points, params, indices, values, rows, out, offsets, key, out32)
    pts, table, idx, val = _inputs(points, params, indices, values, key)
    check_given_out(out, pts)
    _check_writable(out)
    sel = _c(check_rows(rows, pts.shape[0]), np.intp)
    if table.shape[0] == 0:  # then K = 0 or N = 0 (checked): φ(0) v = v
        table = np.zeros((1, 12))
    p = _c(pts, np.float64)
    dst = out if out.flags.c_contiguous else np.ascontiguousarray(out)
    # Repeated rows in different chunks would read written results.
    if np.may_share_memory(dst, p) or (out32 is not None and np.may_share_memory(out32, p)):
        p = p.copy()
    dst32 = _NO_OUT32 if out32 is None else out32
    args = (p, _c(table, np.float64), _c(idx, np.int32), _c(val, np.float64), sel, True, bool(offsets), dst,
            dst32, out32 is not None)
    if not _run("deform_points_entry", sel.shape[0], *args, defer=dst is out):
        return _numpy_rows(points, params, indices, values, rows, out, offsets, key, out32)
    if dst is not out:
        out[sel] = dst[sel]
    return out


def _numpy_rows(
    points: ArrayLike, params: ArrayLike, indices: ArrayLike, values: ArrayLike, rows: ArrayLike,
    out: FloatArray, offsets: bool, key: Hashable | None, out32: NDArray[np.float32] | None,
) -> FloatArray:
    """The numpy kernel's rows call, then the float32 copy of just those rows (an assignment casts
    with astype's rounding)."""
    _np_kernel.deform_points_params_rows(points, params, indices, values, rows, out, offsets=offsets, key=key)
    if out32 is not None:
        sel = np.asarray(rows)  # checked by the call above
        with np.errstate(over="ignore"):  # beyond float32 range is ±inf, silently, as compiled
            out32[sel] = out[sel]
    return out


def vertex_motions(
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    out: FloatArray | NDArray[np.float32] | None = None,
    *,
    rows: ArrayLike | None = None,
    key: Hashable | None = None,
) -> FloatArray | NDArray[np.float32]:
    """`core.deform.vertex_motions` (the contract: out (4, N, 3) float64 or float32, `rows`, the
    identity at rest) on the compiled kernel when it is active; written rows are bit-identical to the
    same rows of a full call with the same backend. `key`: as in `deform_points_params` (naming the
    indices and values); a call with the key of an earlier checked call skips re-validating them.
    `out` must be writable. Inside `batch.collecting` a call with `rows` into a C-contiguous `out` is
    computed when the batch runs (out must not be read before)."""
    def numpy() -> FloatArray | NDArray[np.float32]:
        return _np_kernel.vertex_motions(params, indices, values, out, rows=rows, key=key)

    if _usable() is None:
        return numpy()
    table, idx, val = _weights_inputs(params, indices, values, key)
    n = idx.shape[0]
    out = check_motion_out(out, n)
    _check_writable(out)
    sel = None if rows is None else _c(check_rows(rows, n), np.intp)
    if not table.any():  # every control at rest (also m = 0, which the kernel cannot index)
        return identity_motions(out, sel)
    dst = out if out.flags.c_contiguous else np.ascontiguousarray(out)
    use32 = dst.dtype == np.float32
    args = (_c(table, np.float64), _c(idx, np.int32), _c(val, np.float64), _NO_ROWS if sel is None else sel,
            sel is not None, _NO_MOTIONS if use32 else dst, dst if use32 else _NO_MOTIONS32, bool(use32))
    if not _run("motion_params", n if sel is None else sel.shape[0], *args,
                defer=dst is out and sel is not None):
        return numpy()
    if dst is not out:
        if sel is None:
            np.copyto(out, dst)
        else:
            out[:, sel] = dst[:, sel]
    return out


def linear_maps(params: ArrayLike) -> FloatArray:
    """The linear parts M = R(ω) exp(Y) (n, 3, 3) of φ(P) for parameters (n, 12): `vertex_motions`
    with one control per row at weight 1 (the compiled kernel when it is active)."""
    table = np.ascontiguousarray(params, dtype=np.float64)
    n = table.shape[0]
    if n == 0:
        return np.zeros((0, 3, 3))
    columns = vertex_motions(table, np.arange(n, dtype=np.int32)[:, None], np.ones((n, 1)))
    return np.ascontiguousarray(columns[:3].transpose(1, 2, 0))


# ----------------------------------------------------------------------------------------------
# passes of the incremental update (no numerics)


def rows_reading(hit: ArrayLike, indices: ArrayLike, values: ArrayLike) -> NDArray[np.intp] | None:
    """The sorted vertices with a non-zero weight on a control flagged in `hit` (m,) bool: rows v
    with values[v, k] != 0 and hit[indices[v, k]] for some k (indices (N, K), an index outside [0, m)
    flags nothing; values (N, K)), in one compiled pass (`Kernel.rows_reading`). None when the
    compiled kernel is not active now (the caller then uses numpy)."""
    module = _usable()
    if module is None:
        return None
    flags = _c(hit, np.bool_)
    idx = _c(indices, np.int32)
    val = _c(values, np.float64)
    if idx.shape != val.shape or idx.ndim != 2:
        raise ValueError(f"indices and values must have the same (N, K) shape, got {idx.shape}, {val.shape}")
    out = np.empty(idx.shape[0], dtype=np.intp)
    count = _entry_call("rows_reading", lambda: module.rows_reading(flags, idx, val, out))
    if count is _FAILED:
        return None
    return out[:count]


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the arrays a and b have the same dtype, shape and bytes (bit for bit: −0.0 ≠ 0.0 and a
    NaN equals its own bits), in one compiled pass with early exit (`Kernel.same_words`: 91 µs for
    130k positions where numpy's elementwise compare, which also writes a bool array, takes 120 µs)
    when the kernel is active and both are C-contiguous with a size a multiple of 4 bytes; numpy's
    compare of the words otherwise."""
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.nbytes % 4 or not (a.flags.c_contiguous and b.flags.c_contiguous):
        return a.tobytes() == b.tobytes()
    words_a, words_b = a.reshape(-1).view(np.uint32), b.reshape(-1).view(np.uint32)
    module = _usable()
    if module is not None:
        same = _entry_call("same_words", lambda: module.same_words(words_a, words_b))
        if same is not _FAILED:
            return bool(same)
    return bool(np.array_equal(words_a, words_b))
