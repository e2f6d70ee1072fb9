"""No seams where probes swap ranks: 8 probes, inverse distance, exponent 2, 'SUM', fewer
influences than probes (6; the add operator now sets 8, which keeps all 8: see
tests/core/test_field_ties.py for the defaults and for layouts whose probes tie).

The deformation field d(x) = φ(Σ_k w_k(x) ψ(A_k)) x − x of 8 probes with different rotations and
scales is sampled on fine grids over surfaces a mesh occupies, grids that cross many places where the
6th and 7th strongest probes swap. Criterion, per grid: no jump |d(x) − d(x')| between neighbouring
samples exceeds 3× the largest jump of the untruncated field (the same rig with 8 influences) at the
same spacing, and the largest jumps shrink when their grid steps are sampled 10× and 100× finer (a
true discontinuity keeps its size). The 0.1.0 rule (plain top-K, renormalised) fails it; the
truncation (weights.truncate, MATH.md §12) passes.

Where the strongest probes tie exactly (e.g. the centre of 8 probes at the corners of a cube) no
K-sparse rule whose weights sum to 1 is continuous; the truncation's weights there pool into the mean
of all probes (the untruncated field's value at such a point), so the field stays continuous with
bounded steps (the last test).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from affine_deformers.core import aff3, deform
from affine_deformers.core import weights as wt

K_DEFAULT = 6  # fewer influences than the 8 probes: the truncation at work
JUMP_RATIO = 3.0
SHRINK = 0.25  # a continuous field's largest step shrinks ~10× per 10× refinement; a jump does not


def motions(seed: int, m: int = 8) -> np.ndarray:
    """Parameters (m, 12) of m different motions: rotations up to 1.2 rad, scales 0.7–1.4, shifts."""
    rng = np.random.default_rng(seed)
    A = np.tile(np.eye(4), (m, 1, 1))
    for i in range(m):
        axis = rng.normal(size=3)
        R = aff3.so3_exp(axis / np.linalg.norm(axis) * rng.uniform(0.3, 1.2))
        A[i, :3, :3] = R @ np.diag(np.exp(rng.uniform(-0.35, 0.35, 3)))
        A[i, :3, 3] = rng.normal(scale=0.5, size=3)
    return aff3.params_from_matrices(A)


def plain_top_k(points: np.ndarray, centers: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The 0.1.0 weights: the k largest inverse-distance weights, renormalised (no truncation)."""
    d = np.linalg.norm(points[:, None, :] - centers[None, :, :], axis=2)
    idx, val = wt.top_k(wt.inverse_distance(d, 2.0, 1.0), k)
    return idx, wt.normalize(val, "SUM")


def field(points: np.ndarray, centers: np.ndarray, params: np.ndarray, k: int, rule: str) -> np.ndarray:
    if rule == "plain":
        idx, val = plain_top_k(points, centers, k)
    else:  # the deformer's weights (inverse distance, exponent 2, 'SUM')
        idx, val = wt.probe_weights(points, centers, mode="INVERSE_DISTANCE", exponent=2.0, normalize="SUM",
                                    k=k)
        if idx.max() == len(centers):  # rows that pool weight read the pooled control (index m)
            params = wt.with_pool(params, wt.pool_weights(np.ones(len(centers))))
    return deform.deform_points_params(points, params, idx, val) - points


def fibonacci_sites(m: int, radius: float = 1.0) -> np.ndarray:
    k = np.arange(m) + 0.5
    z = 1 - 2 * k / m
    angle = np.pi * (3 - math.sqrt(5)) * k
    return radius * np.stack([np.sqrt(1 - z * z) * np.cos(angle), np.sqrt(1 - z * z) * np.sin(angle), z], 1)


def sphere_grid(n: int, radius: float = 1.0) -> np.ndarray:
    theta = np.linspace(0.02, np.pi - 0.02, n)
    phi = np.linspace(0.0, 2 * np.pi, 2 * n)
    t, f = np.meshgrid(theta, phi, indexing="ij")
    return radius * np.stack([np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), np.cos(t)], axis=-1)


def tube_grid(n: int, radius: float, half_length: float) -> np.ndarray:
    s = np.linspace(-half_length, half_length, 4 * n)
    phi = np.linspace(0.0, 2 * np.pi, n)
    S, F = np.meshgrid(s, phi, indexing="ij")
    return np.stack([S, radius * np.cos(F), radius * np.sin(F)], axis=-1)


