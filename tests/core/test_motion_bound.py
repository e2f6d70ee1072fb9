"""core.deform.motion_bound: an O(m) bound on every vertex's result, which lets the Blender layer
skip the finiteness pass over N vertices. It must hold on adversarial parameters (large stretches,
lifted rotations, negative weights) and give up (inf) on non-finite or overflowing input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from affine_deformers.core import aff3, deform


def _rows(rng: np.random.Generator, m: int, y_scale: float, u_scale: float,
          theta_max: float) -> np.ndarray:
    axes = rng.normal(size=(m, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    omega = axes * rng.uniform(0.0, theta_max, size=(m, 1))
    u, y = rng.normal(size=(m, 3)) * u_scale, rng.normal(size=(m, 6)) * y_scale
    return np.concatenate([omega, u, y], axis=1)


@pytest.mark.parametrize("y_scale,u_scale,theta_max",
                         [(0.01, 1.0, 1.0), (1.0, 10.0, 3.0), (3.0, 1e3, 6.0 * np.pi), (0.0, 0.0, 19.0)])
def test_bound_holds_for_every_vertex(y_scale: float, u_scale: float, theta_max: float) -> None:
    rng = np.random.default_rng(int(y_scale * 100 + u_scale))
    m, n, k = 7, 4000, 4
    params = _rows(rng, m, y_scale, u_scale, theta_max)
    idx = rng.integers(0, m, size=(n, k)).astype(np.int32)
    val = rng.normal(size=(n, k))  # negative and non-normalised weights too
    radius = 2.5
    pts = rng.normal(size=(n, 3))
    pts *= radius * rng.uniform(0.0, 1.0, size=(n, 1)) ** 0.2 / np.linalg.norm(pts, axis=1, keepdims=True)
    pts[0] *= radius / np.linalg.norm(pts[0])  # one on the sphere itself
    bound = deform.motion_bound(params, float(np.abs(val).sum(axis=1).max()), radius)
    moved = deform.deform_points_params(pts, params, idx, val)
    # the exact map of the blended rows (aff3.phi), not the kernel: the bound is about φ itself
    blended = deform.blend_params(params, idx, val)
    exact = np.einsum("nij,nj->ni", aff3.matrices_from_params(blended)[:, :3, :3], pts) \
        + aff3.matrices_from_params(blended)[:, :3, 3]
    assert np.isfinite(bound)
    # `exact` is φ evaluated in floating point: a pure rotation of a point on the sphere can round
    # to one ulp above its radius, as the kernel's result can
    assert np.linalg.norm(exact, axis=1).max() <= bound * (1 + 1e-12)
    assert np.linalg.norm(moved, axis=1).max() <= bound * (1 + 1e-12)
    # and it is not vacuous: within a modest factor of the largest result for mild rows
    if y_scale <= 0.01:
        assert bound < 4.0 * (radius + float(np.abs(val).sum(axis=1).max()) * u_scale * 3.0)


def test_bound_gives_up_on_bad_rows() -> None:
    rows = np.zeros((2, 12))
    assert deform.motion_bound(rows, 1.0, 3.0) == 3.0  # at rest: the points themselves
    assert deform.motion_bound(np.zeros((0, 12)), 1.0, 3.0) == 3.0
    for k, bad in ((0, np.nan), (4, np.inf), (7, np.nan)):
        broken = rows.copy()
        broken[1, k] = bad
        assert deform.motion_bound(broken, 1.0, 3.0) == math.inf
    huge = rows.copy()
    huge[0, 6] = 800.0  # e^800 overflows float64
    assert deform.motion_bound(huge, 1.0, 3.0) == math.inf
    assert math.isfinite(deform.motion_bound(huge, 0.5, 3.0))  # half the weight: e^400
