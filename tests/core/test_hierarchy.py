"""core.hierarchy: blending down a forest of controls (MATH.md §14), against a direct evaluation of
v' = F_0 ⋯ F_D v with dense cumulative weights and aff3's φ / ψ, vertex by vertex."""

from __future__ import annotations

import numpy as np
import pytest

from affine_deformers import accel
from affine_deformers.core import aff3, hierarchy, unwrap

# A forest: 0 → 1 → 2 → 3 (a chain), 1 → 4 (a sibling of 2), 5 → 6 (a second root).
PARENTS = np.array([-1, 0, 1, 2, 1, -1, 5])


def _motion(rng: np.random.Generator, turn: float = 1.0, affine: bool = True) -> np.ndarray:
    A = np.eye(4)
    w = rng.normal(size=3)
    w *= turn / np.linalg.norm(w)
    S = np.eye(3) + (0.2 * rng.normal(size=(3, 3)) if affine else 0.0)
    A[:3, :3] = aff3.so3_exp(w) @ (S if np.linalg.det(S) > 0 else np.eye(3))
    A[:3, 3] = rng.normal(size=3)
    return A


def _weights(rng: np.random.Generator, n: int, m: int, k: int, normalise: bool = True):
    indices = np.stack([rng.choice(m, size=k, replace=False) for _ in range(n)]).astype(np.int32)
    values = rng.random((n, k))
    values[rng.random((n, k)) < 0.3] = 0.0
    if normalise:
        sums = values.sum(axis=1, keepdims=True)
        values = np.divide(values, sums, out=np.zeros_like(values), where=sums > 0)
    return indices, values


def _reference(points, locals_, indices, values, parents) -> np.ndarray:
    """F_0 ⋯ F_D v, every factor evaluated (no prefix shortcut), one vertex at a time."""
    m = len(parents)
    depth = hierarchy.depths(parents)
    ancestor = np.eye(m, dtype=bool)  # ancestor[a, j]: a is j or above it
    for j in range(m):
        a = parents[j]
        while a >= 0:
            ancestor[a, j] = True
            a = parents[a]
    psi = aff3.params_from_matrices(locals_)
    out = np.empty_like(points)
    for v in range(len(points)):
        w = np.zeros(m)
        np.add.at(w, indices[v], values[v])
        W = ancestor.astype(float) @ w
        x = np.append(points[v], 1.0)
        for d in range(int(depth.max()), -1, -1):
            p = (W[depth == d, None] * psi[depth == d]).sum(axis=0)
            x = aff3.matrices_from_params(p[None])[0] @ x
        out[v] = x[:3]
    return out


def _case(seed: int, n: int = 150, normalise: bool = True, turn: float = 1.0):
    rng = np.random.default_rng(seed)
    m = len(PARENTS)
    locals_ = np.stack([_motion(rng, turn) for _ in range(m)])
    matrices = locals_.copy()
    for i in np.argsort(hierarchy.depths(PARENTS), kind="stable"):
        if PARENTS[i] >= 0:
            matrices[i] = matrices[PARENTS[i]] @ locals_[i]
    indices, values = _weights(rng, n, m, 3, normalise)
    points = rng.normal(size=(n, 3))
    return points, locals_, matrices, indices, values


def test_depths_and_cycles():
    assert hierarchy.depths(PARENTS).tolist() == [0, 1, 2, 3, 2, 0, 1]
    assert hierarchy.depths(np.zeros(0, dtype=int)).tolist() == []
    with pytest.raises(ValueError, match="cycle"):
        hierarchy.depths(np.array([1, 0, -1]))
    with pytest.raises(ValueError, match=r"\[-1"):
        hierarchy.depths(np.array([-1, 5]))


def test_local_motions_compose_back_to_the_full_motions():
    _, locals_, matrices, *_ = _case(0)
    got = hierarchy.local_motions(matrices, PARENTS)
    assert np.allclose(got, locals_, atol=1e-12)


@pytest.mark.parametrize("normalise", [True, False])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_points_match_the_direct_product(seed, normalise):
    points, locals_, matrices, indices, values = _case(seed, normalise=normalise)
    layout = hierarchy.chain_layout(indices, values, PARENTS)
    params = aff3.params_from_matrices(hierarchy.local_motions(matrices, PARENTS))
    got = hierarchy.chain_points(points, params, hierarchy.prefix_table(matrices), layout)
    want = _reference(points, locals_, indices, values, PARENTS)
    assert np.max(np.abs(got - want)) < 1e-10