def rigs() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (probe rest positions (8, 3), sample grid (n1, n2, 3))."""
    rng = np.random.default_rng(12)
    bar = np.stack([np.linspace(-4, 4, 8), np.zeros(8), np.zeros(8)], axis=1)
    bar += rng.normal(scale=0.15, size=(8, 3))
    scattered = rng.normal(size=(8, 3))
    scattered = 1.5 * scattered / np.linalg.norm(scattered, axis=1, keepdims=True)
    return {
        # the benchmark rig: 8 probes spread over a sphere, the sphere itself
        "sphere": (fibonacci_sites(8), sphere_grid(240)),
        # a bar with 8 probes along its axis, sampled on the bar's surface
        "bar": (bar, tube_grid(120, 0.5, 5.0)),
        # 8 probes scattered over a sphere of radius 1.5, sampled on it and on a shell inside
        "scattered": (scattered, sphere_grid(240, 1.5)),
        "scattered_inner": (scattered, sphere_grid(240, 1.2)),
    }


def grid_steps(D: np.ndarray) -> list[np.ndarray]:
    """|d(x) − d(x')| for neighbours along each grid axis: arrays (n1 − 1, n2), (n1, n2 − 1)."""
    return [np.linalg.norm(np.diff(D, axis=a), axis=-1) for a in range(2)]


def top_ranked(G: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """The set of the K_DEFAULT strongest probes at each grid point, as a bit mask."""
    d = np.linalg.norm(G[..., None, :] - centers, axis=-1)
    order = np.argsort(d, axis=-1)[..., :K_DEFAULT]
    return np.bitwise_or.reduce(1 << order, axis=-1)


def refine(G: np.ndarray, centers, params, k, rule, segments, levels=(10, 100)) -> list[float]:
    """Largest step over the given grid segments [(axis, i, j)] sampled `levels` times finer."""
    out = []
    for factor in levels:
        t = np.linspace(0.0, 1.0, factor + 1)[:, None]
        worst = 0.0
        for axis, i, j in segments:
            a = G[i, j]
            b = G[i + 1, j] if axis == 0 else G[i, j + 1]
            D = field(a + t * (b - a), centers, params, k, rule)
            worst = max(worst, float(np.linalg.norm(np.diff(D, axis=0), axis=1).max()))
        out.append(worst)
    return out


def seam_report(name: str, rule: str, seed: int = 3) -> dict:
    centers, G = rigs()[name]
    params = motions(seed)
    flat = G.reshape(-1, 3)
    steps = grid_steps(field(flat, centers, params, K_DEFAULT, rule).reshape(G.shape))
    full = grid_steps(field(flat, centers, params, 8, "defaults").reshape(G.shape))
    ranks = top_ranked(G, centers)
    swaps = [np.diff(ranks, axis=a) != 0 for a in range(2)]
    # the grid steps to look at finer: the 8 largest overall and the 8 largest across a swap
    candidates = []
    for axis in range(2):
        for mask in (np.ones_like(swaps[axis]), swaps[axis]):
            s = np.where(mask, steps[axis], -1.0).ravel()
            for flat_index in np.argsort(s)[-8:]:
                i, j = np.unravel_index(flat_index, steps[axis].shape)
                candidates.append((steps[axis][i, j], axis, int(i), int(j)))
    candidates = sorted(set(candidates), reverse=True)[:12]
    coarse = candidates[0][0]
    finer = refine(G, centers, params, K_DEFAULT, rule, [c[1:] for c in candidates])
    return {
        "swaps": int(sum(s.sum() for s in swaps)),
        "ratio": max(s.max() for s in steps) / max(s.max() for s in full),
        "shrink": [finer[0] / coarse, finer[1] / finer[0]],
    }


@pytest.mark.parametrize("name", ["sphere", "bar", "scattered", "scattered_inner"])
def test_default_probe_weights_have_no_seams(name: str) -> None:
    report = seam_report(name, "defaults")
    print(f"\n{name}: continuous truncation {report}")
    assert report["swaps"] > 200, "the grid crosses many places where the 4th and 5th probes swap"
    assert report["ratio"] <= JUMP_RATIO, report
    assert max(report["shrink"]) <= SHRINK, report


def steepest_step(D: np.ndarray) -> float:
    return max(float(np.linalg.norm(np.diff(D, axis=a), axis=-1).max()) for a in range(3))


def divided_by_excess(points: np.ndarray, centers: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The former continuous truncation: w_j − w_{K+1} renormalised by their sum S (steep where S → 0)."""
    W = wt.inverse_distance(np.linalg.norm(points[:, None, :] - centers[None, :, :], axis=2))
    idx, top = wt.top_k(W, k + 1)
    excess = top[:, :k] - top[:, k:]
    S = excess.sum(axis=1, keepdims=True)
    return idx[:, :k], np.where(S > 0.0, excess / np.where(S > 0.0, S, 1.0), wt.normalize(top[:, :k]))


def test_truncated_influences_have_no_steep_steps_inside_probe_clouds() -> None:
    """Random 8-probe clouds sampled through their whole volume (where near-ties of the strongest
    probes happen, unlike on most surfaces): with 4 and 6 influences every step stays within 3× the
    untruncated field's; dividing the lowered weights by their own sum (the former rule) exceeds it
    with 4 (the test can fail)."""
    worst = {4: 0.0, 6: 0.0, "former": 0.0}
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        centers = rng.normal(size=(8, 3))
        params = motions(seed)
        axis = np.linspace(-1.5, 1.5, 41)
        G = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1)
        flat = G.reshape(-1, 3)
        full_step = steepest_step(field(flat, centers, params, 8, "defaults").reshape(G.shape))
        for k in (4, 6):
            D = field(flat, centers, params, k, "defaults").reshape(G.shape)
            worst[k] = max(worst[k], steepest_step(D) / full_step)
        former = deform.deform_points_params(flat, params, *divided_by_excess(flat, centers, 4)) - flat
        worst["former"] = max(worst["former"], steepest_step(former.reshape(G.shape)) / full_step)
    print(f"\nworst step ÷ untruncated, volume grids: {worst}")
    assert worst[4] <= JUMP_RATIO and worst[6] <= JUMP_RATIO
    assert worst["former"] > JUMP_RATIO, "the former rule does exceed it somewhere (the test can fail)"


@pytest.mark.parametrize("name", ["sphere", "scattered", "scattered_inner"])
def test_plain_top_k_fails_the_same_criterion(name: str) -> None:
    """The control: the 0.1.0 rule on the same grids has steps that do not shrink under refinement.
    (Not on the bar: with 6 of 8 probes kept along a line, the dropped probe is far and its weight
    negligible where it drops, so even plain top-K barely steps there.)"""
    report = seam_report(name, "plain")
    print(f"\n{name}: plain top-K {report}")
    assert report["shrink"][0] > 0.5 and report["shrink"][1] > 0.5, report
    assert report["ratio"] > 1.0


def test_exact_ties_pool_into_the_mean_instead_of_seaming() -> None:
    """8 probes at the corners of a cube: at the centre all 8 weights tie, and along a line through it
    the 4 strongest flip from one face to the other. A 4-sparse rule whose weights sum to 1 jumps
    there (the former rule kept its step under refinement); the truncation pools the weight into the
    mean of the 8 motions near the centre, so its step shrinks like the untruncated field's and the
    centre gets exactly the untruncated value (the mean: all weights equal)."""
    centers = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    params = motions(5)
    b = np.array([0.3, 0.1, 0.05])
    a = -b  # through the centre: the kept 4 are the +x face on one side, the −x face on the other
    steps = {}
    for k in (4, 8):
        for n in (100, 1000, 10000):
            t = np.linspace(0.0, 1.0, n)[:, None]
            D = field(a + t * (b - a), centers, params, k, "defaults")
            steps[k, n] = np.linalg.norm(np.diff(D, axis=0), axis=1).max()
    assert steps[8, 10000] < 0.02 * steps[8, 100], "8 influences: continuous"
    assert steps[4, 10000] < 0.02 * steps[4, 100], "4 influences: continuous through the tie"
    assert steps[4, 10000] <= JUMP_RATIO * steps[8, 10000]
    t = np.linspace(0.0, 1.0, 1000)[:, None]
    line = a + t * (b - a)
    former = deform.deform_points_params(line, params, *divided_by_excess(line, centers, 4)) - line
    former_step = np.linalg.norm(np.diff(former, axis=0), axis=1).max()
    assert former_step > 10 * steps[4, 1000], "the former rule jumps"
    centre = np.zeros((1, 3))
    np.testing.assert_allclose(field(centre, centers, params, 4, "defaults"),
                               field(centre, centers, params, 8, "defaults"), atol=1e-12)
