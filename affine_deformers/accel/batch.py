"""Chunked kernel calls of several deformers run in one hand-over to the helper threads.

An update over many deformed objects makes one row call per deformer (`deform_points_params_rows`,
`vertex_motions`). Each call alone pays the hand-over to the helper threads and back (tens of µs, a
sleeping thread's wake-up included), which for a few thousand rows costs as much as the rows
themselves. While a thread collects (`collecting`), those calls are checked and bound to their
arguments (`native.Call`) instead of run, and `KernelBatch.run` runs them all: every thread goes
through the calls in order, claiming chunks of each from the call's own counter, so one hand-over
serves the whole update. A row's value does not depend on which call, thread or batch computes it:
the results are bit-identical to the calls run one by one.

The caller promises to read none of a collected call's outputs before `run` returns (the calls that
post-process their output are never deferred: state._run's `defer`).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from . import state, threads
from .native import Call

__all__ = ["KernelBatch", "collecting"]


class KernelBatch:
    """Calls collected during an update (`add`), run together (`run`)."""

    def __init__(self) -> None:
        self._calls: list[Call] = []
        self._chunks = 0

    def __len__(self) -> int:
        return len(self._calls)

    def add(self, call: Call, n_rows: int, chunk: int) -> None:
        """Collect `call` over `n_rows` rows (⌈n_rows / chunk⌉ chunks)."""
        self._calls.append(call)
        self._chunks += -(-n_rows // chunk)

    def run(self) -> None:
        """Run every collected call, on the helper threads at once (under the kernel lock), and empty
        the batch. An error (a refused row, no scratch memory) propagates after every thread is done;
        the outputs of the batch's calls are then undefined."""
        calls, chunks = self._calls, self._chunks
        self._calls, self._chunks = [], 0
        if not calls:
            return
        counters = np.zeros(len(calls), dtype=np.int64)

        def entry(_counter: np.ndarray, counters: np.ndarray = counters) -> int:
            # A helper left to finish on its own (threads._Helper.defer) still holds `counters` here.
            base = counters.ctypes.data
            done = 0
            for j, call in enumerate(calls):
                done += call.at(base + 8 * j)
            return done

        module = state._load()
        with state._state.lock:
            count = threads._threads()
            spin = state._spin(module) if module is not None and count > 1 and chunks > 1 else None
            threads._run_chunks(entry, (), chunks, count, spin)


@contextmanager
def collecting(batch: KernelBatch | None) -> Iterator[KernelBatch | None]:
    """Within the block, this thread's deferrable row calls go into `batch` (None: they run at once,
    also inside another block). Nested blocks restore the outer one."""
    current = state._state
    previous = current.collecting
    current.collecting = None if batch is None else (threading.current_thread(), batch)
    try:
        yield batch
    finally:
        current.collecting = previous
