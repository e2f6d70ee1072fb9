"""The compiled kernel (csrc/, loaded by affine_deformers/accel/native.py) against the
numpy kernel and the aff3 reference, its bit-identity guarantees (rows, threads, chunk positions, the
column forms a chunk mixes), the argument checks of its wrappers and the fallback to numpy."""

from __future__ import annotations

import math
import re
import sys
import threading
import time
import types
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from affine_deformers import accel
from affine_deformers.accel import native
from affine_deformers.core import aff3, deform, kernel_stages
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

ROOT = Path(__file__).resolve().parents[2]
#: csrc/affine_internal.h's CHUNK (vertices per chunk; `test_the_c_constants_are_the_python_ones`
#: and the loaded library's ak_chunk() agree with it). A literal, so the numpy runs need no library.
CHUNK = 2048
#: θ² beyond which the C kernel redoes a column with libm sin/cos (its POLY_MAX_S), as numpy's kernel.
POLY_MAX_S = (1.8 * math.pi) ** 2


def _library_or_skip() -> None:
    """Skip when no library is built for this machine (`make native`); a library that is there but
    does not load is a failure of the test using it."""
    try:
        native.library_path()
    except native.KernelUnavailableError as exc:
        pytest.skip(f"the compiled kernel is not available: {exc}")


@pytest.fixture
def kernel(monkeypatch: pytest.MonkeyPatch) -> native.Kernel:
    """The C kernel, enabled and loaded (skips when the library is not built here)."""
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    _library_or_skip()
    module = accel._load()
    assert module is not None, accel.backend()
    assert module.CHUNK == CHUNK
    return module


@pytest.fixture
def fresh_state(monkeypatch: pytest.MonkeyPatch) -> accel._State:
    """A backend that has not tried to load the library yet (restored afterwards)."""
    state = accel._State()
    monkeypatch.setattr(accel.state, "_state", state)  # what every call reads
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


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def _backend(use_kernel: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    if use_kernel:
        monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
        _library_or_skip()
        assert accel.active(), accel.backend()
    else:
        monkeypatch.setenv(accel.ACCEL_ENV, "0")
        assert not accel.active()


# --------------------------------------------------------------------------------------------------
# accuracy


def test_random_blends_match_the_numpy_kernel(kernel: native.Kernel) -> None:
    rng = np.random.default_rng(101)
    pts, params, idx, val = blend_case(rng, 20_000)
    got = accel.deform_points_params(pts, params, idx, val)
    ref = deform.deform_points_params(pts, params, idx, val, cache_weights=False)
    err = np.linalg.norm(got - ref, axis=1) / vertex_scale(pts, deform.blend_params(params, idx, val))
    assert err.max() <= 1e-15, f"worst {err.max():.2e}"
    assert not np.array_equal(got, pts)  # it moved something


@pytest.mark.parametrize("extra", [False, True])
def test_adversarial_parameters_match_the_reference(kernel: native.Kernel, extra: bool) -> None:
    """The adversarial set of test_deform (every KERNEL_ANGLES × KERNEL_SPECTRA pairing, translations
    0 … 1e3) and the lifted angles (both sides of 1.8π, up to 5.5π), one control per vertex with
    weight 1."""
    rng = np.random.default_rng(102)
    P = lifted_params(rng) if extra else adversarial_params()
    assert max(KERNEL_ANGLES) ** 2 > POLY_MAX_S  # the adversarial set reaches the fix-up too
    if extra:
        assert (np.einsum("ij,ij->i", P[:, :3], P[:, :3]) > POLY_MAX_S).sum() == 5
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


def test_common_and_rigid_motions(kernel: native.Kernel) -> None:
    rng = np.random.default_rng(105)
    pts = rng.uniform(-3, 3, size=(3000, 3))
    A = random_affine(rng, 1, log_scale=1.5, t_scale=20.0)[0]
    params = np.broadcast_to(aff3.params_from_matrices(A), (4, 12))
    idx, val = top_k_dense(rng.random((pts.shape[0], 4)), 4, normalize="SUM")
    got = accel.deform_points_params(pts, params, idx, val)
    want = pts @ A[:3, :3].T + A[:3, 3]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * (np.abs(want).max() + 1))


def test_zero_params_return_the_input_bit_for_bit(kernel: native.Kernel) -> None:
    pts = np.array([[-0.0, 0.0, -0.0], [1e-320, -1e-320, 5e-324], [1e300, -1e300, 7.0]])
    got = accel.deform_points_params(pts, np.zeros((3, 12)), np.zeros((3, 2), np.int32), np.ones((3, 2)))
    assert got.tobytes() == pts.tobytes()


def _c_defines(*paths: Path) -> dict[str, float]:
    """The numeric #defines of C files (hexadecimal floats included); a name defined twice must have
    one value."""
    found: dict[str, float] = {}
    for path in paths:
        for name, value in re.findall(r"^#define\s+(\w+)\s+([-+0-9.xXa-fA-Fp]+)\b", path.read_text(), re.M):
            number = float.fromhex(value) if value.lower().startswith("0x") else float(value)
            assert found.setdefault(name, number) == number, (name, path)
    return found


def test_the_c_constants_are_the_python_ones() -> None:
    """What the C sources repeat from the Python side: the chunk, the small-Y line and the fix-up
    threshold of core.deform, the ABI version and the exported entries native.py binds (read from
    csrc/; no library needed)."""
    sources = sorted((ROOT / "csrc").glob("*.[ch]"))
    header = ROOT / "csrc" / "affine_kernel.h"
    if not header.is_file():
        pytest.skip("no C source in this tree")
    c = _c_defines(*sources)
    assert c["CHUNK"] == CHUNK
    assert c["SMALL_Y"] == deform.SMALL_Y
    assert c["POLY_MAX_S"] == POLY_MAX_S == kernel_stages._POLY_MAX_S
    assert c["C_CLAMP_S"] == kernel_stages._C_CLAMP_S
    h = _c_defines(header)
    assert h["AK_ABI_VERSION"] == native.ABI_VERSION
    declared = set(re.findall(r"AK_EXPORT\s+\w+\s+(ak_\w+)\s*\(", header.read_text()))
    assert declared == set(native.EXPORTS) == set(native._SIGNATURES)


# --------------------------------------------------------------------------------------------------
# bit-identity: rows, chunks, threads


def test_rows_are_bit_identical_to_the_full_call(kernel: native.Kernel) -> None:
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
    # each row alone (column 0 of a chunk of zeros) is the same as in the full call
    out = np.zeros((n, 3))
    for r in rng.choice(n, 40, replace=False):
        accel.deform_points_params_rows(pts, params, idx, val, [r], out)
        assert np.array_equal(out[r], full[r])


