"""Rotation-branch unwrapping (core/unwrap.py, MATH.md §8): lifting, lifted se(3) logs, channels."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from affine_deformers.core.aff3 import (
    left_jacobian,
    matrices_from_params,
    params_from_matrices,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
)
from affine_deformers.core.unwrap import (
    EULER_ORDERS,
    axis_angle_to_matrix,
    channel_rotvec,
    euler_to_matrix,
    lift_params,
    lift_rotvec,
    quaternion_to_matrix,
    se3_log_lifted,
)

TAU = 2.0 * np.pi
Z = np.array([0.0, 0.0, 1.0])


def literal_axis_rotation(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return {
        "X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def affine(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    A = np.eye(4)
    A[:3, :3] = R
    A[:3, 3] = t
    return A


def in_plane_gain(w: np.ndarray) -> float:
    """|z| = 2|sin(θ/2)|/θ, the smallest singular value of V(w)."""
    theta = float(np.linalg.norm(w))
    return 1.0 if theta == 0.0 else 2.0 * abs(np.sin(theta / 2.0)) / theta


# --- channels -> matrices -----------------------------------------------------------------------


@pytest.mark.parametrize("order", EULER_ORDERS)
def test_euler_matches_literal_product(order: str) -> None:
    rng = np.random.default_rng(1)
    for angles in rng.uniform(-7.0, 7.0, size=(5, 3)):
        by_axis = dict(zip("XYZ", angles, strict=True))
        expected = np.eye(3)
        for letter in order:  # the first letter is applied first
            expected = literal_axis_rotation(letter, by_axis[letter]) @ expected
        np.testing.assert_allclose(euler_to_matrix(angles, order), expected, atol=1e-14)


def test_xyz_is_rz_ry_rx() -> None:
    x, y, z = 0.1, 0.2, 0.3
    expected = literal_axis_rotation("Z", z) @ literal_axis_rotation("Y", y) @ literal_axis_rotation("X", x)
    np.testing.assert_allclose(euler_to_matrix([x, y, z], "XYZ"), expected, atol=1e-15)
    assert euler_to_matrix([x, y, z], "XYZ")[0, 0] == pytest.approx(0.9363, abs=1e-4)  # mathutils value


def test_quaternion_and_axis_angle_match_scipy_and_blender_conventions() -> None:
    rng = np.random.default_rng(2)
    q = rng.normal(size=(20, 4)) * 3.0  # not unit
    expected = Rotation.from_quat(np.roll(q, -1, axis=1)).as_matrix()  # scipy is (x, y, z, w)
    np.testing.assert_allclose(quaternion_to_matrix(q), expected, atol=1e-14)

    aa = np.concatenate([rng.uniform(-10, 10, size=(20, 1)), rng.normal(size=(20, 3)) * 2.0], axis=1)
    rotvec = aa[:, :1] * aa[:, 1:] / np.linalg.norm(aa[:, 1:], axis=1, keepdims=True)
    np.testing.assert_allclose(axis_angle_to_matrix(aa), Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-13)

    # Blender: a zero quaternion reads as 180° about X, a zero axis as the identity (checked in bpy 5.0).
    np.testing.assert_allclose(quaternion_to_matrix([0, 0, 0, 0]), np.diag([1.0, -1.0, -1.0]), atol=0)
    np.testing.assert_array_equal(axis_angle_to_matrix([1.0, 0, 0, 0]), np.eye(3))


@pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="mathutils comes with the bpy module")
def test_matrices_match_mathutils() -> None:
    import bpy  # noqa: F401  (makes mathutils importable)
    import mathutils

    rng = np.random.default_rng(3)
    for order in EULER_ORDERS:
        angles = rng.uniform(-4, 4, size=3)
        expected = np.array(mathutils.Euler(angles.tolist(), order).to_matrix())
        np.testing.assert_allclose(euler_to_matrix(angles, order), expected, atol=1e-6)
    q = rng.normal(size=4)
    expected = np.array(mathutils.Quaternion(q.tolist()).normalized().to_matrix())
    np.testing.assert_allclose(quaternion_to_matrix(q), expected, atol=1e-6)
    angle, axis = 2.5, rng.normal(size=3)
    expected = np.array(mathutils.Matrix.Rotation(angle, 3, mathutils.Vector(axis).normalized()))
    np.testing.assert_allclose(axis_angle_to_matrix([angle, *axis]), expected, atol=1e-6)


# --- lift_rotvec --------------------------------------------------------------------------------


def test_lift_is_a_bitwise_no_op_for_zero_or_matching_reference() -> None:
    rng = np.random.default_rng(4)
    w = so3_log(so3_exp(rng.normal(size=(200, 3)) * 2.0))
    assert np.array_equal(lift_rotvec(w, np.zeros(3)), w)
    assert np.array_equal(lift_rotvec(w, w), w)
    assert np.array_equal(lift_rotvec(w, w + rng.uniform(-1, 1, size=w.shape)), w)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1),
    st.floats(1e-3, np.pi),
    st.lists(st.floats(-15.0, 15.0), min_size=3, max_size=3),
)
def test_lift_picks_the_nearest_representative(axis: list, theta: float, ref: list) -> None:
    n = np.asarray(axis) / np.linalg.norm(axis)
    w = theta * n
    ref = np.asarray(ref)
    lifted = lift_rotvec(w, ref)
    candidates = [(theta + TAU * k) * n for k in range(-5, 6)]
    best = min(np.linalg.norm(c - ref) for c in candidates)
    assert np.linalg.norm(lifted - ref) <= best + 1e-9
    np.testing.assert_allclose(so3_exp(lifted), so3_exp(w), atol=1e-12)  # same rotation


def test_lift_near_half_turn_flips_axis_towards_reference() -> None:
    w = (np.pi - 1e-3) * Z
    np.testing.assert_allclose(lift_rotvec(w, -3.0 * Z), (np.pi - 1e-3 - TAU) * Z, atol=1e-15)
    np.testing.assert_allclose(lift_rotvec(w, 3.0 * Z), w, atol=0)


def test_lift_of_a_tiny_rotation_uses_the_reference_axis() -> None:
    noise_axis = np.array([1.0, 0.3, -0.2]) / np.linalg.norm([1.0, 0.3, -0.2])
    w = 1e-7 * noise_axis  # an exact 360° turn read back from float32 matrices
    lifted = lift_rotvec(w, TAU * Z)
    np.testing.assert_allclose(lifted, TAU * Z + w, atol=1e-15)
    assert np.array_equal(lift_rotvec(np.zeros(3), 2.0 * TAU * Z), 2.0 * TAU * Z)


# --- continuity and reproduction --------------------------------------------------------------------


def test_twist_0_to_720_every_10_degrees_is_continuous_and_exact() -> None:
    degrees = np.arange(0, 721, 10)
    angles = np.radians(degrees)
    rest = np.tile([0.4, -0.3, 0.0], (angles.size, 1))
    current = rest + angles[:, None] * Z
    w_ref = channel_rotvec("XYZ", rest, current)  # z is outermost in 'XYZ': a twist about world z
    np.testing.assert_allclose(w_ref, angles[:, None] * Z, atol=1e-9)

    R = euler_to_matrix(current, "XYZ") @ np.swapaxes(euler_to_matrix(rest, "XYZ"), 1, 2)
    principal = so3_log(R)
    lifted = lift_rotvec(principal, w_ref)
    np.testing.assert_allclose(lifted, angles[:, None] * Z, atol=1e-9)
    steps = np.linalg.norm(np.diff(lifted, axis=0), axis=1)
    np.testing.assert_allclose(steps, np.radians(10.0), atol=1e-9)  # no jumps anywhere
    assert np.max(np.linalg.norm(np.diff(principal, axis=0), axis=1)) > np.pi  # the principal log jumps


def test_lifted_params_reproduce_the_transform_and_are_continuous_for_a_pivot_twist() -> None:
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    pivot = np.array([1.5, -0.7, 2.0])
    angles = np.radians(np.arange(0, 721, 10))
    A = np.stack([affine(so3_exp(a * axis), pivot - so3_exp(a * axis) @ pivot) for a in angles])
    P = params_from_matrices(A)
    w_ref = angles[:, None] * axis
    lifted = lift_params(P, w_ref, pivot)
    np.testing.assert_allclose(lifted[:, 0:3], w_ref, atol=1e-9)
    # A turn about a fixed pivot has u = c × w on every branch, through 360° and 720° included.
    np.testing.assert_allclose(lifted[:, 3:6], np.cross(pivot, w_ref), atol=1e-8)
    np.testing.assert_allclose(matrices_from_params(lifted), A, atol=1e-9)
    np.testing.assert_array_equal(lifted[:, 6:], P[:, 6:])


def test_lifted_log_reproduces_general_transforms_wherever_v_is_invertible() -> None:
    rng = np.random.default_rng(5)
    axis = rng.normal(size=(400, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0.0, 3.0 * TAU, size=400)
    R = so3_exp(angle[:, None] * axis)
    t = rng.normal(size=(400, 3)) * 3.0
    w, u = se3_log_lifted(R, t, angle[:, None] * axis)
    gain = np.array([in_plane_gain(x) for x in w])
    invertible = gain > 1e-3
    assert invertible.sum() > 350
    R2, t2 = se3_exp(w, u)
    np.testing.assert_allclose(R2[invertible], R[invertible], atol=1e-9)
    np.testing.assert_allclose(t2[invertible], t[invertible], atol=1e-9)
    # ... and the lifted u equals the exact V(w)⁻¹ t there.
    exact = np.linalg.solve(left_jacobian(w[invertible]), t[invertible][..., None])[..., 0]
    np.testing.assert_allclose(u[invertible], exact, rtol=1e-7, atol=1e-9)
    assert np.all(np.isfinite(w)) and np.all(np.isfinite(u))


def test_no_lift_matches_principal_se3_log_exactly() -> None:
    rng = np.random.default_rng(6)
    R = so3_exp(rng.normal(size=(50, 3)))
    t = rng.normal(size=(50, 3))
    w0, u0 = se3_log(R, t)
    w, u = se3_log_lifted(R, t, np.zeros(3))
    assert np.array_equal(w, w0) and np.array_equal(u, u0)


def test_singular_two_pi_k_case_is_finite() -> None:
    R = np.eye(3)
    t = np.array([1.0, 2.0, 3.0])  # in-plane part (1, 2) cannot come from a 2π turn about z
    for k in (1, 2, -1):
        w, u = se3_log_lifted(R, t, k * TAU * Z)
        assert np.all(np.isfinite(w)) and np.all(np.isfinite(u))
        np.testing.assert_allclose(w, k * TAU * Z, atol=1e-12)
        np.testing.assert_allclose(u[2], 3.0, atol=1e-12)  # the axial part of t is reproduced
        assert np.linalg.norm(u) < 1e9
    # Approaching the singularity the in-plane u stays bounded (damped), never inf/NaN.
    for eps in (1e-4, 1e-8, 1e-12, 1e-16):
        w, u = se3_log_lifted(so3_exp((TAU - eps) * Z), t, TAU * Z)
        assert np.all(np.isfinite(u)) and np.linalg.norm(u) < 1e9
    # With the control's pivot, an exact 360° turn about it keeps the continuous u = c × w.
    pivot = np.array([0.5, -1.0, 0.25])
    w, u = se3_log_lifted(so3_exp(TAU * Z), np.zeros(3), TAU * Z, pivot)
    np.testing.assert_allclose(u, np.cross(pivot, TAU * Z), atol=1e-12)


# --- reference rotation vectors from channels -------------------------------------------------------


@pytest.mark.parametrize("degrees", [30.0, 170.0, 190.0, 300.0, 359.0])
def test_modes_agree_for_the_same_physical_motion(degrees: float) -> None:
    delta = np.radians(degrees)
    rest_angle = 0.6
    euler = channel_rotvec("XYZ", [0.0, 0.0, rest_angle], [0.0, 0.0, rest_angle + delta])
    axis_angle = channel_rotvec("AXIS_ANGLE", [rest_angle, 0, 0, 1], [rest_angle + delta, 0, 0, 1])
    half0, half1 = rest_angle / 2, (rest_angle + delta) / 2
    quat = channel_rotvec(
        "QUATERNION", [np.cos(half0), 0, 0, np.sin(half0)], [np.cos(half1), 0, 0, np.sin(half1)]
    )
    for got in (euler, axis_angle, quat):
        np.testing.assert_allclose(got, delta * Z, atol=1e-9)

    # A general rest orientation, turned about world z: Euler (z outermost) vs quaternion channels.
    rest_e = np.array([0.7, -0.4, 1.1])
    cur_e = rest_e + delta * Z
    q_rest = Rotation.from_matrix(euler_to_matrix(rest_e, "XYZ")).as_quat()
    q_cur = Rotation.from_matrix(euler_to_matrix(cur_e, "XYZ")).as_quat()
    q_rest, q_cur = np.roll(q_rest, 1), np.roll(q_cur, 1)  # -> (w, x, y, z)
    if np.dot(q_cur, q_rest) * np.cos(delta / 2) < 0:  # follow the path that turns by +delta
        q_cur = -q_cur
    np.testing.assert_allclose(channel_rotvec("XYZ", rest_e, cur_e), delta * Z, atol=1e-9)
    np.testing.assert_allclose(channel_rotvec("QUATERNION", q_rest, q_cur), delta * Z, atol=1e-9)


def test_large_turns_follow_the_channels() -> None:
    turn = np.radians(400)
    np.testing.assert_allclose(channel_rotvec("XYZ", [0, 0, 0], [0, 0, turn]), turn * Z, atol=1e-9)
    got = channel_rotvec("AXIS_ANGLE", [0, 0, 0, 1], [4 * np.pi, 0, 0, 2])  # 720°, axis length ignored
    np.testing.assert_allclose(got, 4 * np.pi * Z, atol=1e-9)
    # Inner channel of 'ZYX' (z applied first): the turn is about the outer rotations' image of z.
    x, y = 0.3, -0.5
    axis = literal_axis_rotation("X", x) @ literal_axis_rotation("Y", y) @ Z
    got = channel_rotvec("ZYX", [x, y, 0.2], [x, y, 0.2 + np.radians(400)])
    np.testing.assert_allclose(got, np.radians(400) * axis, atol=1e-9)
    # q and −q: the straight 4D path from q to −q·(almost) turns a full 360° (literally followed).
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = np.array([-1.0, 0.0, 0.0, 1e-3])
    expected = 2 * np.arctan2(1e-3, -1.0) * Z  # just under 360°
    np.testing.assert_allclose(channel_rotvec("QUATERNION", q0, q1), expected, atol=1e-12)


def brute_force_unwrap(mode: str, rest: np.ndarray, current: np.ndarray, steps: int) -> np.ndarray:
    """Reference: very fine uniform samples, each principal log lifted against the previous one."""
    from affine_deformers.core.unwrap import channels_to_matrix

    r0_t = np.swapaxes(channels_to_matrix(mode, rest), -1, -2)
    lifted = np.zeros((*rest.shape[:-1], 3))
    for s in np.linspace(0.0, 1.0, steps + 1)[1:]:
        rel = channels_to_matrix(mode, rest + s * (current - rest)) @ r0_t
        lifted = lift_rotvec(so3_log(rel), lifted)
    return lifted


def test_sampled_paths_match_a_fine_brute_force_unwrap() -> None:
    rng = np.random.default_rng(7)
    rest_e = rng.uniform(-1, 1, size=(6, 3))
    cur_e = rest_e + rng.uniform(-5, 5, size=(6, 3))
    got = channel_rotvec("YZX", rest_e, cur_e)
    np.testing.assert_allclose(got, brute_force_unwrap("YZX", rest_e, cur_e, 3000), atol=1e-9)

    # The last row keeps its angle while the axis swings through almost 180° close to zero length:
    # the turn happens in a short stretch of the path, which uniform samples would step over.
    rest_a = np.array(
        [[0.5, 1.0, 0.0, 0.0], [2.0, 0.0, 1.0, 0.2], [-1.0, 0.3, 0.3, 1.0], [3.0, 1.0, 0.0, 0.0]]
    )
    cur_a = np.array(
        [[9.0, 0.0, 1.0, 0.1], [-7.0, 1.0, -0.8, 0.2], [6.0, -0.2, 0.5, -1.0], [3.0, -1.0, 0.02, 0.0]]
    )
    got = channel_rotvec("AXIS_ANGLE", rest_a, cur_a)
    assert np.linalg.norm(got[3]) > np.pi  # past a half turn: the branch matters
    np.testing.assert_allclose(got, brute_force_unwrap("AXIS_ANGLE", rest_a, cur_a, 6000), atol=1e-9)

    # Quaternions use a closed form; check it against the literal sampled path (not unit, any sign).
    q_rest = rng.normal(size=(8, 4)) * rng.uniform(0.5, 3.0, size=(8, 1))
    q_cur = rng.normal(size=(8, 4)) * rng.uniform(0.5, 3.0, size=(8, 1))
    got = channel_rotvec("QUATERNION", q_rest, q_cur)
    assert np.max(np.linalg.norm(got, axis=1)) > np.pi
    np.testing.assert_allclose(got, brute_force_unwrap("QUATERNION", q_rest, q_cur, 3000), atol=1e-9)


def test_per_row_modes_and_shapes() -> None:
    rest = np.array([[0, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=float)
    cur = np.array([[0, 0, 7.0, 0], [np.cos(1.0), 0, 0, np.sin(1.0)], [7.0, 0, 0, 1]])
    got = channel_rotvec(["XYZ", "QUATERNION", "AXIS_ANGLE"], rest, cur)
    np.testing.assert_allclose(got, [7.0 * Z, 2.0 * Z, 7.0 * Z], atol=1e-9)
    assert channel_rotvec("XYZ", np.zeros((2, 5, 3)), np.ones((2, 5, 3))).shape == (2, 5, 3)


def test_bad_channels_raise_value_error() -> None:
    with pytest.raises(ValueError, match="unknown rotation mode"):
        channel_rotvec("XXY", [0, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="needs 4 channels"):
        channel_rotvec("QUATERNION", [0, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="non-finite"):
        channel_rotvec("XYZ", [0, 0, np.nan], [0, 0, 1])
    with pytest.raises(ValueError, match="too many turns"):
        channel_rotvec("XYZ", [0, 0, 0], [0, 0, 1e6])
    with pytest.raises(ValueError, match="last axis of 12"):
        lift_params(np.zeros((2, 11)), np.zeros(3))
