"""Transforms of controls as every kind reads them: world → target space, relative motions, and the
rotation channels that choose the rotation-log branch (MATH.md §8).

C = target_world⁻¹ · control_world is rounded to float32 like the stored rest matrices (base.py), and
A = C · C_rest⁻¹ has an exact (0, 0, 0, 1) bottom row.
"""

from __future__ import annotations

import math

import bpy
import mathutils
import numpy as np

from ... import accel
from ...core import aff3, unwrap
from ..files import nodes
from ..update.validation import MAX_COORDINATE, transform_problem


def world_matrix(obj: bpy.types.Object, depsgraph: bpy.types.Depsgraph) -> np.ndarray:
    """World matrix (4, 4) float64 of `obj` as evaluated in `depsgraph` (bpy.data is stale in renders)."""
    return np.array(obj.evaluated_get(depsgraph).matrix_world, dtype=np.float64)


def local_matrix(target_world: np.ndarray, control_world: np.ndarray) -> np.ndarray:
    """C = target_world⁻¹ · control_world with an exact (0, 0, 0, 1) bottom row, rounded to float32.

    Raises numpy.linalg.LinAlgError when the target's matrix is singular.
    """
    return local_solve(target_world, control_world)[0]


def inverse3(matrix: np.ndarray) -> np.ndarray:
    """M⁻¹ (3, 3) float64 of a 3×3 matrix by its adjugate, adj(M)/det M; LinAlgError when det M = 0
    (non-finite entries give non-finite results, which callers check).

    Closed form rather than LAPACK: a per-control, per-update call of np.linalg.solve cost ~0.4 ms
    (LAPACK's threads wait for cores the kernel's threads hold), this costs microseconds; the
    matrices are transforms (float32 data), for which the adjugate is as accurate as the data."""
    (a, b, c), (d, e, f), (g, h, i) = matrix.tolist()
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    if det == 0.0:
        raise np.linalg.LinAlgError("singular matrix")
    with np.errstate(all="ignore"):
        adjugate = np.array([[A, c * h - b * i, b * f - c * e],
                             [B, a * i - c * g, c * d - a * f],
                             [C, b * g - a * h, a * e - b * d]])
        return adjugate / det


def ordered_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b for (stacks of) small matrices, b a matrix or a vector, with every entry Σ_j a_ij b_jk
    summed in j order by elementwise operations: a product gets the same bits in any batch, alone
    included. numpy's matmul picks BLAS (gemm, gemv) or its own loops by shape and stride, and they
    round differently (measured with OpenBLAS's AVX-512 kernels: a stacked matrix · vector differed
    in the last bit from the same product alone), which the per-control memos cannot allow."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    vector = b.ndim == 1
    if vector:
        b = b[:, None]
    out = a[..., :, 0, None] * b[..., 0, None, :]
    for j in range(1, a.shape[-1]):
        out = out + a[..., :, j, None] * b[..., j, None, :]
    return out[..., 0] if vector else out


def local_solve(target_world: np.ndarray, control_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(`local_matrix`, the float64 3×4 solve it was rounded from): the channel frame reuses the
    solve's linear part (target_world⁻¹ · control_world's 3×3), so one solve serves both."""
    out = np.zeros((4, 4), dtype=np.float64)
    rhs = control_world[:3, :].copy()
    rhs[:, 3] -= target_world[:3, 3]
    solved = ordered_matmul(inverse3(target_world[:3, :3]), rhs)
    out[:3, :] = solved
    out[3, 3] = 1.0
    return out.astype(np.float32), solved


def local_solves(target_world: np.ndarray, control_worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`local_solve` of n controls at once, (C (n, 4, 4) float32, solved (n, 3, 4) float64): the same
    matrix product per control as `local_solve` (numpy's matmul runs it slice by slice), so each C
    has the bits `local_matrix` gives it alone — the bits a rest matrix stored at bind has.
    Raises numpy.linalg.LinAlgError when the target's matrix is singular."""
    rhs = control_worlds[:, :3, :].copy()
    rhs[:, :, 3] -= target_world[:3, 3]
    solved = ordered_matmul(inverse3(target_world[:3, :3]), rhs)
    out = np.zeros((len(control_worlds), 4, 4), dtype=np.float64)
    out[:, :3, :] = solved
    out[:, 3, 3] = 1.0
    return out.astype(np.float32), solved