def _table(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (aff3.params_from_matrices(hierarchy.local_motions(matrices, PARENTS)),
            hierarchy.prefix_table(matrices))


def _apply(columns: np.ndarray, points: np.ndarray) -> np.ndarray:
    linear = columns[0] * points[:, 0:1] + columns[1] * points[:, 1:2] + columns[2] * points[:, 2:3]
    return linear + columns[3]


@pytest.mark.parametrize("seed", [4, 5])
def test_motions_match_points_and_the_compiled_passes_agree(seed):
    points, _, matrices, indices, values = _case(seed)
    layout = hierarchy.chain_layout(indices, values, PARENTS)
    params, prefixes = _table(matrices)
    moved = hierarchy.chain_points(points, params, prefixes, layout)
    columns = hierarchy.chain_motions(params, prefixes, layout)
    passes = (params, layout.indices, layout.values, layout.prefix, prefixes)
    assert np.max(np.abs(_apply(columns, points) - moved)) < 1e-12
    compiled = accel.chain_points(points, *passes)
    assert np.max(np.abs(compiled - moved)) < 1e-12
    offsets = accel.chain_points(points, *passes, offsets=True)
    assert np.array_equal(offsets, compiled - points)
    compiled_m = accel.chain_motions(*passes)
    assert np.max(np.abs(compiled_m - columns)) < 1e-12
    compiled_32 = accel.chain_motions(*passes, np.empty((4, len(points), 3), np.float32))
    assert np.array_equal(compiled_32, compiled_m.astype(np.float32))


@pytest.mark.parametrize("compiled", [False, True])
def test_a_subset_of_rows_gives_the_same_bits(compiled, monkeypatch):
    if not compiled:
        monkeypatch.setenv(accel.ACCEL_ENV, "0")
    points, _, matrices, indices, values = _case(6, n=5000)
    layout = hierarchy.chain_layout(indices, values, PARENTS)
    params, prefixes = _table(matrices)
    args = (params, layout.indices, layout.values, layout.prefix, prefixes)
    whole = accel.chain_points(points, *args, offsets=True)
    whole32 = whole.astype(np.float32)
    whole_m = accel.chain_motions(*args)
    rows = np.sort(np.random.default_rng(0).choice(len(points), 2100, replace=False))
    part, part32 = np.full_like(whole, np.nan), np.zeros_like(whole32)
    accel.chain_points(points, *args, rows, part, offsets=True, out32=part32)
    part_m = np.full_like(whole_m, np.nan)
    accel.chain_motions(*args, part_m, rows=rows)
    assert np.array_equal(part[rows].view(np.int64), whole[rows].view(np.int64))
    assert np.isnan(np.delete(part, rows, axis=0)).all()  # the others untouched
    assert np.array_equal(part32[rows], whole32[rows])
    assert np.array_equal(part_m[:, rows].view(np.int64), whole_m[:, rows].view(np.int64))
    core = hierarchy.chain_points(points, params, prefixes, layout, rows)
    assert np.max(np.abs(core - points[rows] - part[rows])) < 1e-12


def test_fully_weighted_vertices_follow_their_control_exactly_and_use_the_prefix():
    points, _, matrices, _, _ = _case(7, n=len(PARENTS))
    indices = np.arange(len(PARENTS), dtype=np.int32)[:, None]
    values = np.ones((len(PARENTS), 1)) * (1.0 + 3e-8)  # float32-stored weights are this close to 1
    layout = hierarchy.chain_layout(indices, values, PARENTS)
    assert layout.prefix.tolist() == list(range(len(PARENTS)))
    assert len(layout.indices) == 0  # the prefix alone: no blend pass
    params = aff3.params_from_matrices(hierarchy.local_motions(matrices, PARENTS))
    got = hierarchy.chain_points(points, params, hierarchy.prefix_table(matrices), layout)
    want = np.einsum("nij,nj->ni", matrices[:, :3, :3], points) + matrices[:, :3, 3]
    assert np.max(np.abs(got - want)) < 1e-12


def test_the_prefix_stops_where_weight_splits():
    # vertex 0: half on 2, half on 4 (siblings under 1): prefix 1, one level of two controls;
    # vertex 1: half on 0 and 3: prefix 0, levels 1..3 each at 0.5; vertex 2: on roots 0 and 5.
    # vertex 3 (weights not normalised): all of 0 and half of 5 — two roots, so no prefix either.
    indices = np.array([[2, 4], [0, 3], [0, 5], [0, 5]], dtype=np.int32)
    values = np.array([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5], [1.0, 0.5]])
    layout = hierarchy.chain_layout(indices, values, PARENTS)
    m = len(PARENTS)
    assert layout.prefix.tolist() == [1, 0, m, m]  # m: none (the identity row)

    def row(r: int, v: int) -> dict[int, float]:
        idx, val = layout.indices[r], layout.values[r]
        return {int(i): float(w) for i, w in zip(idx[v], val[v], strict=True) if w != 0.0}

    assert len(layout.indices) == 3  # vertex 1 has three factors
    assert [row(0, v) for v in range(4)] == [{2: 0.5, 4: 0.5}, {3: 0.5}, {0: 0.5, 5: 0.5}, {0: 1.0, 5: 0.5}]
    assert [row(1, v) for v in range(4)] == [{}, {2: 0.5}, {}, {}]
    assert [row(2, v) for v in range(4)] == [{}, {1: 0.5}, {}, {}]
    # readers: control 1 is read by vertex 0 (its prefix) and vertex 1 (its level 1)
    assert layout.affected_rows([1]).tolist() == [0, 1]
    assert layout.affected_rows([5, 4]).tolist() == [0, 2, 3]


