"""Continuous choice of the rotation-log branch (MATH.md §8).

The principal logarithm returns a rotation vector w with |w| = θ ∈ [0, π]. Every rotation vector of
the same rotation lies on the line through w: w + 2πk·ŵ (k ∈ ℤ; k = -1 is the axis flip w - 2πŵ). A
control turned past 180° must keep the branch that its motion went through, or the blend flips. The
branch is chosen here from a *reference* rotation vector that is a function of the current frame
alone (the control's own rotation channels, unwrapped along the straight channel path from rest to
current), so a render farm evaluating any frame in a fresh process gets the same answer.

Contents:
- `lift_rotvec(w, w_ref)`: the lift of w nearest the reference.
- `se3_log_lifted(R, t, w_ref)` / `lift_params(P, w_ref)`: the se(3) log on the lifted branch
  (u = V(w)⁻¹ t recomputed; V is singular at |w| = 2πk, handled by a damped inverse, see below).
- `euler_to_matrix`, `quaternion_to_matrix`, `axis_angle_to_matrix`, `channels_to_matrix`: Blender's
  rotation channels → 3×3 rotation matrices.
- `channel_rotvec(mode, rest, current)`: the reference rotation vector of R(current)·R(rest)ᵀ.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .aff3 import _cross, left_jacobian, se3_log, so3_log

TWO_PI = 2.0 * np.pi

# Below this principal angle the axis w/|w| is rounding noise (float32 matrices from Blender give
# |w| ~ 1e-7 for an exact 360° turn), so a lift takes the reference's axis instead. The lifted vector
# then represents the rotation only up to an error of |w| <= AXIS_TOL radians.
AXIS_TOL = 1e-5

# Tikhonov damping of V(w)⁻¹ in the rotation plane (dimensionless; V's in-plane gain is
# |z| = 2|sin(θ/2)|/θ). The reproduction error of t is λ²/(|z|² + λ²) of the part of t that the pivot
# does not explain, i.e. < 1e-10 of it wherever |z| > 1e-3, and u stays below |t|/(2λ) at |z| = 0.
DAMPING = 1e-8

EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
ROTATION_MODES = (*EULER_ORDERS, "QUATERNION", "AXIS_ANGLE")

# Bound on the number of path samples per call (about 7000 turns at the default step).
MAX_PATH_SAMPLES = 65536

# Up to this many channel values, checks run on Python floats instead of numpy reductions.
_FEW_VALUES = 64


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def lift_rotvec(w: np.ndarray, w_ref: np.ndarray, *, axis_tol: float = AXIS_TOL) -> np.ndarray:
    """Rotation vector of the same rotation as w on the branch nearest the reference.

    Candidates are w + 2πk·ŵ, k ∈ ℤ, i.e. the points at signed distance θ + 2πk along ŵ; the one
    nearest w_ref is the one whose position is nearest s = ŵ·w_ref, k = round((s − θ)/2π). When k = 0
    the input is returned bitwise unchanged; that holds whenever |w_ref − w| < π, in particular for
    w_ref = 0 (no channel information) and for a principal w_ref of the same rotation.

    When |w| < axis_tol the axis of w is not trustworthy and the reference's axis n is used:
    w + 2πk·n (exact up to |w|; see AXIS_TOL). If w_ref is zero too, w is returned.

    w, w_ref: (..., 3), broadcast against each other. Returns (..., 3) float64.
    """
    w = np.asarray(w, dtype=np.float64)
    w_ref = np.asarray(w_ref, dtype=np.float64)
    w, w_ref = np.broadcast_arrays(w, w_ref)
    theta = _norm(w)
    ref_len = _norm(w_ref)
    use_ref_axis = (theta < axis_tol) & (ref_len > 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        own_axis = w / np.where(theta > 0.0, theta, 1.0)[..., None]
        ref_axis = w_ref / np.where(ref_len > 0.0, ref_len, 1.0)[..., None]
    axis = np.where(use_ref_axis[..., None], ref_axis, own_axis)
    position = np.einsum("...i,...i->...", w, axis)
    target = np.einsum("...i,...i->...", w_ref, axis)
    turns = np.rint((target - position) / TWO_PI)
    turns = np.where(np.isfinite(turns), turns, 0.0)
    lifted = w + (TWO_PI * turns)[..., None] * axis
    return np.where((turns != 0.0)[..., None], lifted, w)


# `_no_row_lifts` bounds: |w_ref − w| < 3 keeps |k| = |rint((ŵ·w_ref − ŵ·w)/2π)| at 0 with a margin of
# π − 3 ≈ 0.14 rad for rounding, which holds while |w| < 1e6 (rounding ~1e6·ε there).
_NO_LIFT_DIST_SQ = 9.0
_NO_LIFT_NORM_SQ = 1e12


def _no_row_lifts(w: np.ndarray, w_ref: np.ndarray) -> bool:
    """True if `lift_rotvec(w, w_ref)` certainly leaves every row unchanged (k = 0 for all rows).

    With n the axis the lift uses (ŵ, or the reference's axis when |w| < axis_tol; |n| ≤ 1), the
    turn count is k = rint(n·(w_ref − w)/2π), which is 0 whenever |w_ref − w| < π. A cheap sufficient
    test for the usual update (no control past a half turn from its reference); False (NaN included)
    means "run the lift".
    """
    if w.shape[-1:] != (3,) or w_ref.shape != w.shape:
        return False
    d = w_ref - w
    if d.size <= _FEW_VALUES:
        # Python floats for short batches (the result is a decision only; both ways are exact).
        dl, wl = d.ravel().tolist(), w.ravel().tolist()
        for i in range(0, len(dl), 3):
            dist_sq = dl[i] * dl[i] + dl[i + 1] * dl[i + 1] + dl[i + 2] * dl[i + 2]
            norm_sq = wl[i] * wl[i] + wl[i + 1] * wl[i + 1] + wl[i + 2] * wl[i + 2]
            if not (dist_sq < _NO_LIFT_DIST_SQ and norm_sq < _NO_LIFT_NORM_SQ):  # NaN: False
                return False
        return True
    if not (np.einsum("...i,...i->...", d, d) < _NO_LIFT_DIST_SQ).all():
        return False
    return bool((np.einsum("...i,...i->...", w, w) < _NO_LIFT_NORM_SQ).all())


def _damped_translation_log(
    w: np.ndarray, t: np.ndarray, pivot: np.ndarray, damping: float
) -> np.ndarray:
    """u with V(w)·u ≈ t for rotation vectors with |w| ≥ π (lifted branches), never inf or NaN.

    V(w) is the identity along n = w/θ and, in the rotation plane, multiplication by the complex number
    z = (sin θ + i(1 − cos θ))/θ (i ≙ n×). |z| = 2|sin(θ/2)|/θ vanishes at θ = 2πk: there exp(X) moves
    points only along the axis, so an in-plane translation has no exact preimage and the in-plane u is
    not determined by (R, t) at all. We centre the solution on the prior u₀ = c × w, the twist that
    turns about the pivot c (V(w)u₀ = (I − R)c exactly, for any θ), and solve the remainder
    r = t − V(w)u₀ with the Tikhonov inverse conj(z)/(|z|² + λ²) in the plane:

        u = u₀ + n(n·r) + (a·r_⊥ − b·n×r_⊥)/(a² + b² + λ²),   a = sin θ/θ, b = (1 − cos θ)/θ.

    A control that turns about its pivot thus gets the exact, continuous u = c × w through 2πk; any
    other in-plane translation is reproduced except within |z| ≲ λ of the singular angles.
    """
    theta = _norm(w)
    theta_safe = np.where(theta > 0.0, theta, 1.0)
    n = w / theta_safe[..., None]
    a = np.sin(theta) / theta_safe
    b = (1.0 - np.cos(theta)) / theta_safe
    u0 = _cross(pivot, w)
    v_u0 = a[..., None] * u0 + b[..., None] * _cross(n, u0)
    r = t - v_u0
    r_axial = np.einsum("...i,...i->...", n, r)[..., None] * n
    r_plane = r - r_axial
    gain = 1.0 / (a * a + b * b + damping * damping)
    u_plane = gain[..., None] * (a[..., None] * r_plane - b[..., None] * _cross(n, r_plane))
    return u0 + r_axial + u_plane


def _lift_se3(
    w_p: np.ndarray,
    u_p: np.ndarray,
    t: np.ndarray,
    w_ref: np.ndarray,
    pivot: np.ndarray | None,
    damping: float,
    axis_tol: float,
) -> tuple[np.ndarray, np.ndarray]:
    w = lift_rotvec(w_p, w_ref, axis_tol=axis_tol)
    moved = np.any(w != w_p, axis=-1)
    if not np.any(moved):
        return w, np.array(u_p, dtype=np.float64, copy=True)
    c = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=np.float64)
    c = np.broadcast_to(c, w.shape)
    u = np.array(u_p, dtype=np.float64, copy=True)
    u[moved] = _damped_translation_log(w[moved], t[moved], c[moved], damping)
    return w, u


def se3_log_lifted(
    R: np.ndarray,
    t: np.ndarray,
    w_ref: np.ndarray,
    pivot: np.ndarray | None = None,
    *,
    damping: float = DAMPING,
    axis_tol: float = AXIS_TOL,
) -> tuple[np.ndarray, np.ndarray]:
    """se(3) log of (R, t) on the branch whose rotation vector is nearest w_ref.

    Returns (w, u) with w = lift_rotvec(log R, w_ref) and u = V(w)⁻¹ t, so exp([[ŵ, u], [0, 0]])
    reproduces (R, t) (exp is 2π-periodic in the rotation angle). Where the lift is a no-op the
    result is exactly aff3.se3_log(R, t). On lifted branches V(w) becomes singular at |w| = 2πk; u is
    then the damped solution described in `_damped_translation_log`, centred on a turn about `pivot`
    (default: the origin of the frame of R, t; pass the control's origin in that frame).

    R (..., 3, 3), t (..., 3), w_ref (..., 3), pivot (..., 3) or None.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    w_ref = np.asarray(w_ref, dtype=np.float64)
    lead = np.broadcast_shapes(R.shape[:-2], t.shape[:-1], w_ref.shape[:-1])
    t = np.broadcast_to(t, (*lead, 3))
    w_p, u_p = se3_log(np.broadcast_to(R, (*lead, 3, 3)), t)
    return _lift_se3(w_p, u_p, t, np.broadcast_to(w_ref, (*lead, 3)), pivot, damping, axis_tol)


def lift_params(
    params: np.ndarray,
    w_ref: np.ndarray,
    pivot: np.ndarray | None = None,
    *,
    damping: float = DAMPING,
    axis_tol: float = AXIS_TOL,
) -> np.ndarray:
    """Move 12-number parameters (docs/DEVELOPING.md layout) to the branch nearest w_ref.

    Slices 0:3 (ω) are lifted, 3:6 (u) recomputed for the same translation t = V(ω_principal)·u,
    6:12 (log S) are untouched. Rows whose lift is a no-op are returned bitwise unchanged.
    params (..., 12), w_ref (..., 3), pivot (..., 3) or None. Returns a new array.
    """
    params = np.asarray(params, dtype=np.float64)
    if params.shape[-1:] != (12,):
        raise ValueError(f"params must have a last axis of 12, got shape {params.shape}")
    w_ref = np.asarray(w_ref, dtype=np.float64)
    if w_ref.shape[:-1] == params.shape[:-1] and _no_row_lifts(params[..., 0:3], w_ref):
        return np.array(params, order="C")
    lead = np.broadcast_shapes(params.shape[:-1], w_ref.shape[:-1])
    out = np.array(np.broadcast_to(params, (*lead, 12)))
    w_p = out[..., 0:3]
    u_p = out[..., 3:6]
    w = lift_rotvec(w_p, np.broadcast_to(w_ref, (*lead, 3)), axis_tol=axis_tol)
    moved = np.any(w != w_p, axis=-1)
    if not np.any(moved):  # the usual case: no row changes branch, and t is not needed
        return out
    # t = V(ω_p) u_p only for the lifted rows (row by row the same numbers as over the whole batch).
    t = np.einsum("...ij,...j->...i", left_jacobian(w_p[moved]), u_p[moved])
    c = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=np.float64)
    c = np.broadcast_to(c, w.shape)[moved]
    u_p[moved] = _damped_translation_log(w[moved], t, c, damping)
    w_p[moved] = w[moved]
    return out


# --- Blender rotation channels -> matrices ------------------------------------------------------


def _axis_rotation_slots() -> tuple[np.ndarray, np.ndarray]:
    """Layout of the stack [Rx, Ry, Rz] (3, 3, 3), flattened, of right-handed axis rotations.

    The rotation by α about axis a, with (i, j) = (a + 1, a + 2) mod 3, has 1 at (a, a), cos α at
    (i, i) and (j, j), sin α at (j, i), −sin α at (i, j), zeros elsewhere. Returns (the constant part:
    zeros and the three ones, the flat positions of (cos, cos, sin, −sin) for axes 0, 1, 2 in the
    order of `np.concatenate([c, c, s, −s])`).
    """
    template = np.zeros(27)
    slots: list[list[int]] = [[], [], [], []]
    for axis in range(3):
        i, j = (axis + 1) % 3, (axis + 2) % 3
        template[9 * axis + 4 * axis] = 1.0
        for kind, (row, col) in enumerate(((i, i), (j, j), (j, i), (i, j))):
            slots[kind].append(9 * axis + 3 * row + col)
    return template, np.array(slots).reshape(-1)


_AXIS_TEMPLATE, _AXIS_SLOTS = _axis_rotation_slots()


def euler_to_matrix(angles: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """Blender Euler rotation: angles (..., 3) = (x, y, z) in radians, order e.g. 'XYZ'.

    The first letter is applied first: 'XYZ' gives Rz(z)·Ry(y)·Rx(x). The three axis rotations are
    built in one pass over all angles (see `_axis_rotation_slots`): a few numpy calls instead of a few
    dozen on the few-control update path; the products are the same matmuls as factor by factor.
    """
    if order not in EULER_ORDERS:
        raise ValueError(f"unknown Euler order {order!r}; expected one of {', '.join(EULER_ORDERS)}")
    angles = np.asarray(angles, dtype=np.float64)
    if angles.shape[-1:] != (3,):
        raise ValueError(f"Euler angles must have a last axis of 3, got shape {angles.shape}")
    lead = angles.shape[:-1]
    flat = angles.reshape(-1, 3)
    c, s = np.cos(flat), np.sin(flat)
    factors = np.empty((flat.shape[0], 27))
    factors[:] = _AXIS_TEMPLATE
    factors[:, _AXIS_SLOTS] = np.concatenate([c, c, s, -s], axis=1)
    factors = factors.reshape(-1, 3, 3, 3)
    first, second, third = ("XYZ".index(letter) for letter in order)
    out = factors[:, third] @ (factors[:, second] @ factors[:, first])
    return out.reshape(*lead, 3, 3)


def _unit_quaternion(q: np.ndarray) -> np.ndarray:
    """q/|q|; Blender reads a zero quaternion as (0, 1, 0, 0)."""
    length = _norm(q)
    zero = ~(length > 0.0)
    unit = q / np.where(zero, 1.0, length)[..., None]
    return np.where(zero[..., None], np.array([0.0, 1.0, 0.0, 0.0]), unit)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation of the quaternion (w, x, y, z), normalised first (..., 4) -> (..., 3, 3).

    Like Blender's object transform, a zero quaternion is read as (0, 1, 0, 0) (180° about X).
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quaternions must have a last axis of 4, got shape {q.shape}")
    q = _unit_quaternion(q)
    w, x, y, z = (q[..., i] for i in range(4))
    out = np.empty((*q.shape[:-1], 3, 3))
    out[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[..., 0, 1] = 2.0 * (x * y - w * z)
    out[..., 0, 2] = 2.0 * (x * z + w * y)
    out[..., 1, 0] = 2.0 * (x * y + w * z)
    out[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[..., 1, 2] = 2.0 * (y * z - w * x)
    out[..., 2, 0] = 2.0 * (x * z - w * y)
    out[..., 2, 1] = 2.0 * (y * z + w * x)
    out[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return out


def axis_angle_to_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """Rotation of Blender's axis-angle channels (angle, x, y, z) (..., 4) -> (..., 3, 3).

    The axis is normalised; a zero axis gives the identity, as in Blender.
    """
    axis_angle = np.asarray(axis_angle, dtype=np.float64)
    if axis_angle.shape[-1:] != (4,):
        raise ValueError(f"axis-angle channels must have a last axis of 4, got shape {axis_angle.shape}")
    angle = axis_angle[..., 0]
    axis = axis_angle[..., 1:4]
    length = _norm(axis)
    zero = ~(length > 0.0)
    n = axis / np.where(zero, 1.0, length)[..., None]
    angle = np.where(zero, 0.0, angle)
    c, s = np.cos(angle), np.sin(angle)
    K = np.zeros((*n.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -n[..., 2], n[..., 1]
    K[..., 1, 0], K[..., 1, 2] = n[..., 2], -n[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -n[..., 1], n[..., 0]
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + s[..., None, None] * K + (1.0 - c)[..., None, None] * (K @ K)


def channels_to_matrix(mode: str, channels: np.ndarray) -> np.ndarray:
    """Rotation matrix of Blender rotation channels in `mode` (an Euler order, 'QUATERNION' or
    'AXIS_ANGLE'); channels (..., 3) for Euler, (..., 4) otherwise."""
    if mode == "QUATERNION":
        return quaternion_to_matrix(channels)
    if mode == "AXIS_ANGLE":
        return axis_angle_to_matrix(channels)
    return euler_to_matrix(channels, mode)


# --- reference rotation vectors from channels ---------------------------------------------------


def _quaternion_path_rotvec(rest: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Closed form for the normalised straight 4D path from q0 to q1.

    q(s)/|q(s)| runs monotonically along the minor great arc from q̂0 to q̂1, so q̂(s)·q̂0* =
    (cos φ(s), sin φ(s)·n) with a fixed unit n and φ from 0 to α = angle(q̂0, q̂1) ∈ [0, π]: the
    continuous rotation vector along the path is 2φ·n, ending at 2α·n (up to a full 2π turn).
    A path through the zero quaternion (q1 = −c·q0) has no defined axis and gives 0.
    """
    q0, q1 = _unit_quaternion(rest), _unit_quaternion(current)
    # q1 ⊗ conj(q0)
    w0, v0 = q0[..., 0], q0[..., 1:]
    w1, v1 = q1[..., 0], q1[..., 1:]
    real = w1 * w0 + np.einsum("...i,...i->...", v1, v0)
    vec = w0[..., None] * v1 - w1[..., None] * v0 - _cross(v1, v0)
    sin_half = _norm(vec)
    half = np.arctan2(sin_half, real)
    ok = sin_half > 1e-12
    scale = np.where(ok, 2.0 * half / np.where(ok, sin_half, 1.0), 0.0)
    return scale[..., None] * vec


def _path_samples_euler(rest: np.ndarray, current: np.ndarray, max_step: float) -> np.ndarray:
    """Sample parameters s (m, N+1) with every step changing the rotation by < max_step.

    The geodesic distance is bi-invariant, so d(R(e), R(e')) ≤ Σ|Δe_i| for Euler angles.
    """
    total = np.abs(current - rest).sum(axis=-1)
    steps = int(np.floor(total.max(initial=0.0) / max_step)) + 1
    _check_samples(steps)
    return np.broadcast_to(np.linspace(0.0, 1.0, steps + 1), (rest.shape[0], steps + 1))


def _check_samples(steps: int) -> None:
    if steps > MAX_PATH_SAMPLES:
        raise ValueError(
            f"rotation channels change by too many turns to unwrap ({steps} path samples needed, "
            f"limit {MAX_PATH_SAMPLES}); reduce the rotation values"
        )


def _path_samples_axis_angle(rest: np.ndarray, current: np.ndarray, max_step: float) -> np.ndarray:
    """Sample parameters s (m, N) for the straight path in (angle, axis) channel space.

    d(R(a, n), R(a', n')) ≤ |a − a'| + 2·∠(n, n'). The angle is linear in s; the normalised axis runs
    monotonically along the minor arc between the end axes but not uniformly in s, so the grid is the
    union of a uniform grid (angle steps < max_step/2) and the s values where the axis has turned by
    equal fractions of the arc (axis steps < max_step/4).
    """
    m = rest.shape[0]
    x0, x1 = rest[:, 1:], current[:, 1:]
    n_angle = int(np.floor(np.abs(current[:, 0] - rest[:, 0]).max(initial=0.0) / (0.5 * max_step))) + 1
    len0, len1 = _norm(x0), _norm(x1)
    cross = _norm(_cross(x0, x1))
    dot = np.einsum("ij,ij->i", x0, x1)
    both = (len0 > 0.0) & (len1 > 0.0)
    arc = np.where(both, np.arctan2(cross, dot), 0.0)
    n_axis = int(np.floor(2.0 * arc.max(initial=0.0) / (0.5 * max_step))) + 1
    _check_samples(n_angle + n_axis)
    uniform = np.broadcast_to(np.linspace(0.0, 1.0, n_angle + 1), (m, n_angle + 1))
    beta = arc[:, None] * np.linspace(0.0, 1.0, n_axis + 1)[None, :]
    # Point on the chord x0 + s(x1 − x0) whose direction is at angle β from x0 (in their plane).
    sb, cb = np.sin(beta), np.cos(beta)
    denom = cross[:, None] * cb - sb * (dot - len0 * len0)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        s_axis = sb * (len0 * len0)[:, None] / denom
    s_axis = np.where(np.isfinite(s_axis) & both[:, None], np.clip(s_axis, 0.0, 1.0), 0.0)
    return np.sort(np.concatenate([uniform, s_axis], axis=1), axis=1)


def _unwrap_sampled(mode: str, rest: np.ndarray, current: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Follow R(c(s))·R(rest)ᵀ along the samples s (m, N), lifting each step against the previous."""
    r_rest = channels_to_matrix(mode, rest)
    lifted = None
    block = 512
    for start in range(1, s.shape[1], block):
        s_blk = s[:, start : start + block]
        chans = rest[:, None, :] + s_blk[..., None] * (current - rest)[:, None, :]
        rel = channels_to_matrix(mode, chans) @ np.swapaxes(r_rest, -1, -2)[:, None]
        principal = so3_log(rel)
        for j in range(principal.shape[1]):
            step = principal[:, j]
            # Lifting the first step against the zero start moves it only if |ω| rounds to ≥ π
            # (k = rint(−|ω|/2π)); with steps below max_step = π/4 it never does, so skip the call.
            if lifted is None and np.all(_norm(step) < 3.0):
                lifted = step
            else:
                lifted = lift_rotvec(step, np.zeros_like(step) if lifted is None else lifted)
    return np.zeros((rest.shape[0], 3)) if lifted is None else lifted


def _channel_rotvec_one_mode(mode: str, rest: np.ndarray, current: np.ndarray, max_step: float) -> np.ndarray:
    width = 3 if mode in EULER_ORDERS else 4
    if mode not in ROTATION_MODES:
        raise ValueError(f"unknown rotation mode {mode!r}; expected one of {', '.join(ROTATION_MODES)}")
    if rest.shape[-1] != width or current.shape[-1] != width:
        raise ValueError(
            f"rotation mode {mode} needs {width} channels, got {rest.shape[-1]} and {current.shape[-1]}"
        )
    if not _all_finite(rest, current):
        raise ValueError("rotation channels contain non-finite values")
    if mode == "QUATERNION":
        return _quaternion_path_rotvec(rest, current)
    if mode == "AXIS_ANGLE":
        counts = [tuple(count) for count in _sample_counts(mode, rest, current, max_step).tolist()]
    else:
        counts = [(steps, 0.0) for steps in _euler_steps(rest, current, max_step).tolist()]
        if set(counts) == {(0.0, 0.0)}:  # every row within one step: no grouping needed
            return _euler_one_step(mode, rest, current)
    # Each row is sampled at its own count (rows with equal counts share one batch), so a row's result
    # never depends on which other rows it is computed with (callers memoise rows).
    # Grouped with a dict, not np.unique(axis=0): batches are a few controls, where unique's
    # structured-array set-up cost more than the unwrapping itself.
    groups: dict[tuple[float, float], list[int]] = {}
    for i, count in enumerate(counts):
        groups.setdefault(count, []).append(i)
    out = np.zeros((rest.shape[0], 3))
    sample = _path_samples_axis_angle if mode == "AXIS_ANGLE" else _path_samples_euler
    for count, members in groups.items():
        rows = np.array(members)
        if count == (0.0, 0.0) and mode != "AXIS_ANGLE":
            out[rows] = _euler_one_step(mode, rest[rows], current[rows])
            continue
        s = sample(rest[rows], current[rows], max_step)
        out[rows] = _unwrap_sampled(mode, rest[rows], current[rows], s)
    return out


def _all_finite(*arrays: np.ndarray) -> bool:
    """Every entry finite. Few entries: one Python sum (finite iff every entry is, unless it overflows,
    and then numpy decides) instead of a numpy call per array."""
    if sum(a.size for a in arrays) <= _FEW_VALUES and math.isfinite(
        sum(sum(a.ravel().tolist()) for a in arrays)
    ):
        return True
    return all(bool(np.isfinite(a).all()) for a in arrays)


def _euler_steps(rest: np.ndarray, current: np.ndarray, max_step: float) -> np.ndarray:
    """Per row, ⌊Σ|Δe_i| / max_step⌋: the path of that row alone has this many steps plus one."""
    return np.floor(np.abs(current - rest).sum(axis=-1) / max_step)


def _euler_one_step(mode: str, rest: np.ndarray, current: np.ndarray) -> np.ndarray:
    """`_unwrap_sampled` for Euler rows whose channels change by less than one step in total.

    The path grid is then s ∈ {0, 1}: the one sample is e(1) = rest + 1·(current − rest) (formed as
    written, so the same bits as the sampled path), and its principal log ω = log(R(e(1))·R(rest)ᵀ) is
    the answer: lifting it against the zero start gives k = rint(−|ω|/2π) = 0 for |ω| ≤ π.
    Both rotations come from one `euler_to_matrix` call over the stacked channels.
    """
    m = rest.shape[0]
    both = euler_to_matrix(np.concatenate([rest, rest + (current - rest)]), mode)
    return so3_log(both[m:] @ both[:m].transpose(0, 2, 1))


def _sample_counts(mode: str, rest: np.ndarray, current: np.ndarray, max_step: float) -> np.ndarray:
    """Per row, the sample counts `_path_samples_euler` / `_path_samples_axis_angle` would use for that
    row alone, (m, 2) (the same floor expressions, evaluated per row)."""
    if mode != "AXIS_ANGLE":
        steps = _euler_steps(rest, current, max_step)
        return np.stack([steps, np.zeros_like(steps)], axis=-1)
    x0, x1 = rest[:, 1:], current[:, 1:]
    n_angle = np.floor(np.abs(current[:, 0] - rest[:, 0]) / (0.5 * max_step))
    both = (_norm(x0) > 0.0) & (_norm(x1) > 0.0)
    arc = np.where(both, np.arctan2(_norm(_cross(x0, x1)), np.einsum("ij,ij->i", x0, x1)), 0.0)
    n_axis = np.floor(2.0 * arc / (0.5 * max_step))
    return np.stack([n_angle, n_axis], axis=-1)


def channel_rotvec(
    mode: str | Sequence[str],
    rest: np.ndarray,
    current: np.ndarray,
    *,
    max_step: float = np.pi / 4,
) -> np.ndarray:
    """Reference rotation vector of R(current)·R(rest)ᵀ from rotation channels alone.

    The relative rotation is followed along the straight path in channel space from rest to current,
    sampled so that consecutive relative rotations differ by less than max_step, each step's principal
    log lifted against the previous one. Deterministic: it depends on the two channel sets only.
    Euler z going 0 → 400° gives 400° about z; axis-angle 0 → 720° gives 720°; a quaternion path
    (straight in 4D, normalised, q and −q taken literally) gives up to one full turn (closed form).

    mode: one Blender rotation mode for all rows ('XYZ', ..., 'ZYX', 'QUATERNION', 'AXIS_ANGLE'), or a
    sequence of modes, one per row (then rest/current are (m, 4) with Euler rows using the first 3).
    rest, current: (..., 3) for Euler, (..., 4) for quaternion (w, x, y, z) and axis-angle
    (angle, x, y, z), radians. Returns (..., 3), in the frame the channels rotate in (the parent).
    """
    rest = np.asarray(rest, dtype=np.float64)
    current = np.asarray(current, dtype=np.float64)
    if rest.shape != current.shape:
        raise ValueError(f"rest and current channels differ in shape: {rest.shape} vs {current.shape}")
    if not max_step > 0.0:
        raise ValueError("max_step must be positive")
    lead = rest.shape[:-1]
    rest2 = rest.reshape(-1, rest.shape[-1])
    cur2 = current.reshape(-1, current.shape[-1])
    if isinstance(mode, str):
        out = _channel_rotvec_one_mode(mode, rest2, cur2, max_step)
        return out.reshape(*lead, 3)
    modes = np.asarray(mode, dtype=object).reshape(-1)
    if modes.shape[0] != rest2.shape[0]:
        raise ValueError(f"got {modes.shape[0]} rotation modes for {rest2.shape[0]} channel rows")
    distinct = set(modes.tolist())
    if len(distinct) == 1:  # the usual case: every control in one mode, no row selection needed
        (one,) = distinct
        width = 3 if one in EULER_ORDERS else 4
        out = _channel_rotvec_one_mode(one, rest2[:, :width], cur2[:, :width], max_step)
        return out.reshape(*lead, 3)
    out = np.zeros((rest2.shape[0], 3))
    for one in sorted(set(modes.tolist())):
        rows = np.flatnonzero(modes == one)
        width = 3 if one in EULER_ORDERS else 4
        out[rows] = _channel_rotvec_one_mode(one, rest2[rows, :width], cur2[rows, :width], max_step)
    return out.reshape(*lead, 3)
