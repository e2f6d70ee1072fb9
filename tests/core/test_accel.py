"""The optional compiled kernel (affine_deformers/accel) against the numpy kernel and the aff3 reference,
its bit-identity guarantees (rows, threads, chunk positions) and its fallback to numpy."""

from __future__ import annotations

import re
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from affine_deformers import accel
from affine_deformers.core import aff3, deform
from affine_deformers.core.weights import top_k_dense
from tests.core import test_deform
from tests.core.conftest import random_affine
from tests.core.test_deform import (
    KERNEL_ANGLES,
    MOTION_BAD_ARGUMENTS,
    adversarial_params,
    apply_motions,
    assert_matches_reference,
    assert_motions_match_reference,
    identity_motions,
    lifted_sweep,
    motion_bad_call,
    reference,
    sym6,
    vertex_scale,
)


@pytest.fixture
def compiled(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """numba, with the compiled backend enabled and loaded (skips without numba)."""
    numba = pytest.importorskip("numba")
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    assert accel._load() is not None, accel.backend()
    return numba


@pytest.fixture
def fresh_state(monkeypatch: pytest.MonkeyPatch) -> accel._State:
    """A backend that has not tried to load numba yet (restored afterwards)."""
    state = accel._State()
    monkeypatch.setattr(accel, "_state", state)
    return state


def blend_case(rng: np.random.Generator, n: int, m: int = 8, k: int = 4) -> tuple[np.ndarray, ...]:
    pts = rng.normal(scale=3.0, size=(n, 3))
    params = aff3.params_from_matrices(random_affine(rng, m, log_scale=1.0, t_scale=5.0))
    idx, val = top_k_dense(rng.random((n, m)) ** 3, k)
    return pts, params, idx, val


def lifted_params(rng: np.random.Generator) -> np.ndarray:
    """Rows with θ around and beyond 1.8π (the libm fix-up), with stretch and translation."""
    rows = []
    for angle in (1.8 * np.pi - 1e-9, 1.8 * np.pi + 1e-9, 1.95 * np.pi, 2 * np.pi, 3 * np.pi, 5.5 * np.pi):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        y6 = sym6((-0.5, 0.1, 0.9), aff3.so3_exp(rng.normal(size=3)))
        rows.append(np.concatenate([angle * axis, rng.normal(size=3), y6]))
    return np.array(rows)


# --------------------------------------------------------------------------------------------------
# accuracy


def test_random_blends_match_the_numpy_kernel(compiled: ModuleType) -> None:
    rng = np.random.default_rng(101)
    pts, params, idx, val = blend_case(rng, 20_000)
    got = accel.deform_points_params(pts, params, idx, val)
    ref = deform.deform_points_params(pts, params, idx, val, cache_weights=False)
    err = np.linalg.norm(got - ref, axis=1) / vertex_scale(pts, deform.blend_params(params, idx, val))
    assert err.max() <= 1e-15, f"worst {err.max():.2e}"
    assert not np.array_equal(got, pts)  # it moved something


@pytest.mark.parametrize("extra", [False, True])
def test_adversarial_parameters_match_the_reference(compiled: ModuleType, extra: bool) -> None:
    """The adversarial set of test_deform (every KERNEL_ANGLES × KERNEL_SPECTRA pairing, translations
    0 … 1e3) and the lifted angles, one control per vertex with weight 1."""
    rng = np.random.default_rng(102)
    P = lifted_params(rng) if extra else adversarial_params()
    points = rng.uniform(-10.0, 10.0, size=(P.shape[0], 3))
    idx = np.arange(P.shape[0], dtype=np.int32)[:, None]
    got = accel.deform_points_params(points, P, idx, np.ones((P.shape[0], 1)))
    scale = vertex_scale(points, P)
    err = np.linalg.norm(got - reference(points, P), axis=1) / scale
    assert err.max() <= 3e-15, f"row {int(err.argmax())}: {err.max():.2e}"
    np_err = np.linalg.norm(
        got - deform.deform_points_params(points, P, idx, np.ones_like(idx, float)), axis=1
    )
    assert (np_err / scale).max() <= 3e-15


def test_lifted_rotations_take_the_fixup(compiled: ModuleType) -> None:
    """θ > 1.8π: without the libm fix-up the quarter-angle polynomial is off by far more than 1e-12."""
    from affine_deformers.accel import compiled as kernel  # needs numba

    P = lifted_params(np.random.default_rng(103))
    assert (np.einsum("ij,ij->i", P[:, :3], P[:, :3]) > kernel.POLY_MAX_S).sum() >= 5
    assert max(KERNEL_ANGLES) ** 2 > kernel.POLY_MAX_S  # the adversarial set covers it too
    pts = np.random.default_rng(104).normal(size=(P.shape[0], 3)) * 4.0
    W = np.zeros(kernel._N_SCRATCH * kernel._STRIDE)
    S = kernel._STRIDE
    n = P.shape[0]
    for c in range(12):
        W[c * S : c * S + n] = P[:, c]
    for t in range(3):
        W[(12 + t) * S : (12 + t) * S + n] = pts[:, t]
    assert kernel._map(W) == 5
    poly = np.stack([W[(15 + t) * S : (15 + t) * S + n] for t in range(3)], axis=1)
    kernel._fixup(W, n)
    fixed = np.stack([W[(15 + t) * S : (15 + t) * S + n] for t in range(3)], axis=1)
    ref = reference(pts, P)
    scale = vertex_scale(pts, P)
    assert (np.linalg.norm(fixed - ref, axis=1) / scale).max() <= 3e-15
    assert (np.linalg.norm(poly - ref, axis=1) / scale)[1:].max() > 1e-12  # the fix-up was needed


def test_common_and_rigid_motions(compiled: ModuleType) -> None:
    rng = np.random.default_rng(105)
    pts = rng.uniform(-3, 3, size=(3000, 3))
    A = random_affine(rng, 1, log_scale=1.5, t_scale=20.0)[0]
    params = np.broadcast_to(aff3.params_from_matrices(A), (4, 12))
    idx, val = top_k_dense(rng.random((pts.shape[0], 4)), 4, normalize="SUM")
    got = accel.deform_points_params(pts, params, idx, val)
    want = pts @ A[:3, :3].T + A[:3, 3]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * (np.abs(want).max() + 1))


def test_zero_params_return_the_input_bit_for_bit(compiled: ModuleType) -> None:
    pts = np.array([[-0.0, 0.0, -0.0], [1e-320, -1e-320, 5e-324], [1e300, -1e300, 7.0]])
    got = accel.deform_points_params(pts, np.zeros((3, 12)), np.zeros((3, 2), np.int32), np.ones((3, 2)))
    assert got.tobytes() == pts.tobytes()


# --------------------------------------------------------------------------------------------------
# bit-identity: rows, chunks, threads


def test_rows_are_bit_identical_to_the_full_call(compiled: ModuleType) -> None:
    from affine_deformers.accel.compiled import CHUNK  # needs numba

    rng = np.random.default_rng(106)
    n = 3 * CHUNK + 17
    pts, params, idx, val = blend_case(rng, n)
    params[:2] = lifted_params(rng)[[1, 4]]  # some fix-up rows as well
    full = accel.deform_points_params(pts, params, idx, val)
    subsets = {
        "empty": np.zeros(0, dtype=np.int64),
        "one": np.array([CHUNK + 5]),
        "boundaries": np.array([0, CHUNK - 1, CHUNK, CHUNK + 1, 2 * CHUNK - 1, 2 * CHUNK, n - 1]),
        "reversed": np.arange(n)[::-1].copy(),
        "sparse": np.flatnonzero(rng.random(n) < 0.3),
        "chunk+1": np.arange(CHUNK + 1, dtype=np.int32) * 3,
        "repeats": np.array([7, 7, 9, 7]),
    }
    for name, rows in subsets.items():
        for offsets in (False, True):
            out = np.full((n, 3), 7.0)
            assert accel.deform_points_params_rows(pts, params, idx, val, rows, out, offsets=offsets) is out
            want = full[rows] - pts[rows] if offsets else full[rows]
            assert np.array_equal(out[rows], want), name
            assert np.all(np.delete(out, rows, axis=0) == 7.0), name
    # each row alone (vector loop vs scalar remainder) is the same as in the full call
    out = np.zeros((n, 3))
    for r in rng.choice(n, 40, replace=False):
        accel.deform_points_params_rows(pts, params, idx, val, [r], out)
        assert np.array_equal(out[r], full[r])


@pytest.mark.parametrize("n_rel", [0, 1, -1, None])
def test_sizes_around_the_chunk(compiled: ModuleType, n_rel: int | None) -> None:
    from affine_deformers.accel.compiled import CHUNK  # needs numba

    sizes = {0: [0], 1: [1, CHUNK + 1], -1: [CHUNK - 1], None: [CHUNK]}[n_rel]
    rng = np.random.default_rng(107)
    pts, params, idx, val = blend_case(rng, CHUNK + 1)
    full = accel.deform_points_params(pts, params, idx, val)
    for n in sizes:
        got = accel.deform_points_params(pts[:n], params, idx[:n], val[:n])
        assert got.shape == (n, 3)
        assert np.array_equal(got, full[:n])  # a row's value does not depend on N
        if n:
            ref = deform.deform_points_params(pts[:n], params, idx[:n], val[:n], cache_weights=False)
            assert np.abs(got - ref).max() <= 1e-14 * np.abs(ref).max()