def test_affected_rows_hold_every_vertex_a_control_moves():
    points, _, matrices, indices, values = _case(8, n=300)
    layout = hierarchy.chain_layout(indices, values, PARENTS)
    params = aff3.params_from_matrices(hierarchy.local_motions(matrices, PARENTS))
    full = hierarchy.prefix_table(matrices)
    before = hierarchy.chain_points(points, params, full, layout)
    for c in range(len(PARENTS)):
        changed_params, changed_full = params.copy(), full.copy()
        changed_params[c, 0] += 0.1
        changed_full[c, 9] += 0.1
        after = hierarchy.chain_points(points, changed_params, changed_full, layout)
        moved = np.flatnonzero(np.any(after != before, axis=1))
        assert set(moved) <= set(layout.affected_rows([c]).tolist())
        assert len(moved) > 0


def test_weights_moving_across_bones_give_a_continuous_field():
    # A vertex slides from (0.5 on 1, 0.5 on 2) to (0.5 on 2, 0.5 on 3): the bone set changes at t = ½.
    _, _, matrices, _, _ = _case(9)
    t = np.linspace(0.0, 1.0, 2001)
    values = np.stack([np.clip(1 - 2 * t, 0, 1) * 0.5, 0.5 + 0 * t, np.clip(2 * t - 1, 0, 1) * 0.5], axis=1)
    values[:, 1] = 1.0 - values[:, 0] - values[:, 2]
    indices = np.tile(np.array([1, 2, 3], dtype=np.int32), (len(t), 1))
    layout = hierarchy.chain_layout(indices, values, PARENTS)
    params = aff3.params_from_matrices(hierarchy.local_motions(matrices, PARENTS))
    points = np.tile([[0.3, -0.2, 0.7]], (len(t), 1))
    x = hierarchy.chain_points(points, params, hierarchy.prefix_table(matrices), layout)
    steps = np.linalg.norm(np.diff(x, axis=0), axis=1)
    assert steps.max() < 5 * np.median(steps) + 1e-9


