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


# --- fast paths for few controls: each must give what the general path gives, row by row ----------
# The update path calls ψ, the channel reference and the lift for one or two controls at a time, so
# the core skips branches no row needs and runs its checks on Python floats for short batches. These
# tests pin that every such shortcut is either bit-identical to the general path or only a decision
# that the general path would make the same way.


def _boundary_affines() -> list[np.ndarray]:
    """Matrices on both sides of every acceptance boundary of validate_affine."""
    out = []
    for det_part in (np.diag([1e-100, 1e-100, 1e-100]), np.diag([1.0, 1.0, 0.0]),
                     np.diag([1.0, 1.0, -1e-300]), np.diag([1e120, 1.0, 1.0]), np.diag([1e120, 1e120, 1e120]),
                     np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]),  # det rounds near 0
                     np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0 + 1e-15]]),
                     np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 1.0], [0.0, 1.0, 2.0]])):
        A = np.eye(4)
        A[:3, :3] = det_part
        out.append(A)
    tol = aff3.BOTTOM_ROW_TOL
    for slot, value in [(0, tol), (1, -tol), (2, 1.0000001 * tol), (3, 1.0 + tol), (3, 1.0 - 2.0 * tol),
                        (0, -0.0)]:
        A = np.eye(4)
        A[3, slot] = value
        out.append(A)
    for value in (np.nan, np.inf, -np.inf, 1e308):
        for where in ((0, 0), (1, 3), (3, 3)):
            A = np.eye(4)
            A[where] = value
            out.append(A)
    return out


def _full_check_accepts(A: np.ndarray) -> bool:
    try:
        aff3._validate_affine_full(A[None], "transform")
    except ValueError:
        return False
    return True


def test_validation_prechecks_agree_with_the_full_check_on_boundaries():
    """The scalar pre-check (short batches) and the numpy one (long batches) only ever accept what the
    full check accepts, and on finite input of moderate size they decide exactly like it; so whether a
    matrix is accepted never depends on the batch it comes in."""
    cases = _boundary_affines()
    for A in cases:
        full = _full_check_accepts(A)
        scalar = aff3._affine_rows_ok_scalar([A.reshape(16).tolist()])
        vector = aff3._affine_rows_ok(np.tile(A.reshape(1, 16), (aff3._FEW_ROWS + 1, 1)))
        assert not scalar or full, A
        assert not vector or full, A
        if np.all(np.isfinite(A)) and np.abs(A).max() < 1e100:
            assert scalar == full == vector, A
    # accepted alone exactly when accepted in a long batch of good rows
    good = _adversarial()[:20]
    for A in cases:
        alone = _full_check_accepts(A)
        batch = np.concatenate([good, A[None]])
        try:
            aff3.validate_affine(batch)
            in_batch = True
        except ValueError:
            in_batch = False
        assert alone == in_batch, A
    accepted = sum(_full_check_accepts(A) for A in cases)
    assert accepted >= 8 and len(cases) - accepted >= 8


def test_so3_log_shortcut_branches_match_the_general_ones_bitwise():
    """so3_log skips the guarded ratio (every sin θ > 0) and the axis branch (every θ ≤ π/2) when no row
    needs them; the same rows computed next to rows that do need them give the same bits."""
    rng = np.random.default_rng(11)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    thetas = np.concatenate([[1e-300, 1e-12, 1e-8, 0.1999, 0.2, 0.2001], rng.uniform(0.0, np.pi / 2, 34)])
    easy = aff3.so3_exp(thetas[:, None] * axes)
    hard = aff3.so3_exp(np.array([[0.0, 0.0, 0.0], [0.0, 2.5, 0.0], [np.pi, 0.0, 0.0]]))
    alone = aff3.so3_log(easy)
    mixed = aff3.so3_log(np.concatenate([hard[:1], easy, hard[1:]]))[1:-2]
    assert np.array_equal(alone.view(np.int64), mixed.view(np.int64))
    np.testing.assert_allclose(alone, thetas[:, None] * axes, rtol=0, atol=1e-15)
    # Jacobian inverse: closed-form-only batches (θ ∈ [0.2, 2π)) vs the same rows next to series rows
    w = np.concatenate([rng.uniform(0.2, 6.2, (30, 1)) * axes[:30], [[0.2, 0.0, 0.0], [0.0, 5.999, 0.0]]])
    general = aff3.left_jacobian_inv(np.concatenate([[[1e-3, 0.0, 0.0]], w, [[0.0, 0.0, 7.0]]]))[1:-1]
    shortcut = aff3.left_jacobian_inv(w)
    assert np.array_equal(shortcut.view(np.int64), general.view(np.int64))
    np.testing.assert_allclose(shortcut @ aff3.left_jacobian(w), np.broadcast_to(np.eye(3), shortcut.shape),
                               rtol=0, atol=1e-13)