@pytest.mark.parametrize("n_rel", [0, 1, -1, None])
def test_sizes_around_the_chunk(kernel: native.Kernel, n_rel: int | None) -> None:
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
    kernel: native.Kernel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The dispatch runs the entry on the calling thread and on helper threads (a ctypes call
    releases the GIL), which claim chunks from a shared counter; neither the thread count nor which
    thread takes which chunk changes a bit."""
    rng = np.random.default_rng(108)
    n = 4 * CHUNK + 3
    pts, params, idx, val = blend_case(rng, n)
    rows = np.flatnonzero(rng.random(n) < 0.5).astype(np.intp)
    accel.deform_points_params(pts, params, idx, val)  # the entry's first (one-thread) run is done
    submitted = []
    start = accel._Helper.start

    def counting_start(self: accel._Helper, fn: Callable, args: tuple) -> None:
        submitted.append(fn.__name__)
        start(self, fn, args)

    monkeypatch.setattr(accel._Helper, "start", counting_start)
    results = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv(deform.THREADS_ENV, threads)
        plural = "s" * (threads != "1")
        assert accel.backend() == f"C kernel ({kernel.path.name}), {threads} thread{plural}"
        submitted.clear()
        out = accel.deform_points_params(pts, params, idx, val)
        sub = np.zeros((n, 3))
        sub32 = np.zeros((n, 3), dtype=np.float32)
        accel.deform_points_params_rows(pts, params, idx, val, rows, sub, offsets=True, out32=sub32)
        assert submitted == ["deform_points_entry"] * (2 * (int(threads) - 1))  # helpers per call
        results.append((out, sub, sub32))
    for other in results[1:]:
        assert np.array_equal(results[0][0], other[0])
        assert np.array_equal(results[0][1], other[1])
        assert np.array_equal(results[0][2].view(np.uint32), other[2].view(np.uint32))
    # called directly: a counter at c leaves chunks below c alone, a fresh one does every chunk
    out = np.zeros((n, 3))
    args = (pts, params, idx.astype(np.int32), val, np.empty(0, np.int64), False, False, out,
            np.empty((0, 3), np.float32), False)
    counter = np.array([3], dtype=np.int64)
    assert kernel.deform_points_entry(*args, counter) == 2  # chunks 3 and 4
    assert counter[0] == 6  # and one failed claim
    assert np.all(out[: 3 * CHUNK] == 0.0)
    assert np.array_equal(out[3 * CHUNK :], results[0][0][3 * CHUNK :])
    assert kernel.deform_points_entry(*args, np.array([5], np.int64)) == 0  # nothing left
    assert kernel.deform_points_entry(*args, np.zeros(1, np.int64)) == 5
    assert np.array_equal(out, results[0][0])


def test_helper_threads_are_joined_and_their_errors_reach_the_caller() -> None:
    """`_run_chunks` (no kernel needed): every helper shares the call's counter, the call returns only
    after all of them, a helper's exception is raised in the caller, and the helpers stay usable."""

    def make_entry(fail: bool) -> tuple[list, Callable]:
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
    """`_run_chunks` (no kernel needed): when the calling thread's entry reports that it did every
    chunk, the call returns without waiting for a helper that has not woken up yet (it can claim
    nothing, so it writes nothing); that helper is joined before its next job. When the calling
    thread did fewer chunks, or the entry reports nothing (None), every helper is waited for."""
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


def test_out_argument_in_place_and_layouts(kernel: native.Kernel) -> None:
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
    # out a shifted view of points' own memory: read before written, or copied
    buf = np.concatenate([pts, pts[:1]])
    shifted = accel.deform_points_params(buf[1:], params, idx, val, out=buf[:-1])
    assert np.array_equal(shifted, accel.deform_points_params(np.roll(pts, -1, axis=0), params, idx, val))


def test_keyed_calls_skip_checks_but_stay_memory_safe(kernel: native.Kernel) -> None:
    rng = np.random.default_rng(110)
    pts, params, idx, val = blend_case(rng, 3000)
    want = accel.deform_points_params(pts, params, idx, val, key="bind-1")
    assert np.array_equal(accel.deform_points_params(pts, params, idx, val, key="bind-1"), want)
    # a caller breaking its promise gets wrong values, not a crash (indices are clamped to the table)
    bad = idx.copy()
    bad[0, 0] = 10**6
    bad[1, 0] = -5
    got = accel.deform_points_params(pts, params, bad, val, key="bind-1")
    assert np.all(np.isfinite(got))
    clamped = idx.copy()
    clamped[:2, 0] = len(params) - 1  # what the kernel reads instead
    assert np.array_equal(got[:2], accel.deform_points_params(pts[:2], params, clamped[:2], val[:2]))
    assert np.array_equal(got[2:], want[2:])
    with pytest.raises(ValueError, match="indices must lie"):
        accel.deform_points_params(pts, params, bad, val, key="bind-2")
    # shapes are always checked
    with pytest.raises(ValueError):
        accel.deform_points_params(pts, params, idx[:10], val[:10], key="bind-2")


# --------------------------------------------------------------------------------------------------
# the float32 copy of the computed rows (out32), on both backends


#: Offsets whose float32 rounding is delicate: ties to even, just off ties, the float32 overflow
#: threshold (a tie there rounds to inf), beyond it, subnormals and their ties, below the smallest one.
_F32_MAX = float(np.finfo(np.float32).max)
ROUNDING_CASES = np.array([
    1 + 2**-24, 1 + 3 * 2**-24, -(1 + 2**-24), 1 + 2**-24 + 2**-52, 0.1, 1 / 3,
    _F32_MAX, _F32_MAX + 2.0**103, _F32_MAX + 2.0**103 - 2.0**80, -_F32_MAX - 2.0**103, 1e39, -1e300,
    1e-41, -2.5e-39, 2.0**-150, 3 * 2.0**-150, 2.0**-150 * (1 + 2**-30), 1e-300,
])


