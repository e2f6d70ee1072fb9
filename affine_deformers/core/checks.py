"""Argument checks and trivial results shared by the two kernels (core.deform, numpy; accel, compiled),
so both refuse bad input with the same messages and give the same exact answers where no arithmetic
is needed (controls at rest: the input, or the identity motion, bit for bit).

`check_deform_args` and `check_motion_args` are the whole check of core.deform's
`deform_points_params` and `vertex_motions` arguments, in the order core's kernel applies them
(there the weights cache sits between the shape and the content checks of the weights, which a
cache hit skips: `check_weights_shape`, then `check_indices`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32]

__all__ = [
    "check_deform_args",
    "check_given_out",
    "check_indices",
    "check_motion_args",
    "check_motion_indices",
    "check_motion_out",
    "check_out",
    "check_points",
    "check_rows",
    "check_table",
    "check_weights_shape",
    "identity_motions",
    "unchanged",
]


def unchanged(pts: FloatArray, out: FloatArray) -> FloatArray:
    """Every control at the identity: the exact input, so "controls at rest ⇒ mesh unchanged" holds bit
    for bit (the general path gives the same values but may turn −0.0 into +0.0)."""
    if out is not pts:
        np.copyto(out, pts)
    return out


def check_points(points: ArrayLike) -> FloatArray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain non-finite coordinates")
    return pts


def check_table(table: ArrayLike, width: int, name: str) -> FloatArray:
    tab = np.asarray(table, dtype=np.float64)
    if tab.ndim != 2 or tab.shape[1] != width:
        raise ValueError(f"{name} must have shape (m, {width}), got {tab.shape}")
    if not np.all(np.isfinite(tab)):
        bad = int(np.argmax(~np.isfinite(tab).all(axis=1)))
        raise ValueError(f"{name} row {bad} has non-finite values")
    return tab


def check_indices(
    indices: ArrayLike, values: ArrayLike, n_points: int | None, m: int
) -> tuple[IntArray, FloatArray]:
    idx = np.asarray(indices)
    val = np.asarray(values, dtype=np.float64)
    if idx.ndim != 2 or val.shape != idx.shape:
        raise ValueError(f"indices and values must both have shape (N, K), got {idx.shape} and {val.shape}")
    if n_points is not None and idx.shape[0] != n_points:
        raise ValueError(f"indices have {idx.shape[0]} rows for {n_points} points")
    if not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"indices must be integers, got {idx.dtype}")
    if idx.size and (int(idx.min()) < 0 or int(idx.max()) >= m):
        raise ValueError(f"indices must lie in [0, {m}), got [{int(idx.min())}, {int(idx.max())}]")
    if not np.all(np.isfinite(val)):
        raise ValueError("weight values contain non-finite entries")
    return idx, val


def check_out(out: FloatArray | None, pts: FloatArray) -> FloatArray:
    """`out` checked against the points, or a new array when None."""
    return np.empty_like(pts) if out is None else check_given_out(out, pts)


def check_given_out(out: FloatArray, pts: FloatArray) -> FloatArray:
    if not isinstance(out, np.ndarray) or out.shape != pts.shape or out.dtype != np.float64:
        raise ValueError(f"out must be a float64 array of shape {pts.shape}")
    return out


def check_motion_indices(indices: ArrayLike, values: ArrayLike, m: int) -> int:
    """N, the number of vertices, from (N, K) indices (there are no points to take it from);
    ValueError with `check_indices`' messages when the shapes do not fit."""
    shape = np.shape(indices)
    if len(shape) != 2:
        raise ValueError(f"indices must have shape (N, K), got {shape}")
    if np.shape(values) != shape:
        check_indices(indices, values, None, m)  # raises the shape message
    return int(shape[0])


def check_motion_out(
    out: FloatArray | NDArray[np.float32] | None, n: int
) -> FloatArray | NDArray[np.float32]:
    """`out` of `vertex_motions` checked ((4, n, 3), float64 or float32), or a new float64 array."""
    if out is None:
        return np.empty((4, n, 3))
    if not isinstance(out, np.ndarray) or out.shape != (4, n, 3) or out.dtype not in (np.float64, np.float32):
        raise ValueError(f"out must be a float64 or float32 array of shape {(4, n, 3)}")
    return out


def identity_motions(
    out: FloatArray | NDArray[np.float32], sel: NDArray[np.integer] | None
) -> FloatArray | NDArray[np.float32]:
    """The identity map (columns e_x, e_y, e_z, translation 0) in the rows `sel` of `out` (all rows
    when None): the motion of every vertex when every control is at rest, exactly."""
    ident = np.zeros((4, 1, 3), dtype=out.dtype)
    ident[0, 0, 0] = ident[1, 0, 1] = ident[2, 0, 2] = 1.0
    if sel is None:
        out[...] = ident
    else:
        out[:, sel] = ident
    return out


def check_rows(rows: ArrayLike, n_points: int) -> NDArray[np.integer]:
    """`rows` as a checked 1-D integer array of row indices in [0, n_points)."""
    sel = np.asarray(rows)
    if sel.ndim != 1 or not np.issubdtype(sel.dtype, np.integer):
        raise ValueError(f"rows must be a 1-D integer array, got {sel.dtype} {sel.shape}")
    if sel.size and (int(sel.min()) < 0 or int(sel.max()) >= n_points):
        raise ValueError(f"rows must lie in [0, {n_points})")
    return sel


def check_weights_shape(indices: ArrayLike, n_points: int) -> None:
    """(N, K) indices for N = n_points points: the first check of the weights (before their contents)."""
    shape = np.shape(indices)
    if len(shape) != 2 or shape[0] != n_points:
        raise ValueError(f"indices must have shape ({n_points}, K), got {shape}")


def check_deform_args(
    points: ArrayLike, params: ArrayLike, indices: ArrayLike, values: ArrayLike
) -> tuple[FloatArray, FloatArray, NDArray[np.integer], FloatArray]:
    """(points (N, 3), params (m, 12), indices (N, K) integers in [0, m), values (N, K)) checked as
    core.deform.deform_points_params checks them, with its messages."""
    table = check_table(params, 12, "params")
    pts = check_points(points)
    check_weights_shape(indices, pts.shape[0])
    idx, val = check_indices(indices, values, pts.shape[0], table.shape[0])
    return pts, table, idx, val


def check_motion_args(
    params: ArrayLike, indices: ArrayLike, values: ArrayLike
) -> tuple[FloatArray, NDArray[np.integer], FloatArray]:
    """(params (m, 12), indices (N, K) integers in [0, m), values (N, K)) checked as
    core.deform.vertex_motions checks them, with its messages."""
    table = check_table(params, 12, "params")
    check_motion_indices(indices, values, table.shape[0])
    idx, val = check_indices(indices, values, None, table.shape[0])
    return table, idx, val