def test_cross_matches_numpy_cross():
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(2, 50, 3)) * rng.choice([1e-8, 1.0, 1e8], size=(2, 50, 1))
    np.testing.assert_array_equal(aff3._cross(a, b), np.cross(a, b))
    np.testing.assert_array_equal(aff3._cross(a[0], b), np.cross(a[0], b))


def test_lift_shortcut_only_skips_rows_the_lift_leaves_unchanged():
    """lift_params returns its input when every |w_ref − w| < 3 (< π: no row can change branch). Rows
    right at that bound, at every angle up to π, really are left unchanged by the lift itself, and
    the same rows next to one that does lift give the same bits."""
    rng = np.random.default_rng(8)
    n = rng.normal(size=(60, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    theta = np.concatenate([[0.0, 1e-9, 2e-3, 3.1e-3, np.pi - 1e-12, np.pi], rng.uniform(0.0, np.pi, 54)])
    w = theta[:, None] * n
    d = rng.normal(size=(60, 3))
    d *= (np.nextafter(3.0, 0.0) * rng.uniform(0.5, 1.0, (60, 1))) / np.linalg.norm(d, axis=1, keepdims=True)
    d[:6] = np.nextafter(3.0, 0.0) * n[:6]  # straight along the axis: the worst case
    ref = w + d
    P = np.concatenate([w, rng.normal(size=(60, 9))], axis=1)
    assert np.array_equal(unwrap.lift_rotvec(w, ref, axis_tol=3e-3).view(np.int64), w.view(np.int64))
    # just past π along the axis the lift does act, and lift_params must not skip those rows
    beyond = w[:5] + 3.2 * n[:5]
    lifted = unwrap.lift_params(P[:5], beyond, None, damping=1e-3, axis_tol=3e-3)
    assert np.all(lifted[:, :3] != P[:5, :3], axis=1).all()
    assert np.array_equal(lifted[:, :3], unwrap.lift_rotvec(w[:5], beyond, axis_tol=3e-3))
    short = unwrap.lift_params(P, ref, None, damping=1e-3, axis_tol=3e-3)
    assert short is not P and np.array_equal(short.view(np.int64), P.view(np.int64))
    for i in range(len(P)):  # short batches take the check on Python floats
        one = unwrap.lift_params(P[i : i + 1], ref[i : i + 1], None, damping=1e-3, axis_tol=3e-3)
        assert np.array_equal(one.view(np.int64), P[i : i + 1].view(np.int64))
    lifting_row = np.concatenate([[3.0, 0.0, 0.0], np.zeros(9)])
    general = unwrap.lift_params(np.concatenate([P, lifting_row[None]]),
                                 np.concatenate([ref, [[3.0 - TAU, 0, 0]]]), None,
                                 damping=1e-3, axis_tol=3e-3)
    assert np.array_equal(general[:-1].view(np.int64), P.view(np.int64))
    assert general[-1, 0] == pytest.approx(3.0 - TAU)


TAU = 2.0 * np.pi


@pytest.mark.parametrize("order", unwrap.EULER_ORDERS)
def test_one_step_channel_path_is_the_sampled_path_and_matches_scipy(order):
    """Euler rows that change by less than one step skip the sampling machinery; they give the bits of
    the sampled path on its grid s = (0, 1), and the rotation vector of R(cur)·R(rest)ᵀ (scipy)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(21)
    rest = rng.uniform(-4.0, 4.0, (40, 3))
    step = rng.normal(size=(40, 3))
    step *= rng.uniform(0.0, np.pi / 4, (40, 1)) / np.abs(step).sum(axis=1, keepdims=True)
    step[0] = 0.0
    cur = rest + step
    # rest channels several times larger than the current ones: rest + (cur − rest) is then often not
    # cur itself, so the path must form the sample as written
    rest[20:] = rng.choice([-1.0, 1.0], (20, 3)) * rng.uniform(0.15, 0.2, (20, 3))
    cur[20:] = rng.uniform(-0.05, 0.05, (20, 3))
    assert np.any(rest + (cur - rest) != cur)
    fast = unwrap.channel_rotvec(order, rest, cur)
    sampled = unwrap._unwrap_sampled(order, rest, cur, np.tile([0.0, 1.0], (40, 1)))
    assert np.array_equal(fast.view(np.int64), sampled.view(np.int64))
    seq = order.lower()  # Blender's first letter is applied first: scipy's extrinsic sequence

    def rotation(angles):
        return Rotation.from_euler(seq, angles[:, ["xyz".index(c) for c in seq]])

    expected = (rotation(cur) * rotation(rest).inv()).as_rotvec()
    np.testing.assert_allclose(fast, expected, rtol=0, atol=1e-13)
    assert np.array_equal(fast[0], np.zeros(3))


def test_channel_rows_mixing_one_step_and_sampled_paths_do_not_depend_on_the_batch():
    rng = np.random.default_rng(4)
    modes = ["XYZ", "XYZ", "ZXY", "XYZ", "AXIS_ANGLE", "QUATERNION", "ZXY", "XYZ", "YZX", "XYZ"]
    rest = rng.normal(size=(10, 4))
    scale = np.array([0.01, 3.0, 0.1, 0.0, 0.5, 0.3, 5.0, 0.2, 0.05, 1.0])
    cur = rest + rng.normal(size=(10, 4)) * scale[:, None]
    for batch_modes in (modes, ["XYZ"] * 10):
        batch = unwrap.channel_rotvec(batch_modes, rest, cur)
        single = np.concatenate([unwrap.channel_rotvec([m], rest[i : i + 1], cur[i : i + 1])
                                 for i, m in enumerate(batch_modes)])
        assert np.array_equal(batch.view(np.int64), single.view(np.int64))
        for i, m in enumerate(batch_modes):
            R = unwrap.channels_to_matrix(m, cur[i, : 3 if m in unwrap.EULER_ORDERS else 4]) @ \
                unwrap.channels_to_matrix(m, rest[i, : 3 if m in unwrap.EULER_ORDERS else 4]).T
            np.testing.assert_allclose(aff3.so3_exp(batch[i]), R, rtol=0, atol=1e-12)


def test_euler_matrices_are_the_factor_by_factor_products_bitwise():
    """euler_to_matrix builds the three axis rotations in one pass; the result is bit for bit the
    literal construction (one rotation matrix per axis, multiplied in channel order)."""
    rng = np.random.default_rng(2)

    def axis_rotation(axis, angle):
        c, s = np.cos(angle), np.sin(angle)
        i, j = (axis + 1) % 3, (axis + 2) % 3
        out = np.zeros((*np.shape(angle), 3, 3))
        out[..., axis, axis] = 1.0
        out[..., i, i] = c
        out[..., j, j] = c
        out[..., j, i] = s
        out[..., i, j] = -s
        return out

    for order in unwrap.EULER_ORDERS:
        for shape in [(3,), (1, 3), (7, 3), (2, 5, 3)]:
            angles = rng.uniform(-20.0, 20.0, shape)
            axes = ["XYZ".index(c) for c in order]
            expected = axis_rotation(axes[0], angles[..., axes[0]])
            for axis in axes[1:]:
                expected = axis_rotation(axis, angles[..., axis]) @ expected
            got = unwrap.euler_to_matrix(angles, order)
            assert got.shape == expected.shape
            assert np.array_equal(got.view(np.int64), expected.view(np.int64))
