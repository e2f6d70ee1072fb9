"""The shape-preserving pass on the compiled kernel (csrc/affine_solve.c; MATH.md §15): the factor of a
bound system behind an opaque handle, and the per-frame right-hand side, solve and extra iterations.

`CompiledArapSolver.bind(kernel, lock, system)` orders and factors `core.arap.ArapSystem.matrix` once
(nested dissection, supernodal multifrontal Cholesky); `frame(motions, field, iterations)` is then one
compiled call per frame: no factorisation, no allocation after the first iterating frame, the same bits
for the same inputs whatever frames came before. `close()` frees the factor (a finaliser does it if
the object is dropped first). `arap_bind` picks this (when the compiled kernel is active) or core's
numpy solver.
"""

from __future__ import annotations

import threading
import time
import weakref

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core import arap as _arap_core
from ..core.arap import ArapSystem
from . import state
from .native import Kernel
from .state import _FAILED, _entry_call, _usable

FloatArray = NDArray[np.float64]

__all__ = ["ORDERINGS", "CompiledArapSolver", "FactorError", "FactorResult", "arap_bind", "check_ordering",
           "factor"]

#: Ordering name → ak_spd_factor's code (a permutation array selects code 2).
ORDERINGS = {"NATURAL": 0, "NESTED_DISSECTION": 1}


class FactorError(ValueError):
    """The bound system could not be factored (not positive definite, or out of memory)."""


def _release(kernel: Kernel, handle: int, lock: threading.RLock) -> None:
    with lock:
        kernel.spd_free(handle)


#: What `factor` returns: (handle or None, the ordering (n,), ak_spd_factor's info (8,), seconds, name).
FactorResult = tuple[int | None, NDArray[np.int64], NDArray[np.int64], float, str]


def check_ordering(ordering: str | ArrayLike, n: int) -> str | NDArray[np.int64]:
    """An ordering name of ORDERINGS, or a permutation of range(n) as int64 (ValueError otherwise)."""
    if isinstance(ordering, str):
        if ordering not in ORDERINGS:
            raise ValueError(f"ordering must be one of {sorted(ORDERINGS)} or a permutation, "
                             f"got {ordering!r}")
        return ordering
    perm = np.ascontiguousarray(ordering, dtype=np.int64)
    if perm.shape != (n,) or not np.array_equal(np.sort(perm), np.arange(n)):
        raise ValueError(f"ordering must be a permutation of the {n} vertices")
    return perm


def factor(kernel: Kernel, lock: threading.RLock, system: ArapSystem,
           ordering: str | NDArray[np.int64]) -> FactorResult:
    """Order and factor system.matrix in one compiled call (`check_ordering`'s ordering: pivot k is
    vertex ordering[k]); the status is in info[0] (0: the handle is live)."""
    A = system.matrix
    indptr = np.ascontiguousarray(A.indptr, dtype=np.int64)
    indices = np.ascontiguousarray(A.indices, dtype=np.int64)
    data = np.ascontiguousarray(A.data, dtype=np.float64)
    perm = np.empty(system.n, dtype=np.int64)
    info = np.zeros(8, dtype=np.int64)
    given = None if isinstance(ordering, str) else ordering
    code, name = (ORDERINGS[ordering], ordering) if given is None else (2, "GIVEN")
    start = time.perf_counter()
    with lock:
        handle = kernel.spd_factor(indptr, indices, data, code, given, perm, info)
    return handle, perm, info, time.perf_counter() - start, name


