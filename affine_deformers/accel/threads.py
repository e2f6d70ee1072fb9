"""The helper threads a compiled call runs on: `_run_chunks` runs one entry on the calling thread and on
`_Helper` threads at once, all claiming chunks from one shared counter.

A ctypes call releases the GIL, so the entry runs truly in parallel on every thread; each claims the
next chunk until none is left (an atomic increment in C), so a helper that starts late takes fewer
chunks instead of delaying the call, and a row's value does not depend on which thread computed it.
Nothing here knows the library: `state._run` hands over the entry, and the spin-wait measured on it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from ..core.deform import default_threads

__all__ = ["SPIN_MS", "Spin", "measure_spin"]

#: How long an idle helper thread busy-waits (without the GIL) for the next call before it sleeps
#: (0: it sleeps at once). A spin lets calls back to back find it awake, but the core it holds is
#: the one Blender's own threads need right after our handler returns (the depsgraph pass that
#: applies the result, Geometry Nodes, drawing), and a caller no longer waits for a helper that is
#: still asleep (`_Helper.defer`: the caller claims every chunk itself). Measured on a 2-vCPU VM,
#: one probe moving among 8, interleaved runs: 10k vertices 2.15 ms per update with a 1 ms spin,
#: 1.19 ms with 0.1 ms, 1.10 ms with none; 130k vertices 6.99 / 6.13 / 5.67 ms.
SPIN_MS = 0.0

#: (Kernel.spin_wait, its iterations for SPIN_MS): how an idle helper waits for its next job.
Spin = tuple[Callable[[np.ndarray, int, int], bool], int]


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

    def __init__(self, spin: Spin | None) -> None:
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


_helpers: list[_Helper] = []  # grown on demand; used under `state._state.lock` only


def measure_spin(spin_wait: Callable[[np.ndarray, int, int], bool]) -> Spin:
    """(spin_wait, the iterations it makes in SPIN_MS), timed once on this machine."""
    flag = np.zeros(1, dtype=np.int64)
    spin_wait(flag, 0, 1)
    n = 20_000
    t0 = time.perf_counter()
    spin_wait(flag, 0, n)
    per_ms = n / max((time.perf_counter() - t0) * 1e3, 1e-6)
    return spin_wait, max(1, int(SPIN_MS * per_ms))


def _run_chunks(
    entry: Callable[..., None], args: tuple, n_chunks: int, threads: int, spin: Spin | None = None,
) -> None:
    """entry(*args, counter) on min(threads, n_chunks) threads sharing one chunk counter: this one
    and `_Helper` threads (the entries release the GIL; new helpers get `spin`). Each thread claims
    the next chunk until none is left, so a helper that starts late (thread wake-up, a busy core)
    takes fewer chunks instead of delaying the call. A row's value does not depend on the thread.
    The compiled entries return how many chunks the calling thread did: when that is all of them, no
    helper can write anything any more (a chunk is claimed once), so the call returns without waiting
    for helpers still asleep (`_Helper.defer`); any other return value (None) waits for every helper.
    Call under `state._state.lock`."""
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
