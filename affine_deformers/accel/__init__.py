"""Optional compiled backend of the per-vertex kernel, with the numpy kernel as the fallback.

`deform_points_params`, `deform_points_params_rows` and `vertex_motions` have the signatures and the
argument checks (same messages) of `affine_deformers.core.deform`; they run the C kernel
(csrc/affine_kernel.c, loaded by `native.py`) when it is available and the numpy kernel otherwise.
The results agree to ~1e-15 relative (the C kernel uses polynomial transcendentals, see
affine_kernel.c), and within one backend every row is bit-identical whichever call, thread count or
row subset computes it.

The compiled path is skipped when

* the environment variable AFFINE_DEFORMERS_ACCEL is "0" (checked on every call), or the add-on
  preference turned it off (`set_enabled(False)`), or
* the library is missing or failed to load (`native.KernelUnavailableError`: no build for this platform,
  a damaged or foreign file, another ABI version), or an entry failed on its first call: the process
  then stays on numpy and `backend()` says why. Such a failure never reaches the caller.

Loading the library takes milliseconds and compiles nothing; `warm_up` runs every entry once on a
tiny input (and so checks them) ahead of the first update.
Threads: a ctypes call releases the GIL; `_run` runs an entry on the calling thread and on helper
threads of this module, which claim chunks from a shared counter.
Calls into the compiled kernel are serialised by a lock (Blender may evaluate from more than one
thread; a call already uses every thread it is given).
"""

from __future__ import annotations

import os
import threading
import time
import warnings
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core import aff3 as _aff3
from ..core import cage as _cage
from ..core import deform as _np_kernel
from ..core import hierarchy as _np_hierarchy
from ..core import unwrap as _unwrap
from ..core.cage import harmonic as _harmonic
from ..core.checks import (
    check_given_out,
    check_indices,
    check_motion_indices,
    check_motion_out,
    check_out,
    check_points,
    check_rows,
    check_table,
    identity_motions,
    unchanged,
)
from ..core.deform import default_threads
from . import native
from .native import Kernel, KernelUnavailableError

__all__ = [
    "ACCEL_ENV",
    "active",
    "backend",
    "cage_faces",
    "cage_nodes",
    "chain_motions",
    "chain_points",
    "deform_points_params",
    "deform_points_params_rows",
    "linear_maps",
    "node_params",
    "params_from_matrices",
    "polar_log",
    "rows_reading",
    "same_bits",
    "set_enabled",
    "vertex_motions",
    "warm_up",
]

FloatArray = NDArray[np.float64]

#: Environment variable: "0" disables the compiled kernel.
ACCEL_ENV = "AFFINE_DEFORMERS_ACCEL"


class _Seen:
    """The keys of the last few checked calls (a bounded, insertion-ordered set): with many deformed
    objects the calls alternate between deformers, and each keeps its checked key."""

    SIZE = 64

    def __init__(self) -> None:
        self._keys: dict[Hashable, None] = {}

    def __contains__(self, key: Hashable) -> bool:
        return key is not None and key in self._keys

    def add(self, key: Hashable) -> None:
        self._keys.pop(key, None)
        self._keys[key] = None
        if len(self._keys) > self.SIZE:
            del self._keys[next(iter(self._keys))]

    def discard(self, key: Hashable) -> None:
        self._keys.pop(key, None)


class _State:
    """The compiled kernel once loaded, or why the process stays on numpy."""

    def __init__(self) -> None:
        self.module: Kernel | None = None
        self.failure: str | None = None
        self.compiled: set[str] = set()  # entries that have run once
        self.lock = threading.RLock()
        self.checked = _Seen()  # keys naming checked points, indices and values
        self.checked_weights = _Seen()  # keys naming checked indices and values only
        self.checked_chain = _Seen()  # keys naming checked pass indices and values
        self.enabled = True
        self.warming: threading.Thread | None = None  # the thread running `warm_up`
        self.spin: tuple | bool | None = None  # `_spin`'s measurement (False: unavailable)


_state = _State()


def _disabled_by_env() -> bool:
    return not _state.enabled or os.environ.get(ACCEL_ENV, "").strip() == "0"


