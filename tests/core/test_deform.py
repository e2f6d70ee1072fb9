"""The per-vertex kernel (core/deform.py, kernel.py, kernel_stages.py) against the reference
φ(Σ w ψ(A)) v built from aff3."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affine_deformers import core
from affine_deformers.core import aff3, deform, kernel_stages
from affine_deformers.core import kernel as core_kernel
from affine_deformers.core.weights import top_k_dense
from tests.core.conftest import random_affine

# Rotation angles the kernel must handle: series/clamp regions, the polynomial range (θ ≤ 1.8π),
# the np.sin fallback beyond it (lifted rotations), and exactly π.
KERNEL_ANGLES = (
    0.0,
    1e-12,
    1e-8,
    1e-5,
    0.1,
    1.0,
    np.pi / 2,
    np.pi - 1e-9,
    np.pi,
    1.7 * np.pi,
    1.9 * np.pi,
    3.0 * np.pi,
)
# Stretch spectra (of Y = log S): zero, uniform, repeated, clustered at every gap, anisotropy 1e3:1e-3.
KERNEL_SPECTRA = (
    (0.0, 0.0, 0.0),
    (0.7, 0.7, 0.7),
    (0.3, 0.3, 2.0),
    (-1.0, 0.5, 0.5),
    (-6.9, 0.0, 6.9),
    (-6.9, -6.9, 6.9),
    *[(0.3, 0.3 + g, 1.0) for g in (1e-1, 1e-4, 1e-8, 1e-12)],
    *[(0.2, 0.2 + g, 0.2 + 2 * g) for g in (1e-3, 1e-9)],
)


def reference(points: np.ndarray, blended: np.ndarray) -> np.ndarray:
    """v' = φ(p_v) v per vertex with aff3's matrices (np.sin/np.cos, series, divided differences)."""
    A = aff3.matrices_from_params(blended)
    return np.einsum("nij,nj->ni", A[:, :3, :3], points) + A[:, :3, 3]


def vertex_scale(points: np.ndarray, blended: np.ndarray) -> np.ndarray:
    """‖M‖‖v‖ + ‖t‖ per vertex: the size of the terms the result is made of."""
    A = aff3.matrices_from_params(blended)
    return np.linalg.norm(A[:, :3, :3], axis=(1, 2)) * np.linalg.norm(points, axis=1) + np.linalg.norm(
        A[:, :3, 3], axis=1
    )


def assert_matches_reference(
    points: np.ndarray, blended: np.ndarray, got: np.ndarray, tol: float = 1e-12
) -> None:
    ref = reference(points, blended)
    err = np.linalg.norm(got - ref, axis=1) / vertex_scale(points, blended)
    assert err.max() <= tol, f"worst vertex {int(err.argmax())}: {err.max():.3e}"


def sym6(eigs: tuple[float, float, float], frame: np.ndarray) -> np.ndarray:
    return aff3.sym_to6(frame @ np.diag(eigs) @ frame.T)


def adversarial_params() -> np.ndarray:
    """One parameter row per (angle, spectrum, translation) combination."""
    rng = np.random.default_rng(31)
    rows = []
    for i, angle in enumerate(KERNEL_ANGLES):
        for j, eigs in enumerate(KERNEL_SPECTRA):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            frame = aff3.so3_exp(rng.normal(size=3))
            u = rng.normal(size=3) * (0.0, 1e-3, 1.0, 1e3)[(i + j) % 4]
            rows.append(np.concatenate([angle * axis, u, sym6(eigs, frame)]))
    return np.array(rows)


@pytest.fixture(scope="module")
def cloud() -> np.ndarray:
    return np.random.default_rng(2).uniform(-3.0, 3.0, size=(4000, 3))


# --------------------------------------------------------------------------------------------------


def test_kernel_matches_phi_on_adversarial_parameters() -> None:
    P = adversarial_params()
    rng = np.random.default_rng(4)
    points = rng.uniform(-10.0, 10.0, size=(P.shape[0], 3))
    # one control per vertex with weight 1: the kernel sees exactly these parameters
    idx = np.arange(P.shape[0], dtype=np.int32)[:, None]
    got = deform.deform_points_params(points, P, idx, np.ones((P.shape[0], 1)))
    assert_matches_reference(points, P, got)


def test_kernel_matches_phi_on_random_blends(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(5)
    A = random_affine(rng, 8, log_scale=1.0, t_scale=5.0)
    params = aff3.params_from_matrices(A)
    W = rng.random((cloud.shape[0], 8)) ** 3
    idx, val = top_k_dense(W, 4)
    got = deform.deform_points_params(cloud, params, idx, val)
    assert_matches_reference(cloud, deform.blend_params(params, idx, val), got)


def test_dense_contract_matches_sparse_and_reference(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(6)
    A = random_affine(rng, 5)
    W = rng.random((cloud.shape[0], 5))
    W /= W.sum(axis=1, keepdims=True)
    dense = core.deform_points(cloud, A, W)
    params = aff3.params_from_matrices(A)
    assert_matches_reference(cloud, W @ params, dense)
    idx = np.broadcast_to(np.arange(5, dtype=np.int32), (cloud.shape[0], 5))
    sparse = core.deform_points_params(cloud, params, idx, W)
    np.testing.assert_allclose(sparse, dense, rtol=0, atol=1e-13 * np.abs(dense).max())


def test_zero_params_return_the_input_bit_for_bit(cloud: np.ndarray) -> None:
    pts = cloud.copy()
    pts[:3] = [[-0.0, 0.0, -0.0], [1e-320, -1e-320, 5e-324], [1e300, -1e300, 7.0]]
    idx = np.zeros((pts.shape[0], 4), dtype=np.int32)
    val = np.random.default_rng(7).random((pts.shape[0], 4))
    got = deform.deform_points_params(pts, np.zeros((6, 12)), idx, val)
    assert got.tobytes() == pts.tobytes()  # signed zeros and subnormals included
    f32 = pts[3:].astype(np.float32)
    assert np.array_equal(deform.deform_points_params(f32, np.zeros((6, 12)), idx[3:], val[3:]), f32)
    assert (
        deform.blend_linear_sparse(pts, np.broadcast_to(np.eye(4), (6, 4, 4)), idx, val).tobytes()
        == pts.tobytes()
    )


def test_zero_weights_leave_vertices_in_place(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(8)
    params = aff3.params_from_matrices(random_affine(rng, 3))
    idx = rng.integers(0, 3, size=(cloud.shape[0], 2)).astype(np.int32)
    val = np.zeros((cloud.shape[0], 2))
    val[::2, 0] = 0.5  # half the vertices move, the others must not
    got = deform.deform_points_params(cloud, params, idx, val)
    assert np.array_equal(got[1::2], cloud[1::2])
    assert np.all(np.linalg.norm(got[::2] - cloud[::2], axis=1) > 0)


def test_common_motion_is_reproduced(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(9)
    A = random_affine(rng, 1, log_scale=1.5, t_scale=20.0)[0]
    params = np.broadcast_to(aff3.params_from_matrices(A), (4, 12))
    W = rng.random((cloud.shape[0], 4))
    idx, val = top_k_dense(W, 4, normalize="SUM")
    got = deform.deform_points_params(cloud, params, idx, val)
    ref = cloud @ A[:3, :3].T + A[:3, 3]
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * (np.abs(ref).max() + 1))


def test_rigid_controls_give_a_rigid_result(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(10)
    w = rng.normal(size=(5, 3))
    w *= (rng.uniform(0.0, np.pi, 5) / np.linalg.norm(w, axis=1))[:, None]
    A = np.broadcast_to(np.eye(4), (5, 4, 4)).copy()
    A[:, :3, :3] = aff3.so3_exp(w)
    A[:, :3, 3] = rng.normal(size=(5, 3)) * 4.0
    # every vertex of a patch shares the same weights: the patch must move rigidly
    patch = cloud[:200]
    weights = np.broadcast_to(rng.dirichlet(np.ones(5)), (200, 5))
    moved = core.deform_points(patch, A, weights)
    d0 = np.linalg.norm(patch[:, None] - patch[None], axis=-1)
    d1 = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    np.testing.assert_allclose(d1, d0, rtol=0, atol=1e-13 * d0.max())
    e = np.cross(patch[1] - patch[0], patch[2] - patch[0]) @ (patch[3] - patch[0])
    f = np.cross(moved[1] - moved[0], moved[2] - moved[0]) @ (moved[3] - moved[0])
    assert np.sign(e) == np.sign(f)  # no reflection


def test_results_do_not_depend_on_chunks_or_threads(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(11)
    params = aff3.params_from_matrices(random_affine(rng, 6))
    idx, val = top_k_dense(rng.random((cloud.shape[0], 6)), 3)
    base = deform.DeformKernel(chunk_size=16384, threads=1).deform(cloud, params, idx, val)
    for chunk, threads in ((7, 1), (1000, 3), (333, 2)):
        got = deform.DeformKernel(chunk_size=chunk, threads=threads).deform(cloud, params, idx, val)
        np.testing.assert_allclose(got, base, rtol=1e-15, atol=1e-15)


def test_many_controls_take_the_gather_path(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(12)
    m = deform.DENSE_BLEND_MAX_CONTROLS + 10
    params = aff3.params_from_matrices(random_affine(rng, m, log_scale=0.3, t_scale=1.0))
    idx, val = top_k_dense(rng.random((cloud.shape[0], m)) ** 8, 4)
    got = deform.deform_points_params(cloud, params, idx, val)
    assert_matches_reference(cloud, deform.blend_params(params, idx, val), got)


def test_duplicate_indices_in_a_row_add_up() -> None:
    params = aff3.params_from_matrices(random_affine(np.random.default_rng(13), 2))
    pts = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]])
    idx = np.array([[1, 1], [0, 1]], dtype=np.int32)
    val = np.array([[0.25, 0.75], [0.5, 0.5]])
    got = deform.deform_points_params(pts, params, idx, val)
    blended = np.array([params[1], 0.5 * params[0] + 0.5 * params[1]])
    assert_matches_reference(pts, blended, got)


def test_out_argument_and_in_place(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(14)
    params = aff3.params_from_matrices(random_affine(rng, 3))
    idx, val = top_k_dense(rng.random((cloud.shape[0], 3)), 2)
    expected = deform.deform_points_params(cloud, params, idx, val)
    out = np.empty_like(cloud)
    assert deform.deform_points_params(cloud, params, idx, val, out=out) is out
    assert np.array_equal(out, expected)
    pts = cloud.copy()
    deform.deform_points_params(pts, params, idx, val, out=pts)
    assert np.array_equal(pts, expected)
    with pytest.raises(ValueError, match="out must be"):
        deform.deform_points_params(cloud, params, idx, val, out=np.empty((3, 3)))


def test_linear_blend_mode(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(15)
    A = random_affine(rng, 4)
    idx, val = top_k_dense(rng.random((cloud.shape[0], 4)), 3, normalize="NONE")
    val *= 0.5
    got = deform.blend_linear_sparse(cloud, A, idx, val)
    T = np.einsum("nk,nkij->nij", val, A[idx]) + (1.0 - val.sum(1))[:, None, None] * np.eye(4)
    ref = np.einsum("nij,nj->ni", T[:, :3, :3], cloud) + T[:, :3, 3]
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    # weights summing to 1 on a common matrix give that matrix
    common = deform.blend_linear_sparse(
        cloud, np.broadcast_to(A[0], (4, 4, 4)), idx, val / val.sum(1, keepdims=True)
    )
    np.testing.assert_allclose(
        common, cloud @ A[0, :3, :3].T + A[0, :3, 3], rtol=0, atol=1e-12 * np.abs(ref).max()
    )


#: Arguments that must be refused, with the message (core.deform; accel reuses it for its dispatch).
BAD_ARGUMENTS = [
    ({"points": np.zeros((4, 2))}, r"points must have shape \(N, 3\)"),
    ({"points": np.full((4, 3), np.nan)}, "non-finite coordinates"),
    ({"params": np.zeros((3, 11))}, r"params must have shape \(m, 12\)"),
    (
        {"params": np.where(np.arange(36).reshape(3, 12) == 13, np.inf, 0.0)},
        "params row 1 has non-finite",
    ),
    ({"indices": np.full((4, 2), 3, dtype=np.int32)}, r"indices must lie in \[0, 3\)"),
    ({"indices": np.full((4, 2), -1, dtype=np.int32)}, r"indices must lie in \[0, 3\)"),
    ({"indices": np.zeros((4, 2))}, "indices must be integers"),
    (
        {"indices": np.zeros((5, 2), dtype=np.int32), "values": np.zeros((5, 2))},
        r"indices must have shape \(4, K\)",
    ),
    ({"indices": np.zeros(4, dtype=np.int32)}, r"indices must have shape \(4, K\)"),
    ({"values": np.zeros((4, 3))}, "indices and values must both have shape"),
    ({"values": np.full((4, 2), np.nan)}, "weight values contain non-finite"),
]


@pytest.mark.parametrize(("kwargs", "message"), BAD_ARGUMENTS)
def test_bad_arguments_raise_value_error(kwargs: dict, message: str) -> None:
    args = {
        "points": np.zeros((4, 3)),
        "params": np.zeros((3, 12)),
        "indices": np.zeros((4, 2), dtype=np.int32),
        "values": np.ones((4, 2)),
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        deform.deform_points_params(args["points"], args["params"], args["indices"], args["values"])


def test_dense_contract_rejects_bad_transforms() -> None:
    A = np.broadcast_to(np.eye(4), (3, 4, 4)).copy()
    A[2, 0, 0] = -1.0
    with pytest.raises(ValueError, match="transform 2 has determinant"):
        core.deform_points(np.zeros((2, 3)), A, np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"weights must have shape \(2, 3\)"):
        core.deform_points(np.zeros((2, 3)), np.eye(4)[None].repeat(3, 0), np.ones((2, 2)))


def test_empty_input() -> None:
    got = deform.deform_points_params(
        np.zeros((0, 3)), np.ones((2, 12)), np.zeros((0, 2), np.int32), np.zeros((0, 2))
    )
    assert got.shape == (0, 3)


@settings(max_examples=100, deadline=None)
@given(
    st.integers(1, 6),
    st.integers(1, 4),
    st.sampled_from([0.0, 1e-9, 0.3, 1.5]),
    st.sampled_from([0.5, 1.0, 3.0]),
    st.integers(0, 2**32 - 1),
)
def test_property_kernel_matches_reference(m: int, k: int, y_scale: float, w_scale: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    P = np.concatenate(
        [
            rng.normal(scale=w_scale, size=(m, 3)),
            rng.normal(scale=10.0, size=(m, 3)),
            rng.normal(scale=y_scale, size=(m, 6)),
        ],
        axis=1,
    )
    pts = rng.normal(scale=5.0, size=(64, 3))
    idx = rng.integers(0, m, size=(64, k)).astype(np.int32)
    val = rng.random((64, k))
    got = deform.deform_points_params(pts, P, idx, val)
    assert_matches_reference(pts, deform.blend_params(P, idx, val), got)


def test_weights_cache_follows_the_contents_not_the_object(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(16)
    params = aff3.params_from_matrices(random_affine(rng, 5))
    idx, val = top_k_dense(rng.random((cloud.shape[0], 5)), 3)
    kernel = deform.DeformKernel(threads=1)

    def same(a: np.ndarray, b: np.ndarray) -> bool:  # the cached and scattered blends may round apart
        return bool(np.allclose(a, b, rtol=0, atol=1e-13 * np.abs(b).max()))

    first = kernel.deform(cloud, params, idx, val)  # first sight: blended chunk by chunk
    assert same(kernel.deform(cloud, params, idx, val), first)  # seen again: dense weights built
    assert same(kernel.deform(cloud, params, idx, val), first)  # and reused
    val[:10] = 0.0  # mutated in place: the same object must not reuse the stale dense weights
    idx[10:20, 0] = (idx[10:20, 0] + 1) % 5
    fresh = deform.DeformKernel(threads=1).deform(cloud, params, idx, val)
    assert same(kernel.deform(cloud, params, idx, val), fresh)
    assert np.array_equal(fresh[:10], cloud[:10])
    # several weight sets in turn (deformers on different objects) all stay correct
    other = top_k_dense(rng.random((cloud.shape[0], 5)), 2)
    for _ in range(3):
        assert same(kernel.deform(cloud, params, *other), deform.deform_points_params(cloud, params, *other))
        assert same(kernel.deform(cloud, params, idx, val), fresh)
    assert len(kernel._weights_cache) == 3  # the stale copy, the mutated set and the other set
    # fewer points than the cached weights have rows: rejected, not silently sliced
    with pytest.raises(ValueError, match="indices must have shape"):
        kernel.deform(cloud[:10], params, idx, val)
    # a bad index after a good call is still caught
    bad = idx.copy()
    bad[5, 1] = 5
    with pytest.raises(ValueError, match="indices must lie"):
        kernel.deform(cloud, params, bad, val)


def test_default_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(deform.THREADS_ENV, "3")
    assert deform.default_threads() == 3
    monkeypatch.setenv(deform.THREADS_ENV, "zero")
    assert 1 <= deform.default_threads() <= deform.MAX_DEFAULT_THREADS


def test_default_threads_use_every_core(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(deform.THREADS_ENV, raising=False)
    try:
        for cores, expected in ((2, 2), (64, deform.MAX_DEFAULT_THREADS), (None, 1)):
            monkeypatch.setattr(core_kernel.os, "cpu_count", lambda cores=cores: cores)
            core_kernel._cpu_count.cache_clear()  # the core count is read once per process
            assert deform.default_threads() == expected, cores
    finally:
        monkeypatch.undo()
        core_kernel._cpu_count.cache_clear()


@pytest.mark.parametrize("m", [8, 60])  # dense-blend and gather paths
def test_any_subset_of_rows_is_bit_identical_to_the_full_call(m: int) -> None:
    """The Blender layer recomputes only the vertices a changed control influences and keeps the
    others: that is exact only if a row's result does not depend on the other rows, the thread count
    or whether the weights came from the cache."""
    rng = np.random.default_rng(23)
    n = 3 * deform.DEFAULT_CHUNK + 77
    pts = rng.normal(scale=3.0, size=(n, 3))
    params = aff3.params_from_matrices(random_affine(rng, m))
    params[1] = 0.0  # a control at rest
    idx, val = top_k_dense(rng.random((n, m)) ** 3, 4)
    one = deform.DeformKernel(threads=1)
    full = one.deform(pts, params, idx, val).copy()  # first sight: scattered per chunk
    assert np.array_equal(one.deform(pts, params, idx, val), full)  # cached dense weights
    assert np.array_equal(deform.DeformKernel(threads=3).deform(pts, params, idx, val), full)
    for fraction in (1e-4, 0.03, 0.5, 0.97):
        rows = np.flatnonzero(rng.random(n) < fraction)
        sub = deform.deform_points_params(pts[rows], params, idx[rows], val[rows], cache_weights=False)
        assert np.array_equal(sub, full[rows]), fraction
    # cache_weights=False leaves the kernel's cache alone
    kernel = deform.DeformKernel(threads=1)
    kernel.deform(pts[:50], params, idx[:50], val[:50], cache_weights=False)
    assert kernel._weights_cache == []


@pytest.mark.parametrize("m", [8, 60])
def test_rows_entry_point_writes_exactly_the_full_rows(m: int) -> None:
    rng = np.random.default_rng(29)
    n = 2 * deform.DEFAULT_CHUNK + 5
    pts = rng.normal(scale=2.0, size=(n, 3))
    params = aff3.params_from_matrices(random_affine(rng, m))
    idx, val = top_k_dense(rng.random((n, m)) ** 3, 4)
    full = deform.deform_points_params(pts, params, idx, val).copy()
    deform.deform_points_params(pts, params, idx, val)  # now the dense weights are cached (m = 8)
    rows = np.flatnonzero(rng.random(n) < 0.3)
    out = np.full((n, 3), 7.0)
    deform.deform_points_params_rows(pts, params, idx, val, rows, out)
    assert np.array_equal(out[rows], full[rows])
    untouched = np.setdiff1d(np.arange(n), rows)
    assert np.all(out[untouched] == 7.0)
    deform.deform_points_params_rows(pts, params, idx, val, rows, out, offsets=True)
    assert np.array_equal(out[rows], full[rows] - pts[rows])
    with pytest.raises(ValueError, match="rows must lie"):
        deform.deform_points_params_rows(pts, params, idx, val, np.array([n]), out)


@pytest.mark.parametrize("m", [8, 60])
def test_keyed_calls_reuse_gathered_rows_and_stay_bit_identical(m: int) -> None:
    """With a caller key the kernel keeps the gathered inputs of recent row sets (an interactive drag
    recomputes the same rows every update) and skips re-checking the weights: the values must not
    change, new row sets and new keys must not see stale data, and the cache stays bounded."""
    rng = np.random.default_rng(31)
    n = 2 * deform.DEFAULT_CHUNK + 11
    pts = rng.normal(scale=2.0, size=(n, 3))
    idx, val = top_k_dense(rng.random((n, m)) ** 3, 4)
    kernel = deform.DeformKernel(threads=2)
    for frame in range(4):
        params = aff3.params_from_matrices(random_affine(rng, m))
        full = deform.DeformKernel(threads=1).deform(pts, params, idx, val, cache_weights=False)
        assert np.array_equal(kernel.deform(pts, params, idx, val, key="bind-1"), full)
        for fraction in (0.2, 0.2, 0.5):  # the second 0.2 set differs from the first
            rows = np.flatnonzero(np.random.default_rng(frame * 10 + int(10 * fraction)).random(n) < fraction)
            for _ in range(2):  # the second call finds the row set in the cache
                out = np.full((n, 3), 7.0)
                kernel.deform_rows(pts, params, idx, val, rows, out, offsets=True, key="bind-1")
                assert np.array_equal(out[rows], full[rows] - pts[rows])
                assert np.all(np.delete(out, rows, axis=0) == 7.0)
        assert len(kernel._row_sets) <= deform.ROW_SETS_KEPT
    # another key (a rebind: new weights) must not be served the first key's dense weights or rows
    idx2, val2 = top_k_dense(rng.random((n, m)) ** 2, 3)
    expected = deform.DeformKernel(threads=1).deform(pts, params, idx2, val2, cache_weights=False)
    assert np.array_equal(kernel.deform(pts, params, idx2, val2, key="bind-2"), expected)
    out = np.zeros((n, 3))
    kernel.deform_rows(pts, params, idx2, val2, rows, out, key="bind-2")
    assert np.array_equal(out[rows], expected[rows])


def rigid_case(rng: np.random.Generator, n: int, m: int = 8, k: int = 4) -> tuple[np.ndarray, ...]:
    """(points, table, idx, val) as a rig of rigid controls gives them: rotations and translations
    stored in float32 (as Blender hands matrices over), so ψ's stretch Y is rounding noise (~1e-8)
    and blends of them take the Taylor form of exp(Y). Control 0 is stretched (rows that reach it
    take the closed form, so chunks are mixed) and control 1 is lifted to θ = 1.9π (the fix-up).
    Every 50th row (from row 3) has control 1 alone (Taylor form and fix-up). The last 4 rows have
    one table row each, with weight 1: Y entries exactly at ±SMALL_Y (Taylor form, where its
    truncation is largest), and one entry one ulp beyond (closed form)."""
    A = np.broadcast_to(np.eye(4), (m, 4, 4)).copy()
    A[:, :3, :3] = aff3.so3_exp(rng.normal(size=(m, 3)))
    A[:, :3, 3] = rng.normal(scale=3.0, size=(m, 3))
    table = aff3.params_from_matrices(A.astype(np.float32).astype(np.float64))
    assert np.abs(table[:, 6:]).max() < 1e-6
    table[0, 6:] = sym6((-0.4, 0.1, 0.6), aff3.so3_exp(rng.normal(size=3)))
    table[1, :3] *= 1.9 * np.pi / np.linalg.norm(table[1, :3])
    edge, beyond = deform.SMALL_Y, np.nextafter(deform.SMALL_Y, 1.0)
    extra = np.tile(table[2], (4, 1))
    extra[0, 6:] = edge * np.array([1, -1, 1, 1, -1, 1])
    extra[1, 6:] = edge * np.array([-1, -1, -1, 1, 1, 1])
    extra[2, 6:] = edge
    extra[2, 9] = beyond
    extra[3, 6:] = -edge
    extra[3, 6] = -beyond
    table = np.vstack([table, extra])
    pts = rng.normal(scale=3.0, size=(n, 3))
    idx, val = top_k_dense(rng.random((n, m)) ** 3, k)
    alone = np.r_[np.arange(3, n - 4, 50), n - 4 + np.arange(4)]
    idx[alone] = 0
    idx[alone, 0] = 1  # control 1 alone: θ = 1.9π, small Y
    idx[-4:, 0] = np.arange(m, m + 4)
    val[alone] = 0.0
    val[alone, 0] = 1.0
    return pts, table, idx, val


def test_rigid_blends_match_the_reference_and_small_rows_keep_their_bits() -> None:
    """Rows whose blended Y is small take exp(Y) from its Taylor polynomial: as accurate as the
    closed form (up to |Y_ij| = SMALL_Y), and a row's bits do not depend on the form its chunk
    neighbours need (rows calls recompute a subset, whose chunks hold other neighbours)."""
    rng = np.random.default_rng(47)
    n = deform.DEFAULT_CHUNK + 77
    pts, table, idx, val = rigid_case(rng, n)
    P = deform.blend_params(table, idx, val)
    small = np.all(np.abs(P[:, 6:]) <= deform.SMALL_Y, axis=1)
    assert 1000 < small.sum() < n - 1000
    assert small[-4:].tolist() == [True, True, False, False]
    kernel = deform.DeformKernel(threads=1)
    full = kernel.deform(pts, table, idx, val).copy()
    motions = kernel.motions(table, idx, val).copy()
    # θ reaches 1.9π here (the lifted control), where R(ω) is only defined to ~ε θ (`lifted_sweep`)
    assert_matches_reference(pts, P, full, tol=5e-15)
    assert_motions_match_reference(P, motions, 5e-15)
    calm = np.einsum("ij,ij->i", P[:, :3], P[:, :3]) < 1.0
    err = np.linalg.norm(full - reference(pts, P), axis=1) / vertex_scale(pts, P)
    assert err[calm].max() <= 2e-15
    # at |Y_ij| = SMALL_Y the cubic term is ~1e-13 of the result: a Taylor coefficient 4 % off or
    # the term left out shows here (the rows are at ~1e-16)
    assert err[-4:-2].max() <= 1e-15
    assert max(e.max() for e in motion_errors(P[-4:-2], motions[:, -4:-2])) <= 1e-15
    for rows in (np.flatnonzero(small), np.flatnonzero(~small), np.arange(n - 4, n)):
        for chunk in (deform.DEFAULT_CHUNK, 333):
            one = deform.DeformKernel(chunk_size=chunk, threads=2)
            got = one.deform(pts[rows], table, idx[rows], val[rows], cache_weights=False)
            assert np.array_equal(got, full[rows]), (rows.size, chunk)
            out = np.zeros((4, n, 3))
            one.motions(table, idx, val, out, rows=rows)
            assert np.array_equal(out[:, rows], motions[:, rows]), (rows.size, chunk)


def test_lifted_rotations_raise_no_numpy_warnings() -> None:
    """Rows past θ = 1.8π take the exact fallback; the polynomial path must not leave NaN warnings on the
    way (they print in the user's console at every update)."""
    import warnings

    theta = np.linspace(1.7 * np.pi, 14.0 * np.pi, 64)  # the polynomial leaves [0, 1] near 11.4π
    params = np.zeros((64, 12))
    params[:, :3] = theta[:, None] * np.array([0.48, -0.6, 0.64])
    params[:, 3:6] = 0.3
    pts = np.random.default_rng(3).normal(size=(64, 3))
    idx = np.arange(64, dtype=np.int32)[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = deform.deform_points_params(pts, params, idx, np.ones((64, 1)), cache_weights=False)
    scale = vertex_scale(pts, params).max()
    np.testing.assert_allclose(out, reference(pts, params), rtol=0, atol=1e-13 * scale)


# --------------------------------------------------------------------------------------------------
# vertex_motions: the per-vertex affine map φ(p_v) itself, planar (4, N, 3)


def motion_errors(blended: np.ndarray, motions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, ‖M − M_ref‖/‖M_ref‖ and ‖t − t_ref‖/(‖M_ref‖ + ‖t_ref‖) against aff3's matrices
    (np.sin/np.cos, series, divided differences) of the blended parameters."""
    A = aff3.matrices_from_params(blended)
    M = np.stack([motions[0], motions[1], motions[2]], axis=-1)  # out[c, v] is column c of M_v
    m_scale = np.linalg.norm(A[:, :3, :3], axis=(1, 2))
    err_m = np.linalg.norm(M - A[:, :3, :3], axis=(1, 2)) / m_scale
    err_t = np.linalg.norm(motions[3] - A[:, :3, 3], axis=1) / (m_scale + np.linalg.norm(A[:, :3, 3], axis=1))
    return err_m, err_t


def assert_motions_match_reference(
    blended: np.ndarray, motions: np.ndarray, tol: float | np.ndarray = 3e-15
) -> None:
    """Both errors of `motion_errors` within tol (a number, or one per vertex)."""
    err_m, err_t = motion_errors(blended, motions)
    for name, err in (("M", err_m), ("t", err_t)):
        worst = int(np.argmax(err / tol))
        assert np.all(err <= tol), f"{name} of vertex {worst}: {err[worst]:.3e}"


def apply_motions(motions: np.ndarray, points: np.ndarray) -> np.ndarray:
    """φ(p_v) v = v₀ out[0, v] + v₁ out[1, v] + v₂ out[2, v] + out[3, v]."""
    return (
        points[:, 0:1] * motions[0] + points[:, 1:2] * motions[1] + points[:, 2:3] * motions[2] + motions[3]
    )


def identity_motions(n: int) -> np.ndarray:
    ident = np.zeros((4, n, 3))
    ident[0, :, 0] = ident[1, :, 1] = ident[2, :, 2] = 1.0
    return ident


def test_motions_match_aff3_on_adversarial_parameters() -> None:
    P = adversarial_params()
    idx = np.arange(P.shape[0], dtype=np.int32)[:, None]
    got = deform.vertex_motions(P, idx, np.ones((P.shape[0], 1)))
    assert got.shape == (4, P.shape[0], 3) and got.dtype == np.float64
    assert all(got[c].flags.c_contiguous for c in range(4))
    assert_motions_match_reference(P, got)


def test_motions_match_aff3_on_random_blends(cloud: np.ndarray) -> None:
    rng = np.random.default_rng(41)
    params = aff3.params_from_matrices(random_affine(rng, 8, log_scale=1.0, t_scale=5.0))
    idx, val = top_k_dense(rng.random((cloud.shape[0], 8)) ** 3, 4)
    kernel = deform.DeformKernel(threads=1)
    first = kernel.motions(params, idx, val)  # weights blended per chunk
    assert_motions_match_reference(deform.blend_params(params, idx, val), first)
    assert np.array_equal(kernel.motions(params, idx, val), first)  # cached dense weights: same bits


@pytest.mark.parametrize("m", [8, 60])  # dense-blend and gather paths
def test_motions_applied_to_points_equal_deform_points_params(cloud: np.ndarray, m: int) -> None:
    rng = np.random.default_rng(42)
    params = aff3.params_from_matrices(random_affine(rng, m, log_scale=1.0, t_scale=5.0))
    idx, val = top_k_dense(rng.random((cloud.shape[0], m)) ** 3, 4)
    moved = deform.deform_points_params(cloud, params, idx, val)
    got = apply_motions(deform.vertex_motions(params, idx, val), cloud)
    err = np.linalg.norm(got - moved, axis=1) / vertex_scale(cloud, deform.blend_params(params, idx, val))
    assert err.max() <= 1e-14, f"worst vertex {int(err.argmax())}: {err.max():.3e}"
    # and on the adversarial set (translations up to 1e3, anisotropy 1e3:1e-3, lifted angles)
    P = adversarial_params()
    pts = rng.uniform(-10.0, 10.0, size=(P.shape[0], 3))
    idx1 = np.arange(P.shape[0], dtype=np.int32)[:, None]
    one = np.ones((P.shape[0], 1))
    got = apply_motions(deform.vertex_motions(P, idx1, one), pts)
    err = np.linalg.norm(got - deform.deform_points_params(pts, P, idx1, one), axis=1) / vertex_scale(pts, P)
    assert err.max() <= 1e-14, f"worst adversarial row {int(err.argmax())}: {err.max():.3e}"


def lifted_sweep() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(params, θ, tolerance): 64 rotations from 1.7π to 14π with stretch and translation. |ω| itself
    carries a rounding of ε θ, so R(ω) (and aff3's reference) are only that well defined: the
    tolerance is 3e-15 · max(1, θ/2π)."""
    rng = np.random.default_rng(43)
    theta = np.linspace(1.7 * np.pi, 14.0 * np.pi, 64)
    axis = rng.normal(size=(64, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    params = np.concatenate(
        [theta[:, None] * axis, rng.normal(size=(64, 3)), 0.3 * rng.normal(size=(64, 6))], axis=1
    )
    return params, theta, 3e-15 * np.maximum(1.0, theta / (2.0 * np.pi))


def test_motions_of_lifted_rotations(monkeypatch: pytest.MonkeyPatch) -> None:
    """θ past 1.8π (lifted rotations, up to 14π): the exact fallback applies to the motion too, and
    the polynomial path leaves no NaN warnings on the way."""
    import warnings

    params, theta, tol = lifted_sweep()
    idx = np.arange(64, dtype=np.int32)[:, None]
    one = np.ones((64, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = deform.vertex_motions(params, idx, one)
    assert_motions_match_reference(params, got, tol)
    # without the fallback the quarter-angle polynomial is far off there: the fallback did the work
    monkeypatch.setattr(kernel_stages, "_exact_rotation_coeffs", lambda *args: None)
    with np.errstate(invalid="ignore"):
        err_m, _ = motion_errors(params, deform.vertex_motions(params, idx, one))
    assert np.nanmax(err_m[theta > 1.8 * np.pi + 0.1]) > 1e-6


@pytest.mark.parametrize("m", [8, 60])  # dense-blend and gather paths
def test_motion_rows_are_bit_identical_to_the_full_call(m: int) -> None:
    """The Blender layer recomputes the motions of the vertices a moved control influences and keeps
    the others: each written row must equal the full call's bit for bit (any thread count, chunk
    size, row subset, cached or scattered weights), and no other row may be touched."""
    rng = np.random.default_rng(44)
    n = 3 * deform.DEFAULT_CHUNK + 77
    params = aff3.params_from_matrices(random_affine(rng, m))
    params[1] = 0.0  # a control at rest
    params[2, :3] *= 5.9 / np.linalg.norm(params[2, :3])  # and one past 1.8π (the exact fallback)
    idx, val = top_k_dense(rng.random((n, m)) ** 3, 4)
    full = deform.DeformKernel(threads=1).motions(params, idx, val)
    for chunk, threads in ((deform.DEFAULT_CHUNK, 3), (1000, 2), (333, 1)):
        kernel = deform.DeformKernel(chunk_size=chunk, threads=threads)
        assert np.array_equal(kernel.motions(params, idx, val), full), (chunk, threads)  # scattered
        assert np.array_equal(kernel.motions(params, idx, val), full), (chunk, threads)  # dense, cached
        for fraction in (1e-4, 0.03, 0.5, 0.97):
            rows = np.flatnonzero(rng.random(n) < fraction)
            for key in (None, "bind-1", "bind-1"):  # the second keyed call finds the gathered rows
                out = np.full((4, n, 3), 7.0)
                assert kernel.motions(params, idx, val, out, rows=rows, key=key) is out
                assert np.array_equal(out[:, rows], full[:, rows]), (chunk, threads, fraction, key)
                assert np.all(np.delete(out, rows, axis=1) == 7.0)
        assert len(kernel._row_sets) <= deform.ROW_SETS_KEPT
    # reversed, repeated and int32 rows
    rows = np.r_[np.arange(n)[::-1], [5, 5]].astype(np.int32)
    out = np.zeros((4, n, 3))
    deform.vertex_motions(params, idx, val, out, rows=rows)
    assert np.array_equal(out, full)
    with pytest.raises(ValueError, match=r"rows must lie in \[0, "):
        deform.vertex_motions(params, idx, val, out, rows=np.array([n]))


def test_keyed_motion_row_sets_are_shared_with_deform_rows() -> None:
    """A row set gathered by `motions` (no points) and found by `deform_rows` with the same key gets
    its points then; one gathered by `deform_rows` serves `motions`. Both stay exact."""
    rng = np.random.default_rng(45)
    n = 2 * deform.DEFAULT_CHUNK + 11
    pts = rng.normal(scale=2.0, size=(n, 3))
    params = aff3.params_from_matrices(random_affine(rng, 6))
    idx, val = top_k_dense(rng.random((n, 6)) ** 3, 3)
    rows = np.flatnonzero(rng.random(n) < 0.2)
    full_m = deform.DeformKernel(threads=1).motions(params, idx, val)
    full_p = deform.DeformKernel(threads=1).deform(pts, params, idx, val)
    for order in ("motions first", "points first"):
        kernel = deform.DeformKernel(threads=2)
        for what in (("m", "p") if order == "motions first" else ("p", "m")) * 2:
            if what == "m":
                out = np.zeros((4, n, 3))
                kernel.motions(params, idx, val, out, rows=rows, key=order)
                assert np.array_equal(out[:, rows], full_m[:, rows]), order
            else:
                out = np.zeros((n, 3))
                kernel.deform_rows(pts, params, idx, val, rows, out, key=order)
                assert np.array_equal(out[rows], full_p[rows]), order
        assert len(kernel._row_sets) == 1


def test_motions_float32_out_is_the_rounded_float64() -> None:
    rng = np.random.default_rng(46)
    n = deform.DEFAULT_CHUNK + 9
    params = aff3.params_from_matrices(random_affine(rng, 5, log_scale=1.5, t_scale=50.0))
    params[0, 3:6] = [1e300, -1e40, 3.4e38]  # translations beyond float32's range: ±inf, as astype
    idx, val = top_k_dense(rng.random((n, 5)) ** 3, 3)
    full = deform.vertex_motions(params, idx, val)
    with np.errstate(over="ignore"):
        want = full.astype(np.float32)
    assert np.isinf(want).any()
    out32 = np.full((4, n, 3), -3.25, dtype=np.float32)
    assert deform.vertex_motions(params, idx, val, out32) is out32
    assert np.array_equal(out32.view(np.uint32), want.view(np.uint32))
    rows = np.flatnonzero(rng.random(n) < 0.3)
    out32 = np.full((4, n, 3), -3.25, dtype=np.float32)
    deform.vertex_motions(params, idx, val, out32, rows=rows)
    assert np.array_equal(out32[:, rows].view(np.uint32), want[:, rows].view(np.uint32))
    assert np.all(np.delete(out32, rows, axis=1) == np.float32(-3.25))


def test_zero_params_give_the_identity_motion_bit_for_bit() -> None:
    n = 50
    idx = np.zeros((n, 3), dtype=np.int32)
    val = np.random.default_rng(47).random((n, 3))
    ident = identity_motions(n)
    got = deform.vertex_motions(np.zeros((4, 12)), idx, val)
    assert got.tobytes() == ident.tobytes()  # no −0.0 anywhere
    out32 = np.full((4, n, 3), 9.0, dtype=np.float32)
    deform.vertex_motions(np.zeros((4, 12)), idx, val, out32)
    assert out32.tobytes() == ident.astype(np.float32).tobytes()
    rows = np.array([3, 1, 40])
    out = np.full((4, n, 3), 9.0)
    deform.vertex_motions(np.zeros((4, 12)), idx, val, out, rows=rows)
    assert out[:, rows].tobytes() == ident[:, rows].tobytes()
    assert np.all(np.delete(out, rows, axis=1) == 9.0)
    # no controls at all, and zero weights on moving controls (the general path: equal, signs aside)
    empty = deform.vertex_motions(np.zeros((0, 12)), np.zeros((n, 0), np.int32), np.zeros((n, 0)))
    assert empty.tobytes() == ident.tobytes()
    params = aff3.params_from_matrices(random_affine(np.random.default_rng(48), 4))
    assert np.array_equal(deform.vertex_motions(params, idx, np.zeros((n, 3))), ident)


def test_motions_out_argument_and_layouts() -> None:
    rng = np.random.default_rng(49)
    n = 3000
    params = aff3.params_from_matrices(random_affine(rng, 4))
    idx, val = top_k_dense(rng.random((n, 4)), 2)
    want = deform.vertex_motions(params, idx, val)
    strided = np.zeros((4, n, 6))[:, :, ::2]
    assert deform.vertex_motions(params, idx.astype(np.int64), np.asfortranarray(val), strided) is strided
    assert np.array_equal(strided, want)
    assert deform.vertex_motions(params, idx, val, rows=np.arange(n)).shape == (4, n, 3)
    empty = deform.vertex_motions(np.ones((2, 12)), np.zeros((0, 2), np.int32), np.zeros((0, 2)))
    assert empty.shape == (4, 0, 3)


_MOTION_OUT_MESSAGE = r"out must be a float64 or float32 array of shape \(4, 4, 3\)"
#: Arguments `vertex_motions` must refuse (its own and those of deform_points_params without points).
MOTION_BAD_ARGUMENTS = [
    *[(kw, msg) for kw, msg in BAD_ARGUMENTS if "points" not in kw and "(4, K)" not in msg.replace("\\", "")],
    ({"indices": np.zeros(4, dtype=np.int32)}, r"indices must have shape \(N, K\)"),
    ({"out": np.zeros((4, 4, 3), dtype=np.float16)}, _MOTION_OUT_MESSAGE),
    ({"out": np.zeros((4, 3))}, _MOTION_OUT_MESSAGE),
    ({"out": np.zeros((3, 4, 3))}, _MOTION_OUT_MESSAGE),
    ({"out": [[[0.0] * 3] * 4] * 4}, _MOTION_OUT_MESSAGE),
    ({"rows": np.array([4])}, r"rows must lie in \[0, 4\)"),
    ({"rows": np.array([-1])}, r"rows must lie in \[0, 4\)"),
    ({"rows": np.zeros((1, 1), dtype=np.int64)}, "rows must be a 1-D integer array"),
    ({"rows": np.array([0.0])}, "rows must be a 1-D integer array"),
]


def motion_bad_call(fn: Callable[..., np.ndarray], kwargs: dict) -> None:
    """fn (core's or accel's vertex_motions) with valid arguments but for `kwargs`."""
    args = {
        "params": np.ones((3, 12)) * 0.1,
        "indices": np.zeros((4, 2), dtype=np.int32),
        "values": np.ones((4, 2)),
        "out": None,
        "rows": None,
    }
    args.update(kwargs)
    fn(args["params"], args["indices"], args["values"], args["out"], rows=args["rows"])


@pytest.mark.parametrize(("kwargs", "message"), MOTION_BAD_ARGUMENTS)
def test_motions_bad_arguments_raise_value_error(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        motion_bad_call(deform.vertex_motions, kwargs)
