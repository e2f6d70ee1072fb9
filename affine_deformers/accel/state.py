"""The compiled backend's state: whether calls go to the C library now, loading it on first use, and
how a call reaches it (`_entry_call` for one-thread entries, `_run` for chunked ones on the helper
threads).

The compiled path is skipped when

* the environment variable AFFINE_DEFORMERS_ACCEL is "0" (checked on every call), or the add-on
  preference turned it off (`set_enabled(False)`), or
* the library is missing or failed to load (`native.KernelUnavailableError`: no build for this platform,
  a damaged or foreign file, another ABI version), or an entry failed on its first call: the process
  then stays on numpy and `backend()` says why. Such a failure never reaches the caller.

Calls into the compiled kernel are serialised by `_state.lock` (Blender may evaluate from more than
one thread; a call already uses every thread it is given). Every call reads this module's `_state`
anew, so a test replaces it here (`state._state`). The module is not called `backend`: that name is
the function `accel.backend()`, which would hide a submodule of the same name in the package.
"""

from __future__ import annotations

import os
import threading
import warnings
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from . import native, threads
from .native import Kernel, KernelUnavailableError

__all__ = ["ACCEL_ENV", "active", "backend", "pinned", "set_enabled"]

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
        self.spin: threads.Spin | bool | None = None  # `_spin`'s measurement (False: unavailable)
        #: (thread, batch) while that thread collects deferrable calls into a batch (batch.collecting)
        self.collecting: tuple[threading.Thread, Any] | None = None
        #: (thread, what `_usable` gave it) while that thread runs in `pinned`
        self.pinned: tuple[threading.Thread, Kernel | None] | None = None


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
    callers that cache results key them on `active()`). Within `pinned`, what it gave at the start."""
    pin = _state.pinned
    if pin is not None and pin[0] is threading.current_thread():
        return pin[1]
    warming = _state.warming
    if warming is not None and warming is not threading.current_thread():
        return None
    return _load()


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


@contextmanager
def pinned() -> Iterator[None]:
    """Within the block this thread's calls find the backend as it was at the start (`_usable`: one
    look at the environment and the preference instead of one per call), so an update runs on one
    backend throughout. An entry failing inside still switches to numpy at once. Blocks nest."""
    current = _state
    outer = current.pinned
    thread = threading.current_thread()
    if outer is not None and outer[0] is thread:
        yield
        return
    current.pinned = (thread, _usable())
    try:
        yield
    finally:
        current.pinned = outer


def _fail(reason: str, warn: bool = True) -> None:
    """Stay on numpy for the rest of the process."""
    _state.failure = reason
    _state.module = None
    _state.pinned = None
    if warn:
        warnings.warn(f"affine_deformers: compiled kernel disabled ({reason}); using numpy", stacklevel=3)


def backend() -> str:
    """'C kernel (<library file>), <n> threads' or 'numpy (<reason>)'. Loads the library if not done yet."""
    if not _state.enabled:
        return "numpy (compiled kernel turned off in the preferences)"
    if _disabled_by_env():
        return f"numpy ({ACCEL_ENV}=0)"
    module = _load()
    if module is None:
        return f"numpy ({_state.failure})"
    n = threads._threads()
    return f"{module.describe()}, {n} thread{'s' if n != 1 else ''}"


def _spin(module: Kernel) -> threads.Spin | None:
    """(Kernel.spin_wait, iterations for SPIN_MS), measured once; None when SPIN_MS is 0 or it
    fails (the helpers then just sleep between calls)."""
    if _state.spin is None:
        try:
            _state.spin = threads.measure_spin(module.spin_wait)
        except Exception:
            _state.spin = False
    return (_state.spin or None) if threads.SPIN_MS > 0.0 else None


def _run(name: str, n: int, *args: object, defer: bool = False) -> bool:
    """Kernel.<name>(*args, counter) for an n-row work list (⌈n/CHUNK⌉ chunks) on `threads._threads`
    threads (`threads._run_chunks`; an entry's first call, which checks it, on this thread alone);
    False if the backend is (or just became) unavailable, in which case the caller recomputes with
    numpy.

    `defer`: the caller reads none of the call's outputs before the batch this thread is collecting
    runs (batch.collecting): then a checked entry is only checked and bound to its arguments here, and
    runs with the batch's other calls (`Kernel.<name>_call`, batch.KernelBatch)."""
    module = _load()
    if module is None:
        return False
    collecting = _state.collecting
    if (defer and collecting is not None and collecting[0] is threading.current_thread()
            and name in _state.compiled):
        collecting[1].add(getattr(module, name.removesuffix("_entry") + "_call")(*args), n, module.CHUNK)
        return True
    entry = getattr(module, name)
    n_chunks = -(-n // module.CHUNK)

    def chunks() -> None:
        count = threads._threads() if name in _state.compiled else 1  # an entry's first run on one thread
        spin = _spin(module) if count > 1 and n_chunks > 1 else None
        threads._run_chunks(entry, args, n_chunks, count, spin)

    return _entry_call(name, chunks) is not _FAILED


# ----------------------------------------------------------------------------------------------
# arguments as the entries take them


def _c(a: np.ndarray, dtype: type) -> np.ndarray:
    """`a` as a C-contiguous array of `dtype`."""
    return np.ascontiguousarray(a, dtype=dtype)


# Empty arrays for the arguments an entry does not read (no rows, no float32 copy, ...): the wrappers
# in native.py check every argument's dtype, so each has the right one.
_NO_OUT32 = np.empty((0, 3), dtype=np.float32)
_NO_POINTS = np.empty((0, 3))
_NO_ROWS = np.empty(0, dtype=np.intp)
_NO_MOTIONS = np.empty((4, 0, 3))
_NO_MOTIONS32 = np.empty((4, 0, 3), dtype=np.float32)