def test_a_child_twisted_past_half_a_turn_under_a_turned_parent_stays_on_its_axis():
    # Bar along x: parent 0 at the origin turned 10° about z, child 1 at x = 1 twisted 270° about x.
    parents = np.array([-1, 0])
    parent = np.eye(4)
    parent[:3, :3] = aff3.so3_exp(np.array([0.0, 0.0, np.radians(10.0)]))
    twist = np.eye(4)
    twist[:3, :3] = aff3.so3_exp(np.array([np.radians(270.0), 0.0, 0.0]))
    joint = np.eye(4)
    joint[0, 3] = 1.0
    local = joint @ twist @ np.linalg.inv(joint)
    matrices = np.stack([parent, parent @ local])
    params = aff3.params_from_matrices(hierarchy.local_motions(matrices, parents))
    params = unwrap.lift_params(params, np.array([[0.0, 0.0, 0.0], [np.radians(270.0), 0.0, 0.0]]),
                                np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))  # the 270° branch
    assert np.isclose(np.linalg.norm(params[1, :3]), np.radians(270.0))
    ring = np.array([[1.0, 0.2 * np.cos(a), 0.2 * np.sin(a)] for a in np.linspace(0, 2 * np.pi, 12)])
    layout = hierarchy.chain_layout(np.array([[0, 1]] * len(ring)), np.full((len(ring), 2), 0.5), parents)
    got = hierarchy.chain_points(ring, params, hierarchy.prefix_table(matrices), layout)
    back = (got - parent[:3, 3]) @ parent[:3, :3]  # undo the parent's turn: the child's local frame
    assert np.allclose(back[:, 0], 1.0, atol=1e-12)  # on the joint's plane
    assert np.allclose(np.hypot(back[:, 1], back[:, 2]), 0.2, atol=1e-12)  # at the ring's radius
    angle = np.degrees(np.arctan2(back[0, 2], back[0, 1]))
    assert np.isclose(angle % 360.0, 135.0, atol=1e-9)


# --- the truncation's pooled weight on the tree (MATH.md §12) ------------------------------------


def test_pool_mix_rows_are_children_means_by_tree_share():
    """μ_i mixes control i's children by the scale-weighted share of each one's subtree, μ_⊤ the
    roots; a leaf's row is the leaf itself (or 0 as local parameters); every row sums to 1."""
    scales = np.array([1.0, 1.0, 2.0, 1.0, 1.0, 1.0, 3.0])
    mix = hierarchy.pool_mix(PARENTS, scales)
    a = scales / scales.sum()
    share = hierarchy.subtree_sums(a, PARENTS)
    np.testing.assert_allclose(share[[0, 5]], [6 / 10, 4 / 10])
    np.testing.assert_allclose(mix.sum(axis=1), 1.0)
    np.testing.assert_allclose(mix[1, [2, 4]], share[[2, 4]] / share[[2, 4]].sum())  # two children
    np.testing.assert_allclose(mix[0, 1], 1.0)
    np.testing.assert_allclose(mix[7, [0, 5]], share[[0, 5]])  # μ_⊤: the roots
    np.testing.assert_array_equal(mix[[3, 4, 6], [3, 4, 6]], 1.0)  # leaves
    local = hierarchy.pool_mix(PARENTS, scales, leaves=False)
    assert not local[[3, 4, 6]].any() and np.array_equal(local[[0, 1, 2, 5, 7]], mix[[0, 1, 2, 5, 7]])
    np.testing.assert_array_equal(hierarchy.pool_parents(PARENTS),
                                  [-1, 0, 1, 2, 1, -1, 5, 0, 1, 2, 3, 4, 5, 6, -1])


def _pooled_field(points, matrices, indices, values, scales=None):  # type: ignore[no-untyped-def]
    m = len(PARENTS)
    scales = np.ones(m) if scales is None else scales
    params = aff3.params_from_matrices(hierarchy.local_motions(matrices, PARENTS))
    P, M = hierarchy.pool_tables(params, matrices, hierarchy.pool_mix(PARENTS, scales))
    layout = hierarchy.chain_layout(indices, values, hierarchy.pool_parents(PARENTS))
    return hierarchy.chain_points(points, P, hierarchy.prefix_table(M), layout)