class CompiledArapSolver:
    """A bound system's factor and the compiled frame. Use `bind`; `stats` holds the sizes and times:
    n, nnz_matrix, nnz_factor (nonzeros of the Cholesky factor L, diagonal included), supernodes,
    stored (values kept: the supernodes' panels, relaxation zeros included), bytes (the factor and its
    scratch; grows by 144 per element at the first iterating frame), flops (multiply-adds of the
    numeric factorisation over the stored panels), max_front (rows of the largest front), ordering,
    factorizations (1: never again per frame), and bind_seconds (ordering, symbolic and numeric
    factorisation; the assembly is core's)."""

    def __init__(self, kernel: Kernel, lock: threading.RLock, system: ArapSystem, handle: int,
                 perm: NDArray[np.int64], stats: dict) -> None:
        self._kernel = kernel
        self._lock = lock
        self.system = system
        self.perm = perm
        self.stats = stats
        self._handle: int | None = handle
        self._finalizer = weakref.finalize(self, _release, kernel, handle, lock)
        el = system.elements
        # the element arrays in the layout the C entry reads, made once
        self._corners = np.ascontiguousarray(el.corners, dtype=np.int64)
        self._grads = np.ascontiguousarray(el.gradients, dtype=np.float64)
        self._weights = np.ascontiguousarray(el.weights, dtype=np.float64)
        self._normals = np.ascontiguousarray(el.normals, dtype=np.float64)

    @classmethod
    def bind(cls, kernel: Kernel, lock: threading.RLock, system: ArapSystem,
             ordering: str | ArrayLike = "NESTED_DISSECTION") -> CompiledArapSolver:
        """Order and factor system.matrix (`factor`, then `from_factor`)."""
        result = factor(kernel, lock, system, check_ordering(ordering, system.n))
        return cls.from_factor(kernel, lock, system, result)

    @classmethod
    def from_factor(cls, kernel: Kernel, lock: threading.RLock, system: ArapSystem,
                    result: FactorResult) -> CompiledArapSolver:
        """The solver of a `factor` result; FactorError when the factorisation failed (not positive
        definite — a bound system always is, up to rounding — or out of memory)."""
        handle, perm, info, seconds, name = result
        status = int(info[0])
        if handle is None:
            if status == 2:
                raise FactorError(f"the shape-preserving pass's system is not positive definite (at vertex "
                                  f"{int(info[4])}): its mesh may have near-degenerate faces or no anchor")
            raise FactorError(f"the compiled factorisation failed (status {status}: out of memory)")
        stats = {"backend": "C", "n": system.n, "nnz_matrix": int(system.matrix.data.size),
                 "nnz_factor": int(info[1]), "supernodes": int(info[2]), "bytes": int(info[3]),
                 "stored": int(info[5]), "flops": int(info[6]), "max_front": int(info[7]), "ordering": name,
                 "bind_seconds": seconds, "factorizations": 1}
        return cls(kernel, lock, system, handle, perm, stats)

    def _live(self) -> int:
        if self._handle is None:
            raise ValueError("this solver has been closed")
        return self._handle

    def solve(self, rhs: ArrayLike) -> FloatArray:
        """L⁻¹ rhs for rhs (n, k): a new array."""
        b = np.array(rhs, dtype=np.float64, order="C", copy=True)
        if b.ndim != 2 or b.shape[0] != self.system.n:
            raise ValueError(f"rhs must have shape ({self.system.n}, k), got {b.shape}")
        with self._lock:
            self._kernel.spd_solve(self._live(), b)
        return b

    def frame(self, motions: ArrayLike, field: ArrayLike, iterations: int = 1,
              out: FloatArray | None = None) -> FloatArray:
        """The positions x (n, 3) of one frame (core.arap.solve_frame): `motions` the blended maps at the
        elements as `vertex_motions` writes them (4 or 3, E, 3) float64, `field` the per-vertex field's
        positions (n, 3), `iterations` ≥ 1 (each beyond the first swaps in the solved rotations).
        iterations 0 returns the right-hand side (tests). `out` (n, 3) float64 C-contiguous if given."""
        n, E = self.system.n, self.system.elements.count
        mot = np.ascontiguousarray(motions, dtype=np.float64)
        if mot.ndim != 3 or mot.shape[0] not in (3, 4) or mot.shape[1:] != (E, 3):
            raise ValueError(f"motions must be planar columns (4, {E}, 3), got {mot.shape}")
        y = np.ascontiguousarray(field, dtype=np.float64)
        if y.shape != (n, 3):
            raise ValueError(f"field must have shape ({n}, 3), got {y.shape}")
        if out is None:
            out = np.empty((n, 3))
        with self._lock:
            self._kernel.arap_frame(self._live(), n, self._corners, self._grads, self._weights, self._normals,
                                    mot, y, int(iterations), out)
            self.stats["bytes"] = self._kernel.spd_bytes(self._live())
        return out

    def close(self) -> None:
        """Free the factor now (idempotent); later calls raise ValueError."""
        if self._handle is not None:
            self._handle = None
            self._finalizer()

    def __enter__(self) -> CompiledArapSolver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def arap_bind(system: ArapSystem, *, ordering: str | ArrayLike = "NESTED_DISSECTION"
              ) -> CompiledArapSolver | _arap_core.NumpyArapSolver:
    """The shape-preserving pass's solver for a bound system (`core.arap.bind_system`, MATH.md §15): the
    compiled factor (`CompiledArapSolver`, ordered and factored here, once per bind) when the
    compiled kernel is active, else core's `NumpyArapSolver` (conjugate gradients every frame). Both
    have `frame(motions, field, iterations=1, out=None)`, `stats` and `close()`. `ordering`:
    'NESTED_DISSECTION', 'NATURAL' or a permutation of the vertices (the compiled factor only).
    `FactorError` (a ValueError) when the system cannot be factored."""
    if system.n < 1:
        raise ValueError("the shape-preserving pass needs a mesh with vertices")
    ordering = check_ordering(ordering, system.n)
    module = _usable()
    if module is not None:
        lock = state._state.lock
        result = _entry_call("spd_factor", lambda: factor(module, lock, system, ordering))
        if result is not _FAILED:
            return CompiledArapSolver.from_factor(module, lock, system, result)
    return _arap_core.NumpyArapSolver(system)


def _warm_arap() -> None:
    """arap_bind and one frame on a single triangle (the compiled pass's entries, once)."""
    elements = _arap_core.triangle_elements(np.eye(3), np.array([[0, 1, 2]]))
    solver = arap_bind(_arap_core.bind_system(elements, np.ones(3)))
    if isinstance(solver, CompiledArapSolver):
        _entry_call("arap_frame", lambda: solver.frame(np.eye(3)[:, None, :], np.eye(3)))
    solver.close()