def set_enabled(enabled: bool) -> None:
    """Use the compiled kernel when available (True, the default) or always numpy (False): the add-on
    preference. The environment variable still wins when it says "0"."""
    _state.enabled = bool(enabled)


def active() -> bool:
    """True when calls from this thread go to the compiled kernel now (loads the library on first use)."""
    return _usable() is not None


def _usable() -> Kernel | None:
    """The compiled kernel if this thread may call it now. While another thread runs `warm_up`,
    None: an update then runs on numpy instead of waiting for it (the two kernels agree to ~1e-15;
    callers that cache results key them on `active()`)."""
    warming = _state.warming
    if warming is not None and warming is not threading.current_thread():
        return None
    return _load()


def warm_up() -> str:
    """Load the library and run every entry once on a tiny input (and the helper threads'
    `spin_wait`), so that an entry that fails does so here, not in the first real update; returns
    `backend()`. Safe to call from a helper thread: calls into the compiled kernel are serialised by
    a lock, and a failure only switches the process to numpy."""
    pts = np.zeros((2, 3))
    params = np.zeros((1, 12))
    params[0, 6] = 1e-3  # not all zero: the all-at-rest shortcut would skip the kernel
    idx = np.zeros((2, 1), dtype=np.int32)
    val = np.ones((2, 1))
    _state.warming = threading.current_thread()
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
        module = _load()
        if module is not None:
            with _state.lock:
                _spin(module)  # Kernel.spin_wait, for the helper threads
    finally:
        _state.warming = None
    return backend()


def _load() -> Kernel | None:
    """The compiled kernel, loading the library on first use; None when unavailable (reason recorded)."""
    if _disabled_by_env() or _state.failure is not None:
        return None
    if _state.module is None:
        with _state.lock:
            if _state.module is None and _state.failure is None:
                try:
                    _state.module = native.load()
                except KernelUnavailableError as exc:
                    # A package built without the library (--platform none) has none by design: say so
                    # in backend() (the preferences show it), without a warning at every start.
                    _fail(str(exc), warn=False)
                except Exception as exc:
                    _fail(f"loading the compiled kernel failed: {type(exc).__name__}: {exc}")
    return _state.module


_FAILED = object()  # what `_entry_call` returns when the entry could not be compiled


def _entry_call(name: str, call: Callable[[], Any]) -> Any:
    """`call()`, which runs the compiled entry `name`, under the kernel lock. A failure on its first
    run switches the process to numpy and returns _FAILED, so the caller falls back; once the entry
    has run, an exception is a real error and propagates."""
    with _state.lock:
        try:
            result = call()
        except Exception as exc:
            if name in _state.compiled:
                raise
            _fail(f"the compiled {name} failed: {type(exc).__name__}: {exc}")
            return _FAILED
        _state.compiled.add(name)
    return result


def _fail(reason: str, warn: bool = True) -> None:
    """Stay on numpy for the rest of the process."""
    _state.failure = reason
    _state.module = None
    if warn:
        warnings.warn(f"affine_deformers: compiled kernel disabled ({reason}); using numpy", stacklevel=3)


#: How long an idle helper thread busy-waits (without the GIL) for the next call before it sleeps
#: (0: it sleeps at once). A spin lets calls back to back find it awake, but the core it holds is
#: the one Blender's own threads need right after our handler returns (the depsgraph pass that
#: applies the result, Geometry Nodes, drawing), and a caller no longer waits for a helper that is
#: still asleep (`_Helper.defer`: the caller claims every chunk itself). Measured on a 2-vCPU VM,
#: one probe moving among 8, interleaved runs: 10k vertices 2.15 ms per update with a 1 ms spin,
#: 1.19 ms with 0.1 ms, 1.10 ms with none; 130k vertices 6.99 / 6.13 / 5.67 ms.
SPIN_MS = 0.0


