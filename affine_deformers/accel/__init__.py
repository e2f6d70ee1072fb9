"""Optional compiled backend of the kernel (C via ctypes, never bpy), with the numpy kernel as the
fallback: the facade the Blender layer calls (`from .. import accel; accel.X`).

Each entry has the contract of the core function it names (arguments, checks and messages, results:
core is the reference and the one place they are written; only the chain entries, a kernel-level form
of core.hierarchy's, hold theirs in chains.py) and runs the C library (csrc/, loaded by `native.py`)
when it is available, numpy otherwise. The two agree to ~1e-15 relative
(the C kernel uses polynomial transcendentals), and within one backend every row is bit-identical
whichever call, thread count or row subset computes it; results cached across updates are keyed on
`active()`.

The modules, one concern each:

* `state` — whether calls go to the library now (`active`, `backend`, `set_enabled`, `pinned`,
  AFFINE_DEFORMERS_ACCEL), loading it on first use, the lock, and how a call reaches an entry;
* `threads` — the helper threads a chunked call runs on (`_run_chunks`, `_Helper`);
* `batch` — the row calls of many deformers collected during an update and run in one hand-over
  (`KernelBatch`, `collecting`);
* `vertex` — the per-vertex map (`deform_points_params(_rows)`, `vertex_motions`, `linear_maps`) and
  the incremental update's passes (`rows_reading`, `same_bits`);
* `chains` — the bone blend's products of passes (`chain_points`, `chain_motions`);
* `controls` — ψ of moved controls (`params_from_matrices`, `polar_log`) and the cage nodes'
  pivot (`node_params`);
* `cage` — a cage's faces and nodes per update (`cage_faces`, `cage_nodes`);
* `arap` — the shape-preserving pass (`arap_bind`, `CompiledArapSolver`);
* `native` — the library: finding, loading, and each C entry as a numpy function.

Loading the library takes milliseconds and compiles nothing; `warm_up` (here: it touches every
module) runs every entry once on a tiny input, and so checks them, ahead of the first update.
"""

from __future__ import annotations

import threading

import numpy as np

# Internal names stay reachable as accel.X for tests and tools (the `X as X` form re-exports them):
# `_state` is the state at import (a test that needs a fresh one replaces `state._state`, which
# every call reads), `_unwrap` is core.unwrap as `accel.cage` calls it.
from ..core import cage as _cage
from ..core import unwrap as _unwrap  # noqa: F401
from . import arap, native, state
from .arap import _warm_arap, arap_bind
from .batch import KernelBatch, collecting
from .cage import cage_faces, cage_nodes
from .chains import chain_motions, chain_points
from .controls import node_params, params_from_matrices, polar_log
from .state import ACCEL_ENV, _load, _spin, active, backend, pinned, set_enabled
from .state import _State as _State
from .state import _state as _state
from .threads import _Helper as _Helper
from .threads import _run_chunks as _run_chunks
from .threads import _threads as _threads
from .vertex import (
    deform_points_params,
    deform_points_params_rows,
    linear_maps,
    rows_reading,
    same_bits,
    vertex_motions,
)

__all__ = [
    "ACCEL_ENV",
    "KernelBatch",
    "active",
    "arap",
    "arap_bind",
    "backend",
    "cage_faces",
    "cage_nodes",
    "chain_motions",
    "chain_points",
    "collecting",
    "deform_points_params",
    "deform_points_params_rows",
    "linear_maps",
    "native",
    "node_params",
    "params_from_matrices",
    "pinned",
    "polar_log",
    "rows_reading",
    "same_bits",
    "set_enabled",
    "vertex_motions",
    "warm_up",
]


def warm_up() -> str:
    """Load the library and run every entry once on a tiny input (and the helper threads'
    `spin_wait`), so that an entry that fails does so here, not in the first real update; returns
    `backend()`. Safe to call from a helper thread: calls into the compiled kernel are serialised by
    a lock, and a failure only switches the process to numpy. While it runs, other threads' calls
    use numpy (`state._usable`)."""
    pts = np.zeros((2, 3))
    params = np.zeros((1, 12))
    params[0, 6] = 1e-3  # not all zero: the all-at-rest shortcut would skip the kernel
    idx = np.zeros((2, 1), dtype=np.int32)
    val = np.ones((2, 1))
    state._state.warming = threading.current_thread()
    try:
        deform_points_params(pts, params, idx, val)  # deform_points_entry
        vertex_motions(params, idx, val)  # motion_params
        polar_log(np.eye(3)[None])  # polar_log
        params_from_matrices(np.eye(4)[None])  # psi_rows
        node_params(np.zeros((1, 3)), np.ones((1, 1)), params)  # node_pivot
        tetra = _cage.CageTopology.from_polygons([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
        corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        moved = corners.copy()
        moved[3, 0] = 0.1
        cage_faces(corners, moved, tetra)  # cage_faces
        cage_nodes(np.zeros((1, 3)), np.ones((1, 4)), params.repeat(4, axis=0), np.arange(4))  # cage_nodes
        rows_reading(np.ones(1, dtype=bool), idx, val)  # rows_reading
        same_bits(pts, pts)  # same_words
        prefixes = np.zeros((1, 12))
        prefixes[0, [0, 4, 8]] = 1.0
        chain_points(pts, params, idx[None], val[None], idx[:, 0], prefixes)  # chain_points_entry
        chain_motions(params, idx[None], val[None], idx[:, 0], prefixes)  # chain_motion_entry
        _warm_arap()  # spd_factor, arap_frame, spd_bytes, spd_free
        module = _load()
        if module is not None:
            with state._state.lock:
                _spin(module)  # Kernel.spin_wait, for the helper threads
    finally:
        state._state.warming = None
    return backend()