def test_a_pooled_node_blends_as_its_mix_of_controls():
    """Weight x on μ_i (or μ_⊤) moves a vertex exactly as weights x·mix on the controls (the mix's
    rows of core.hierarchy.pool_mix), down the hierarchy."""
    rng = np.random.default_rng(3)
    m = len(PARENTS)
    A = np.stack([_motion(rng, 0.8) for _ in range(m)])
    scales = rng.uniform(0.5, 2.0, m)
    mix = hierarchy.pool_mix(PARENTS, scales)
    n = 60
    points = rng.normal(size=(n, 3))
    kept, kv = _weights(rng, n, m, 3)
    node = rng.integers(m, 2 * m + 1, size=(n, 1)).astype(np.int32)
    x = rng.uniform(0.0, 1.0, size=(n, 1))
    pooled = _pooled_field(points, A, np.hstack([kept, node]), np.hstack([kv * (1 - x), x]), scales)
    dense = np.zeros((n, m))
    np.add.at(dense, (np.arange(n)[:, None], kept), kv * (1 - x))
    dense += x * mix[node[:, 0] - m]
    idx = np.broadcast_to(np.arange(m, dtype=np.int32), (n, m))
    params = aff3.params_from_matrices(hierarchy.local_motions(A, PARENTS))
    direct = hierarchy.chain_points(points, params, hierarchy.prefix_table(A),
                                    hierarchy.chain_layout(idx, dense, PARENTS))
    np.testing.assert_allclose(pooled, direct, atol=1e-10)


def test_pool_point_is_local_sums_to_one_and_follows_a_common_motion():
    """PoolPoint: shares sum to 1 on 4 nodes of the pooled numbering; a vertex whose weight lies in
    one subtree pools there, not in another tree; a motion shared by all controls moves every
    vertex exactly, however its weight is pooled."""
    rng = np.random.default_rng(8)
    m = len(PARENTS)
    W = rng.random((200, m)) ** 4
    W[:50, 5:] = 0.0  # all of its weight in the first tree
    idx, shares = hierarchy.PoolPoint(PARENTS)(W)
    assert idx.shape == (200, 4) and idx.min() >= 0 and idx.max() <= 2 * m
    np.testing.assert_allclose(shares.sum(axis=1), 1.0)
    first_tree = np.array([0, 1, 2, 3, 4])
    assert np.isin(idx[:50][shares[:50] > 0], np.concatenate([first_tree, m + first_tree])).all()
    G = _motion(rng, 1.2)
    A = np.broadcast_to(G, (m, 4, 4)).copy()
    kept, kv = _weights(rng, 200, m, 3)
    kv[kv.sum(axis=1) == 0.0, 0] = 1.0  # every row a partition of unity
    lam = rng.uniform(0.0, 1.0, (200, 1))
    points = rng.normal(size=(200, 3))
    moved = _pooled_field(points, A, np.hstack([kept, idx]), np.hstack([kv * (1 - lam), lam * shares]))
    np.testing.assert_allclose(moved, points @ G[:3, :3].T + G[:3, 3], atol=1e-10)


def test_pool_point_moves_continuously_with_the_weights():
    """Weights moving along a path through every configuration (a bone's weight rising past its
    siblings', a subtree's share crossing 1/2): the pooled weights on the controls (mix applied)
    change by at most a bounded multiple of the weights' own change."""
    rng = np.random.default_rng(11)
    m = len(PARENTS)
    mix = hierarchy.pool_mix(PARENTS, np.ones(m))
    a, b = rng.random(m) ** 3, rng.random(m) ** 3
    t = np.linspace(0.0, 1.0, 20001)[:, None]
    W = (1 - t) * a + t * b
    idx, shares = hierarchy.PoolPoint(PARENTS)(W)
    nodes = np.vstack([np.eye(m), mix])
    on_controls = np.einsum("nk,nkm->nm", shares, nodes[idx])
    cumulative = hierarchy.subtree_sums(on_controls, PARENTS)
    fractions = hierarchy.subtree_sums(W / W.sum(axis=1, keepdims=True), PARENTS)
    step = np.abs(np.diff(cumulative, axis=0)).max()
    assert step <= 4.0 * m * np.abs(np.diff(fractions, axis=0)).max() / hierarchy.POOL_BAND


def test_a_flat_forest_pools_to_the_mean_of_all_controls():
    """Every control a root (no hierarchy) and none holding half the weight: the pooled weight goes
    to μ_⊤, the scale-weighted mean, as the probes' pooled control (core.weights.pool_weights)."""
    parents = np.full(6, -1)
    W = 0.5 + np.random.default_rng(2).random((30, 6))
    idx, shares = hierarchy.PoolPoint(parents)(W)
    on = shares > 0.0
    assert np.all(idx[on] == 12) and np.allclose(shares.sum(axis=1), 1.0)
    mix = hierarchy.pool_mix(parents, np.arange(1.0, 7.0))
    np.testing.assert_allclose(mix[6], np.arange(1.0, 7.0) / 21.0)