class _Helper:
    """A thread that runs one job at a time for `_run_chunks`: `start` hands it over, `join` waits
    for it and re-raises its exception. Two locks used as binary semaphores, so the hand-over is one
    lock release each way (a thread pool's futures cost ~0.1 ms more per call here); after a job it
    spins for up to SPIN_MS on a job counter (`Kernel.spin_wait`, GIL released) before it blocks.
    Daemon: it only ever waits for a job or runs one the caller waits for.

    `defer` instead of `join`: for a job that provably has nothing left to do (every chunk of its
    call was claimed by other threads, so when it runs it claims none and writes nothing), the wait
    moves to the next `start` or `join` — by then the thread has long woken up — instead of keeping
    the caller waiting for a sleeping thread to get a core back (0.05–4 ms) for no work."""

    def __init__(self, spin: tuple[Callable[[np.ndarray, int, int], bool], int] | None) -> None:
        self._go = threading.Lock()
        self._go.acquire()
        self._done = threading.Lock()
        self._done.acquire()
        self._posted = np.zeros(1, dtype=np.int64)  # jobs handed over so far (read by spin_wait)
        self._job: tuple[Callable[..., None], tuple] | None = None
        self._error: BaseException | None = None
        self._spin = spin
        self._deferred = False  # a handed-over job not joined yet (`defer`)
        threading.Thread(target=self._loop, name="affine_deformers accel", daemon=True).start()

    def _loop(self) -> None:
        seen = 0
        while True:
            if not self._go.acquire(blocking=False):
                if self._spin is not None:
                    spin_wait, n = self._spin
                    spin_wait(self._posted, seen, n)
                self._go.acquire()
            fn, args = self._job  # type: ignore[misc]
            try:
                fn(*args)
            except BaseException as exc:  # handed to the caller by join()
                self._error = exc
            finally:
                self._job = None
                seen = int(self._posted[0])  # no new job before join() returns
                self._done.release()

    def start(self, fn: Callable[..., None], args: tuple) -> None:
        if self._deferred:
            self.join()
        self._job = (fn, args)
        self._posted[0] += 1
        self._go.release()

    def join(self) -> None:
        self._deferred = False
        self._done.acquire()
        error, self._error = self._error, None
        if error is not None:
            raise error

    def defer(self) -> None:
        """Leave the current job to finish on its own (see the class doc); joined later."""
        self._deferred = True


_helpers: list[_Helper] = []  # grown on demand; used under _state.lock only


def _spin(module: Kernel) -> tuple[Callable[[np.ndarray, int, int], bool], int] | None:
    """(Kernel.spin_wait, iterations for SPIN_MS), measured once; None when SPIN_MS is 0 or it
    fails (the helpers then just sleep between calls)."""
    if _state.spin is None:
        try:
            fn = module.spin_wait
            flag = np.zeros(1, dtype=np.int64)
            fn(flag, 0, 1)
            n = 20_000
            t0 = time.perf_counter()
            fn(flag, 0, n)
            per_ms = n / max((time.perf_counter() - t0) * 1e3, 1e-6)
            _state.spin = (fn, max(1, int(SPIN_MS * per_ms)))
        except Exception:
            _state.spin = False
    return (_state.spin or None) if SPIN_MS > 0.0 else None


def _run_chunks(
    entry: Callable[..., None], args: tuple, n_chunks: int, threads: int,
    spin: tuple[Callable[[np.ndarray, int, int], bool], int] | None = None,
) -> None:
    """entry(*args, counter) on min(threads, n_chunks) threads sharing one chunk counter: this one
    and `_Helper` threads (the entries release the GIL; new helpers get `spin`). Each thread claims
    the next chunk until none is left, so a helper that starts late (thread wake-up, a busy core)
    takes fewer chunks instead of delaying the call. A row's value does not depend on the thread.
    The compiled entries return how many chunks the calling thread did: when that is all of them, no
    helper can write anything any more (a chunk is claimed once), so the call returns without waiting
    for helpers still asleep (`_Helper.defer`); any other return value (None) waits for every helper.
    Call under _state.lock."""
    counter = np.zeros(1, dtype=np.int64)
    own = None
    n_helpers = max(0, min(threads, n_chunks) - 1)
    while len(_helpers) < n_helpers:
        _helpers.append(_Helper(spin))
    started: list[_Helper] = []
    try:
        for helper in _helpers[:n_helpers]:
            helper.start(entry, (*args, counter))
            started.append(helper)
        own = entry(*args, counter)
    finally:
        errors = []
        # The helpers write into the caller's arrays: never return before those that can are done.
        alone = isinstance(own, int) and own >= n_chunks  # `own` unbound only when raising
        for helper in started:
            try:
                if alone:
                    helper.defer()
                else:
                    helper.join()
            except Exception as exc:
                errors.append(exc)
    if errors:
        raise errors[0]