def test_thread_counts_give_bitwise_equal_results(
    compiled: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The dispatch runs the entry on the calling thread and on helper threads (it releases the GIL),
    which claim chunks from a shared counter; neither the thread count nor which thread takes which
    chunk changes a bit."""
    from affine_deformers.accel import compiled as kernel  # needs numba

    numba = compiled
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has a single thread")
    rng = np.random.default_rng(108)
    n = 4 * kernel.CHUNK + 3
    pts, params, idx, val = blend_case(rng, n)
    rows = np.flatnonzero(rng.random(n) < 0.5).astype(np.intp)
    accel.deform_points_params(pts, params, idx, val)  # compiled (or loaded) before counting helpers
    submitted = []
    start = accel._Helper.start

    def counting_start(self: accel._Helper, fn: object, args: tuple) -> None:
        submitted.append(fn.__name__)
        start(self, fn, args)

    monkeypatch.setattr(accel._Helper, "start", counting_start)
    results = []
    for threads in ("1", "2"):
        monkeypatch.setenv(deform.THREADS_ENV, threads)
        assert accel.backend().endswith(f"{threads} thread" + ("s" if threads == "2" else ""))
        submitted.clear()
        out = accel.deform_points_params(pts, params, idx, val)
        sub = np.zeros((n, 3))
        sub32 = np.zeros((n, 3), dtype=np.float32)
        accel.deform_points_params_rows(pts, params, idx, val, rows, sub, offsets=True, out32=sub32)
        assert submitted == ([] if threads == "1" else ["deform_points_entry"] * 2)  # one helper per call
        results.append((out, sub, sub32))
    assert np.array_equal(results[0][0], results[1][0])
    assert np.array_equal(results[0][1], results[1][1])
    assert np.array_equal(results[0][2].view(np.uint32), results[1][2].view(np.uint32))
    # called directly: a counter at c leaves chunks below c alone, a fresh one does every chunk
    out = np.zeros((n, 3))
    args = (pts, params, idx.astype(np.int32), val, np.empty(0, np.intp), False, False, out,
            np.empty((0, 3), np.float32), False)
    counter = np.array([3], dtype=np.int64)
    kernel.deform_points_entry(*args, counter)
    assert counter[0] == 6  # chunks 3 and 4 claimed, one failed claim
    assert np.all(out[: 3 * kernel.CHUNK] == 0.0)
    assert np.array_equal(out[3 * kernel.CHUNK :], results[0][0][3 * kernel.CHUNK :])
    kernel.deform_points_entry(*args, np.zeros(1, np.int64))
    assert np.array_equal(out, results[0][0])


def test_helper_threads_are_joined_and_their_errors_reach_the_caller() -> None:
    """`_run_chunks` (no numba needed): every helper shares the call's counter, the call returns only
    after all of them, a helper's exception is raised in the caller, and the helpers stay usable."""
    import threading
    import time

    def make_entry(fail: bool) -> tuple[list, object]:
        seen = []

        def entry(tag: str, counter: np.ndarray) -> None:
            if threading.current_thread() is not threading.main_thread():
                time.sleep(0.05)
                if fail:
                    raise RuntimeError("helper failed")
            seen.append((tag, threading.get_ident(), id(counter)))

        return seen, entry

    with accel._state.lock:
        seen, entry = make_entry(fail=False)
        accel._run_chunks(entry, ("a",), 5, 3)
        assert len(seen) == 3 and len({ident for _, ident, _ in seen}) == 3  # all joined before return
        assert len({c for _, _, c in seen}) == 1  # one counter for the call
        seen, entry = make_entry(fail=True)
        with pytest.raises(RuntimeError, match="helper failed"):
            accel._run_chunks(entry, ("b",), 5, 3)
        seen, entry = make_entry(fail=False)
        accel._run_chunks(entry, ("c",), 2, 8)  # at most one thread per chunk
        assert len(seen) == 2
        accel._run_chunks(entry, ("d",), 0, 8)  # no chunk: this thread only
        assert len(seen) == 3 and seen[-1][1] == threading.get_ident()


def test_a_helper_with_nothing_left_to_do_is_not_waited_for() -> None:
    """`_run_chunks` (no numba needed): when the calling thread's entry reports that it did every
    chunk, the call returns without waiting for a helper that has not woken up yet (it can claim
    nothing, so it writes nothing); that helper is joined before its next job. When the calling
    thread did fewer chunks, or the entry reports nothing (None), every helper is waited for."""
    import threading
    import time

    seen: list[tuple[str, bool]] = []

    def entry(tag: str, own: int | None, counter: np.ndarray) -> int | None:
        helper = threading.current_thread() is not threading.main_thread()
        if helper:
            time.sleep(0.3)
        seen.append((tag, helper))
        return None if helper else own

    with accel._state.lock:
        t0 = time.perf_counter()
        accel._run_chunks(entry, ("alone", 2), 2, 2)
        assert time.perf_counter() - t0 < 0.25  # the sleeping helper was not waited for
        assert seen == [("alone", False)]
        t0 = time.perf_counter()
        accel._run_chunks(entry, ("shared", 1), 2, 2)  # the caller did 1 of 2 chunks: wait
        assert time.perf_counter() - t0 >= 0.3  # ... for the deferred job, then for this one
        assert seen == [("alone", False), ("alone", True), ("shared", False), ("shared", True)]
        seen.clear()
        accel._run_chunks(entry, ("unknown", None), 2, 2)  # no count: wait
        assert seen == [("unknown", False), ("unknown", True)]


def test_out_argument_in_place_and_layouts(compiled: ModuleType) -> None:
    rng = np.random.default_rng(109)
    pts, params, idx, val = blend_case(rng, 5000)
    want = accel.deform_points_params(pts, params, idx, val)
    same = pts.copy()
    assert accel.deform_points_params(same, params, idx, val, out=same) is same
    assert np.array_equal(same, want)
    # Fortran-ordered / strided / int64 / read-only inputs and a strided out
    out = np.zeros((5000, 6))[:, ::2]
    got = accel.deform_points_params(
        np.asfortranarray(pts), params[:, :], idx.astype(np.int64), np.asfortranarray(val), out=out
    )
    assert got is out and np.array_equal(out, want)
    ro = pts.copy()
    ro.flags.writeable = False
    assert np.array_equal(accel.deform_points_params(ro, params, idx, val), want)
    rows = np.arange(0, 5000, 7)
    sub = np.zeros((5000, 6))[:, ::2]
    accel.deform_points_params_rows(pts, params, idx, val, rows, sub)
    assert np.array_equal(sub[rows], want[rows])
    assert np.all(np.delete(sub, rows, axis=0) == 0.0)
    # in place with offsets (out is points): every row must read the original point
    inplace = pts.copy()
    accel.deform_points_params_rows(inplace, params, idx, val, np.r_[rows, rows[:3]], inplace, offsets=True)
    assert np.array_equal(inplace[rows], want[rows] - pts[rows])


def test_keyed_calls_skip_checks_but_stay_memory_safe(compiled: ModuleType) -> None:
    rng = np.random.default_rng(110)
    pts, params, idx, val = blend_case(rng, 3000)
    want = accel.deform_points_params(pts, params, idx, val, key="bind-1")
    assert np.array_equal(accel.deform_points_params(pts, params, idx, val, key="bind-1"), want)
    # a caller breaking its promise gets wrong values, not a crash (indices are clamped)
    bad = idx.copy()
    bad[0, 0] = 10**6
    bad[1, 0] = -5
    got = accel.deform_points_params(pts, params, bad, val, key="bind-1")
    assert np.all(np.isfinite(got))
    with pytest.raises(ValueError, match="indices must lie"):
        accel.deform_points_params(pts, params, bad, val, key="bind-2")
    # shapes are always checked
    with pytest.raises(ValueError):
        accel.deform_points_params(pts, params, idx[:10], val[:10], key="bind-2")


# --------------------------------------------------------------------------------------------------
# the float32 copy of the computed rows (out32), on both backends


def _backend(use_numba: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    if use_numba:
        pytest.importorskip("numba")
        monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
        assert accel.active(), accel.backend()
    else:
        monkeypatch.setenv(accel.ACCEL_ENV, "0")
        assert not accel.active()


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


#: Offsets whose float32 rounding is delicate: ties to even, just off ties, the float32 overflow
#: threshold (a tie there rounds to inf), beyond it, subnormals and their ties, below the smallest one.
_F32_MAX = float(np.finfo(np.float32).max)
ROUNDING_CASES = np.array([
    1 + 2**-24, 1 + 3 * 2**-24, -(1 + 2**-24), 1 + 2**-24 + 2**-52, 0.1, 1 / 3,
    _F32_MAX, _F32_MAX + 2.0**103, _F32_MAX + 2.0**103 - 2.0**80, -_F32_MAX - 2.0**103, 1e39, -1e300,
    1e-41, -2.5e-39, 2.0**-150, 3 * 2.0**-150, 2.0**-150 * (1 + 2**-30), 1e-300,
])


@pytest.mark.parametrize("use_numba", [True, False])
def test_out32_rows_are_the_float32_of_the_offsets(use_numba: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """out32[rows] is bit for bit out[rows].astype(float32); every other row of out32 (and of out) is
    left alone; out itself is what a call without out32 gives."""
    _backend(use_numba, monkeypatch)
    chunk = 2048  # compiled.CHUNK (not imported: the numpy run must not need numba)
    if use_numba:
        from affine_deformers.accel.compiled import CHUNK

        assert chunk == CHUNK
    rng = np.random.default_rng(113)
    n = 2 * chunk + 33
    pts, params, idx, val = blend_case(rng, n)
    params[:2] = lifted_params(rng)[[1, 4]]  # fix-up rows too
    subsets = {
        "empty": np.zeros(0, dtype=np.intp),
        "one": np.array([chunk + 5]),
        "boundaries": np.array([0, chunk - 1, chunk, chunk + 1, 2 * chunk - 1, 2 * chunk, n - 1]),
        "reversed": np.arange(n)[::-1].copy(),
        "sparse": np.flatnonzero(rng.random(n) < 0.3),
        "int32 rows": np.arange(0, n, 3, dtype=np.int32),
    }
    for name, rows in subsets.items():
        for offsets in (False, True):
            want = np.full((n, 3), 7.0)
            accel.deform_points_params_rows(pts, params, idx, val, rows, want, offsets=offsets)
            out = np.full((n, 3), 7.0)
            out32 = np.full((n, 3), -3.25, dtype=np.float32)
            got = accel.deform_points_params_rows(pts, params, idx, val, rows, out, offsets=offsets,
                                                  out32=out32)
            assert got is out
            assert np.array_equal(out, want), name  # out is unaffected by out32
            assert np.array_equal(_bits(out32[rows]), _bits(out[rows].astype(np.float32))), name
            assert np.all(np.delete(out32, rows, axis=0) == np.float32(-3.25)), name
            if len(rows):
                assert not np.all(out32[rows] == np.float32(-3.25)), name  # it wrote something


@pytest.mark.parametrize("use_numba", [True, False])
def test_out32_rounds_like_numpy_at_ties_overflow_and_subnormals(
    use_numba: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Pure translations applied to the origin give the translation exactly, so the offsets are
    chosen doubles: their float32 in out32 is numpy's cast of them, bit for bit (±inf included)."""
    _backend(use_numba, monkeypatch)
    u = np.resize(ROUNDING_CASES, (-(-len(ROUNDING_CASES) // 3) * 3)).reshape(-1, 3)
    n = len(u)
    params = np.zeros((n, 12))
    params[:, 3:6] = u  # ω = 0, Y = 0: φ(p) 0 = u
    idx = np.arange(n, dtype=np.int32)[:, None]
    out = np.zeros((n, 3))
    out32 = np.zeros((n, 3), dtype=np.float32)
    rows = np.arange(n)[::-1].copy()
    accel.deform_points_params_rows(np.zeros((n, 3)), params, idx, np.ones((n, 1)), rows, out, offsets=True,
                                    out32=out32)
    assert np.array_equal(out, u)  # the cases reach the cast unchanged
    with np.errstate(over="ignore"):
        want = u.astype(np.float32)
    assert np.isinf(want).sum() >= 4 and np.any((want != 0) & (np.abs(want) < np.finfo(np.float32).tiny))
    assert np.array_equal(_bits(out32), _bits(want))


OUT32_BAD = [
    (np.zeros((4, 3)), "out32 must be a writable C-contiguous float32"),
    (np.zeros((5, 3), dtype=np.float32), "out32 must be a writable C-contiguous float32"),
    (np.zeros((3, 4), dtype=np.float32).T, "out32 must be a writable C-contiguous float32"),
    (np.zeros((4, 6), dtype=np.float32)[:, ::2], "out32 must be a writable C-contiguous float32"),
    ("read-only", "out32 must be a writable C-contiguous float32"),
    ("aliases out", "out32 must not share memory with out"),
]


@pytest.mark.parametrize("use_numba", [True, False])
@pytest.mark.parametrize(("bad", "message"), OUT32_BAD)
def test_bad_out32_raises_before_writing(
    bad: object, message: str, use_numba: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    _backend(use_numba, monkeypatch)
    out = np.zeros((4, 3))
    if isinstance(bad, str) and bad == "read-only":
        bad = np.zeros((4, 3), dtype=np.float32)
        bad.flags.writeable = False
    elif isinstance(bad, str):
        bad = np.ndarray((4, 3), dtype=np.float32, buffer=out)  # a float32 view of out's bytes
    args = (np.ones((4, 3)), np.ones((3, 12)) * 0.1, np.zeros((4, 2), dtype=np.int32), np.ones((4, 2)))
    with pytest.raises(ValueError, match=message):
        accel.deform_points_params_rows(*args, np.array([0, 3]), out, offsets=True, out32=bad)
    assert not np.any(out)


# --------------------------------------------------------------------------------------------------
# validation: the messages of core.deform, on both backends

BAD_ARGUMENTS = [
    *test_deform.BAD_ARGUMENTS,
    ({"out": np.zeros((3, 3))}, "out must be a float64 array"),
    ({"rows": np.array([4])}, r"rows must lie in \[0, 4\)"),
    ({"rows": np.array([-1])}, r"rows must lie in \[0, 4\)"),
    ({"rows": np.zeros((1, 1), dtype=np.int64)}, "rows must be a 1-D integer array"),
]


@pytest.mark.parametrize("use_numba", [True, False])
@pytest.mark.parametrize(("kwargs", "message"), BAD_ARGUMENTS)
def test_bad_arguments_raise_the_core_messages(
    kwargs: dict, message: str, use_numba: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if use_numba:
        pytest.importorskip("numba")
        monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    else:
        monkeypatch.setenv(accel.ACCEL_ENV, "0")
    args = {
        "points": np.zeros((4, 3)),
        "params": np.ones((3, 12)) * 0.1,
        "indices": np.zeros((4, 2), dtype=np.int32),
        "values": np.ones((4, 2)),
        "rows": np.array([0, 3]),
        "out": np.zeros((4, 3)),
    }
    args.update(kwargs)
    a = (args["points"], args["params"], args["indices"], args["values"])
    rows_only = "rows" in kwargs
    if not rows_only:
        with pytest.raises(ValueError, match=message):
            accel.deform_points_params(*a, out=args["out"])
        with pytest.raises(ValueError, match=message):  # core raises the same
            deform.deform_points_params(*a, out=args["out"])
    if "out" not in kwargs or "rows" in kwargs:
        with pytest.raises(ValueError, match=message):
            accel.deform_points_params_rows(*a, args["rows"], args["out"])
    if rows_only:
        with pytest.raises(ValueError, match=message):
            deform.deform_points_params_rows(*a, args["rows"], args["out"])


# --------------------------------------------------------------------------------------------------
# fallback to numpy (unconditional: no numba needed)


def test_env_var_disables_the_compiled_path(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    assert accel.backend() == "numpy (AFFINE_DEFORMERS_ACCEL=0)"
    calls = []
    monkeypatch.setattr(
        deform, "deform_points_params", lambda *a, **k: calls.append("full") or np.full((2, 3), 5.0)
    )
    rng = np.random.default_rng(111)
    pts, params, idx, val = blend_case(rng, 2)
    assert np.all(accel.deform_points_params(pts, params, idx, val) == 5.0)
    assert calls == ["full"]
    assert fresh_state.module is None and fresh_state.failure is None  # never tried to load numba


def test_fallback_gives_the_numpy_results(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    rng = np.random.default_rng(112)
    pts, params, idx, val = blend_case(rng, 500)
    want = deform.deform_points_params(pts, params, idx, val, cache_weights=False)
    assert np.array_equal(accel.deform_points_params(pts, params, idx, val), want)
    rows = np.array([3, 1, 400])
    out = np.full((500, 3), 9.0)
    accel.deform_points_params_rows(pts, params, idx, val, rows, out, offsets=True)
    assert np.array_equal(out[rows], want[rows] - pts[rows])
    assert np.all(np.delete(out, rows, axis=0) == 9.0)


def test_missing_numba_falls_back_for_the_process(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    # a missing numba: `import numba` raises ImportError
    monkeypatch.setitem(sys.modules, "numba", None)
    monkeypatch.delitem(sys.modules, "affine_deformers.accel.compiled", raising=False)
    monkeypatch.delattr(accel, "compiled", raising=False)
    rng = np.random.default_rng(113)
    pts, params, idx, val = blend_case(rng, 300)
    want = deform.deform_points_params(pts, params, idx, val, cache_weights=False)
    import warnings

    with warnings.catch_warnings():
        # no numba is how a package built without wheels runs: reported by backend(), not warned about
        warnings.simplefilter("error")
        got = accel.deform_points_params(pts, params, idx, val)
    assert np.array_equal(got, want)
    assert re.match(r"numpy \(numba unavailable: (ModuleNotFound|Import)Error: ", accel.backend())
    # sticky: no second attempt, no second warning
    monkeypatch.delitem(sys.modules, "numba")
    out = np.zeros((300, 3))
    accel.deform_points_params_rows(pts, params, idx, val, np.arange(300), out)
    assert np.array_equal(out, want)
    assert fresh_state.module is None and "numba" in fresh_state.failure


def test_compile_failure_falls_back(monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State) -> None:
    """An error from the first call of an entry point (numba compiles there) is a platform problem:
    numpy takes over for the process, the caller gets correct results."""
    import types

    def broken(*args: object) -> None:
        raise RuntimeError("LLVM is unhappy")

    fake = types.SimpleNamespace(deform_points_entry=broken, CHUNK=2048)
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.setattr(fresh_state, "module", fake)
    monkeypatch.setitem(
        sys.modules,
        "numba",
        types.SimpleNamespace(
            config=types.SimpleNamespace(NUMBA_NUM_THREADS=1), set_num_threads=lambda n: None, __version__="x"
        ),
    )
    rng = np.random.default_rng(114)
    pts, params, idx, val = blend_case(rng, 200)
    with pytest.warns(UserWarning, match="LLVM is unhappy"):
        got = accel.deform_points_params(pts, params, idx, val)
    assert np.array_equal(got, deform.deform_points_params(pts, params, idx, val, cache_weights=False))
    assert accel.backend() == "numpy (compiling deform_points_entry failed: RuntimeError: LLVM is unhappy)"


@pytest.mark.parametrize("entry", ["polar_log", "psi_rows", "node_pivot"])
def test_a_one_thread_entry_failing_to_compile_falls_back(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State, entry: str
) -> None:
    """The per-control entries share the rule of the per-vertex ones: an error on the first call
    switches the process to numpy and the caller still gets numpy's result; once an entry has run,
    an error is a bug and propagates."""
    import types

    from affine_deformers.core import aff3
    from affine_deformers.core.cage import harmonic

    def broken(*args: object) -> None:
        raise RuntimeError("LLVM is unhappy")

    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.setattr(fresh_state, "module", types.SimpleNamespace(**{entry: broken}))
    rng = np.random.default_rng(115)
    A = np.tile(np.eye(4), (3, 1, 1))
    A[:, :3, :3] += 0.1 * rng.normal(size=(3, 3, 3))
    points, weights, faces = rng.normal(size=(5, 3)), rng.random((5, 3)), 0.01 * rng.normal(size=(3, 12))
    calls = {
        "polar_log": lambda: accel.polar_log(A[:, :3, :3]),
        "psi_rows": lambda: accel.params_from_matrices(A),
        "node_pivot": lambda: accel.node_params(points, weights, faces),
    }
    with pytest.warns(UserWarning, match="LLVM is unhappy"):
        got = calls[entry]()
    if entry == "node_pivot":  # numpy's result instead
        assert np.allclose(got, harmonic.node_params(points, weights, faces, maps=accel.linear_maps))
    else:  # None: the caller uses numpy
        assert got is None
    assert accel.backend() == f"numpy (compiling {entry} failed: RuntimeError: LLVM is unhappy)"
    assert aff3.params_from_matrices(A).shape == (3, 12)
    fresh_state.module, fresh_state.failure = types.SimpleNamespace(**{entry: broken}), None
    fresh_state.compiled.add(entry)
    with pytest.raises(RuntimeError, match="LLVM is unhappy"):
        calls[entry]()


def test_importing_accel_does_not_import_numba() -> None:
    import subprocess

    code = "import sys, affine_deformers.accel as a; assert 'numba' not in sys.modules; print('ok')"
    res = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
        check=False,
    )
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr


def test_no_cache_locator_decorates_without_cache() -> None:
    """numba raises RuntimeError at decoration when it has nowhere to write its cache (read-only
    install, no user cache dir): the module must still import, uncached (decoration only, no compile)."""
    pytest.importorskip("numba")
    import subprocess

    code = (
        "from numba.core import caching\n"
        "caching.CacheImpl._locator_classes = []\n"
        "from affine_deformers.accel import compiled as c\n"
        "print(*(type(getattr(c, name)._cache).__name__ for name in c.ENTRIES))\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
        check=False,
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["NullCache"] * 11  # one per entry


def test_calls_from_other_threads_use_numpy_while_the_kernel_compiles(monkeypatch):
    """An interactive update must not wait seconds for the compiler: while `warm_up` runs in a helper
    thread, other threads get the numpy kernel's result (and `active()` says so); afterwards the
    compiled one."""
    pytest.importorskip("numba")
    import threading

    rng = np.random.default_rng(5)
    pts = rng.normal(size=(50, 3))
    params = aff3.params_from_matrices(random_affine(rng, 3))
    idx, val = top_k_dense(rng.random((50, 3)), 2)
    expected_numpy = deform.DeformKernel(threads=1).deform(pts, params, idx, val, cache_weights=False)
    helper = threading.Thread(target=lambda: None)
    monkeypatch.setattr(accel._state, "warming", helper)  # as if `helper` were compiling right now
    assert not accel.active()
    assert np.array_equal(accel.deform_points_params(pts, params, idx, val), expected_numpy)
    monkeypatch.setattr(accel._state, "warming", None)
    assert accel.warm_up().startswith("numba ")
    assert accel.active() and accel._state.warming is None
    compiled = accel.deform_points_params(pts, params, idx, val)
    assert np.abs(compiled - expected_numpy).max() < 1e-12


# --------------------------------------------------------------------------------------------------
# vertex_motions: the compiled twin (motion_params) and its dispatch


def _motion_case(rng: np.random.Generator, n: int, m: int = 8) -> tuple[np.ndarray, ...]:
    _, params, idx, val = blend_case(rng, n, m)
    params[:2] = lifted_params(rng)[[1, 4]]  # fix-up rows as well
    return params, idx, val


@pytest.mark.parametrize("extra", [False, True])
def test_motions_match_aff3_and_the_numpy_kernel(compiled: ModuleType, extra: bool) -> None:
    """The adversarial set (every KERNEL_ANGLES × KERNEL_SPECTRA pairing, translations 0 … 1e3) and the
    lifted angles, one control per vertex with weight 1: M_v and t_v against aff3 and numpy."""
    rng = np.random.default_rng(120)
    P = lifted_params(rng) if extra else adversarial_params()
    idx = np.arange(P.shape[0], dtype=np.int32)[:, None]
    one = np.ones((P.shape[0], 1))
    got = accel.vertex_motions(P, idx, one)
    assert got.shape == (4, P.shape[0], 3) and got.dtype == np.float64
    assert_motions_match_reference(P, got)
    want = deform.vertex_motions(P, idx, one)
    scale = np.linalg.norm(want[:3], axis=(0, 2)) + np.linalg.norm(want[3], axis=1)
    assert (np.abs(got - want).max(axis=(0, 2)) / scale).max() <= 3e-15
    # φ(p_v) v from the motion is the compiled point map's v'
    pts = rng.uniform(-10.0, 10.0, size=(P.shape[0], 3))
    moved = accel.deform_points_params(pts, P, idx, one)
    assert (np.linalg.norm(apply_motions(got, pts) - moved, axis=1) / vertex_scale(pts, P)).max() <= 1e-14


def test_motions_of_random_blends(compiled: ModuleType) -> None:
    rng = np.random.default_rng(121)
    pts, params, idx, val = blend_case(rng, 20_000)
    got = accel.vertex_motions(params, idx, val)
    blended = deform.blend_params(params, idx, val)
    assert_motions_match_reference(blended, got)
    want = deform.vertex_motions(params, idx, val)
    scale = np.linalg.norm(want[:3], axis=(0, 2)) + np.linalg.norm(want[3], axis=1)
    assert (np.abs(got - want).max(axis=(0, 2)) / scale).max() <= 1e-15
    assert not np.array_equal(got, want)  # it did run the compiled kernel
    err = np.linalg.norm(apply_motions(got, pts) - accel.deform_points_params(pts, params, idx, val), axis=1)
    assert (err / vertex_scale(pts, blended)).max() <= 1e-14


def test_motions_of_lifted_rotations_up_to_14_pi(compiled: ModuleType) -> None:
    params, _, tol = lifted_sweep()
    idx = np.arange(len(params), dtype=np.int32)[:, None]
    assert_motions_match_reference(params, accel.vertex_motions(params, idx, np.ones((len(params), 1))), tol)


def test_motion_fixup_redoes_lifted_rotations(compiled: ModuleType) -> None:
    """θ > 1.8π: `_map_motion` counts the rows, `_fixup_motion` redoes them with libm (without it the
    quarter-angle polynomial is off by far more than 1e-12)."""
    from affine_deformers.accel import compiled as kernel  # needs numba

    P = lifted_params(np.random.default_rng(122))
    n = P.shape[0]
    S = kernel._STRIDE
    W = np.zeros(kernel._N_MOTION_SCRATCH * S)
    for c in range(12):
        W[c * S : c * S + n] = P[:, c]

    def motions() -> np.ndarray:
        rows = W.reshape(-1, S)[12:24, :n]  # (12, n): M e_x, M e_y, M e_z, t as component rows
        return rows.reshape(4, 3, n).transpose(0, 2, 1).copy()

    assert kernel._map_motion(W) == 5
    poly = motions()
    kernel._fixup_motion(W, n)
    assert_motions_match_reference(P, motions())
    with pytest.raises(AssertionError):
        assert_motions_match_reference(P[1:], poly[:, 1:], 1e-12)  # the fix-up was needed


def test_motion_rows_are_bit_identical_to_the_full_call(compiled: ModuleType) -> None:
    from affine_deformers.accel.compiled import CHUNK  # needs numba

    rng = np.random.default_rng(123)
    n = 3 * CHUNK + 17
    params, idx, val = _motion_case(rng, n)
    full = accel.vertex_motions(params, idx, val)
    subsets = {
        "empty": np.zeros(0, dtype=np.int64),
        "one": np.array([CHUNK + 5]),
        "boundaries": np.array([0, CHUNK - 1, CHUNK, CHUNK + 1, 2 * CHUNK - 1, 2 * CHUNK, n - 1]),
        "reversed": np.arange(n)[::-1].copy(),
        "sparse": np.flatnonzero(rng.random(n) < 0.3),
        "chunk+1": np.arange(CHUNK + 1, dtype=np.int32) * 3,
        "repeats": np.array([7, 7, 9, 7]),
    }
    for name, rows in subsets.items():
        for key in (None, "bind-1"):
            out = np.full((4, n, 3), 7.0)
            assert accel.vertex_motions(params, idx, val, out, rows=rows, key=key) is out
            assert np.array_equal(out[:, rows], full[:, rows]), name
            assert np.all(np.delete(out, rows, axis=1) == 7.0), name
    # each row alone, at column 0 of a one-row chunk: random rows and every fix-up row (θ > 1.8π: a
    # vectorised fix-up loop would give those other bits in a full chunk than in a short one)
    theta_sq = np.einsum("ij,ij->i", *2 * [deform.blend_params(params, idx, val)[:, :3]])
    lifted = np.flatnonzero(theta_sq > (1.8 * np.pi) ** 2)
    assert len(lifted) >= 50
    out = np.zeros((4, n, 3))
    for r in np.r_[rng.choice(n, 40, replace=False), lifted]:
        accel.vertex_motions(params, idx, val, out, rows=[r])
        assert np.array_equal(out[:, r], full[:, r]), r
    for size in (1, CHUNK - 1, CHUNK, CHUNK + 1):  # a row's value does not depend on N
        assert np.array_equal(accel.vertex_motions(params, idx[:size], val[:size]), full[:, :size])


def test_motion_thread_counts_give_bitwise_equal_results(
    compiled: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    from affine_deformers.accel import compiled as kernel  # needs numba

    numba = compiled
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has a single thread")
    rng = np.random.default_rng(124)
    n = 4 * kernel.CHUNK + 3
    params, idx, val = _motion_case(rng, n)
    rows = np.flatnonzero(rng.random(n) < 0.5).astype(np.intp)
    results = []
    for threads in ("1", "2"):
        monkeypatch.setenv(deform.THREADS_ENV, threads)
        full = accel.vertex_motions(params, idx, val)
        sub = np.zeros((4, n, 3), dtype=np.float32)
        accel.vertex_motions(params, idx, val, sub, rows=rows)
        results.append((full, sub))
    assert np.array_equal(results[0][0], results[1][0])
    assert np.array_equal(results[0][1].view(np.uint32), results[1][1].view(np.uint32))


@pytest.mark.parametrize("use_numba", [True, False])
def test_motions_float32_out_is_the_rounded_float64(use_numba: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A float32 out gets the float64 result rounded once (astype's rounding, full call and rows), and
    the compiled kernel has one specialisation for both output types (two could disagree when only
    one of them comes from numba's cache)."""
    _backend(use_numba, monkeypatch)
    rng = np.random.default_rng(125)
    n = 2 * 2048 + 33  # compiled.CHUNK (not imported: the numpy run must not need numba)
    params, idx, val = _motion_case(rng, n)
    full = accel.vertex_motions(params, idx, val)
    out32 = np.full((4, n, 3), -3.25, dtype=np.float32)
    assert accel.vertex_motions(params, idx, val, out32) is out32
    assert np.array_equal(_bits(out32), _bits(full.astype(np.float32)))
    rows = np.flatnonzero(rng.random(n) < 0.3)
    out32 = np.full((4, n, 3), -3.25, dtype=np.float32)
    accel.vertex_motions(params, idx, val, out32, rows=rows)
    assert np.array_equal(_bits(out32[:, rows]), _bits(full[:, rows].astype(np.float32)))
    assert np.all(np.delete(out32, rows, axis=1) == np.float32(-3.25))
    if use_numba:
        from affine_deformers.accel import compiled as kernel

        assert len(kernel.motion_params.signatures) == 1


@pytest.mark.parametrize("use_numba", [True, False])
def test_motions_float32_rounding_at_ties_overflow_and_subnormals(
    use_numba: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Pure translations give t = u exactly, so the translations are chosen doubles: their float32 is
    numpy's cast of them, bit for bit (±inf included); M is the identity."""
    _backend(use_numba, monkeypatch)
    u = np.resize(ROUNDING_CASES, (-(-len(ROUNDING_CASES) // 3) * 3)).reshape(-1, 3)
    n = len(u)
    params = np.zeros((n, 12))
    params[:, 3:6] = u
    idx = np.arange(n, dtype=np.int32)[:, None]
    full = accel.vertex_motions(params, idx, np.ones((n, 1)))
    assert np.array_equal(full[3], u) and np.array_equal(full[:3], identity_motions(n)[:3])
    out32 = np.zeros((4, n, 3), dtype=np.float32)
    accel.vertex_motions(params, idx, np.ones((n, 1)), out32, rows=np.arange(n)[::-1].copy())
    with np.errstate(over="ignore"):
        want = full.astype(np.float32)
    assert np.isinf(want).sum() >= 4 and np.any((want != 0) & (np.abs(want) < np.finfo(np.float32).tiny))
    assert np.array_equal(_bits(out32), _bits(want))


@pytest.mark.parametrize("use_numba", [True, False])
def test_motions_of_zero_params_are_the_identity(use_numba: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    _backend(use_numba, monkeypatch)
    n = 40
    idx = np.zeros((n, 2), dtype=np.int32)
    val = np.ones((n, 2))
    ident = identity_motions(n)
    assert accel.vertex_motions(np.zeros((3, 12)), idx, val).tobytes() == ident.tobytes()
    out32 = np.full((4, n, 3), 5.0, dtype=np.float32)
    rows = np.array([0, 39, 7])
    accel.vertex_motions(np.zeros((3, 12)), idx, val, out32, rows=rows)
    assert out32[:, rows].tobytes() == ident[:, rows].astype(np.float32).tobytes()
    assert np.all(np.delete(out32, rows, axis=1) == 5.0)
    empty = accel.vertex_motions(np.zeros((0, 12)), np.zeros((n, 0), np.int32), np.zeros((n, 0)))
    assert empty.tobytes() == ident.tobytes()
    # zero weights on moving controls: the general path, the identity up to the sign of zeros
    params = aff3.params_from_matrices(random_affine(np.random.default_rng(126), 3))
    assert np.array_equal(accel.vertex_motions(params, idx, np.zeros((n, 2))), ident)


def test_motions_out_layouts_and_keys(compiled: ModuleType) -> None:
    rng = np.random.default_rng(127)
    n = 5000
    params, idx, val = _motion_case(rng, n)
    want = accel.vertex_motions(params, idx, val)
    strided = np.zeros((4, n, 6))[:, :, ::2]
    got = accel.vertex_motions(params, idx.astype(np.int64), np.asfortranarray(val), strided)
    assert got is strided and np.array_equal(strided, want)
    rows = np.arange(0, n, 7)
    sub = np.zeros((4, n, 6), dtype=np.float32)[:, :, ::2]
    accel.vertex_motions(params, idx, val, sub, rows=rows)
    assert np.array_equal(_bits(sub[:, rows]), _bits(want[:, rows].astype(np.float32)))
    assert np.all(np.delete(sub, rows, axis=1) == 0.0)
    ro = np.zeros((4, n, 3))
    ro.flags.writeable = False
    with pytest.raises(ValueError, match="out must be writable"):
        accel.vertex_motions(params, idx, val, ro)
    # keyed: the second call skips the checks; a caller breaking its promise gets wrong values, not a
    # crash (indices are clamped); a new key is checked again
    assert np.array_equal(accel.vertex_motions(params, idx, val, key="bind-m"), want)
    assert np.array_equal(accel.vertex_motions(params, idx, val, key="bind-m"), want)
    bad = idx.copy()
    bad[0, 0] = 10**6
    bad[1, 0] = -5
    assert np.all(np.isfinite(accel.vertex_motions(params, bad, val, key="bind-m")))
    with pytest.raises(ValueError, match="indices must lie"):
        accel.vertex_motions(params, bad, val, key="bind-m2")
    with pytest.raises(ValueError, match="indices and values must both have shape"):
        accel.vertex_motions(params, idx, val[:10], key="bind-m")  # shapes are always checked


@pytest.mark.parametrize("use_numba", [True, False])
@pytest.mark.parametrize(("kwargs", "message"), [*MOTION_BAD_ARGUMENTS])
def test_motions_bad_arguments_raise_the_core_messages(
    kwargs: dict, message: str, use_numba: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    _backend(use_numba, monkeypatch)
    with pytest.raises(ValueError, match=message):
        motion_bad_call(accel.vertex_motions, kwargs)


def test_motions_fall_back_to_numpy(monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State) -> None:
    """AFFINE_DEFORMERS_ACCEL=0 gives the numpy kernel's values; a compile failure of motion_params
    switches the process to numpy with correct results, like the other entry points."""
    import types

    rng = np.random.default_rng(128)
    params, idx, val = _motion_case(rng, 300)
    want = deform.vertex_motions(params, idx, val)
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    assert np.array_equal(accel.vertex_motions(params, idx, val), want)
    assert fresh_state.module is None and fresh_state.failure is None  # never tried to load numba

    def broken(*args: object) -> None:
        raise RuntimeError("LLVM is unhappy")

    monkeypatch.delenv(accel.ACCEL_ENV)
    monkeypatch.setattr(fresh_state, "module", types.SimpleNamespace(motion_params=broken, CHUNK=2048))
    monkeypatch.setitem(
        sys.modules,
        "numba",
        types.SimpleNamespace(
            config=types.SimpleNamespace(NUMBA_NUM_THREADS=1), set_num_threads=lambda n: None, __version__="x"
        ),
    )
    rows = np.array([3, 1, 200])
    out = np.full((4, 300, 3), 9.0)
    with pytest.warns(UserWarning, match="LLVM is unhappy"):
        accel.vertex_motions(params, idx, val, out, rows=rows)
    assert np.array_equal(out[:, rows], want[:, rows])
    assert np.all(np.delete(out, rows, axis=1) == 9.0)
    assert accel.backend() == "numpy (compiling motion_params failed: RuntimeError: LLVM is unhappy)"


def test_warm_up_compiles_exactly_the_entries_one_specialisation_each(
    compiled: ModuleType, fresh_state: accel._State
) -> None:
    """warm_up runs both compiled entries once (so the first update does not compile) and the helper
    threads' spin_wait, nothing else; every other jitted function of the module is inlined into them
    (a separately compiled callee, or a prange body, would make a cache-loaded entry differ from one
    compiled in the session: module doc); after calls of every kind (full, rows, offsets, out32,
    float32 motions) each entry still has one specialisation, which numba can keep in its cache."""
    from numba.core.registry import CPUDispatcher

    from affine_deformers.accel import compiled as kernel  # needs numba

    assert accel.warm_up().startswith("numba ")
    assert fresh_state.compiled == set(kernel.ENTRIES) == {"deform_points_entry", "motion_params",
                                                           "polar_log", "node_pivot", "chain_points_entry",
                                                           "chain_motion_entry", "cage_faces", "cage_nodes",
                                                           "psi_rows", "rows_reading", "same_words"}
    assert fresh_state.spin and fresh_state.spin[0] is kernel.spin_wait  # the helpers' busy-wait
    jitted = {name: f for name, f in vars(kernel).items() if isinstance(f, CPUDispatcher)}
    for name, f in jitted.items():
        if name in (*kernel.ENTRIES, "spin_wait"):
            assert f.targetoptions.get("nogil") and not f.targetoptions.get("parallel"), name
        else:
            assert f.targetoptions.get("inline") == "always", name
    flag = np.array([5], dtype=np.int64)
    assert kernel.spin_wait(flag, 4, 10**9) and not kernel.spin_wait(flag, 5, 1000)
    rng = np.random.default_rng(129)
    pts, params, idx, val = blend_case(rng, 300)
    accel.deform_points_params(pts, params, idx, val)
    out = np.zeros((300, 3))
    accel.deform_points_params_rows(pts, params, idx, val, [3, 1], out, offsets=True,
                                    out32=np.zeros((300, 3), np.float32))
    accel.deform_points_params_rows(pts, params, idx.astype(np.int64), val, np.array([2], np.int32), out)
    accel.vertex_motions(params, idx, val, np.zeros((4, 300, 3), np.float32), rows=[5])
    accel.vertex_motions(params, idx, val, rows=np.arange(9))
    accel.polar_log(np.eye(3)[None] * 2.0)
    accel.params_from_matrices(np.eye(4)[None] * 2.0 + np.diag([0.0, 0.0, 0.0, -1.0]))
    accel.node_params(rng.normal(size=(4, 3)), rng.random((4, 3)), params[:3], faces=np.array([0, 2]))
    from tests.core.test_cage import box_cage

    cage, topology = box_cage((2, 2, 2), (1.0, 1.0, 1.0))
    faces, reached, _ = accel.cage_faces(cage, cage * 1.1, topology)
    accel.cage_nodes(pts[:5], rng.random((5, topology.n_faces)), faces.params, np.flatnonzero(reached),
                     valid=np.arange(topology.n_faces) != 3)
    prefixes = np.eye(4)[:3].T.reshape(1, 12).repeat(2, axis=0)
    chain = (idx[None], val[None], np.zeros(300, np.int32), prefixes)
    accel.chain_points(pts, params, *chain)
    accel.chain_points(pts, params, *chain, [3, 1], out, offsets=True, out32=np.zeros((300, 3), np.float32))
    accel.chain_points(pts, params, chain[0].astype(np.int64), val[None], np.ones(300, np.int64), prefixes,
                       np.array([2], np.int32), out)
    accel.chain_motions(params, *chain, np.zeros((4, 300, 3), np.float32), rows=[5])
    accel.chain_motions(params, *chain, rows=np.arange(9))
    for name in (*kernel.ENTRIES, "spin_wait"):
        fn = getattr(kernel, name)
        assert len(fn.signatures) == 1, (name, fn.signatures)
        if type(fn._cache).__name__ != "NullCache":
            assert fn._cache.load_overload(fn.signatures[0], fn.targetctx) is not None, name


def lifted_case(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """Random blends of ordinary and lifted controls (θ from 1.5π to 6π): ~a fifth of the vertices
    have θ > 1.8π, at every position of a chunk; returns (points, params, idx, val, lifted rows)."""
    pts, params, idx, val = blend_case(rng, n, m=8)
    lifted = []
    for angle in np.linspace(1.5 * np.pi, 6.0 * np.pi, 8):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        y6 = sym6(tuple(rng.normal(scale=0.5, size=3)), aff3.so3_exp(rng.normal(size=3)))
        lifted.append(np.concatenate([angle * axis, rng.normal(size=3) * 3.0, y6]))
    params = np.concatenate([params, lifted, lifted_params(rng)])
    w = rng.random((n, params.shape[0])) ** 3
    w[:, 8:] *= rng.random((n, 1)) < 0.3
    idx, val = top_k_dense(w, 4)
    theta_sq = np.einsum("ij,ij->i", *2 * [deform.blend_params(params, idx, val)[:, :3]])
    return pts, params, idx.astype(np.int32), val, np.flatnonzero(theta_sq > (1.8 * np.pi) ** 2)


def test_every_lifted_row_alone_equals_its_row_in_a_full_chunk(compiled: ModuleType) -> None:
    """θ > 1.8π: each such row recomputed alone (column 0 of a one-row chunk) has the bits of the full
    call, points (plain, offsets, float32 copy) and motions — all of them, not a sample: a vectorised
    fix-up loop gives a row other bits in the vector body than in the scalar remainder."""
    from affine_deformers.accel.compiled import CHUNK  # needs numba

    rng = np.random.default_rng(130)
    n = 3 * CHUNK + 17
    pts, params, idx, val, lifted = lifted_case(rng, n)
    assert len(lifted) >= 500 and len(np.unique(lifted % CHUNK)) >= 400
    full = accel.deform_points_params(pts, params, idx, val)
    motions = accel.vertex_motions(params, idx, val)
    out = np.zeros((n, 3))
    off = np.zeros((n, 3))
    out32 = np.zeros((n, 3), np.float32)
    mot = np.zeros((4, n, 3))
    for r in lifted:
        accel.deform_points_params_rows(pts, params, idx, val, [r], out, key="lifted")
        accel.deform_points_params_rows(pts, params, idx, val, [r], off, offsets=True, out32=out32,
                                        key="lifted")
        accel.vertex_motions(params, idx, val, mot, rows=[r], key="lifted")
    assert np.array_equal(out[lifted], full[lifted])
    assert np.array_equal(off[lifted], full[lifted] - pts[lifted])
    assert np.array_equal(_bits(out32[lifted]), _bits((full[lifted] - pts[lifted]).astype(np.float32)))
    assert np.array_equal(mot[:, lifted], motions[:, lifted])


def test_rigid_blends_take_the_small_form_with_the_same_bits_in_any_chunk(compiled: ModuleType) -> None:
    """Rows whose blended Y is small (rigid controls) take the Taylor form of exp(Y) in a loop of
    their own: as accurate as the closed form, and a row has the same bits in a chunk of small rows
    only, in a mixed one and alone (points: plain, offsets, float32 copy; motions), θ > 1.8π rows
    through the fix-up included; both kernels draw the line at the same SMALL_Y."""
    from affine_deformers.accel import compiled as kernel  # needs numba

    assert kernel.SMALL_Y == deform.SMALL_Y
    rng = np.random.default_rng(132)
    n = 3 * kernel.CHUNK + 17
    pts, table, idx, val = test_deform.rigid_case(rng, n)
    P = deform.blend_params(table, idx, val)
    is_small = np.all(np.abs(P[:, 6:]) <= kernel.SMALL_Y, axis=1)
    small, other = np.flatnonzero(is_small), np.flatnonzero(~is_small)
    lifted = np.einsum("ij,ij->i", P[:, :3], P[:, :3]) > kernel.POLY_MAX_S
    assert 500 < len(small) < n - 500 and lifted[small].sum() >= 100
    full = accel.deform_points_params(pts, table, idx, val)
    motions = accel.vertex_motions(table, idx, val)
    assert_matches_reference(pts, P, full, tol=5e-15)  # θ up to 1.9π (see the numpy twin)
    assert_motions_match_reference(P, motions, 5e-15)
    err = np.linalg.norm(full - reference(pts, P), axis=1) / vertex_scale(pts, P)
    assert err[-4:-2].max() <= 1e-15  # at |Y_ij| = SMALL_Y: the cubic term is ~1e-13 there
    assert max(e.max() for e in test_deform.motion_errors(P[-4:-2], motions[:, -4:-2])) <= 1e-15
    for rows in (small, other, np.arange(n - 4, n), small[lifted[small]]):
        out = np.full((n, 3), 7.0)
        off = np.full((n, 3), 7.0)
        out32 = np.zeros((n, 3), np.float32)
        mot = np.full((4, n, 3), 7.0)
        accel.deform_points_params_rows(pts, table, idx, val, rows, out)
        accel.deform_points_params_rows(pts, table, idx, val, rows, off, offsets=True, out32=out32)
        accel.vertex_motions(table, idx, val, mot, rows=rows)
        assert np.array_equal(out[rows], full[rows]), len(rows)
        assert np.array_equal(off[rows], full[rows] - pts[rows]), len(rows)
        assert np.array_equal(_bits(out32[rows]), _bits((full[rows] - pts[rows]).astype(np.float32)))
        assert np.array_equal(mot[:, rows], motions[:, rows]), len(rows)
    out = np.zeros((n, 3))
    mot = np.zeros((4, n, 3))
    alone = np.r_[rng.choice(small, 40, replace=False), small[lifted[small]][:20], n - 4, n - 3, n - 2]
    for r in alone:  # column 0 of a chunk whose other columns are zero (small)
        accel.deform_points_params_rows(pts, table, idx, val, [r], out, key="rigid")
        accel.vertex_motions(table, idx, val, mot, rows=[r], key="rigid")
    assert np.array_equal(out[alone], full[alone])
    assert np.array_equal(mot[:, alone], motions[:, alone])


_CACHE_CHILD = """
import json, sys
import numpy as np
from affine_deformers import accel
from affine_deformers.accel import compiled

case = np.load(sys.argv[1])
pts, params, idx, val, rows, lifted = (case[k] for k in ("pts", "params", "idx", "val", "rows", "lifted"))
prefixes = np.concatenate([params[:5, :9] * 0.1 + np.eye(3).ravel(), params[:5, 3:6]], axis=1)
prefix = (np.arange(len(pts)) % 5).astype(np.int32)
chain = (np.stack([idx, np.roll(idx, 1, axis=0)]), np.stack([val, np.roll(val, 1, axis=0)]), prefix, prefixes)
res = {}
for step in sys.argv[3].split(","):
    if step == "points-full":
        res[step] = accel.deform_points_params(pts, params, idx, val)
    elif step == "points-rows":
        out = np.zeros_like(pts)
        accel.deform_points_params_rows(pts, params, idx, val, rows, out)
        res[step] = out[rows]
    elif step == "motions-full":
        res[step] = accel.vertex_motions(params, idx, val)
    elif step == "motions-rows":
        res[step] = accel.vertex_motions(params, idx, val, rows=rows)[:, rows]
    elif step == "chain-points-full":  # two passes: the blend, then the same weights one row down
        res[step] = accel.chain_points(pts, params, *chain)
    elif step == "chain-points-rows":
        out = np.zeros_like(pts)
        accel.chain_points(pts, params, *chain, rows, out)
        res[step] = out[rows]
    elif step == "chain-motions-full":
        res[step] = accel.chain_motions(params, *chain)
    elif step == "chain-motions-rows":
        res[step] = accel.chain_motions(params, *chain, rows=rows)[:, rows]
    elif step in ("rigid-full", "rigid-rows"):  # rigid controls: the Taylor form of exp(Y)
        r_pts, r_table, r_idx, r_val, r_rows = (case[f"rigid_{k}"] for k in ("pts", "table", "idx", "val",
                                                                            "rows"))
        if step == "rigid-full":
            res["rigid-points"] = accel.deform_points_params(r_pts, r_table, r_idx, r_val)
            res["rigid-motions"] = accel.vertex_motions(r_table, r_idx, r_val)
        else:
            out = np.zeros_like(r_pts)
            accel.deform_points_params_rows(r_pts, r_table, r_idx, r_val, r_rows, out)
            res["rigid-points-rows"] = out[r_rows]
            res["rigid-motions-rows"] = accel.vertex_motions(r_table, r_idx, r_val, rows=r_rows)[:, r_rows]
    elif step == "lifted-alone":  # every θ > 1.8π row alone
        out = np.zeros_like(pts)
        mot = np.zeros((4,) + pts.shape)
        for r in lifted:
            accel.deform_points_params_rows(pts, params, idx, val, [r], out, key="k")
            accel.vertex_motions(params, idx, val, mot, rows=[r], key="k")
        res["points-alone"], res["motions-alone"] = out[lifted], mot[:, lifted]
    elif step == "polar":
        res["polar-R"], res["polar-Y"] = accel.polar_log(case["polar"])
        motions = np.broadcast_to(np.eye(4), (len(case["polar"]), 4, 4)).copy()
        motions[:, :3, :3] = case["polar"]
        res["psi"] = accel.params_from_matrices(motions)
    elif step == "nodes":
        res["nodes"] = accel.node_params(pts[:300], val[:300], params[: val.shape[1]])
    elif step == "cage":  # a box cage, a few vertices moved (the faces they reach, and the volume)
        from tests.core.test_cage import box_cage

        cage, topology = box_cage((3, 4, 2), (2.0, 1.5, 1.0))
        moved = cage + np.where(np.arange(len(cage))[:, None] % 7 == 0, 0.1 * pts[: len(cage)], 0.0)
        faces, reached, volume = accel.cage_faces(cage, moved, topology)
        res["cage"], res["cage-volume"] = faces.params, np.array([volume])
        reached = np.flatnonzero(reached)
        weights = np.asfortranarray(val[: 2 * len(faces.params), :4].reshape(-1, len(faces.params)))
        res["cage-nodes"] = accel.cage_nodes(pts[: len(weights)], weights, faces.params, reached)[0]
np.savez(sys.argv[2], **res)
stats = {name: getattr(compiled, name).stats for name in compiled.ENTRIES}
print(json.dumps({n: [sum(s.cache_hits.values()), sum(s.cache_misses.values())] for n, s in stats.items()}))
"""


def test_cache_loaded_and_session_compiled_entries_agree_bitwise(
    compiled: ModuleType, tmp_path: Path
) -> None:
    """numba's on-disk cache: an entry compiled in one process and the same entry loaded from the
    cache in another give the same bits, whichever call (full or rows) compiled or loaded it. Three
    processes, fresh cache dirs: A compiles the point entry with a full call and the motion entry
    with a rows call, B (at the same time) the point entry with a rows call; then C loads A's cache
    and calls point rows first, then full, motions full first, then rows, then every θ > 1.8π row
    alone. The layout before (a point entry for full calls, one for rows, both with a prange) failed
    this: C's cache-loaded full call differed from A's (and from C's own rows call, compiled there)
    in the last bit of ~1 row in 5, cache-loaded motions from compiled ones in ~2 of 5, and C's
    θ > 1.8π rows alone from the same rows of its full call."""
    import json
    import os
    import subprocess

    from affine_deformers.accel.compiled import CHUNK  # needs numba

    rng = np.random.default_rng(131)
    n = 2 * CHUNK + 33
    pts, params, idx, val, lifted = lifted_case(rng, n)
    rows = rng.permutation(np.union1d(np.flatnonzero(rng.random(n) < 0.3), lifted)).astype(np.intp)
    assert len(lifted) >= 300 and np.isin(lifted, rows).all()
    case = tmp_path / "case.npz"
    polar = rng.normal(size=(500, 3, 3))
    polar[np.linalg.det(polar) < 0.0] *= -1.0
    r_pts, r_table, r_idx, r_val = test_deform.rigid_case(rng, n)
    r_rows = rng.permutation(np.flatnonzero(rng.random(n) < 0.4))
    np.savez(case, pts=pts, params=params, idx=idx, val=val, rows=rows, lifted=lifted, polar=polar,
             rigid_pts=r_pts, rigid_table=r_table, rigid_idx=r_idx, rigid_val=r_val, rigid_rows=r_rows)
    child = tmp_path / "child.py"
    child.write_text(_CACHE_CHILD)
    root = Path(__file__).resolve().parents[2]

    def start(cache: str, name: str, steps: str) -> subprocess.Popen:
        env = {k: v for k, v in os.environ.items() if k not in (accel.ACCEL_ENV, "NUMBA_DISABLE_JIT")}
        env["NUMBA_CACHE_DIR"] = str(tmp_path / cache)
        env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
        return subprocess.Popen([sys.executable, str(child), str(case), str(tmp_path / name), steps],
                                cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def finish(proc: subprocess.Popen) -> dict:
        stdout, stderr = proc.communicate(timeout=600)
        assert proc.returncode == 0, stderr
        return json.loads(stdout.strip().splitlines()[-1])

    a = start("cache-a", "a.npz",
              "points-full,motions-rows,polar,nodes,cage,chain-points-full,chain-motions-rows,rigid-full")
    b = start("cache-b", "b.npz", "points-rows,chain-points-rows")
    stats_a, stats_b = finish(a), finish(b)
    c = start("cache-a", "c.npz",
              "points-rows,points-full,motions-full,motions-rows,lifted-alone,polar,nodes,cage,"
              "chain-points-rows,chain-points-full,chain-motions-full,chain-motions-rows,rigid-rows,rigid-full")
    stats_c = finish(c)
    assert stats_a == {"deform_points_entry": [0, 1], "motion_params": [0, 1], "polar_log": [0, 1],
                       "node_pivot": [0, 1], "chain_points_entry": [0, 1],
                       "chain_motion_entry": [0, 1], "cage_faces": [0, 1],
                       "cage_nodes": [0, 1], "psi_rows": [0, 1], "rows_reading": [0, 0],
                       "same_words": [0, 0]}, stats_a  # compiled there (all but the last two)
    assert stats_b == {"deform_points_entry": [0, 1], "motion_params": [0, 0], "polar_log": [0, 0],
                       "node_pivot": [0, 0], "chain_points_entry": [0, 1],
                       "chain_motion_entry": [0, 0], "cage_faces": [0, 0], "cage_nodes": [0, 0],
                       "psi_rows": [0, 0], "rows_reading": [0, 0], "same_words": [0, 0]}, stats_b
    for name in ("deform_points_entry", "motion_params", "polar_log", "node_pivot", "chain_points_entry",
                 "chain_motion_entry", "cage_faces", "cage_nodes", "psi_rows"):
        assert stats_c[name][0] >= 1 and stats_c[name][1] == 0, (name, stats_c)  # loaded from A's cache
    ra, rb, rc = (np.load(tmp_path / f"{x}.npz") for x in "abc")
    full, motions = ra["points-full"], rc["motions-full"]
    assert np.array_equal(rc["points-rows"], full[rows])  # C: loaded, rows first; A: compiled, full
    assert np.array_equal(rc["points-full"], full)
    assert np.array_equal(rb["points-rows"], rc["points-full"][rows])  # B: compiled, rows; C: loaded, full
    assert np.array_equal(ra["motions-rows"], motions[:, rows])  # A: compiled, rows; C: loaded, full first
    assert np.array_equal(rc["motions-rows"], motions[:, rows])
    assert np.array_equal(ra["polar-R"], rc["polar-R"]) and np.array_equal(ra["polar-Y"], rc["polar-Y"])
    assert np.array_equal(ra["psi"], rc["psi"])
    assert np.array_equal(ra["nodes"], rc["nodes"])
    assert np.array_equal(ra["cage"], rc["cage"]) and np.array_equal(ra["cage-volume"], rc["cage-volume"])
    assert np.array_equal(ra["cage-nodes"], rc["cage-nodes"]) and np.abs(ra["cage-nodes"]).max() > 0.0
    assert np.abs(ra["cage"]).max() > 0.0  # some face moved
    assert np.array_equal(rc["points-alone"], full[lifted])  # every θ > 1.8π row alone, cached
    assert np.array_equal(rc["motions-alone"], motions[:, lifted])
    chain_full, chain_motions = ra["chain-points-full"], rc["chain-motions-full"]
    assert np.array_equal(rc["chain-points-full"], chain_full)  # loaded (C) = compiled (A)
    assert np.array_equal(rb["chain-points-rows"], chain_full[rows])  # compiled with rows (B)
    assert np.array_equal(rc["chain-points-rows"], chain_full[rows])
    assert np.array_equal(ra["chain-motions-rows"], chain_motions[:, rows])
    assert np.array_equal(rc["chain-motions-rows"], chain_motions[:, rows])
    assert np.array_equal(rc["rigid-points"], ra["rigid-points"])  # the Taylor form, loaded = compiled
    assert np.array_equal(rc["rigid-points-rows"], ra["rigid-points"][r_rows])
    assert np.array_equal(rc["rigid-motions"], ra["rigid-motions"])
    assert np.array_equal(rc["rigid-motions-rows"], ra["rigid-motions"][:, r_rows])
    # and this process (its entries compiled or loaded, whichever happened here)
    assert np.array_equal(accel.deform_points_params(pts, params, idx, val), full)
    assert np.array_equal(accel.vertex_motions(params, idx, val), motions)


# --------------------------------------------------------------------------------------------------
# polar_log: the polar split of ψ (a cage's corner tetrahedra)


def test_polar_log_matches_numpys_svd(compiled: ModuleType) -> None:
    """R = U Vᵀ and Ŷ = V diag(log σ) Vᵀ from the compiled Jacobi SVD agree with numpy's SVD to
    ~1e-15 relative, for random, rigid (exactly and nearly), repeated-σ and stretched matrices, and
    ψ through it (`params_from_matrices(polar=…)`) agrees with the numpy path; None when the kernel
    is off."""
    rng = np.random.default_rng(141)
    M = rng.normal(size=(600, 3, 3))
    M[np.linalg.det(M) < 0.0] *= -1.0
    rigid = aff3.so3_exp(rng.normal(size=(200, 3)) * 2.0)
    M = np.concatenate([M, rigid, rigid * 1.0000001 + 1e-9 * rng.normal(size=rigid.shape),
                        rigid @ np.diag([0.1, 1.0, 10.0]), 2.0 * np.eye(3)[None], np.eye(3)[None]])
    R, Y = accel.polar_log(M)
    U, sigma, Vh = np.linalg.svd(M)
    assert np.abs(R - U @ Vh).max() < 1e-13
    Yn = Vh.transpose(0, 2, 1) @ (np.log(sigma)[:, :, None] * Vh)
    # log σ_min carries both SVDs' rounding of σ_min relative to σ_max: ε κ(M)
    kappa = sigma[:, 0] / sigma[:, 2]
    assert (np.abs(Y - Yn).max(axis=(1, 2)) < 1e-14 * np.maximum(kappa, 10.0)).all()
    assert np.array_equal(R[-1], np.eye(3)) and np.array_equal(Y[-1], np.zeros((3, 3)))
    A = np.broadcast_to(np.eye(4), (len(M), 4, 4)).copy()
    A[:, :3, :3] = M
    A[:, :3, 3] = rng.normal(size=(len(M), 3))
    P, Pc = aff3.params_from_matrices(A), aff3.params_from_matrices(A, accel.polar_log)
    scale = np.maximum(kappa, 10.0) * np.maximum(1.0, np.abs(P).max(axis=1))
    assert (np.abs(Pc - P).max(axis=1) < 1e-14 * scale).all()
    assert np.array_equal(aff3.params_from_matrices(A, lambda m: None), P)  # None: numpy's SVD
    accel.set_enabled(False)
    try:
        assert accel.polar_log(M) is None
    finally:
        accel.set_enabled(True)


def _psi_cases(rng: np.random.Generator) -> np.ndarray:
    """Motions (n, 4, 4) in Aff+(3) where ψ is delicate: rotations of θ = 0, 1e-9, 0.19 / 0.21 (the
    series switch of V⁻¹), π − 1e-7, π exactly, 1.9π-looking (principal ≤ π), strong anisotropy,
    shear, repeated singular values, tiny and huge scale, translations far from the origin."""
    angles = np.array([0.0, 1e-9, 0.19, 0.21, 1.0, np.pi - 1e-7, np.pi, 2.5])
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rotations = aff3.so3_exp(angles[:, None] * axes)
    stretches = [np.eye(3), np.diag([1e-3, 1.0, 1e3]), np.diag([2.0, 2.0, 0.5]),
                 np.array([[1.0, 0.7, 0.0], [0.0, 1.0, 0.3], [0.0, 0.0, 1.0]]),
                 1e-4 * np.eye(3), 1e4 * np.eye(3)]
    motions = []
    for R in rotations:
        for S in stretches:
            A = np.eye(4)
            A[:3, :3] = R @ S
            A[:3, 3] = rng.normal(size=3) * 10.0 ** rng.integers(-6, 4)
            motions.append(A)
    random = np.broadcast_to(np.eye(4), (200, 4, 4)).copy()
    M = rng.normal(size=(200, 3, 3))
    M[np.linalg.det(M) < 0.0] *= -1.0
    random[:, :3, :3] = M
    random[:, :3, 3] = rng.normal(size=(200, 3))
    return np.concatenate([np.array(motions), random])


def test_compiled_psi_matches_numpy_and_scipy(compiled: ModuleType) -> None:
    """`accel.params_from_matrices` (ψ of the moved controls in one compiled call) agrees with
    core.aff3's numpy ψ to ~1e-14 relative on the delicate cases of `_psi_cases`, and with an
    independent reference: scipy's polar decomposition and matrix logarithms, X = logm([R t; 0 1]),
    Y = logm(S) (except at a half turn, where ±ω are both principal and logm has no real value).
    A motion outside Aff+(3) raises numpy's own ValueError; None when the kernel is off."""
    from scipy.linalg import logm, polar

    rng = np.random.default_rng(151)
    A = _psi_cases(rng)
    P = aff3.params_from_matrices(A)
    Pc = accel.params_from_matrices(A)
    sigma = np.linalg.svd(A[:, :3, :3], compute_uv=False)
    kappa = np.maximum(sigma[:, 0] / sigma[:, 2], 10.0)
    scale = kappa * np.maximum(1.0, np.abs(P).max(axis=1))
    assert Pc.shape == P.shape and (np.abs(Pc - P).max(axis=1) < 1e-14 * scale).all()
    for a, p in zip(A, Pc, strict=True):
        R, S = polar(a[:3, :3], side="right")  # M = R S
        X = np.real(logm(np.block([[R, a[:3, 3:]], [np.zeros((1, 3)), np.ones((1, 1))]])))
        Y = np.real(logm(S))
        w = np.array([X[2, 1], X[0, 2], X[1, 0]])
        if abs(np.linalg.norm(p[:3]) - np.pi) < 1e-6:  # half turn: ±ω both principal, no real logm
            continue
        ref = np.concatenate([w, X[:3, 3], [Y[0, 0], Y[1, 1], Y[2, 2], Y[0, 1], Y[0, 2], Y[1, 2]]])
        cond = np.linalg.cond(a[:3, :3])
        assert np.abs(p - ref).max() < 1e-8 * max(cond, 1.0) * max(1.0, np.abs(ref).max()), (a, p, ref)
    single = accel.params_from_matrices(A[3])
    assert single.shape == (12,) and np.array_equal(single, Pc[3])
    mirrored = A[:2].copy()
    mirrored[1, :3, :3] *= -1.0
    for bad in (mirrored, np.full((1, 4, 4), np.nan)):
        with pytest.raises(ValueError) as numpy_error:
            aff3.params_from_matrices(bad)
        with pytest.raises(ValueError, match=re.escape(str(numpy_error.value))):
            accel.params_from_matrices(bad)
    accel.set_enabled(False)
    try:
        assert accel.params_from_matrices(A) is None
    finally:
        accel.set_enabled(True)


def test_compiled_node_params_match_the_numpy_blend(compiled: ModuleType) -> None:
    """`accel.node_params` (the per-face and per-node steps of the harmonic cage's pivoted node blend
    in the compiled kernel) agrees with `core.cage.harmonic.node_params` to ~1e-15 relative: small
    (θ < 0.2, the series of V⁻¹), ordinary and large rotations (θ up to 1.9π, the libm
    θ-coefficients), with subsets of faces and invalid faces; the numpy version when the kernel is
    off."""
    from affine_deformers.core.cage import harmonic

    rng = np.random.default_rng(151)
    F, G = 60, 200
    theta = np.concatenate([rng.uniform(0.0, 0.2, 20), rng.uniform(0.2, 3.0, 30), rng.uniform(5.7, 5.97, 10)])
    axis = rng.normal(size=(F, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    P = np.concatenate([theta[:, None] * axis, rng.normal(size=(F, 3)), 0.3 * rng.normal(size=(F, 6))],
                       axis=1)
    W = rng.random((G, F)) * (rng.random((G, F)) < 0.2)
    x = rng.normal(size=(G, 3)) * 2.0
    faces = np.flatnonzero(rng.random(F) < 0.7)
    valid = rng.random(F) < 0.9
    for kwargs in ({}, {"faces": faces}, {"faces": faces, "valid": valid}):
        want = harmonic.node_params(x, W, P, maps=accel.linear_maps, **kwargs)
        got = accel.node_params(x, np.asfortranarray(W), P, **kwargs)
        assert np.abs(got - want).max() < 1e-13 * max(1.0, np.abs(want).max()), kwargs
    accel.set_enabled(False)
    try:
        got = accel.node_params(x, W, P, faces=faces)
        assert np.array_equal(got, harmonic.node_params(x, W, P, faces=faces, maps=accel.linear_maps))
    finally:
        accel.set_enabled(True)


def test_same_bits_is_a_bitwise_compare(compiled: ModuleType) -> None:
    """same_bits is True exactly for equal dtype, shape and bytes: one flipped bit anywhere (in a full
    block or the tail, first or last word) is found, −0.0 differs from 0.0 and a NaN equals itself;
    the numpy fallback and odd layouts give the same answers."""
    rng = np.random.default_rng(307)
    for n in (0, 1, 4095, 4096, 4097, 3 * 130_001):
        a = rng.standard_normal(n).astype(np.float32)
        b = a.copy()
        for enabled in (True, False):
            accel.set_enabled(enabled)
            try:
                assert accel.same_bits(a, b), (n, enabled)
                for i in {0, n // 2, n - 1} if n else ():
                    c = b.copy()
                    c.view(np.uint32)[i] ^= np.uint32(1 << int(rng.integers(0, 32)))
                    assert not accel.same_bits(a, c), (n, i, enabled)
            finally:
                accel.set_enabled(True)
    zero = np.zeros((5, 3), np.float32)
    assert not accel.same_bits(zero, -zero)
    nan = np.full((5, 3), np.nan, np.float32)
    assert accel.same_bits(nan, nan.copy())
    assert not accel.same_bits(zero, zero.reshape(3, 5))  # same bytes, another shape
    assert not accel.same_bits(zero, zero.astype(np.float64))
    odd = np.zeros(7, np.uint8)
    assert accel.same_bits(odd, odd.copy()) and not accel.same_bits(odd, odd + 1)
    strided = np.zeros((6, 3), np.float32)[::2]
    assert accel.same_bits(strided, strided.copy())


def test_rows_reading_matches_numpy(compiled: ModuleType) -> None:
    """The compiled pass gives exactly the sorted vertices with a non-zero weight on a flagged control
    (zero weights on flagged controls, indices outside the flags and NaN weights included); it is None
    with the kernel off."""
    rng = np.random.default_rng(211)
    n, m, k = 3000, 120, 5
    idx = rng.integers(0, m, size=(n, k)).astype(np.int32)
    val = np.where(rng.random((n, k)) < 0.4, 0.0, rng.random((n, k)))
    val[7, 2] = np.nan
    idx[11, 0], val[11, 0] = m + 3, 1.0  # outside the flags: reads nothing
    idx[12, :], val[12, :] = -1, 1.0
    for share in (0.0, 0.05, 0.5, 1.0):
        hit = rng.random(m) < share
        inside = (idx >= 0) & (idx < m)
        want = np.flatnonzero((inside & hit[np.clip(idx, 0, m - 1)] & (val != 0.0)).any(axis=1))
        got = accel.rows_reading(hit, idx, val)
        assert got.dtype == np.intp and np.array_equal(got, want), share
    assert accel.rows_reading(np.ones(m, bool), idx[:0], val[:0]).size == 0
    with pytest.raises(ValueError, match="shape"):
        accel.rows_reading(np.ones(m, bool), idx, val[:, :2])
    accel.set_enabled(False)
    try:
        assert accel.rows_reading(np.ones(m, bool), idx, val) is None
    finally:
        accel.set_enabled(True)
