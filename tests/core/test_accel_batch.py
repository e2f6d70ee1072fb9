"""accel.KernelBatch / accel.collecting: the row calls of many deformers collected during an update
and run in one hand-over give bit for bit what each call gives run at once, in any thread count,
and the calls whose output must be read at once are never deferred."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from affine_deformers import accel
from affine_deformers.accel import threads
from tests.core.test_accel import CHUNK, blend_case, kernel, lifted_params  # noqa: F401  (fixture)


def _cases(rng: np.random.Generator) -> list[tuple[np.ndarray, ...]]:
    """Meshes of several sizes around the chunk, each with its own table and rows (one empty)."""
    cases = []
    for n, share in ((5, 1.0), (CHUNK - 1, 0.5), (CHUNK + 1, 1.0), (3 * CHUNK + 17, 0.3), (40, 0.0)):
        pts, params, idx, val = blend_case(rng, n, m=6, k=3)
        params[:2] = lifted_params(rng)[[0, 5]]
        rows = np.flatnonzero(rng.random(n) < share)
        cases.append((pts, params, idx, val, rows))
    return cases


@pytest.mark.parametrize("count", [1, 2, 3])
def test_a_batch_gives_each_call_its_own_results_bit_for_bit(kernel, monkeypatch, count: int) -> None:  # noqa: F811
    monkeypatch.setattr(threads, "_threads", lambda: count)
    rng = np.random.default_rng(7)
    cases = _cases(rng)
    alone, alone32, motions_alone = [], [], []
    for pts, params, idx, val, rows in cases:
        out, out32 = np.full((len(pts), 3), 5.0), np.full((len(pts), 3), 5.0, dtype=np.float32)
        accel.deform_points_params_rows(pts, params, idx, val, rows, out, offsets=True, out32=out32)
        alone.append(out)
        alone32.append(out32)
        motions = np.full((4, len(pts), 3), 3.0, dtype=np.float32)
        motions_alone.append(accel.vertex_motions(params, idx, val, out=motions, rows=rows))
    batch = accel.KernelBatch()
    outs, outs32, motions_batched = [], [], []
    with accel.collecting(batch):
        for pts, params, idx, val, rows in cases:
            out, out32 = np.full((len(pts), 3), 5.0), np.full((len(pts), 3), 5.0, dtype=np.float32)
            # temporaries: the batch keeps what its calls point into alive
            accel.deform_points_params_rows(pts.copy(), params.copy(), idx.copy(), val.copy(), rows.copy(),
                                             out, offsets=True, out32=out32)
            motions = np.full((4, len(pts), 3), 3.0, dtype=np.float32)
            accel.vertex_motions(params, idx, val, out=motions, rows=rows)
            outs.append(out)
            outs32.append(out32)
            motions_batched.append(motions)
    assert len(batch) == 2 * len(cases)
    assert all(np.all(out == 5.0) for out in outs), "nothing is computed before the batch runs"
    batch.run()
    assert len(batch) == 0
    for want, got in zip(alone + alone32 + motions_alone, outs + outs32 + motions_batched, strict=True):
        assert want.tobytes() == got.tobytes()
    batch.run()  # an empty batch does nothing


def test_calls_whose_output_is_read_at_once_are_not_deferred(kernel) -> None:  # noqa: F811
    rng = np.random.default_rng(8)
    pts, params, idx, val = blend_case(rng, 300)
    rows = np.arange(0, 300, 3)
    want = accel.deform_points_params(pts, params, idx, val)
    batch = accel.KernelBatch()
    with accel.collecting(batch):
        full = accel.deform_points_params(pts, params, idx, val)  # a full call: its caller reads it
        strided = np.full((300, 6), 9.0)[:, ::2]  # not C-contiguous: copied back after the call
        accel.deform_points_params_rows(pts, params, idx, val, rows, strided)
        motions = accel.vertex_motions(params, idx, val)  # no rows
    assert len(batch) == 0
    assert np.array_equal(full, want)
    assert np.array_equal(strided[rows], want[rows])
    assert np.array_equal(motions, accel.vertex_motions(params, idx, val))


def test_only_the_collecting_thread_defers_and_blocks_nest(kernel) -> None:  # noqa: F811
    rng = np.random.default_rng(9)
    pts, params, idx, val = blend_case(rng, 200)
    rows = np.arange(200)
    outer, inner = accel.KernelBatch(), accel.KernelBatch()
    other = np.zeros((200, 3))

    def elsewhere() -> None:
        accel.deform_points_params_rows(pts, params, idx, val, rows, other)

    with accel.collecting(outer):
        with accel.collecting(inner):
            accel.deform_points_params_rows(pts, params, idx, val, rows, np.zeros((200, 3)))
        accel.deform_points_params_rows(pts, params, idx, val, rows, np.zeros((200, 3)))
        with accel.collecting(None):  # None: at once
            now = np.zeros((200, 3))
            accel.deform_points_params_rows(pts, params, idx, val, rows, now)
        thread = threading.Thread(target=elsewhere)
        thread.start()
        thread.join()
    assert (len(outer), len(inner)) == (1, 1)
    want = accel.deform_points_params(pts, params, idx, val)
    assert np.array_equal(now, want)
    assert np.array_equal(other, want)
    outer.run()
    inner.run()


def test_without_the_compiled_kernel_nothing_is_deferred(monkeypatch) -> None:
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    rng = np.random.default_rng(10)
    pts, params, idx, val = blend_case(rng, 100)
    out = np.zeros((100, 3))
    batch = accel.KernelBatch()
    with accel.collecting(batch):
        accel.deform_points_params_rows(pts, params, idx, val, np.arange(100), out)
    assert len(batch) == 0
    assert np.array_equal(out, accel.deform_points_params(pts, params, idx, val))


def test_a_pinned_block_runs_on_the_backend_it_started_with(kernel, monkeypatch) -> None:  # noqa: F811
    """accel.pinned: an update's calls all see the backend of its start, the environment read once;
    other threads and the time after the block see the current one."""
    seen = []
    with accel.pinned():
        monkeypatch.setenv(accel.ACCEL_ENV, "0")
        assert accel.active()
        with accel.pinned():  # nested: the outer pin holds
            assert accel.active()
        thread = threading.Thread(target=lambda: seen.append(accel.active()))
        thread.start()
        thread.join()
    assert seen == [False]
    assert not accel.active()
    with accel.pinned():
        monkeypatch.delenv(accel.ACCEL_ENV)
        assert not accel.active()
    assert accel.active()


def test_chain_rows_in_a_batch_are_the_rows_computed_at_once(kernel) -> None:  # noqa: F811
    """The bones' blend down a hierarchy (accel.chain_points / chain_motions with rows) batched as the
    vertex map is: the same bits as at once."""
    rng = np.random.default_rng(11)
    n, passes = CHUNK + 300, 2
    pts, params, idx, val = blend_case(rng, n, m=5, k=3)
    idx3 = np.stack([idx, np.roll(idx, 1, axis=0)])[:passes]
    val3 = np.stack([val, val[::-1]])[:passes]
    prefix = rng.integers(0, 3, n).astype(np.int32)
    prefixes = np.eye(4)[:3].T.reshape(1, 12).repeat(3, axis=0)
    prefixes[:, 9:] = rng.normal(size=(3, 3))
    rows = np.flatnonzero(rng.random(n) < 0.6)
    chain = (idx3, val3, prefix, prefixes)
    alone = accel.chain_points(pts, params, *chain, rows, np.full((n, 3), 2.0), offsets=True)
    alone_m = accel.chain_motions(params, *chain, np.full((4, n, 3), 2.0, np.float32), rows=rows)
    batch = accel.KernelBatch()
    out, out_m = np.full((n, 3), 2.0), np.full((4, n, 3), 2.0, np.float32)
    with accel.collecting(batch):
        accel.chain_points(pts, params, *chain, rows, out, offsets=True)
        accel.chain_motions(params, *chain, out_m, rows=rows)
        full = accel.chain_points(pts, params, *chain)  # no rows: at once
    assert len(batch) == 2
    assert np.all(out == 2.0) and np.all(out_m == 2.0)
    batch.run()
    assert out.tobytes() == alone.tobytes()
    assert out_m.tobytes() == alone_m.tobytes()
    assert np.array_equal(full[rows] - pts[rows], alone[rows])
