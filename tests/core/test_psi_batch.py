"""Rows of ψ, of the branch lift and of the channel reference are computed independently of the other
rows in the batch, bit for bit. The Blender layer memoises parameters per control (evaluate.py) and only
recomputes the controls that changed, so this independence is what makes the memo a pure function:
a frame gives the same bits whichever controls were computed together before."""

from __future__ import annotations

import numpy as np
import pytest

from affine_deformers.core import aff3, unwrap


def _affine(w, stretch=(1.0, 1.0, 1.0), t=(0.0, 0.0, 0.0), shear=0.0) -> np.ndarray:
    A = np.eye(4)
    S = np.diag(stretch).astype(np.float64)
    S[0, 1] = shear
    A[:3, :3] = aff3.so3_exp(np.asarray(w, dtype=np.float64)) @ S
    A[:3, 3] = t
    return A


def _adversarial() -> np.ndarray:
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    thetas = [0.0, 1e-12, 1e-8, 1e-3, 0.2, 1.0, np.pi / 2, 3.0, np.pi - 1e-6, np.pi - 1e-9, np.pi]
    stretches = [(1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (1.0, 1.0, 1.0 + 1e-12), (1e3, 1.0, 1e-3), (0.5, 3.0, 3.0)]
    rows = []
    for i, theta in enumerate(thetas):
        for j, stretch in enumerate(stretches):
            t = (0.3 * i, -1e3 * (j == 3), 2.0)
            rows.append(_affine(theta * axis, stretch, t=t, shear=0.1 * (j == 4)))
    return np.stack(rows)


def test_psi_rows_do_not_depend_on_the_batch():
    A = _adversarial()
    batch = aff3.params_from_matrices(A)
    single = np.concatenate([aff3.params_from_matrices(A[i : i + 1]) for i in range(len(A))])
    assert np.array_equal(batch.view(np.int64), single.view(np.int64))
    reverse = aff3.params_from_matrices(A[::-1])[::-1]
    assert np.array_equal(batch.view(np.int64), reverse.view(np.int64))
    assert np.abs(batch).max() > 1.0  # the set really is non-trivial


@pytest.mark.parametrize("det_sign, message", [(-1.0, "determinant"), (0.0, "determinant")])
def test_mirrored_or_singular_rows_are_rejected_alone_and_in_a_batch(det_sign, message):
    A = _adversarial()[:5].copy()
    A[3, :3, 0] *= det_sign
    with pytest.raises(ValueError, match=message):
        aff3.params_from_matrices(A)
    with pytest.raises(ValueError, match=message):
        aff3.params_from_matrices(A[3:4])


def test_lift_rows_do_not_depend_on_the_batch():
    rng = np.random.default_rng(3)
    A = _adversarial()
    P = aff3.params_from_matrices(A)
    w = P[:, 0:3]
    n = w / np.where(np.linalg.norm(w, axis=1) > 0, np.linalg.norm(w, axis=1), 1.0)[:, None]
    turns = rng.integers(-2, 3, len(P))
    # references one or more turns away (and zero-angle rows with a reference: its axis is used)
    ref = w + (2 * np.pi * turns)[:, None] * np.where(np.linalg.norm(w, axis=1)[:, None] > 0, n, [0, 0, 1.0])
    pivots = rng.normal(size=(len(P), 3)) * 5.0
    batch = unwrap.lift_params(P, ref, pivots, damping=1e-3, axis_tol=3e-3)
    single = np.concatenate([unwrap.lift_params(P[i : i + 1], ref[i : i + 1], pivots[i : i + 1],
                                                damping=1e-3, axis_tol=3e-3) for i in range(len(P))])
    assert np.array_equal(batch.view(np.int64), single.view(np.int64))
    assert np.any(batch[:, :3] != P[:, :3])  # some rows really were lifted


def test_channel_reference_rows_do_not_depend_on_the_batch():
    """Rows with very different turn counts (so different path sample counts) in one batch give the same
    bits as each row alone; before, every row was sampled at the largest count of the batch."""
    modes = ["XYZ", "XYZ", "ZYX", "AXIS_ANGLE", "AXIS_ANGLE", "QUATERNION", "XYZ"]
    rest = np.array([[0, 0, 0, 0], [0.1, 0.2, 0.3, 0], [0.2, 0, 0.1, 0], [0.0, 0, 0, 1],
                     [0.5, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]], dtype=np.float64)
    cur = np.array([[0, 0, 4 * np.pi + 0.1, 0], [0.1, 0.2, 0.35, 0], [0.2, 0, 0.1 + np.radians(400), 0],
                    [6 * np.pi, 0, 0, 1], [0.6, 0, 1, 0.2], [0.9, 0.1, 0.2, 0.3], [0, 0, 0, 0]])
    batch = unwrap.channel_rotvec(modes, rest, cur)
    single = np.concatenate([unwrap.channel_rotvec([m], rest[i : i + 1], cur[i : i + 1])
                             for i, m in enumerate(modes)])
    assert np.array_equal(batch.view(np.int64), single.view(np.int64))
    np.testing.assert_allclose(batch[0], [0, 0, 4 * np.pi + 0.1], atol=1e-9)
    np.testing.assert_allclose(batch[3], [0, 0, 6 * np.pi], atol=1e-9)
    assert np.array_equal(batch[6], np.zeros(3))


def test_channel_reference_matches_sampling_every_row_at_the_largest_count():
    """The old behaviour (one sample count for the whole batch) and the per-row one agree to rounding."""
    rest = np.zeros((3, 3))
    cur = np.array([[0, 0, 0.3], [0, 0, 7 * np.pi + 0.2], [0.4, -0.2, 2.9]])
    s = unwrap._path_samples_euler(rest, cur, np.pi / 4)
    old = unwrap._unwrap_sampled("XYZ", rest, cur, s)
    new = unwrap.channel_rotvec("XYZ", rest, cur)
    np.testing.assert_allclose(new, old, rtol=0, atol=1e-13)


def test_params_from_matrices_equals_psi_in_the_layout_bit_for_bit():
    """The lean ψ path forms the 12 numbers directly; it must equal params_from_xy(*psi(A)) exactly."""
    rng = np.random.default_rng(7)
    A = np.tile(np.eye(4), (300, 1, 1))
    A[:, :3, :] = rng.normal(size=(300, 3, 4))
    A = np.concatenate([_adversarial(), A[np.linalg.det(A[:, :3, :3]) > 0]])
    lean = aff3.params_from_matrices(A)
    layered = aff3.params_from_xy(*aff3.psi(A))
    assert np.array_equal(lean.view(np.int64), layered.view(np.int64))
    assert aff3.params_from_matrices(A[0]).shape == (12,)
    assert aff3.params_from_matrices(A[:6].reshape(2, 3, 4, 4)).shape == (2, 3, 12)


def test_lift_params_without_a_lift_returns_the_rows_unchanged():
    P = aff3.params_from_matrices(_adversarial())
    lifted = unwrap.lift_params(P, P[:, 0:3], np.ones((len(P), 3)), damping=1e-3, axis_tol=3e-3)
    assert lifted is not P and np.array_equal(lifted.view(np.int64), P.view(np.int64))
