"""Probe defaults show no seams (issue 12): 8 probes, inverse distance, exponent 2, 'SUM', 6 influences
(what the add operator sets; files of 0.1.0 keep their 4).

The deformation field d(x) = φ(Σ_k w_k(x) ψ(A_k)) x − x of 8 probes with different rotations and
scales is sampled on fine grids over surfaces a mesh occupies, grids that cross many places where the
4th and 5th strongest probes swap. Criterion, per grid: no jump |d(x) − d(x')| between neighbouring
samples exceeds 3× the largest jump of the untruncated field (the same rig with 8 influences) at the
same spacing, and the largest jumps shrink when their grid steps are sampled 10× and 100× finer (a
true discontinuity keeps its size). The 0.1.0 rule (plain top-K, renormalised) fails it; the
continuous truncation (weights.truncate) passes.

Where the criterion cannot hold: at a point where the 5 strongest weights tie exactly (e.g. the
centre of 8 probes at the corners of a cube) no 4-sparse normalised rule is continuous, and near such
near-ties (deep inside a cloud of probes, far from all of them) steps are steeper than the
untruncated field's (measured up to ~6× in random 8-probe clouds, volume grids); see weights.truncate
and the last test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from affine_deformers.core import aff3, deform
from affine_deformers.core import weights as wt

K_DEFAULT = 6  # object.affine_probe_deformer_add's default max_influences
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
    else:  # the deformer's defaults
        idx, val = wt.probe_weights(points, centers, mode="INVERSE_DISTANCE", exponent=2.0, normalize="SUM",
                                    k=k)
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


def test_default_influences_have_no_steep_steps_inside_probe_clouds() -> None:
    """Random 8-probe clouds sampled through their whole volume (where near-ties of the strongest
    probes happen, unlike on most surfaces): with the default 6 influences every step stays within
    3× the untruncated field's; with 4 some clouds exceed it (why the default is 6)."""
    worst = {4: 0.0, 6: 0.0}
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        centers = rng.normal(size=(8, 3))
        params = motions(seed)
        axis = np.linspace(-1.5, 1.5, 41)
        G = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1)
        full = field(G.reshape(-1, 3), centers, params, 8, "defaults").reshape(G.shape)
        full_step = max(np.linalg.norm(np.diff(full, axis=a), axis=-1).max() for a in range(3))
        for k in worst:
            D = field(G.reshape(-1, 3), centers, params, k, "defaults").reshape(G.shape)
            step = max(np.linalg.norm(np.diff(D, axis=a), axis=-1).max() for a in range(3))
            worst[k] = max(worst[k], step / full_step)
    print(f"\nworst step ÷ untruncated, volume grids: {worst}")
    assert worst[K_DEFAULT] <= JUMP_RATIO
    assert worst[4] > JUMP_RATIO, "4 influences do exceed it somewhere (the test can fail)"


@pytest.mark.parametrize("name", ["sphere", "scattered", "scattered_inner"])
def test_plain_top_k_fails_the_same_criterion(name: str) -> None:
    """The control: the 0.1.0 rule on the same grids has steps that do not shrink under refinement.
    (Not on the bar: with 6 of 8 probes kept along a line, the dropped probe is far and its weight
    negligible where it drops, so even plain top-K barely steps there.)"""
    report = seam_report(name, "plain")
    print(f"\n{name}: plain top-K {report}")
    assert report["shrink"][0] > 0.5 and report["shrink"][1] > 0.5, report
    assert report["ratio"] > 1.0


def test_exact_ties_are_inherent_point_seams() -> None:
    """8 probes at the corners of a cube: at the centre all 8 weights tie, and along a line through it
    the 4 kept probes flip from one face to the other. The truncated field's step there keeps its
    size under refinement (no 4-sparse normalised rule is continuous at such a point), while 8
    influences are smooth; the centre itself gets one of the one-sided limits, not the rest shape."""
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
    assert steps[4, 10000] > 0.9 * steps[4, 100], "4 influences at an exact tie: a jump"
    _, val = wt.probe_weights(np.zeros((1, 3)), centers, k=4)
    assert val.sum() == pytest.approx(1.0) and np.all(val > 0), "the tied centre still follows the probes"