@pytest.mark.parametrize("use_kernel", [True, False])
def test_out32_rows_are_the_float32_of_the_offsets(use_kernel: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """out32[rows] is bit for bit out[rows].astype(float32); every other row of out32 (and of out) is
    left alone; out itself is what a call without out32 gives."""
    _backend(use_kernel, monkeypatch)
    rng = np.random.default_rng(113)
    n = 2 * CHUNK + 33
    pts, params, idx, val = blend_case(rng, n)
    params[:2] = lifted_params(rng)[[1, 4]]  # fix-up rows too
    subsets = {
        "empty": np.zeros(0, dtype=np.intp),
        "one": np.array([CHUNK + 5]),
        "boundaries": np.array([0, CHUNK - 1, CHUNK, CHUNK + 1, 2 * CHUNK - 1, 2 * CHUNK, n - 1]),
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


@pytest.mark.parametrize("use_kernel", [True, False])
def test_out32_rounds_like_numpy_at_ties_overflow_and_subnormals(
    use_kernel: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Pure translations applied to the origin give the translation exactly, so the offsets are
    chosen doubles: their float32 in out32 is numpy's cast of them, bit for bit (±inf included)."""
    _backend(use_kernel, monkeypatch)
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


@pytest.mark.parametrize("use_kernel", [True, False])
@pytest.mark.parametrize(("bad", "message"), OUT32_BAD)
def test_bad_out32_raises_before_writing(
    bad: object, message: str, use_kernel: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    _backend(use_kernel, monkeypatch)
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


@pytest.mark.parametrize("use_kernel", [True, False])
@pytest.mark.parametrize(("kwargs", "message"), BAD_ARGUMENTS)
def test_bad_arguments_raise_the_core_messages(
    kwargs: dict, message: str, use_kernel: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    _backend(use_kernel, monkeypatch)
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
# the Kernel wrappers: what the C code reads and writes is checked before it runs


def _entry_arguments(name: str) -> dict[str, object]:
    """Valid keyword arguments of Kernel.<name>: 5 vertices, 3 controls, 2 weights each; outputs
    filled with 7."""
    rng = np.random.default_rng(7)
    n, m, k = 5, 3, 2
    table = 0.1 * rng.normal(size=(m, 12))
    idx = rng.integers(0, m, size=(n, k)).astype(np.int32)
    val = rng.random((n, k))
    rows = np.array([4, 0], np.int64)
    counter = np.zeros(1, np.int64)
    out3, out3_32, motions = np.full((n, 3), 7.0), np.full((n, 3), 7.0, np.float32), np.full((4, n, 3), 7.0)
    no_motions32 = np.empty((4, 0, 3), np.float32)
    chain = {"table": table, "idx": np.stack([idx, idx[::-1].copy()]), "val": np.stack([val, val]),
             "prefix": np.array([0, 1, 0, 1, 1], np.int32),
             "mats": np.concatenate([np.eye(3).ravel(), [1.0, 2.0, 3.0]])[None].repeat(2, axis=0),
             "rows": rows, "use_rows": True}
    M = aff3.so3_exp(rng.normal(size=(n, 3))) * 1.5
    if name == "deform_points_entry":
        return {"points": rng.normal(size=(n, 3)), "table": table, "idx": idx, "val": val, "rows": rows,
                "use_rows": True, "offsets": True, "out": out3, "out32": out3_32, "use32": True,
                "counter": counter}
    if name == "motion_params":
        return {"table": table, "idx": idx, "val": val, "rows": rows, "use_rows": True, "out": motions,
                "out32": no_motions32, "use32": False, "counter": counter}
    if name == "chain_points_entry":
        return {"points": rng.normal(size=(n, 3)), **chain, "offsets": False, "out": out3, "out32": out3_32,
                "use32": True, "counter": counter}
    if name == "chain_motion_entry":
        return {**chain, "out": motions, "out32": no_motions32, "use32": False, "counter": counter}
    if name == "polar_log":
        return {"M": M, "R": np.full((n, 3, 3), 7.0), "Yh": np.full((n, 3, 3), 7.0)}
    if name == "psi_rows":
        return {"rows": np.concatenate([M.reshape(n, 9), rng.normal(size=(n, 3))], axis=1)}
    if name == "node_pivot":
        return {"finish": True, "A": 0.1 * rng.normal(size=(n, 21)), "x": rng.normal(size=(n, 3)),
                "out": np.full((n, 12), 7.0)}
    if name == "rows_reading":
        return {"hit": np.array([True, False, True]), "idx": idx, "val": val, "out": np.full(n, 7, np.int64)}
    if name == "same_words":
        words = rng.integers(0, 2**32, size=n, dtype=np.uint32)
        return {"a": words, "b": words.copy()}
    if name == "spin_wait":
        return {"flag": np.zeros(1, np.int64), "seen": 0, "n": 10}
    raise AssertionError(name)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = a.copy()
    a.flags.writeable = False
    return a


def _strided(a: np.ndarray) -> np.ndarray:
    """The same values and shape, not C-contiguous."""
    return np.repeat(a, 2, axis=-1)[..., ::2]


def _as(dtype: type) -> Callable[[np.ndarray], np.ndarray]:
    return lambda a: a.astype(dtype)


_TYPE, _VALUE = TypeError, ValueError
#: (entry, argument, its replacement from the valid value, the exception, its message).
WRAPPER_BAD = [
    ("deform_points_entry", "points", _as(np.float32), _TYPE, "points must be a C-contiguous float64"),
    ("deform_points_entry", "points", np.asfortranarray, _TYPE, "points must be a C-contiguous float64"),
    ("deform_points_entry", "points", _strided, _TYPE, "points must be a C-contiguous float64"),
    ("deform_points_entry", "points", lambda a: np.zeros((5, 4)), _VALUE, r"points must have shape \(5, 3\)"),
    ("deform_points_entry", "points", lambda a: a[:4].copy(), _VALUE, r"one \(N, K\) shape, got \(5, 2\)"),
    ("deform_points_entry", "table", lambda a: a[:, :11].copy(), _VALUE, r"table must have shape \(m >= 1"),
    ("deform_points_entry", "table", lambda a: a[:0].copy(), _VALUE, r"table must have shape \(m >= 1, 12\)"),
    ("deform_points_entry", "table", _as(np.float32), _TYPE, "table must be a C-contiguous float64"),
    ("deform_points_entry", "idx", _as(np.int64), _TYPE, "idx must be a C-contiguous int32"),
    ("deform_points_entry", "idx", lambda a: a[:, :1].copy(), _VALUE, r"one \(N, K\) shape"),
    ("deform_points_entry", "val", lambda a: a[:, :1].copy(), _VALUE, r"one \(N, K\) shape"),
    ("deform_points_entry", "val", np.asfortranarray, _TYPE, "val must be a C-contiguous float64"),
    ("deform_points_entry", "rows", lambda a: np.array([5]), _VALUE, r"rows must be in \[0, 5\)"),
    ("deform_points_entry", "rows", lambda a: np.array([0, -1]), _VALUE, r"rows must be in \[0, 5\)"),
    ("deform_points_entry", "rows", _as(np.int32), _TYPE, "rows must be a C-contiguous int64"),
    ("deform_points_entry", "rows", lambda a: a[:, None].copy(), _VALUE, "rows must be 1-D"),
    ("deform_points_entry", "out", lambda a: a[:4].copy(), _VALUE, r"out must have shape \(5, 3\)"),
    ("deform_points_entry", "out", _as(np.float32), _TYPE, "out must be a C-contiguous float64"),
    ("deform_points_entry", "out", _strided, _TYPE, "out must be a C-contiguous float64"),
    ("deform_points_entry", "out", _readonly, _VALUE, "out must be writable"),
    ("deform_points_entry", "out32", _as(np.float64), _TYPE, "out32 must be a C-contiguous float32"),
    ("deform_points_entry", "out32", lambda a: a[:4].copy(), _VALUE, r"out32 must have shape \(5, 3\)"),
    ("deform_points_entry", "counter", _as(np.int32), _TYPE, "counter must be a C-contiguous int64"),
    ("deform_points_entry", "counter", _readonly, _VALUE, "counter must be writable"),
    ("motion_params", "out", lambda a: a[:, :4].copy(), _VALUE, r"out must have shape \(4, 5, 3\)"),
    ("motion_params", "out", _strided, _TYPE, "out must be a C-contiguous float64"),
    ("motion_params", "out", _readonly, _VALUE, "out must be writable"),
    ("motion_params", "rows", lambda a: np.array([5]), _VALUE, r"rows must be in \[0, 5\)"),
    ("motion_params", "idx", lambda a: a[None], _VALUE, r"one \(N, K\) shape"),
    ("motion_params", "out32", _as(np.float64), _TYPE, "out32 must be a C-contiguous float32"),
    ("chain_points_entry", "prefix", lambda a: a[:4].copy(), _VALUE, r"prefix must have shape \(5,\)"),
    ("chain_points_entry", "prefix", _as(np.int64), _TYPE, "prefix must be a C-contiguous int32"),
    ("chain_points_entry", "mats", lambda a: a[:, :9].copy(), _VALUE, r"mats must have shape"),
    ("chain_points_entry", "mats", lambda a: a[:0].copy(), _VALUE, r"mats must have shape"),
    ("chain_points_entry", "idx", lambda a: a[0].copy(), _VALUE, r"one \(P, N, K\) shape"),
    ("chain_points_entry", "points", lambda a: a[:4].copy(), _VALUE, r"points must have shape \(5, 3\)"),
    ("chain_points_entry", "rows", lambda a: np.array([9]), _VALUE, r"rows must be in \[0, 5\)"),
    ("chain_points_entry", "out32", lambda a: a[:, :2].copy(), _VALUE, r"out32 must have shape \(5, 3\)"),
    ("chain_motion_entry", "out", lambda a: a[:3].copy(), _VALUE, r"out must have shape \(4, 5, 3\)"),
    ("chain_motion_entry", "val", _as(np.float32), _TYPE, "val must be a C-contiguous float64"),
    ("chain_motion_entry", "table", lambda a: a[:, :11].copy(), _VALUE, r"table must have shape"),
    ("polar_log", "M", _as(np.float32), _TYPE, "M must be a C-contiguous float64"),
    ("polar_log", "R", lambda a: a[:4].copy(), _VALUE, r"R must have shape \(5, 3, 3\)"),
    ("polar_log", "Yh", _readonly, _VALUE, "Yh must be writable"),
    ("psi_rows", "rows", lambda a: a[:, :11].copy(), _VALUE, r"rows must have shape \(n, 12\)"),
    ("psi_rows", "rows", np.asfortranarray, _TYPE, "rows must be a C-contiguous float64"),
    ("psi_rows", "rows", _readonly, _VALUE, "rows must be writable"),
    ("node_pivot", "x", lambda a: a[:4].copy(), _VALUE, r"x must have shape \(5, 3\)"),
    ("node_pivot", "A", lambda a: a[:, :12].copy(), _VALUE, r"A must have shape \(5, 21\)"),
    ("node_pivot", "out", lambda a: a[:, :9].copy(), _VALUE, r"out must have shape \(5, 12\)"),
    ("rows_reading", "hit", _as(np.uint8), _TYPE, "hit must be a C-contiguous bool"),
    ("rows_reading", "out", lambda a: a[:4].copy(), _VALUE, r"out must have shape \(5,\)"),
    ("rows_reading", "out", _as(np.int32), _TYPE, "out must be a C-contiguous int64"),
    ("rows_reading", "val", lambda a: a[:, :1].copy(), _VALUE, "idx and val must be"),
    ("same_words", "b", lambda a: a[:4].copy(), _VALUE, "a and b must be 1-D of one length"),
    ("same_words", "a", _as(np.int32), _TYPE, "a must be a C-contiguous uint32"),
    ("spin_wait", "flag", lambda a: np.zeros(2, np.int64), _VALUE, r"flag must have shape \(1,\)"),
    ("spin_wait", "flag", _as(np.int32), _TYPE, "flag must be a C-contiguous int64"),
]


@pytest.mark.parametrize(("entry", "name", "bad", "error", "message"), WRAPPER_BAD,
                         ids=[f"{e}-{a}-{i}" for i, (e, a, *_) in enumerate(WRAPPER_BAD)])
def test_kernel_wrappers_refuse_arrays_the_c_code_cannot_read_safely(
    kernel: native.Kernel, entry: str, name: str, bad: Callable, error: type, message: str
) -> None:
    """Each entry's wrapper checks dtypes, C-contiguity, shapes that agree, writability and the rows
    it will write to, and raises before the C code runs (nothing is written); the same call with
    the valid argument runs."""
    fn = getattr(kernel, entry)
    fn(**_entry_arguments(entry))  # valid
    args = _entry_arguments(entry)
    args[name] = bad(args[name])
    before = {k: v.copy() for k, v in args.items() if isinstance(v, np.ndarray)}
    with pytest.raises(error, match=message):
        fn(**args)
    for k, v in before.items():
        assert np.array_equal(args[k], v, equal_nan=True), k  # nothing written


def test_kernel_wrappers_refuse_an_empty_chunk_counter(kernel: native.Kernel) -> None:
    """The chunk counter is read and written through its pointer: an array with no element (here an
    empty view into a larger buffer) must be refused, not written past."""
    for entry in ("deform_points_entry", "motion_params", "chain_points_entry", "chain_motion_entry"):
        buf = np.zeros(3, np.int64)
        args = _entry_arguments(entry)
        args["counter"] = buf[1:1]
        with pytest.raises(ValueError, match="counter"):
            getattr(kernel, entry)(**args)
        assert not buf.any(), entry


def test_the_kernel_entries_compute_what_accel_returns(kernel: native.Kernel) -> None:
    """The wrappers called directly (one thread, a fresh counter each) give the bits of the accel
    calls: rows with offsets and the float32 copy, motions, the chain; out-of-range table indices
    and prefixes are clamped to the last row (never read out of bounds)."""
    for entry in ("deform_points_entry", "chain_points_entry"):
        a = _entry_arguments(entry)
        assert getattr(kernel, entry)(**a) == 1
        rows, pts, weights = a["rows"], a["points"], (a["table"], a["idx"], a["val"])
        if entry == "deform_points_entry":
            want = accel.deform_points_params(pts, *weights)[rows] - pts[rows]
        else:
            want = accel.chain_points(pts, *weights, a["prefix"], a["mats"])[rows]
        assert np.array_equal(a["out"][rows], want), entry
        assert np.array_equal(_bits(a["out32"][rows]), _bits(want.astype(np.float32))), entry
        assert np.all(np.delete(a["out"], rows, axis=0) == 7.0)
        assert np.all(np.delete(a["out32"], rows, axis=0) == 7.0)
    a = _entry_arguments("motion_params")
    kernel.motion_params(**a)
    want = accel.vertex_motions(a["table"], a["idx"], a["val"])
    assert np.array_equal(a["out"][:, a["rows"]], want[:, a["rows"]])
    # clamping: an index past the table, a negative one (huge as unsigned) read the last row
    a = _entry_arguments("deform_points_entry")
    a["idx"][4] = [10**6, -5]
    a["use_rows"] = False
    kernel.deform_points_entry(**a)
    clamped = _entry_arguments("deform_points_entry")
    clamped["idx"][4] = len(clamped["table"]) - 1
    clamped["use_rows"] = False
    kernel.deform_points_entry(**clamped)
    assert np.array_equal(a["out"], clamped["out"])
    a = _entry_arguments("chain_points_entry")
    a["prefix"][:] = [7, -1, 0, 2**31 - 1, 1]
    kernel.chain_points_entry(**a)
    clamped = _entry_arguments("chain_points_entry")
    clamped["prefix"][:] = [1, 1, 0, 1, 1]
    kernel.chain_points_entry(**clamped)
    assert np.array_equal(a["out"], clamped["out"])


# --------------------------------------------------------------------------------------------------
# fallback to numpy (no library needed unless said)


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
    assert fresh_state.module is None and fresh_state.failure is None  # never tried to load the library


def test_the_preference_turns_the_compiled_path_off(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    """set_enabled(False) (the add-on preference): numpy, the library not even loaded, and backend()
    says so; set_enabled(True) brings the compiled kernel back unless the environment says 0."""
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    accel.set_enabled(False)
    assert accel.backend() == "numpy (compiled kernel turned off in the preferences)"
    assert not accel.active()
    rng = np.random.default_rng(116)
    pts, params, idx, val = blend_case(rng, 300)
    want = deform.deform_points_params(pts, params, idx, val, cache_weights=False)
    assert np.array_equal(accel.deform_points_params(pts, params, idx, val), want)
    assert np.array_equal(accel.vertex_motions(params, idx, val), deform.vertex_motions(params, idx, val))
    assert accel.polar_log(np.eye(3)[None]) is None and accel.params_from_matrices(np.eye(4)) is None
    assert fresh_state.module is None and fresh_state.failure is None
    accel.set_enabled(True)
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    assert accel.backend() == "numpy (AFFINE_DEFORMERS_ACCEL=0)"  # the environment still wins
    monkeypatch.delenv(accel.ACCEL_ENV)
    _library_or_skip()
    assert accel.backend().startswith("C kernel (") and accel.active()


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


def _assert_numpy_for_the_process(fresh_state: accel._State, reason: str) -> None:
    """Every call gives numpy's result without a warning, backend() names the reason, and no later
    call tries to load the library again."""
    rng = np.random.default_rng(113)
    pts, params, idx, val = blend_case(rng, 300)
    want = deform.deform_points_params(pts, params, idx, val, cache_weights=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a build without the library is reported, not warned about
        got = accel.deform_points_params(pts, params, idx, val)
        assert np.array_equal(got, want)
        assert accel.backend() == f"numpy ({reason})"
        assert not accel.active()
        out = np.zeros((300, 3))
        accel.deform_points_params_rows(pts, params, idx, val, np.arange(300), out)
        assert np.array_equal(out, want)
        assert np.array_equal(accel.vertex_motions(params, idx, val), deform.vertex_motions(params, idx, val))
        assert accel.polar_log(np.eye(3)[None]) is None
        assert accel.rows_reading(np.ones(8, bool), idx, val) is None
        assert accel.same_bits(pts, pts.copy())
    assert fresh_state.module is None and fresh_state.failure == reason


def test_a_missing_library_falls_back_to_numpy_for_the_process(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State, tmp_path: Path
) -> None:
    """$AFFINE_DEFORMERS_KERNEL_LIB naming no file: numpy, backend() says why, no warning; the
    reason sticks (no second attempt once the variable is gone)."""
    missing = tmp_path / "nowhere" / "affine_kernel.so"
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.setenv(native.LIBRARY_ENV, str(missing))
    reason = f"{native.LIBRARY_ENV}={missing} is not a file"
    _assert_numpy_for_the_process(fresh_state, reason)
    monkeypatch.delenv(native.LIBRARY_ENV)
    _assert_numpy_for_the_process(fresh_state, reason)


def test_a_library_that_is_not_installed_falls_back_to_numpy(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State, tmp_path: Path
) -> None:
    """No build in any place the loader looks (the wheel package, the source tree's build/native):
    the reason names the file and the places."""
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.delenv(native.LIBRARY_ENV, raising=False)
    monkeypatch.delenv(native.VARIANT_ENV, raising=False)
    monkeypatch.setattr(native, "host_platform", lambda: "linux_x64")
    monkeypatch.setattr(native, "_candidate_dirs", lambda plat: [tmp_path / "a", tmp_path / "b"])
    _assert_numpy_for_the_process(
        fresh_state, f"the compiled kernel library (affine_kernel.so) is not installed (looked in "
        f"{tmp_path / 'a'}, {tmp_path / 'b'})")


def test_a_platform_without_a_build_falls_back_to_numpy(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.delenv(native.LIBRARY_ENV, raising=False)
    monkeypatch.setattr(native, "host_platform", lambda: None)
    reason = accel.backend()[len("numpy ("):-1]
    assert reason.startswith("no compiled kernel for ")
    _assert_numpy_for_the_process(fresh_state, reason)


def test_a_file_that_is_not_a_library_falls_back_to_numpy(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State, tmp_path: Path
) -> None:
    damaged = tmp_path / "affine_kernel.so"
    damaged.write_bytes(b"\x7fELF but not really a shared library")
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.setenv(native.LIBRARY_ENV, str(damaged))
    reason = accel.backend()[len("numpy ("):-1]
    assert reason.startswith("affine_kernel.so does not load: ")
    _assert_numpy_for_the_process(fresh_state, reason)


def test_a_library_of_another_build_falls_back_to_numpy(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    """A shared library that loads but lacks the entries (here numpy's own extension module)."""
    try:
        from numpy._core import _multiarray_umath
    except ImportError:  # numpy < 1.26
        from numpy.core import _multiarray_umath

    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.setenv(native.LIBRARY_ENV, _multiarray_umath.__file__)
    name = Path(_multiarray_umath.__file__).name
    _assert_numpy_for_the_process(fresh_state, f"{name} lacks ak_abi_version: a different build")


def test_a_library_of_another_abi_version_falls_back_to_numpy(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    """The library's ak_abi_version() must be the one native.py is written for (faked from the
    Python side: this module expecting the next version)."""
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    _library_or_skip()
    path, _ = native.library_path()
    monkeypatch.setattr(native, "ABI_VERSION", native.ABI_VERSION + 1)
    _assert_numpy_for_the_process(
        fresh_state, f"{path.name} has ABI version {native.ABI_VERSION - 1}; this add-on needs "
        f"{native.ABI_VERSION}")


def test_an_unexpected_error_while_loading_falls_back_with_a_warning(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    """Anything but KernelUnavailableError from loading is unexpected: numpy for the process, with a
    warning (once)."""

    def broken() -> native.Kernel:
        raise ValueError("the loader is unhappy")

    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.setattr(native, "load", broken)
    rng = np.random.default_rng(117)
    pts, params, idx, val = blend_case(rng, 50)
    with pytest.warns(UserWarning, match="the loader is unhappy"):
        got = accel.deform_points_params(pts, params, idx, val)
    assert np.array_equal(got, deform.deform_points_params(pts, params, idx, val, cache_weights=False))
    reason = "loading the compiled kernel failed: ValueError: the loader is unhappy"
    assert accel.backend() == f"numpy ({reason})"
    _assert_numpy_for_the_process(fresh_state, reason)  # and no second warning


def _broken(*args: object) -> None:
    raise RuntimeError("the kernel is unhappy")


def test_an_entry_failing_on_its_first_call_falls_back(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State
) -> None:
    """An error from the first call of an entry is a platform problem: numpy takes over for the
    process (with a warning), the caller gets correct results."""
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    fake = types.SimpleNamespace(deform_points_entry=_broken, CHUNK=CHUNK)
    monkeypatch.setattr(fresh_state, "module", fake)
    rng = np.random.default_rng(114)
    pts, params, idx, val = blend_case(rng, 200)
    with pytest.warns(UserWarning, match="the kernel is unhappy"):
        got = accel.deform_points_params(pts, params, idx, val)
    assert np.array_equal(got, deform.deform_points_params(pts, params, idx, val, cache_weights=False))
    reason = "the compiled deform_points_entry failed: RuntimeError: the kernel is unhappy"
    assert accel.backend() == f"numpy ({reason})"
    _assert_numpy_for_the_process(fresh_state, reason)


@pytest.mark.parametrize("entry", ["polar_log", "psi_rows", "node_pivot", "rows_reading", "same_words",
                                   "cage_faces", "cage_nodes"])
def test_a_one_thread_entry_failing_on_its_first_call_falls_back(
    monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State, entry: str
) -> None:
    """The per-control entries share the rule of the per-vertex ones: an error on the first call
    switches the process to numpy and the caller still gets numpy's result (or None: the caller
    then uses numpy); once an entry has run, an error is a bug and propagates."""
    from affine_deformers.core.cage import harmonic
    from tests.core.test_cage import box_cage

    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    monkeypatch.setattr(fresh_state, "module", types.SimpleNamespace(**{entry: _broken}))
    rng = np.random.default_rng(115)
    A = np.tile(np.eye(4), (3, 1, 1))
    A[:, :3, :3] += 0.1 * rng.normal(size=(3, 3, 3))
    points, weights, faces = rng.normal(size=(5, 3)), rng.random((5, 3)), 0.01 * rng.normal(size=(3, 12))
    cage, topology = box_cage((2, 2, 2), (1.0, 1.0, 1.0))
    words = rng.random(40).astype(np.float32)
    calls = {
        "polar_log": lambda: accel.polar_log(A[:, :3, :3]),
        "psi_rows": lambda: accel.params_from_matrices(A),
        "node_pivot": lambda: accel.node_params(points, weights, faces),
        "rows_reading": lambda: accel.rows_reading(np.ones(3, bool), np.zeros((5, 3), np.int32), weights),
        "same_words": lambda: accel.same_bits(words, words.copy()),
        "cage_faces": lambda: accel.cage_faces(cage, cage * 1.1, topology),
        "cage_nodes": lambda: accel.cage_nodes(points, rng.random((5, topology.n_faces)),
                                               0.01 * rng.normal(size=(topology.n_faces, 12)), np.arange(3)),
    }
    with pytest.warns(UserWarning, match="the kernel is unhappy"):
        got = calls[entry]()
    if entry == "node_pivot":  # numpy's result instead
        assert np.allclose(got, harmonic.node_params(points, weights, faces, maps=accel.linear_maps))
    elif entry == "same_words":  # numpy's compare instead
        assert got is True
    else:  # None: the caller uses numpy
        assert got is None
    assert accel.backend() == f"numpy (the compiled {entry} failed: RuntimeError: the kernel is unhappy)"
    fresh_state.module, fresh_state.failure = types.SimpleNamespace(**{entry: _broken}), None
    fresh_state.compiled.add(entry)
    with pytest.raises(RuntimeError, match="the kernel is unhappy"):
        calls[entry]()


def test_importing_accel_does_not_load_the_library() -> None:
    """The library is loaded on first use, not at import (Blender imports the add-on at every start),
    and loading it takes milliseconds (nothing is compiled on the user's machine)."""
    import os
    import subprocess

    _library_or_skip()
    code = (
        "import sys, time\n"
        "import affine_deformers.accel as a\n"
        "maps = open('/proc/self/maps').read() if sys.platform.startswith('linux') else ''\n"
        "assert a._state.module is None and a._state.failure is None\n"
        "assert 'affine_kernel' not in maps\n"
        "t0 = time.perf_counter()\n"
        "kernel = a._load()\n"
        "took = time.perf_counter() - t0\n"
        "assert kernel is not None, a.backend()\n"
        "maps = open('/proc/self/maps').read() if sys.platform.startswith('linux') else kernel.path.name\n"
        "assert kernel.path.name in maps\n"
        "print(took)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != accel.ACCEL_ENV}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env,
                         check=False)
    assert res.returncode == 0, res.stderr
    assert float(res.stdout.strip()) < 0.25


def test_calls_from_other_threads_use_numpy_while_the_kernel_warms_up(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An interactive update does not wait for `warm_up`: while it runs in a helper thread, other
    threads get the numpy kernel's result (and `active()` says so); afterwards the compiled one."""
    _library_or_skip()
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(50, 3))
    params = aff3.params_from_matrices(random_affine(rng, 3))
    idx, val = top_k_dense(rng.random((50, 3)), 2)
    expected_numpy = deform.DeformKernel(threads=1).deform(pts, params, idx, val, cache_weights=False)
    helper = threading.Thread(target=lambda: None)
    monkeypatch.setattr(accel._state, "warming", helper)  # as if `helper` were warming up right now
    assert not accel.active()
    assert np.array_equal(accel.deform_points_params(pts, params, idx, val), expected_numpy)
    monkeypatch.setattr(accel._state, "warming", None)
    assert accel.warm_up().startswith("C kernel (")
    assert accel.active() and accel._state.warming is None
    compiled = accel.deform_points_params(pts, params, idx, val)
    assert np.abs(compiled - expected_numpy).max() < 1e-12


#: Every Kernel entry `affine_deformers.accel` calls through `_run` or `_entry_call`.
ENTRIES = {"deform_points_entry", "motion_params", "polar_log", "node_pivot", "chain_points_entry",
           "chain_motion_entry", "cage_faces", "cage_nodes", "psi_rows", "rows_reading", "same_words",
           "spd_factor", "arap_frame"}


def test_warm_up_runs_every_entry_once(kernel: native.Kernel, fresh_state: accel._State) -> None:
    """warm_up runs each entry accel calls once (so one that fails does so there, not in the first
    update) and measures the helper threads' spin_wait; calls of every kind afterwards (full, rows,
    offsets, out32, float32 motions, int64 indices, the cage and chain entries) all run compiled."""
    source = "".join(path.read_text() for path in Path(accel.__file__).parent.glob("*.py"))
    assert set(re.findall(r"\b_(?:run|entry_call)\(\s*\"(\w+)\"", source)) == ENTRIES
    assert all(callable(getattr(native.Kernel, name, None)) for name in (*ENTRIES, "spin_wait"))
    assert accel.warm_up() == f"C kernel ({kernel.path.name}), {accel._threads()} thread" + (
        "s" * (accel._threads() != 1))
    assert fresh_state.compiled == ENTRIES and fresh_state.failure is None
    spin = fresh_state.spin
    assert spin and spin[0].__func__ is native.Kernel.spin_wait and spin[0].__self__ is fresh_state.module
    assert spin[1] >= 1
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
    accel.rows_reading(np.ones(8, bool), idx, val)
    accel.same_bits(pts, pts.copy())
    assert fresh_state.compiled == ENTRIES and fresh_state.failure is None and accel.active()


def test_spin_wait_returns_when_the_flag_changes_or_after_n_iterations(kernel: native.Kernel) -> None:
    """True as soon as flag[0] differs from `seen` (a store by another thread included: the wait
    releases the GIL), False after n iterations of an unchanged flag."""
    flag = np.array([5], dtype=np.int64)
    assert not kernel.spin_wait(flag, 5, 0)
    t0 = time.perf_counter()
    assert not kernel.spin_wait(flag, 5, 100_000)
    per_iteration = max((time.perf_counter() - t0) / 100_000, 1e-10)
    n = int(10.0 / per_iteration)  # ~10 s unless the flag changes
    t0 = time.perf_counter()
    assert kernel.spin_wait(flag, 4, n)  # already different: at once
    assert time.perf_counter() - t0 < 1.0
    result = []
    waiter = threading.Thread(target=lambda: result.append(kernel.spin_wait(flag, 5, n)))
    t0 = time.perf_counter()
    waiter.start()
    time.sleep(0.05)
    flag[0] = 6
    waiter.join(timeout=30.0)
    assert result == [True]
    assert time.perf_counter() - t0 < 5.0


# --------------------------------------------------------------------------------------------------
# vertex_motions: the compiled twin (motion_params) and its dispatch


def _motion_case(rng: np.random.Generator, n: int, m: int = 8) -> tuple[np.ndarray, ...]:
    _, params, idx, val = blend_case(rng, n, m)
    params[:2] = lifted_params(rng)[[1, 4]]  # fix-up rows as well
    return params, idx, val


@pytest.mark.parametrize("extra", [False, True])
def test_motions_match_aff3_and_the_numpy_kernel(kernel: native.Kernel, extra: bool) -> None:
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


def test_motions_of_random_blends(kernel: native.Kernel) -> None:
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


def test_motions_of_lifted_rotations_up_to_14_pi(kernel: native.Kernel) -> None:
    params, _, tol = lifted_sweep()
    idx = np.arange(len(params), dtype=np.int32)[:, None]
    assert_motions_match_reference(params, accel.vertex_motions(params, idx, np.ones((len(params), 1))), tol)


def test_motion_rows_are_bit_identical_to_the_full_call(kernel: native.Kernel) -> None:
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
    kernel: native.Kernel, monkeypatch: pytest.MonkeyPatch
) -> None:
    rng = np.random.default_rng(124)
    n = 4 * CHUNK + 3
    params, idx, val = _motion_case(rng, n)
    rows = np.flatnonzero(rng.random(n) < 0.5).astype(np.intp)
    results = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv(deform.THREADS_ENV, threads)
        full = accel.vertex_motions(params, idx, val)
        sub = np.zeros((4, n, 3), dtype=np.float32)
        accel.vertex_motions(params, idx, val, sub, rows=rows)
        results.append((full, sub))
    for other in results[1:]:
        assert np.array_equal(results[0][0], other[0])
        assert np.array_equal(results[0][1].view(np.uint32), other[1].view(np.uint32))


@pytest.mark.parametrize("use_kernel", [True, False])
def test_motions_float32_out_is_the_rounded_float64(
    use_kernel: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A float32 out gets the float64 result rounded once (astype's rounding, full call and rows)."""
    _backend(use_kernel, monkeypatch)
    rng = np.random.default_rng(125)
    n = 2 * CHUNK + 33
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


@pytest.mark.parametrize("use_kernel", [True, False])
def test_motions_float32_rounding_at_ties_overflow_and_subnormals(
    use_kernel: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Pure translations give t = u exactly, so the translations are chosen doubles: their float32 is
    numpy's cast of them, bit for bit (±inf included); M is the identity."""
    _backend(use_kernel, monkeypatch)
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


@pytest.mark.parametrize("use_kernel", [True, False])
def test_motions_of_zero_params_are_the_identity(use_kernel: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    _backend(use_kernel, monkeypatch)
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


def test_motions_out_layouts_and_keys(kernel: native.Kernel) -> None:
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


@pytest.mark.parametrize("use_kernel", [True, False])
@pytest.mark.parametrize(("kwargs", "message"), [*MOTION_BAD_ARGUMENTS])
def test_motions_bad_arguments_raise_the_core_messages(
    kwargs: dict, message: str, use_kernel: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    _backend(use_kernel, monkeypatch)
    with pytest.raises(ValueError, match=message):
        motion_bad_call(accel.vertex_motions, kwargs)


def test_motions_fall_back_to_numpy(monkeypatch: pytest.MonkeyPatch, fresh_state: accel._State) -> None:
    """AFFINE_DEFORMERS_ACCEL=0 gives the numpy kernel's values; a failure of motion_params on its first call
    switches the process to numpy with correct results, like the other entry points."""
    rng = np.random.default_rng(128)
    params, idx, val = _motion_case(rng, 300)
    want = deform.vertex_motions(params, idx, val)
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    assert np.array_equal(accel.vertex_motions(params, idx, val), want)
    assert fresh_state.module is None and fresh_state.failure is None  # never tried to load the library

    monkeypatch.delenv(accel.ACCEL_ENV)
    monkeypatch.setattr(fresh_state, "module", types.SimpleNamespace(motion_params=_broken, CHUNK=CHUNK))
    rows = np.array([3, 1, 200])
    out = np.full((4, 300, 3), 9.0)
    with pytest.warns(UserWarning, match="the kernel is unhappy"):
        accel.vertex_motions(params, idx, val, out, rows=rows)
    assert np.array_equal(out[:, rows], want[:, rows])
    assert np.all(np.delete(out, rows, axis=1) == 9.0)
    assert accel.backend() == "numpy (the compiled motion_params failed: RuntimeError: the kernel is unhappy)"


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


def test_every_lifted_row_alone_equals_its_row_in_a_full_chunk(kernel: native.Kernel) -> None:
    """θ > 1.8π: each such row recomputed alone (column 0 of a one-row chunk) has the bits of the full
    call, points (plain, offsets, float32 copy) and motions — all of them, not a sample: a vectorised
    fix-up loop gives a row other bits in the vector body than in the scalar remainder."""
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


def test_rigid_blends_take_the_small_form_with_the_same_bits_in_any_chunk(kernel: native.Kernel) -> None:
    """Rows whose blended Y is small (rigid controls) take the Taylor form of exp(Y) in a loop of
    their own: as accurate as the closed form, and a row has the same bits in a chunk of small rows
    only, in a mixed one and alone (points: plain, offsets, float32 copy; motions), θ > 1.8π rows
    through the fix-up included (both kernels draw the line at the same SMALL_Y:
    `test_the_c_constants_are_the_python_ones`)."""
    rng = np.random.default_rng(132)
    n = 3 * CHUNK + 17
    pts, table, idx, val = test_deform.rigid_case(rng, n)
    P = deform.blend_params(table, idx, val)
    is_small = np.all(np.abs(P[:, 6:]) <= deform.SMALL_Y, axis=1)
    small, other = np.flatnonzero(is_small), np.flatnonzero(~is_small)
    lifted = np.einsum("ij,ij->i", P[:, :3], P[:, :3]) > POLY_MAX_S
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


#: The column forms of a chunk in the C kernel: exp(Y) by its cubic Taylor polynomial (every
#: |Y_ij| ≤ SMALL_Y) or the closed form, each with θ ≤ 1.8π (polynomials) or θ > 1.8π (redone with
#: libm sin/cos, the fix-up).
FORMS = ("small", "closed", "lifted closed", "lifted small")


def _theta_edges() -> tuple[float, float]:
    """(a, b): consecutive doubles with a² ≤ POLY_MAX_S < b² (ω = (a, 0, 0) is the last polynomial
    θ, ω = (b, 0, 0) the first fix-up one)."""
    a = math.sqrt(POLY_MAX_S)
    while a * a > POLY_MAX_S:
        a = math.nextafter(a, 0.0)
    while math.nextafter(a, math.inf) ** 2 <= POLY_MAX_S:
        a = math.nextafter(a, math.inf)
    return a, math.nextafter(a, math.inf)


def forms_of(params: np.ndarray) -> np.ndarray:
    """The FORMS name of each parameter row, by the C kernel's tests."""
    small = np.all(np.abs(params[:, 6:]) <= deform.SMALL_Y, axis=1)
    w = params[:, :3]
    lifted = w[:, 0] * w[:, 0] + w[:, 1] * w[:, 1] + w[:, 2] * w[:, 2] > POLY_MAX_S  # as the C code sums
    return np.where(lifted, np.where(small, "lifted small", "lifted closed"),
                    np.where(small, "small", "closed"))


def forms_case(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(points, params): one parameter row per vertex (with weight 1 the row is the vertex's blend),
    more than a chunk of each of the first three FORMS and 400 of the last, shuffled; among them the
    edges: every |Y_ij| exactly SMALL_Y (small) and one of them an ulp beyond (closed), θ² on either
    side of POLY_MAX_S, θ = 0 and tiny, Y = 0."""
    small_y = deform.SMALL_Y
    below, above = _theta_edges()
    blocks = []
    for form, count in (("small", CHUNK + 150), ("closed", CHUNK + 150), ("lifted closed", CHUNK + 150),
                        ("lifted small", 400)):
        lifted, small = form.startswith("lifted"), form.endswith("small")
        theta = rng.uniform(*((1.8 * np.pi, 6.0 * np.pi) if lifted else (0.0, 1.8 * np.pi)), count)
        axis = rng.normal(size=(count, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        w = theta[:, None] * axis
        if small:  # rigid controls: Y is noise, or zero
            y6 = rng.uniform(-small_y, small_y, size=(count, 6))
            y6 *= rng.choice([1.0, 1e-4, 0.0], size=(count, 1))
        else:
            y6 = np.array([sym6(tuple(rng.normal(scale=0.5, size=3)), aff3.so3_exp(rng.normal(size=3)))
                           for _ in range(count)])
        y6[3:9] = small_y * rng.choice([-1.0, 1.0], size=(6, 6))  # on the line: small
        if not small:
            for j in range(6):  # one entry an ulp beyond: closed
                y6[3 + j, j] = np.nextafter(y6[3 + j, j], 2.0 * y6[3 + j, j])
        w[9] = (above if lifted else below, 0.0, 0.0)
        w[10] = (0.0, 0.0, -(above if lifted else below))
        if not lifted:
            w[11:13] = (0.0, 0.0, 0.0), (1e-12, 0.0, -1e-12)
        blocks.append(np.concatenate([w, rng.normal(scale=3.0, size=(count, 3)), y6], axis=1))
        assert np.all(forms_of(blocks[-1]) == form)
    params = rng.permutation(np.concatenate(blocks))
    return rng.normal(scale=3.0, size=(len(params), 3)), params


def test_chunks_mixing_the_column_forms_give_every_row_its_own_bits(
    kernel: native.Kernel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A chunk computes the Taylor form where every column is small, the closed form where none is,
    both (each column taking its own) where they mix, and redoes θ > 1.8π columns with libm: a
    row's bits do not depend on which of these its chunk needed — full call (mixed chunks), rows of
    one form only, a chunk of exactly CHUNK rows of one form (one loop only), reversed, each row
    alone (column 0 of a chunk of zeros), 1 or 2 threads; for points (plain, offsets, float32 copy),
    motions (float64, float32) and the chain entries (two passes, a prefix). Every row matches the
    reference and the numpy kernel."""
    rng = np.random.default_rng(133)
    pts, params = forms_case(rng)
    n = len(params)
    form = forms_of(params)
    idx = np.arange(n, dtype=np.int32)[:, None]
    one = np.ones((n, 1))
    prefixes = np.concatenate([np.eye(3).ravel(), np.zeros(3)])[None].repeat(3, axis=0)
    prefixes[1:, :9] += 0.2 * rng.normal(size=(2, 9))
    prefixes[1:, 9:] = rng.normal(size=(2, 3))
    chain = (np.stack([idx, idx]), np.stack([one, one]), (np.arange(n) % 3).astype(np.int32), prefixes)

    def compute(rows: np.ndarray | None) -> dict[str, np.ndarray]:
        """Every output for `rows` (None: full calls), as (len(rows), ...) arrays."""
        sel = np.arange(n) if rows is None else rows
        res = {}
        if rows is None:
            res["points"] = accel.deform_points_params(pts, params, idx, one)[sel]
            res["motions"] = accel.vertex_motions(params, idx, one)[:, sel]
            res["motions32"] = accel.vertex_motions(params, idx, one, np.zeros((4, n, 3), np.float32))[:, sel]
            res["chain"] = accel.chain_points(pts, params, *chain)[sel]
            res["chain motions"] = accel.chain_motions(params, *chain)[:, sel]
            return res
        out, off, out32 = np.full((n, 3), 7.0), np.full((n, 3), 7.0), np.zeros((n, 3), np.float32)
        accel.deform_points_params_rows(pts, params, idx, one, rows, out, key="forms")
        accel.deform_points_params_rows(pts, params, idx, one, rows, off, offsets=True, out32=out32,
                                        key="forms")
        assert np.array_equal(off[sel], out[sel] - pts[sel])
        assert np.array_equal(_bits(out32[sel]), _bits(off[sel].astype(np.float32)))
        res["points"] = out[sel]
        res["motions"] = accel.vertex_motions(params, idx, one, rows=rows, key="forms")[:, sel]
        res["motions32"] = accel.vertex_motions(params, idx, one, np.zeros((4, n, 3), np.float32), rows=rows,
                                                key="forms")[:, sel]
        cp = np.full((n, 3), 7.0)
        accel.chain_points(pts, params, *chain, rows, cp, key="forms-chain")
        res["chain"] = cp[sel]
        res["chain motions"] = accel.chain_motions(params, *chain, rows=rows, key="forms-chain")[:, sel]
        return res

    full = compute(None)
    P = params
    theta = np.linalg.norm(P[:, :3], axis=1)
    tol = 5e-15 * np.maximum(1.0, theta / (2.0 * np.pi))  # |ω| itself carries ε θ
    err = np.linalg.norm(full["points"] - reference(pts, P), axis=1) / vertex_scale(pts, P)
    worst = int(np.argmax(err / tol))
    assert np.all(err <= tol), f"row {worst} ({form[worst]}): {err[worst]:.2e}"
    assert_motions_match_reference(P, full["motions"], tol)
    numpy_points = deform.deform_points_params(pts, P, idx, one, cache_weights=False)
    np_err = np.linalg.norm(full["points"] - numpy_points, axis=1) / vertex_scale(pts, P)
    assert np.all(np_err <= tol)
    want = deform.vertex_motions(P, idx, one)
    scale = np.linalg.norm(want[:3], axis=(0, 2)) + np.linalg.norm(want[3], axis=1)
    assert np.all(np.abs(full["motions"] - want).max(axis=(0, 2)) / scale <= tol)
    assert np.array_equal(_bits(full["motions32"]), _bits(full["motions"].astype(np.float32)))
    # one pass with the identity prefix is the point map itself
    ident = np.zeros((n,), np.int32)
    single = (idx[None], one[None], ident, prefixes[:1])
    assert np.array_equal(accel.chain_points(pts, params, *single), full["points"])
    assert np.array_equal(accel.chain_motions(params, *single), full["motions"])

    by_form = {f: np.flatnonzero(form == f) for f in FORMS}
    assert all(len(by_form[f]) > CHUNK for f in FORMS[:3])
    subsets = {
        **{f"{f} only": rows for f, rows in by_form.items()},
        **{f"one chunk of {f}": by_form[f][:CHUNK] for f in FORMS[:3]},  # no column of another form
        "one chunk of small and lifted small": np.sort(np.r_[by_form["small"][: CHUNK - 400],
                                                             by_form["lifted small"]]),
        "reversed": np.arange(n)[::-1].copy(),
        "every third": np.arange(1, n, 3),
    }
    for name, rows in subsets.items():
        got = compute(rows)
        for key, value in got.items():
            want = full[key][:, rows] if "motions" in key else full[key][rows]
            assert np.array_equal(value, want), (name, key)
    alone = np.concatenate([rng.choice(rows, 12, replace=False) for rows in by_form.values()])
    edges = np.flatnonzero((np.abs(P[:, 6:]).max(axis=1) >= deform.SMALL_Y)
                           & (np.abs(P[:, 6:]).max(axis=1) <= np.nextafter(deform.SMALL_Y, 1.0)))
    theta_sq = P[:, 0] * P[:, 0] + P[:, 1] * P[:, 1] + P[:, 2] * P[:, 2]
    near = np.flatnonzero(np.abs(theta_sq - POLY_MAX_S) <= 4 * np.spacing(POLY_MAX_S))
    assert len(edges) >= 24 and len(near) >= 8
    for r in np.unique(np.r_[alone, edges, near]):
        got = compute(np.array([r]))
        for key, value in got.items():
            assert np.array_equal(value, full[key][:, [r]] if "motions" in key else full[key][[r]]), (r, key)
    # and the thread count
    for threads in ("1", "2"):
        monkeypatch.setenv(deform.THREADS_ENV, threads)
        again = compute(None)
        for key, value in again.items():
            assert np.array_equal(value, full[key]), (threads, key)


# --------------------------------------------------------------------------------------------------
# polar_log: the polar split of ψ (a cage's corner tetrahedra)


def test_polar_log_matches_numpys_svd(kernel: native.Kernel) -> None:
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


def test_compiled_psi_matches_numpy_and_scipy(kernel: native.Kernel) -> None:
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


def test_compiled_node_params_match_the_numpy_blend(kernel: native.Kernel) -> None:
    """`accel.node_params` (the per-face and per-node steps of the harmonic cage's pivoted node blend
    in the compiled kernel) agrees with `core.harmonic.node_params` to ~1e-15 relative: small
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


def test_same_bits_is_a_bitwise_compare(kernel: native.Kernel) -> None:
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


def test_rows_reading_matches_numpy(kernel: native.Kernel) -> None:
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
