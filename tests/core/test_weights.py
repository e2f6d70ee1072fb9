"""Weights (core/weights.py): kernels, falloff, normalisation, top-K, chunking."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from affine_deformers.core import aff3, deform
from affine_deformers.core import weights as wt


def test_inverse_distance() -> None:
    d = np.array([0.0, 1e-12, 0.5, 1.0, 2.0, 4.0])
    w = wt.inverse_distance(d, exponent=2.0, reference=2.0)
    np.testing.assert_allclose(w[2:], [16.0, 4.0, 1.0, 0.25], rtol=1e-15)
    # a vertex on the control: finite, equal to the floor value, dominant
    assert np.isfinite(w[0]) and w[0] == w[1] == (1.0 / wt.MIN_DISTANCE_FRACTION) ** 2
    assert wt.inverse_distance([0.0], 3.0, min_distance=0.1)[0] == pytest.approx(1000.0)
    for bad in ({"exponent": 0.0}, {"reference": -1.0}, {"min_distance": 0.0}):
        with pytest.raises(ValueError):
            wt.inverse_distance(d, **bad)


def test_smooth_falloff_is_exactly_zero_at_and_after_the_radius() -> None:
    R = 1.5
    d = np.array([0.0, 0.75, R * (1 - 1e-12), R, R * (1 + 1e-15), 2 * R, 1e300, np.inf])
    w = wt.smooth_falloff(d, R)
    assert w[0] == 1.0
    assert w[1] == pytest.approx((1 - 0.25) ** 2)
    assert 0.0 < w[2] < 1e-22
    assert np.all(w[3:] == 0.0)


@pytest.mark.parametrize("power", [2, 3])
def test_smooth_falloff_is_smooth_at_the_radius(power: int) -> None:
    # one-sided derivatives at R vanish up to order power − 1 (C¹ for 2, C² for 3)
    R, h = 2.0, 1e-4
    f = lambda d: wt.smooth_falloff(np.array([d]), R, power)[0]  # noqa: E731
    d1 = (f(R) - f(R - h)) / h
    assert abs(d1) < 10 * h ** (power - 1)
    if power == 3:
        d2 = (f(R) - 2 * f(R - h) + f(R - 2 * h)) / h**2
        assert abs(d2) < 100 * h


def test_normalize_modes() -> None:
    W = np.array([[1.0, 3.0, 0.0], [0.0, 0.0, 0.0], [2.0, 2.0, 4.0]])
    s = wt.normalize(W, "SUM")
    np.testing.assert_allclose(s, [[0.25, 0.75, 0.0], [0.0, 0.0, 0.0], [0.25, 0.25, 0.5]], rtol=1e-15)
    assert not np.any(np.isnan(s))
    assert np.array_equal(wt.normalize(W, "NONE"), W)
    sm = wt.normalize(W, "SOFTMAX")
    e = np.exp([1.0 - 3.0, 0.0])
    np.testing.assert_allclose(sm[0], [e[0] / e.sum(), e[1] / e.sum(), 0.0], rtol=1e-15)
    assert np.array_equal(sm[1], [0.0, 0.0, 0.0])  # all-zero row stays zero
    np.testing.assert_allclose(sm.sum(axis=1), [1.0, 0.0, 1.0], rtol=1e-15)
    # huge raw weights (a vertex on a probe) do not overflow
    assert np.all(np.isfinite(wt.normalize(np.array([[1e300, 1.0]]), "SOFTMAX")))
    with pytest.raises(ValueError, match="normalize mode"):
        wt.normalize(W, "MAX")


def test_top_k_orders_by_value_then_index() -> None:
    W = np.array([[0.1, 0.5, 0.5, 0.2], [0.0, 0.0, 0.0, 0.0], [4.0, 3.0, 2.0, 1.0]])
    idx, val = wt.top_k(W, 2)
    assert idx.dtype == np.int32
    assert idx.tolist() == [[1, 2], [0, 1], [0, 1]]
    assert val.tolist() == [[0.5, 0.5], [0.0, 0.0], [4.0, 3.0]]
    idx, val = wt.top_k(W, 10)  # K = min(k, m)
    assert idx.shape == (3, 4) and np.array_equal(np.take_along_axis(W, idx.astype(np.intp), 1), val)


def _dense(idx: np.ndarray, val: np.ndarray, m: int) -> np.ndarray:
    """Sparse weights as a dense (n, m + 1) array (column m: the pooled control)."""
    dense = np.zeros((len(idx), m + 1))
    np.put_along_axis(dense, idx.astype(np.intp), val, 1)
    return dense


def test_truncation_is_continuous_where_controls_swap_ranks() -> None:
    """Along a path where the 3rd and 4th strongest of 6 controls swap, plain top-3 jumps; the
    truncation changes by O(step) per step ('SUM' and 'SOFTMAX'), and each row's kept and pooled
    weights sum to 1."""
    t = np.linspace(0.0, 1.0, 2001)[:, None]
    W = np.hstack([np.full_like(t, 5.0), np.full_like(t, 4.0), 2.0 + t, 3.0 - t, 0.5 + 0 * t, 0.2 + 0 * t])
    idx, val = wt.top_k(W, 3)
    plain = _dense(idx, wt.normalize(val, "SUM"), 6)
    assert np.abs(np.diff(plain, axis=0)).max() > 0.1, "plain top-K does jump (the test can fail)"
    for mode in ("SUM", "SOFTMAX"):
        dense = _dense(*wt.sparse_from_blocks(len(W), 6, lambda lo, hi: W[lo:hi], 3, mode), 6)
        np.testing.assert_allclose(dense.sum(1), 1.0, atol=1e-15)
        assert np.abs(np.diff(dense, axis=0)).max() < 5 * (t[1, 0] - t[0, 0]), mode
    # the 'SUM' values: (w_j − w_4)/D, D = max(S, c T) with T the total over all six
    idx, val = wt.sparse_from_blocks(len(W), 6, lambda lo, hi: W[lo:hi], 3, "SUM")
    fourth = np.sort(W, axis=1)[:, -4]
    kept = np.take_along_axis(W, idx[:, :3].astype(np.intp), 1)
    excess = kept - fourth[:, None]
    D = np.maximum(excess.sum(1), wt.POOL_FLOOR * W.sum(1))
    np.testing.assert_allclose(val[:, :3], excess / D[:, None], atol=1e-15)
    # truncate without a total: D = max(S, c Σ kept), exactly renormalised where S is large
    idx, val = wt.truncate(W, 3)
    D = np.maximum(excess.sum(1), wt.POOL_FLOOR * kept.sum(1))
    np.testing.assert_allclose(val, excess / D[:, None], atol=1e-15)
    idx, val = wt.truncate(W, 6)
    np.testing.assert_allclose(val, wt.normalize(wt.top_k(W, 6)[1], "SUM"), rtol=1e-15)


def test_truncation_slope_is_bounded_where_the_strongest_tie() -> None:
    """A path through a point where the 4 strongest of 6 weights tie (K = 3): dividing by
    S = Σ (w_j − w_4) (the former rule) swings the weights by O(1) across a hair's width; the
    bounded rule keeps every slope within its stated bound 2 (1 + K v_j) max|∂w| / (floor · T),
    and at the tie itself all of the weight is pooled (the rows' limit there, not a jump)."""
    t = np.linspace(-1.0, 1.0, 4001)[:, None]
    h = 1e-3  # the ties split by a hair: ±h t
    W = np.hstack([2.0 + h * t, 2.0 - h * t, 2.0 + 0.5 * h * t, 2.0 - 0.5 * h * t,
                   np.full_like(t, 1.0), np.full_like(t, 0.5)])
    idx, top = wt.top_k(W, 4)
    excess = top[:, :3] - top[:, 3:]
    steep = _dense(idx[:, :3], excess / np.maximum(excess.sum(1, keepdims=True), 1e-300), 6)
    assert np.abs(np.diff(steep, axis=0)).max() > 0.3, "the former rule does swing (the test can fail)"
    idx, val = wt.sparse_from_blocks(len(W), 6, lambda lo, hi: W[lo:hi], 3, "SUM")
    dense = _dense(idx, val, 6)
    slope = np.abs(np.diff(dense[:, :6], axis=0)).max() / (t[1, 0] - t[0, 0])
    T = W.sum(1).min()
    assert slope <= 2 * (1 + 3) * h / (wt.POOL_FLOOR * T)
    mid = len(t) // 2
    assert np.all(dense[mid, :6] == 0.0) and dense[mid, 6] == 1.0
    np.testing.assert_allclose(dense.sum(1), 1.0, atol=1e-15)


def test_pooled_control_keeps_common_motions_exact() -> None:
    """Rows that pool weight read index m, whose parameters are the probes' mean (with_pool): a motion
    shared by every probe moves every vertex exactly by it, also where weight is pooled; a vertex
    equidistant from all probes (all pooled) gets the mean of their motions, the untruncated field's
    value there."""
    octahedron = np.concatenate([np.eye(3), -np.eye(3)])
    pts = np.random.default_rng(4).uniform(-0.6, 0.6, (400, 3))
    pts[0] = 0.0
    idx, val = wt.probe_weights(pts, octahedron, k=4)
    assert idx.shape == (400, 5) and np.all(idx[:, 4] == 6)
    assert val[0, :4].sum() == 0.0 and val[0, 4] == 1.0, "the tied centre pools everything"
    np.testing.assert_allclose(val.sum(1), 1.0, atol=1e-15)
    G = np.eye(4)
    G[:3, :3] = aff3.so3_exp([0.3, -0.4, 0.2]) * 1.3
    G[:3, 3] = [0.5, -1.0, 2.0]
    params = wt.with_pool(np.tile(aff3.params_from_matrices(G), (6, 1)), wt.pool_weights(np.ones(6)))
    moved = deform.deform_points_params(pts, params, idx, val)
    np.testing.assert_allclose(moved, pts @ G[:3, :3].T + G[:3, 3], atol=1e-12)
    # the centre gets the mean of the six motions (scale-weighted), as the untruncated weights give
    P = aff3.params_from_matrices(np.stack([np.eye(4) + 0.1 * i * np.eye(4, k=3) for i in range(6)]))
    a = wt.pool_weights([1.0, 1.0, 2.0, 0.0, 1.0, 1.0])
    np.testing.assert_allclose(a, [1 / 6, 1 / 6, 1 / 3, 0.0, 1 / 6, 1 / 6])
    np.testing.assert_allclose(wt.with_pool(P, a)[6], a @ P, rtol=1e-15)
    with pytest.raises(ValueError, match="pool coefficients"):
        wt.with_pool(P, a[:5])


def test_nothing_is_pooled_when_every_control_is_kept_or_truncation_leaves_a_partition() -> None:
    """m ≤ K: no pooled column, the rows are the normalised weights (the untruncated field); a
    falloff with at most K probes reaching any vertex pools nothing either (w_{K+1} = 0), so the
    column is left out; 'NONE' and painted weights never pool."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(-2, 2, (300, 3))
    centers = rng.uniform(-2, 2, (6, 3))
    idx, val = wt.probe_weights(pts, centers, k=6)
    assert idx.shape == (300, 6)
    W = wt.inverse_distance(np.linalg.norm(pts[:, None] - centers[None], axis=2))
    np.testing.assert_allclose(_dense(idx, val, 6)[:, :6], W / W.sum(1, keepdims=True), rtol=1e-14)
    far = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [10, 10, 10]])
    idx, val = wt.probe_weights(pts, far, mode="FALLOFF", radius=3.0, k=2)
    assert idx.shape == (300, 2)
    assert wt.probe_weights(pts, centers, k=2, normalize="NONE")[0].shape == (300, 2)
    assert wt.top_k_dense(W, 2)[0].shape == (300, 2)


def test_raw_truncation_keeps_dominant_weights_and_never_raises_one() -> None:
    """normalize 'NONE': v = min(w, 2 (w − w_{K+1})): a weight at least twice the first dropped one
    stays as it is (a vertex on a probe follows it fully), smaller ones ramp to 0 at the swap, and
    every value is continuous in W (slope at most 2)."""
    W = np.array([[1.0, 0.3, 0.25, 0.2], [0.5, 0.45, 0.4, 0.4]])
    idx, val = wt.truncate(W, 3, raw=True)
    np.testing.assert_allclose(val[0], [1.0, 0.2, 0.1], rtol=1e-15)
    np.testing.assert_allclose(val[1], [0.2, 0.1, 0.0], atol=1e-15)
    t = np.linspace(0.0, 1.0, 2001)[:, None]
    path = np.hstack([np.full_like(t, 1.0), 0.2 + 0.2 * t, 0.4 - 0.2 * t, np.full_like(t, 0.1)])
    idx, val = wt.truncate(path, 2, raw=True)
    dense = np.zeros_like(path)
    np.put_along_axis(dense, idx.astype(np.intp), val, 1)
    # slope ≤ 2 (|dw| + |dw_{K+1}|) = 2 · (0.2 + 0.2) per unit t
    assert np.abs(np.diff(dense, axis=0)).max() <= 0.8 * (t[1, 0] - t[0, 0]) + 1e-12
    assert np.all(dense <= path + 1e-15)
    ids, raw = wt.probe_weights(np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0, 0], [3, 0, 0], [0, 3, 0],
                                                                      [0, 0, 3]]), normalize="NONE", k=2)
    assert ids[0, 0] == 0 and raw[0, 0] == 1.0, "on a probe: its full motion"


def test_top_k_renormalises_to_one() -> None:
    rng = np.random.default_rng(1)
    W = rng.random((500, 9))
    idx, val = wt.top_k_dense(W, 3, normalize="SUM")  # painted weights: the 3 largest, as painted
    np.testing.assert_allclose(val.sum(axis=1), 1.0, rtol=0, atol=4e-16)
    kept = np.take_along_axis(W, idx.astype(np.intp), 1)
    np.testing.assert_allclose(val, kept / kept.sum(1, keepdims=True), rtol=1e-15)
    # the kept entries are the three largest of each row
    assert np.all(kept.min(axis=1) >= np.sort(W, axis=1)[:, -3])
    raw_idx, raw_val = wt.top_k_dense(W, 3, normalize="NONE")
    assert np.array_equal(raw_idx, idx) and np.array_equal(raw_val, kept)


@pytest.mark.parametrize("chunk", [1, 7, 64, 10_000])
def test_chunked_equals_unchunked(chunk: int) -> None:
    rng = np.random.default_rng(2)
    pts = rng.uniform(-2, 2, (300, 3))
    centers = rng.uniform(-2, 2, (11, 3))
    for mode in ("INVERSE_DISTANCE", "FALLOFF"):
        for norm in ("NONE", "SUM", "SOFTMAX"):
            ref = wt.probe_weights(pts, centers, mode=mode, radius=1.5, normalize=norm, k=4)
            got = wt.probe_weights(pts, centers, mode=mode, radius=1.5, normalize=norm, k=4, chunk_size=chunk)
            assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])


def test_probe_weights_inverse_distance() -> None:
    centers = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    idx, val = wt.probe_weights(pts, centers, mode="INVERSE_DISTANCE", exponent=2.0, normalize="SUM", k=2)
    assert idx[0, 0] == 0 and val[0, 0] > 1 - 1e-10  # a vertex on a probe follows it
    assert idx[1, :2].tolist() == [0, 1] and val[1, 0] == val[1, 1]  # midway: equal weights
    # distances 0.5 and 1.5 to the two nearest probes, minus the third's weight (√9.25 away): their
    # excess keeps more than half of the total weight, so they are renormalised and nothing is pooled
    w = np.array([1 / 0.25, 1 / 2.25]) - 1 / 9.25
    assert w.sum() >= wt.POOL_FLOOR * (1 / 0.25 + 1 / 2.25 + 1 / 9.25)
    np.testing.assert_allclose(val[2], w / w.sum(), rtol=1e-14)
    # farther out the three probes are about as near: their excess is small, the rest is pooled
    # (column 2, index 3: the pooled control)
    far = np.array([[0.7, 1.0, 8.0]])
    idx, val = wt.probe_weights(far, centers, mode="INVERSE_DISTANCE", exponent=2.0, normalize="SUM", k=2)
    w = 1.0 / ((far - centers) ** 2).sum(1)
    top = np.sort(w)[::-1]
    np.testing.assert_allclose(val[0, :2], (top[:2] - top[2]) / (wt.POOL_FLOOR * w.sum()), rtol=1e-14)
    assert idx[0, 2] == 3 and val[0].sum() == pytest.approx(1.0, rel=1e-15) and val[0, 2] > 0.5
    scaled = wt.probe_weights(
        pts, centers, mode="INVERSE_DISTANCE", normalize="SUM", k=2, scales=[0.0, 1.0, 1.0]
    )
    assert scaled[0][1, 0] == 1  # the zero-scaled probe drops out of the top-K


def test_raw_inverse_distance_weights_are_capped_at_one() -> None:
    centers = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    pts = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [2.0, 0.0, 0.0]])
    idx, val = wt.probe_weights(pts, centers, mode="INVERSE_DISTANCE", radius=1.0, normalize="NONE", k=2)
    assert val[0].tolist() == [1.0, 1.0 / 16.0]  # on a probe: full motion, not 1e12 times it
    assert val[1, 0] == 1.0 and idx[1, 0] == 0
    assert val[2].tolist() == [0.25, 0.25]


def test_probe_weights_falloff_locality() -> None:
    centers = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    pts = np.array([[0.5, 0.0, 0.0], [5.0, 0.0, 0.0], [9.0, 0.0, 0.0]])
    idx, val = wt.probe_weights(pts, centers, mode="FALLOFF", radius=2.0, normalize="SUM", k=2)
    assert val[0, 0] == 1.0 and idx[0, 0] == 0 and val[0, 1] == 0.0
    assert np.array_equal(val[1], [0.0, 0.0])  # out of every radius: stays put
    assert idx[2, 0] == 1 and val[2, 0] == 1.0
    _, soft = wt.probe_weights(pts, centers, mode="FALLOFF", radius=2.0, normalize="SOFTMAX", k=2)
    assert np.array_equal(soft[1], [0.0, 0.0]) and soft[0, 1] == 0.0


def test_probe_weights_from_painted_groups() -> None:
    painted = np.array([[0.2, 0.8, 0.0], [-1.0, 0.0, 0.5], [0.0, 0.0, 0.0]])
    idx, val = wt.probe_weights(
        np.zeros((3, 3)), np.zeros((3, 3)), mode="VERTEX_GROUPS", dense=painted, normalize="SUM", k=2
    )
    assert idx[0].tolist() == [1, 0] and np.allclose(val[0], [0.8, 0.2], rtol=0, atol=1e-16)
    assert idx[1, 0] == 2 and val[1].tolist() == [1.0, 0.0]  # negative paint clamped to 0
    assert val[2].tolist() == [0.0, 0.0]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mode": "NEAREST"}, "weight mode"),
        ({"mode": "VERTEX_GROUPS"}, "needs the dense painted weights"),
        ({"mode": "VERTEX_GROUPS", "dense": np.ones((2, 2))}, "painted weights must have shape"),
        ({"radius": 0.0}, "radius must be positive"),
        ({"normalize": "MAX"}, "normalize mode"),
        ({"k": 0}, "k must be at least 1"),
        ({"scales": [1.0, -1.0]}, "scales must be"),
        ({"points": np.full((3, 3), np.nan)}, "non-finite"),
    ],
)
def test_probe_weights_errors(kwargs: dict, message: str) -> None:
    args = {"points": np.zeros((3, 3)), "centers": np.ones((2, 3))}
    pts, ctr = kwargs.pop("points", args["points"]), args["centers"]
    with pytest.raises(ValueError, match=message):
        wt.probe_weights(pts, ctr, **kwargs)


def test_sparse_from_blocks_checks_blocks() -> None:
    with pytest.raises(ValueError, match="has shape"):
        wt.sparse_from_blocks(10, 3, lambda lo, hi: np.ones((hi - lo, 2)), k=2)
    with pytest.raises(ValueError, match="negative"):
        wt.sparse_from_blocks(10, 3, lambda lo, hi: -np.ones((hi - lo, 3)), k=2)
    with pytest.raises(ValueError, match="non-finite"):
        wt.sparse_from_blocks(10, 3, lambda lo, hi: np.full((hi - lo, 3), np.nan), k=2)
    calls = []

    def block(lo: int, hi: int) -> np.ndarray:
        calls.append(hi - lo)
        return np.ones((hi - lo, 3))

    wt.sparse_from_blocks(10, 3, block, k=2, chunk_size=4)
    assert calls == [4, 4, 2]  # bounded blocks: O(chunk · m) memory


@settings(max_examples=150, deadline=None)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(1, 20), st.integers(1, 8)), elements=st.floats(0.0, 1e6)),
    st.integers(1, 9),
    st.sampled_from(["NONE", "SUM", "SOFTMAX"]),
    st.integers(1, 25),
)
def test_property_sparse_weights(W: np.ndarray, k: int, mode: str, chunk: int) -> None:
    idx, val = wt.top_k_dense(W, k, normalize=mode, chunk_size=chunk)
    K = min(k, W.shape[1])
    assert idx.shape == val.shape == (W.shape[0], K)
    assert np.all((idx >= 0) & (idx < W.shape[1]))
    assert np.all([len(set(r)) == K for r in idx.tolist()])  # no control twice in a row
    assert np.all(np.isfinite(val)) and np.all(val >= 0)
    kept = np.take_along_axis(W, idx.astype(np.intp), 1)
    assert np.all(kept.min(axis=1) >= np.sort(W, axis=1)[:, -K])
    total = val.sum(axis=1)
    if mode != "NONE":
        positive = kept.max(axis=1) > 0
        np.testing.assert_allclose(total[positive], 1.0, rtol=0, atol=1e-14)
        assert np.all(total[~positive] == 0.0)
    ref = wt.top_k_dense(W, k, normalize=mode)
    assert np.array_equal(ref[0], idx) and np.array_equal(ref[1], val)


def test_segment_distances_match_a_dense_sampling_of_the_segments():
    from affine_deformers.core.weights import segment_distances

    rng = np.random.default_rng(5)
    points = rng.normal(size=(200, 3)) * 2.0
    heads = rng.normal(size=(4, 3))
    tails = heads + rng.normal(size=(4, 3))
    tails[3] = heads[3]  # a zero-length segment: the distance to its head
    t = np.linspace(0.0, 1.0, 20001)
    samples = heads[:, None, :] + t[None, :, None] * (tails - heads)[:, None, :]  # (m, S, 3)
    brute = np.sqrt(((points[:, None, None, :] - samples[None]) ** 2).sum(-1)).min(axis=2)
    got = segment_distances(points, heads, tails)
    assert np.allclose(got, brute, atol=1e-3)  # the sampling step bounds the brute-force error
    assert np.allclose(got[:, 3], np.linalg.norm(points - heads[3], axis=1))
    assert np.all(got <= brute + 1e-12)  # the exact minimum is never above a sampled one


def test_probe_weights_with_tails_use_the_segment_distance():
    from affine_deformers.core.weights import probe_weights

    points = np.array([[0.5, 1.0, 0.0], [3.0, 0.0, 0.0]])
    heads = np.array([[0.0, 0.0, 0.0], [3.0, 5.0, 0.0]])
    tails = np.array([[1.0, 0.0, 0.0], [3.0, 6.0, 0.0]])
    idx, val = probe_weights(points, heads, tails=tails, mode="FALLOFF", radius=1.5, normalize="NONE", k=2)
    dense = np.zeros((2, 2))
    np.put_along_axis(dense, idx, val, axis=1)
    assert dense[0, 0] > 0.0 and dense[0, 1] == 0.0  # 1.0 from segment 0 (0.5 from its line, 1.1 from head)
    assert dense[1, 0] == 0.0  # 2.0 beyond the radius from segment 0's tail