def _threads() -> int:
    """Threads a compiled call may use: default_threads() ($AFFINE_DEFORMERS_THREADS or the cores)."""
    return default_threads()


def backend() -> str:
    """'C kernel (<library file>), <n> threads' or 'numpy (<reason>)'. Loads the library if not done yet."""
    if not _state.enabled:
        return "numpy (compiled kernel turned off in the preferences)"
    if _disabled_by_env():
        return f"numpy ({ACCEL_ENV}=0)"
    module = _load()
    if module is None:
        return f"numpy ({_state.failure})"
    n = _threads()
    return f"{module.describe()}, {n} thread{'s' if n != 1 else ''}"


def _run(name: str, n: int, *args: object) -> bool:
    """Kernel.<name>(*args, counter) for an n-row work list (⌈n/CHUNK⌉ chunks) on `_threads`
    threads (`_run_chunks`; an entry's first call, which checks it, on this thread alone); False if
    the backend is (or just became) unavailable, in which case the caller recomputes with numpy."""
    module = _load()
    if module is None:
        return False
    entry = getattr(module, name)
    n_chunks = -(-n // module.CHUNK)

    def chunks() -> None:
        threads = _threads() if name in _state.compiled else 1  # an entry's first run on one thread
        spin = _spin(module) if threads > 1 and n_chunks > 1 else None
        _run_chunks(entry, args, n_chunks, threads, spin)

    return _entry_call(name, chunks) is not _FAILED


# ----------------------------------------------------------------------------------------------
# argument preparation (the checks and messages of core.deform)


def _c(a: np.ndarray, dtype: type) -> np.ndarray:
    """`a` as a C-contiguous array of `dtype`."""
    return np.ascontiguousarray(a, dtype=dtype)


def _inputs(
    points: ArrayLike, params: ArrayLike, indices: ArrayLike, values: ArrayLike, key: Hashable | None
) -> tuple[FloatArray, FloatArray, NDArray[np.int32], FloatArray]:
    """Checked points, table, indices and values. With a key seen before, only the shapes are
    checked (the caller vouches for the contents; the kernel clamps indices, so memory stays safe)."""
    table = check_table(params, 12, "params")
    if key in _state.checked:
        pts = np.asarray(points, dtype=np.float64)
        idx = np.asarray(indices)
        val = np.asarray(values, dtype=np.float64)
        if (
            pts.ndim != 2
            or pts.shape[1] != 3
            or idx.shape != val.shape
            or idx.ndim != 2
            or idx.shape[0] != pts.shape[0]
            or not np.issubdtype(idx.dtype, np.integer)
        ):
            _state.checked.discard(key)
            return _inputs(points, params, indices, values, None)
    else:
        pts = check_points(points)
        idx = np.asarray(indices)
        if idx.ndim != 2 or idx.shape[0] != pts.shape[0]:
            # the message of core.deform's weights cache, which checks this first
            raise ValueError(f"indices must have shape ({pts.shape[0]}, K), got {idx.shape}")
        idx, val = check_indices(idx, values, pts.shape[0], table.shape[0])
        if key is not None:
            _state.checked.add(key)
    return pts, table, idx, val


def _check_out32(out32: object, shape: tuple[int, ...]) -> None:
    if (
        not isinstance(out32, np.ndarray)
        or out32.dtype != np.float32
        or out32.shape != shape
        or not out32.flags.c_contiguous
        or not out32.flags.writeable
    ):
        raise ValueError(f"out32 must be a writable C-contiguous float32 array of shape {shape}")


# ----------------------------------------------------------------------------------------------
# entry points


def deform_points_params(
    points: ArrayLike,
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    out: FloatArray | None = None,
    *,
    key: Hashable | None = None,
) -> FloatArray:
    """v' = φ(p_v) v with p_v = Σ_k values[v, k] · params[indices[v, k]] for every row v of points.

    As `core.deform.deform_points_params` (same arguments, checks and messages): points (N, 3),
    params (m, 12), indices (N, K) integer in [0, m), values (N, K); returns (N, 3) float64 (`out` if
    given; it may be `points` itself). All-zero params return the input bit for bit. `key`: a
    hashable token the caller guarantees names these exact points, indices and values; a call with
    the key of the previous checked call skips re-validating them.
    """
    if _usable() is None:
        return _np_kernel.deform_points_params(points, params, indices, values, out, key=key)
    pts, table, idx, val = _inputs(points, params, indices, values, key)
    out = check_out(out, pts)
    if not out.flags.writeable:
        raise ValueError("out must be writable")
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
        return _np_kernel.deform_points_params(points, params, indices, values, out, key=key)
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
    """`deform_points_params` for the vertices `rows` only: out[v] = φ(p_v) points[v] (minus points[v]
    when `offsets`) for v in rows; the other rows of `out` (float64, (N, 3)) are left as they are.

    As `core.deform.deform_points_params_rows`; each written row is bit-identical to the same row of
    `deform_points_params` with the same backend. `out32`: an optional (N, 3) float32 C-contiguous
    array that also gets out[v] rounded to float32 (bit for bit what out.astype(np.float32) holds
    there) for v in rows, and nothing elsewhere: a float32 copy of `out` is kept up to date without
    converting the whole array.
    """
    if out32 is not None:
        _check_out32(out32, np.shape(out))
        if np.may_share_memory(out32, out):
            raise ValueError("out32 must not share memory with out")
    if _usable() is None:
        return _numpy_rows(points, params, indices, values, rows, out, offsets, key, out32)
    pts, table, idx, val = _inputs(points, params, indices, values, key)
    check_given_out(out, pts)
    if not out.flags.writeable:
        raise ValueError("out must be writable")
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
    if not _run("deform_points_entry", sel.shape[0], *args):
        return _numpy_rows(points, params, indices, values, rows, out, offsets, key, out32)
    if dst is not out:
        out[sel] = dst[sel]
    return out


_NO_OUT32 = np.empty((0, 3), dtype=np.float32)
_NO_POINTS = np.empty((0, 3))
_NO_ROWS = np.empty(0, dtype=np.intp)
_NO_MOTIONS = np.empty((4, 0, 3))
_NO_MOTIONS32 = np.empty((4, 0, 3), dtype=np.float32)


def _weights_inputs(
    params: ArrayLike, indices: ArrayLike, values: ArrayLike, key: Hashable | None
) -> tuple[FloatArray, NDArray[np.integer], FloatArray]:
    """Checked table, indices and values (no points: `vertex_motions`). With a key of an earlier
    checked call (with or without points) only the shapes are checked, as in `_inputs`."""
    table = check_table(params, 12, "params")
    if key in _state.checked or key in _state.checked_weights:
        idx = np.asarray(indices)
        val = np.asarray(values, dtype=np.float64)
        if idx.ndim == 2 and idx.shape == val.shape and np.issubdtype(idx.dtype, np.integer):
            return table, idx, val
    check_motion_indices(indices, values, table.shape[0])
    idx, val = check_indices(indices, values, None, table.shape[0])
    if key is not None:
        _state.checked_weights.add(key)
    return table, idx, val


def vertex_motions(
    params: ArrayLike,
    indices: ArrayLike,
    values: ArrayLike,
    out: FloatArray | NDArray[np.float32] | None = None,
    *,
    rows: ArrayLike | None = None,
    key: Hashable | None = None,
) -> FloatArray | NDArray[np.float32]:
    """Each vertex's affine map φ(p_v) as out[:, v] = (M_v e_x, M_v e_y, M_v e_z, t_v): as
    `core.deform.vertex_motions` (same arguments, checks and messages; out (4, N, 3) float64 or
    float32, a float32 out gets the float64 value rounded once; `rows` recomputes only those rows,
    bit-identical to the same rows of a full call with the same backend). `key`: as in
    `deform_points_params` (naming the indices and values); a call with the key of an earlier checked
    call skips re-validating them."""
    if _usable() is None:
        return _np_kernel.vertex_motions(params, indices, values, out, rows=rows, key=key)
    table, idx, val = _weights_inputs(params, indices, values, key)
    n = idx.shape[0]
    out = check_motion_out(out, n)
    if not out.flags.writeable:
        raise ValueError("out must be writable")
    sel = None if rows is None else _c(check_rows(rows, n), np.intp)
    if not table.any():  # every control at rest (also m = 0, which the kernel cannot index)
        return identity_motions(out, sel)
    dst = out if out.flags.c_contiguous else np.ascontiguousarray(out)
    use32 = dst.dtype == np.float32
    args = (_c(table, np.float64), _c(idx, np.int32), _c(val, np.float64), _NO_ROWS if sel is None else sel,
            sel is not None, _NO_MOTIONS if use32 else dst, dst if use32 else _NO_MOTIONS32, bool(use32))
    if not _run("motion_params", n if sel is None else sel.shape[0], *args):
        return _np_kernel.vertex_motions(params, indices, values, out, rows=rows, key=key)
    if dst is not out:
        if sel is None:
            np.copyto(out, dst)
        else:
            out[:, sel] = dst[:, sel]
    return out


def polar_log(M: ArrayLike) -> tuple[FloatArray, FloatArray] | None:
    """(R, Ŷ) (n, 3, 3) each with M = R exp(Ŷ), R = U Vᵀ, Ŷ = V diag(log σ) Vᵀ for the SVD
    M = U diag(σ) Vᵀ of each of the (n, 3, 3) matrices M (det > 0, checked by the caller), computed
    by the compiled kernel (`Kernel.polar_log`, agreeing with numpy's SVD to ~1e-15); None when the
    compiled kernel is not active now (the caller then uses numpy): the `polar` argument of
    `core.aff3.params_from_matrices`."""
    module = _usable()
    if module is None:
        return None
    m = _c(np.asarray(M, dtype=np.float64).reshape(-1, 3, 3), np.float64)
    R = np.empty_like(m)
    Yh = np.empty_like(m)
    if _entry_call("polar_log", lambda: module.polar_log(m, R, Yh)) is _FAILED:
        return None
    return R, Yh


def params_from_matrices(A: ArrayLike) -> FloatArray | None:
    """`core.aff3.params_from_matrices(A)`: ψ in the 12-number layout, A (..., 4, 4) ↦ (..., 12),
    with the same ValueError for a motion outside Aff+(3), in one compiled call (`Kernel.psi_rows`;
    the same parameters to ~1e-15). The few controls that moved in an update cost microseconds
    instead of numpy's per-call overhead on a handful of 3×3 matrices. None when the compiled kernel
    is not active now (the caller then uses the numpy function)."""
    module = _usable()
    if module is None:
        return None
    checked = _aff3.validate_affine(A)
    flat = checked.reshape(-1, 4, 4)
    rows = np.empty((flat.shape[0], 12))
    rows[:, :9] = flat[:, :3, :3].reshape(-1, 9)
    rows[:, 9:] = flat[:, :3, 3]
    bad = _entry_call("psi_rows", lambda: module.psi_rows(rows))
    if bad is _FAILED:
        return None
    if bad >= 0:  # numpy names the transform in its error (or finds the row finite after all)
        return _aff3.params_from_matrices(checked)
    return rows.reshape(*checked.shape[:-2], 12)


def node_params(node_points: ArrayLike, node_weights: ArrayLike, face_params: ArrayLike, *,
                faces: ArrayLike | None = None, valid: ArrayLike | None = None) -> FloatArray:
    """`core.cage.harmonic.node_params` (same arguments and result, to ~1e-15) with its per-face
    and per-node steps in the compiled kernel (`Kernel.node_pivot`): B_f = V(ω_f)⁻¹ (M_f − I) for
    the faces, the blend over the node's faces (`face_columns`, numpy), then u′ = u + B x +
    V(ω)⁻¹ (x − M x) for the nodes. The numpy version (with `linear_maps`) when the compiled kernel
    is not active now."""
    module = _usable()
    if module is None:
        return _harmonic.node_params(node_points, node_weights, face_params, faces=faces, valid=valid,
                                     maps=linear_maps)
    W = np.asarray(node_weights, dtype=np.float64)
    x = _c(node_points, np.float64)
    P = np.asarray(face_params, dtype=np.float64)
    faces = np.arange(W.shape[1]) if faces is None else np.asarray(faces, dtype=np.intp)
    face_rows = _c(P[faces], np.float64)
    B = np.empty((faces.size, 9))
    nodes = np.empty((x.shape[0], 12))

    def both_steps() -> None:
        module.node_pivot(False, face_rows, _NO_POINTS, B)
        blend = _harmonic.face_columns(W, faces, valid, np.concatenate([face_rows, B], axis=1))
        module.node_pivot(True, np.ascontiguousarray(blend), x, nodes)

    if _entry_call("node_pivot", both_steps) is _FAILED:
        return _harmonic.node_params(node_points, node_weights, face_params, faces=faces, valid=valid,
                                     maps=linear_maps)
    return nodes


def cage_faces(rest: ArrayLike, current: ArrayLike, topology: _cage.CageTopology
               ) -> tuple[_cage.FaceMotions, NDArray[np.bool_], float] | None:
    """(`core.cage.face_motions(rest, current, topology, faces=reached)`, reached (F,) bool =
    `core.cage.affected_faces(rest, current, topology)`, `core.cage.signed_volume(current, topology)`)
    with the 'NEIGHBOURS' apex, in one compiled call (`Kernel.cage_faces`: corner frames, stencil
    apex, fold guard, ψ with the polar split of `polar_log`, the mean over each face's corners, for
    the faces reached only; agreeing with the numpy functions to ~1e-15). Faces whose corners need a
    lift onto the first corner's rotation branch (past a half turn from it) are lifted and averaged
    here with `unwrap.lift_params`, as face_motions does. None when the compiled kernel is not
    active now (the caller then uses the numpy functions)."""
    module = _usable()
    if module is None:
        return None
    tables = _cage.face_tables(rest, topology)
    cur = _c(np.asarray(current, dtype=np.float64), np.float64)
    if cur.shape != tables.rest.shape:
        raise ValueError(f"current must have shape {tables.rest.shape}, got {cur.shape}")
    F = topology.n_faces
    params = np.empty((F, 12))
    corner_params = np.empty((tables.triples.shape[0], 12))
    flags = np.empty(F, dtype=np.int64)
    moved = np.empty(cur.shape[0], dtype=np.bool_)
    volume = _entry_call("cage_faces", lambda: module.cage_faces(
        cur, tables.rest, tables.triples, tables.first, tables.usable, tables.weight, tables.rest_ok,
        tables.centres, tables.inverses, tables.stencil_vertices, tables.stencil_gamma,
        tables.stencil_moments, tables.stencil_spread, tables.stencil_active, tables.fan, moved,
        params, corner_params, flags))
    if volume is _FAILED:
        return None
    reached = (flags & module.FACE_REACHED) != 0
    has_corner = (flags & module.FACE_HAS_CORNER) != 0
    valid = has_corner & (((flags & module.FACE_VALID) != 0) | ~reached)
    lift = np.flatnonzero(flags & module.FACE_NEEDS_LIFT)
    for f in lift.tolist():  # rare: a face whose corners straddle a half turn
        span = np.arange(tables.first[f], tables.first[f + 1])
        rows = span[tables.usable[span]]
        lifted = _unwrap.lift_params(corner_params[rows], corner_params[rows[0], 0:3])
        params[f] = (tables.weight[rows, None] * lifted).sum(axis=0)
    return _cage.FaceMotions(params, valid, _cage.face_messages(has_corner, valid)), reached, float(volume)


def cage_nodes(node_points: ArrayLike, node_weights: ArrayLike, face_params: ArrayLike, reached: ArrayLike,
               valid: ArrayLike | None = None, totals: ArrayLike | None = None
               ) -> tuple[FloatArray, NDArray[np.bool_], FloatArray] | None:
    """(params (G, 12), touched (G,), totals (G,)): `core.cage.harmonic.node_params(node_points,
    node_weights, face_params, faces=reached, valid=valid)` for the nodes with weight on a reached
    face (touched), zeros for the others, in one compiled call (`Kernel.cage_nodes`; the same
    parameters to ~1e-15). node_weights (G, F), best column-major (its transpose is then read
    without a copy); reached: the indices of the faces that moved; valid (F,) bool or None (all
    valid). totals: the node sums Σ_f W_cf valid_f that an earlier call with the same node_weights
    and valid returned (what every update with them needs, so a caller keeps them), or None to
    compute them; passing them changes no bit of the result. None when the compiled kernel is not
    active now (the caller then uses `node_params`)."""
    module = _usable()
    if module is None:
        return None
    W = np.asarray(node_weights, dtype=np.float64)
    x = _c(node_points, np.float64)
    P = np.asarray(face_params, dtype=np.float64)
    reached = _c(reached, np.int64)
    G, F = W.shape
    keep = np.ones(F, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    faces = reached[keep[reached]]
    terms = np.empty((faces.size, 21))
    blend = np.empty((21, G))
    out = np.empty((G, 12))
    touched = np.empty(G, dtype=np.bool_)
    fill = totals is None
    sums = np.empty(G) if fill else _c(totals, np.float64)
    if sums.shape != (G,):
        raise ValueError(f"totals must have shape ({G},), got {sums.shape}")
    Wt, rows, keep64 = _c(W.T, np.float64), _c(P[faces], np.float64), keep.astype(np.float64)
    if _entry_call("cage_nodes", lambda: module.cage_nodes(
            Wt, reached, faces, rows, keep64, sums, fill, x, terms, blend, out, touched)) is _FAILED:
        return None
    return out, touched, sums


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


def linear_maps(params: ArrayLike) -> FloatArray:
    """The linear parts M = R(ω) exp(Y) (n, 3, 3) of φ(P) for parameters (n, 12): `vertex_motions`
    with one control per row at weight 1 (the compiled kernel when it is active)."""
    table = np.ascontiguousarray(params, dtype=np.float64)
    n = table.shape[0]
    if n == 0:
        return np.zeros((0, 3, 3))
    columns = vertex_motions(table, np.arange(n, dtype=np.int32)[:, None], np.ones((n, 1)))
    return np.ascontiguousarray(columns[:3].transpose(1, 2, 0))


def _chain_inputs(
    table: ArrayLike, indices: ArrayLike, values: ArrayLike, prefix: ArrayLike, prefixes: ArrayLike,
    key: Hashable | None,
) -> tuple[FloatArray, NDArray[np.int32], FloatArray, NDArray[np.int32], FloatArray]:
    """Checked table (m, 12), pass indices (P, N, K) in [0, m), values (P, N, K), prefix (N,) in
    [0, m') and prefix matrices (m', 12) for `chain_points` / `chain_motions`. With the key of the
    previous checked call only the shapes are checked (as `_inputs`: the kernel clamps indices, so
    memory stays safe)."""
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
    if key not in _state.checked_chain:
        if idx.size and (idx.min() < 0 or idx.max() >= tab.shape[0]):
            raise ValueError(f"indices must be in [0, {tab.shape[0]})")
        if pre.size and (pre.min() < 0 or pre.max() >= mats.shape[0]):
            raise ValueError(f"prefix must be in [0, {mats.shape[0]})")
        if not (np.isfinite(val).all() and np.isfinite(mats).all()):
            raise ValueError("values and prefixes must be finite")
        if key is not None:
            _state.checked_chain.add(key)
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
    `deform_points_params`): a call with the key of the previous checked call skips re-validating them."""
    if key in _state.checked_chain:
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
    if _usable() is None or not _run("chain_points_entry", n, *args):
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
    `key`: as in `chain_points` (naming the indices, values and prefix)."""
    tab, idx, val, pre, mats = _chain_inputs(params, indices, values, prefix, prefixes, key)
    n = pre.shape[0]
    out = check_motion_out(out, n)
    if not out.flags.writeable:
        raise ValueError("out must be writable")
    sel = None if rows is None else _c(check_rows(rows, n), np.intp)
    dst = out if out.flags.c_contiguous else np.ascontiguousarray(out)
    use32 = dst.dtype == np.float32
    args = (_c(tab, np.float64), _c(idx, np.int32), _c(val, np.float64), _c(pre, np.int32),
            _c(mats, np.float64), _NO_ROWS if sel is None else sel, sel is not None,
            _NO_MOTIONS if use32 else dst, dst if use32 else _NO_MOTIONS32, bool(use32))
    if _usable() is None or not _run("chain_motion_entry", n if sel is None else sel.shape[0], *args):
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