def local_solves_rows(targets: np.ndarray,
                      control_worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`local_solves` of n controls, each against its own target's world matrix (targets (n, 4, 4)):
    (C (n, 4, 4) float32, solved (n, 3, 4) float64, solvable (n,) bool). The same elementwise
    products as `local_solves`, so each C has the bits `local_matrix` gives it alone; each distinct
    target is inverted once. A row whose target is singular is not solvable (its values are
    meaningless), instead of the LinAlgError `local_solves` raises."""
    n = len(control_worlds)
    inverses = np.empty((n, 3, 3))
    solvable = np.ones(n, dtype=bool)
    found: dict[bytes, np.ndarray | None] = {}
    for i, target in enumerate(targets):
        key = target.tobytes()
        if key not in found:
            try:
                found[key] = inverse3(target[:3, :3])
            except np.linalg.LinAlgError:
                found[key] = None
        inverse = found[key]
        if inverse is None:
            inverses[i], solvable[i] = np.eye(3), False
        else:
            inverses[i] = inverse
    rhs = control_worlds[:, :3, :].copy()
    rhs[:, :, 3] -= targets[:, :3, 3]
    solved = ordered_matmul(inverses, rhs)
    out = np.zeros((n, 4, 4), dtype=np.float64)
    out[:, :3, :] = solved
    out[:, 3, 3] = 1.0
    return out.astype(np.float32), solved, solvable


def frame_rotations(linear: np.ndarray, modes: list[str], channels: np.ndarray,
                    scales: np.ndarray) -> np.ndarray:
    """`frame_rotation` of n controls at once (linear (n, 3, 3), channels (n, 4), scales (n, 6)),
    every row on its own (the polar split by one stacked SVD, R = U Vᵀ)."""
    n = len(linear)
    kinds_of_mode = set(modes)
    if len(kinds_of_mode) == 1:
        R = _channel_matrices(modes[0], channels)
    else:
        R = np.empty((n, 3, 3))
        for mode in kinds_of_mode:
            rows = [i for i, m in enumerate(modes) if m == mode]
            R[rows] = _channel_matrices(mode, channels[rows])
    with np.errstate(all="ignore"):
        frame = ordered_matmul(linear / (scales[:, :3] * scales[:, 3:])[:, None, :], R.transpose(0, 2, 1))
        det = np.linalg.det(frame)  # non-finite entries give a non-finite det
        usable = np.isfinite(det) & (np.abs(det) > 1e-30)
    if usable.all():
        return _rotation_parts(frame * np.sign(det)[:, None, None])  # a mirrored frame negated
    out = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    if usable.any():
        out[usable] = _rotation_parts((frame * np.sign(det)[:, None, None])[usable])
    return out


def _rotation_parts(frames: np.ndarray) -> np.ndarray:
    """R = U Vᵀ (n, 3, 3) of the SVDs U Σ Vᵀ of frames (n, 3, 3) with det > 0: the compiled polar
    split when the kernel is active (accel.polar_log, ~1e-15 from numpy's; microseconds instead of
    LAPACK's per-call cost), numpy's stacked SVD otherwise. Row by row either way, so a frame has
    the same bits in any batch (callers memoising frames key them on accel.active())."""
    split = accel.polar_log(frames)
    if split is not None:
        return split[0]
    U, _, Vh = np.linalg.svd(frames)
    return ordered_matmul(U, Vh)


def _channel_matrices(mode: str, channels: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of channels (n, 4) in the layout of `rotation_channels`."""
    euler = mode not in ("QUATERNION", "AXIS_ANGLE")
    return unwrap.channels_to_matrix(mode, channels[:, :3] if euler else channels)


def relative_motion(current: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """A = current · rest⁻¹ for affine 4×4 matrices, with an exact (0, 0, 0, 1) bottom row."""
    out = np.eye(4)
    lin = ordered_matmul(current[:3, :3], inverse3(rest[:3, :3]))
    out[:3, :3] = lin
    out[:3, 3] = current[:3, 3] - ordered_matmul(lin, rest[:3, 3])
    return out


def rotation_channels(obj: bpy.types.Object, mode: str | None = None) -> tuple[float, ...]:
    """The object's own rotation channels in the layout of props.AffineDeformerProbe.rest_rotation
    (`mode`: obj.rotation_mode, when the caller has read it already)."""
    if mode is None:
        mode = obj.rotation_mode
    if mode == "QUATERNION":
        return tuple(obj.rotation_quaternion)
    if mode == "AXIS_ANGLE":
        return tuple(obj.rotation_axis_angle)
    return (*obj.rotation_euler, 0.0)


def _channel_matrix(mode: str, channels) -> np.ndarray:
    channels = np.asarray(channels, dtype=np.float64)
    return unwrap.channels_to_matrix(mode, channels if mode in ("QUATERNION", "AXIS_ANGLE") else channels[:3])


def channel_frame(evaluated: bpy.types.Object, target_world: np.ndarray) -> np.ndarray:
    """Rotation Q (3, 3) from the frame `evaluated`'s rotation channels turn in to the target's space.

    Blender composes matrix_world = W·T·D·R·S (W: parent and constraints, T: location, D: delta
    rotation, R: the channels' rotation, S: scale × delta scale), so turning the channels by ΔR
    (R → ΔR·R) turns the object by ΔR in the frame of W·D, and Q is the rotation part of
    target_world⁻¹·W·D = target_world⁻¹·matrix_world·S⁻¹·Rᵀ (polar split; a mirrored frame is
    negated first, since rotation vectors are pseudovectors). Identity when that matrix is singular
    or not finite: the motion is then rejected anyway, or the branch falls back to the shortest.
    """
    world = np.array(evaluated.matrix_world, dtype=np.float64)
    try:
        with np.errstate(all="ignore"):
            linear = ordered_matmul(inverse3(target_world[:3, :3]), world[:3, :3])
    except np.linalg.LinAlgError:
        return np.eye(3)
    scale = (*evaluated.scale, *evaluated.delta_scale)
    return frame_rotation(linear, evaluated.rotation_mode, rotation_channels(evaluated), scale)


def frame_rotation(linear: np.ndarray, mode: str, channels, scale) -> np.ndarray:
    """`channel_frame` from linear = target_world⁻¹ · matrix_world's 3×3 (float64), the rotation
    channels and scale = (*scale, *delta_scale) as read from the evaluated object."""
    R = _channel_matrix(mode, channels)
    factors = np.array(scale, dtype=np.float64)
    with np.errstate(all="ignore"):
        frame = ordered_matmul(linear / (factors[:3] * factors[3:])[None, :], R.T)
    if not np.isfinite(frame).all():
        return np.eye(3)
    (a, b, c), (d, e, f), (g, h, i) = frame.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if not (math.isfinite(det) and abs(det) > 1e-30):
        return np.eye(3)
    rotation, _ = aff3.polar(frame if det > 0.0 else -frame)
    return rotation


def rest_channels_in_mode(rest_mode: str, rest_rotation, mode: str) -> tuple[float, float, float, float]:
    """The rest rotation's channels in rotation mode `mode` (for a control whose mode changed since bind).

    Same mode: unchanged. Otherwise the rest rotation matrix converted to the principal values of the
    new mode (Euler angles in [-π, π], quaternion with w ≥ 0, axis-angle angle in [0, π]): turns keyed
    in the new mode are then counted from there. Blender itself keeps Euler turns across an Euler order
    switch but cannot carry them into a quaternion or axis-angle, so such a switch shows the rotation
    the converted channels hold (at most one turn).
    """
    if rest_mode == mode:
        return tuple(float(c) for c in rest_rotation)
    matrix = mathutils.Matrix(_channel_matrix(rest_mode, rest_rotation).tolist())
    if mode == "QUATERNION":
        return tuple(matrix.to_quaternion())
    if mode == "AXIS_ANGLE":
        axis, angle = matrix.to_quaternion().to_axis_angle()
        return (angle, *axis)
    return (*matrix.to_euler(mode), 0.0)


def reference_rotvecs(rest_modes: list[str], rest_rotations, modes: list[str], current_rotations,
                      frames: np.ndarray | None = None) -> np.ndarray:
    """Reference rotation vectors (m, 3) in the target's space for choosing the rotation-log branch.

    w_ref,i = Q_i · channel_rotvec(mode_i, rest_i, current_i): control i's own turn since bind read
    from its rotation channels (unwrapped along the straight channel path, so Rotation Z = 400°
    means 400°; rest channels in another mode are converted, see `rest_channels_in_mode`), carried
    into the target's space by its channel frame Q_i (`channel_frame`; None = identity frames).
    Depends on the current frame's channels only. ValueError (from core.unwrap) when channels are
    non-finite or turn too often to unwrap.
    """
    m = len(modes)
    if m == 0:
        return np.zeros((0, 3))
    rest = np.array([rest_channels_in_mode(r_mode, r_rot, mode)
                     for r_mode, r_rot, mode in zip(rest_modes, rest_rotations, modes, strict=True)])
    w_channels = unwrap.channel_rotvec(list(modes), rest, np.asarray(current_rotations, dtype=np.float64))
    if frames is None or len(frames) != m:
        return w_channels
    return np.einsum("mij,mj->mi", frames, w_channels)


_resync_wanted = False


def want_resync() -> None:
    """Ask the handlers to re-sync the relations (relations.sync_scene): a control the modifier does
    not name was found unevaluated (its visibility changed with no depsgraph update seeing it)."""
    global _resync_wanted
    _resync_wanted = True


def take_resync() -> bool:
    """Whether a re-sync was asked for since the last call."""
    global _resync_wanted
    wanted, _resync_wanted = _resync_wanted, False
    return wanted


def control_evaluated(control: bpy.types.Object, evaluated: bpy.types.Object,
                      depsgraph: bpy.types.Depsgraph, related: bool = False) -> bool:
    """Whether the depsgraph really evaluates `control` (its evaluated copy `evaluated`) this update.

    `related`: an enabled modifier of ours names the control on its inputs (nodes.evaluates), so the
    depsgraph evaluates it with the target. Otherwise a control disabled in viewports (or renders) is
    not evaluated, yet `evaluated_get` may still return a stale copy (the deformer's pointer to the
    control puts an ID node in the depsgraph). Evaluated objects are then those the depsgraph lists,
    plus objects hidden only with the eye icon (evaluated but not listed)."""
    if not evaluated.is_evaluated:
        return False
    if related:
        return True
    try:
        if control.hide_get(view_layer=depsgraph.view_layer):
            return True
    except RuntimeError:  # not in the depsgraph's view layer
        return False
    listed = depsgraph.objects.get(control.name)  # by name: a linear search in Python is 4x slower
    return listed is not None and listed.original == control


def unnamed_control_stale(control: bpy.types.Object, evaluated: bpy.types.Object,
                          depsgraph: bpy.types.Depsgraph) -> bool:
    """Whether `control`, which no modifier of ours names, is not evaluated by `depsgraph`: in a
    render the full test (`control_evaluated`); in the viewport only its own flag, since
    relations.sync_scene follows every visibility change a depsgraph update sees, and the full test's
    lookup in the depsgraph's object list costs O(objects) per control per update."""
    if depsgraph.mode == "RENDER":
        return not control_evaluated(control, evaluated, depsgraph)
    return control.hide_viewport or not evaluated.is_evaluated


class StaleControls:
    """The controls of one deformer found unevaluated this update (a visibility change not synced yet
    would otherwise be read stale): `stale(control, evaluated)` is True for a control that the
    deformer's modifier does not name (nodes.named_controls) and `unnamed_control_stale` finds not
    evaluated, and then asks for a re-sync (`want_resync`). The viewport's test is one flag, cheaper
    than listing the modifier's controls, so there the list is made only for a control that fails it;
    a render's test is not, so there it comes second."""

    def __init__(self, obj: bpy.types.Object, attr: str, depsgraph: bpy.types.Depsgraph, any_control: bool):
        self._obj, self._attr, self._depsgraph = obj, attr, depsgraph
        render = any_control and depsgraph.mode == "RENDER"
        self._named = nodes.named_controls(obj, attr, depsgraph) if render else None

    def stale(self, control: bpy.types.Object, evaluated: bpy.types.Object) -> bool:
        named = self._named
        if (named is not None and control in named) or not unnamed_control_stale(control, evaluated,
                                                                                   self._depsgraph):
            return False
        if named is None:
            named = self._named = nodes.named_controls(self._obj, self._attr, self._depsgraph)
        if control in named:
            return False
        want_resync()
        return True


#: Marks the read-ahead's helper scene (read_ahead.py): not a scene of the artist's, so an object only
#: it holds is in no scene.
HELPER_MARK = "affine_deformers_read_ahead"


def in_a_scene(obj: bpy.types.Object) -> bool:
    """Whether a scene of the artist's holds `obj` (not the read-ahead's helper): `obj.users_scene`
    without its cost in the common case (it lists every object of every scene, O(objects) per call);
    a lookup by name finds the object directly, and only a miss (e.g. a linked object sharing a
    local one's name) takes the full scan."""
    name = obj.name
    for scene in bpy.data.scenes:
        if scene.objects.get(name) == obj and not scene.get(HELPER_MARK):
            return True
    return any(not scene.get(HELPER_MARK) for scene in obj.users_scene)


def motion_problem(matrix: np.ndarray, what: str = "transform") -> str:
    """Why the motion `matrix` (4, 4) is not in Aff+(3) or out of range, as the end of a sentence
    about its control ('is mirrored (negative scale)', 'is scaled to zero', 'has a non-finite
    transform (NaN or infinity)' or 'has a transform out of range (…)', with `what` for
    'transform'), or '' when it is usable."""
    try:
        aff3.validate_affine(matrix)
    except ValueError:
        if not np.all(np.isfinite(matrix)):
            return transform_problem(matrix, what)
        if np.linalg.det(matrix[:3, :3]) < 0.0:
            return "is mirrored (negative scale)"
        return "is scaled to zero"
    return transform_problem(matrix, what)


def finite_transform(matrix: np.ndarray) -> bool:
    """Whether every entry of `matrix` is finite and below MAX_COORDINATE in magnitude (NaN fails too;
    `transform_problem` words why not).

    Over the entries as Python floats: for a 4×4 that is a few microseconds, where numpy's abs and
    reduce cost ~30 µs per update once the kernel's pass has evicted them from the caches."""
    return all(abs(value) < MAX_COORDINATE for value in np.asarray(matrix, dtype=np.float64).ravel().tolist())
