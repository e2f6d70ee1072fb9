"""Deformer kinds: what each kind of control gives the shared bind / evaluate machinery.

A kind provides
  (a) at bind: `store_rest(obj, deformer, depsgraph)` records the rest control data on the deformer,
      and `sparse_weights(obj, deformer, rest_points)` returns the per-vertex top-K weights computed
      from that stored rest data only (so re-weighting never needs the current poses);
  (b) per frame: `current_motions(obj, deformer, depsgraph)` returns the controls' motions
      A_i = C_i · C_rest,i⁻¹ in the target's local space, plus validity.
The probe kind lives here, the cage kind in cage_kind.py.

Matrices are expressed in the target's local space, C = target_world⁻¹ · control_world, and rounded
to float32 exactly like the stored rest matrices, so a control whose current matrix is bitwise equal
to its rest matrix is recognised as "at rest" and contributes exactly the identity.
"""

from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass, field

import bpy
import mathutils
import numpy as np

from ..core import aff3, surface, unwrap, weights
from . import nodes


class BindError(Exception):
    """Bind-time failure with a message meant for the artist."""


@dataclass
class Motions:
    """Current motions of a deformer's controls.

    matrices: (m, 4, 4) float64, A_i in Aff+(3) (identity where at_rest);
    at_rest: (m,) bool, control i is exactly at its rest pose (its parameters are exactly zero);
    error: '' or a message naming the first invalid control (the mesh then keeps its rest shape);
    rest_rotation_modes / rest_rotations (m, 4) and rotation_modes / current_rotations (m, 4): the
    controls' own rotation channels at bind and now (layout of props.AffineDeformerProbe), for choosing
    the rotation-log branch of controls turned past 180°; empty for kinds without channels.
    channel_frames (m, 3, 3): rotation taking vectors of the frame each control's channels turn in
    (its parent frame) to the target's local space; pivots (m, 3): the controls' current origins in
    the target's local space (see `reference_rotvecs`); empty = identity frames / origin pivots.

    Optional, for kinds whose blend parameters are not ψ of one matrix per control (cages):
    params (m, 12): the controls' blend parameters, used instead of ψ(matrices) (matrices then hold
    φ(params), for the linear blend); outer (4, 4): a motion applied after the blend,
    v' = outer · blend(v) (None = identity); valid (m,) bool: False marks a control to skip — its
    weight goes to the vertex's other controls (evaluate.redistribute); warning: a non-fatal status
    (the deformation is still shown); outer_reference (3,) and outer_pivot (3,): the reference
    rotation vector (see `reference_rotvecs`) and current origin, in the target's space, of the object
    whose motion `outer` is, for choosing the rotation-log branch when `outer` is scaled by a strength
    (None = principal branch).
    """

    matrices: np.ndarray
    at_rest: np.ndarray
    error: str = ""
    rest_rotation_modes: list[str] = field(default_factory=list)
    rest_rotations: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    rotation_modes: list[str] = field(default_factory=list)
    current_rotations: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    channel_frames: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    pivots: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    params: np.ndarray | None = None
    outer: np.ndarray | None = None
    valid: np.ndarray | None = None
    warning: str = ""
    outer_reference: np.ndarray | None = None
    outer_pivot: np.ndarray | None = None

    @classmethod
    def invalid(cls, m: int, error: str) -> Motions:
        return cls(np.broadcast_to(np.eye(4), (m, 4, 4)).copy(), np.ones(m, dtype=bool), error)


def world_matrix(obj: bpy.types.Object, depsgraph: bpy.types.Depsgraph) -> np.ndarray:
    """World matrix (4, 4) float64 of `obj` as evaluated in `depsgraph` (bpy.data is stale in renders)."""
    return np.array(obj.evaluated_get(depsgraph).matrix_world, dtype=np.float64)


def local_matrix(target_world: np.ndarray, control_world: np.ndarray) -> np.ndarray:
    """C = target_world⁻¹ · control_world with an exact (0, 0, 0, 1) bottom row, rounded to float32.

    Raises numpy.linalg.LinAlgError when the target's matrix is singular.
    """
    return _local_solve(target_world, control_world)[0]


def _local_solve(target_world: np.ndarray, control_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(`local_matrix`, the float64 3×4 solve it was rounded from): the channel frame reuses the
    solve's linear part (target_world⁻¹ · control_world's 3×3), so one LAPACK call serves both."""
    out = np.zeros((4, 4), dtype=np.float64)
    rhs = control_world[:3, :].copy()
    rhs[:, 3] -= target_world[:3, 3]
    solved = np.linalg.solve(target_world[:3, :3], rhs)
    out[:3, :] = solved
    out[3, 3] = 1.0
    return out.astype(np.float32), solved


def relative_motion(current: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """A = current · rest⁻¹ for affine 4×4 matrices, with an exact (0, 0, 0, 1) bottom row."""
    out = np.eye(4)
    lin = np.linalg.solve(rest[:3, :3].T, current[:3, :3].T).T
    out[:3, :3] = lin
    out[:3, 3] = current[:3, 3] - lin @ rest[:3, 3]
    return out


def rest_matrices(deformer) -> np.ndarray:
    """Stored rest matrices (m, 4, 4) float32 (row-major, as written by store_rest)."""
    flat = np.empty(len(deformer.probes) * 16, dtype=np.float32)
    if len(deformer.probes):
        deformer.probes.foreach_get("rest_matrix", flat)
    return flat.reshape(-1, 4, 4)


def probe_label(item) -> str:
    obj = item.object
    return obj.name if obj is not None else (item.name or "?")


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
            linear = np.linalg.solve(target_world[:3, :3], world[:3, :3])
    except np.linalg.LinAlgError:
        return np.eye(3)
    scale = (*evaluated.scale, *evaluated.delta_scale)
    return _frame_rotation(linear, evaluated.rotation_mode, rotation_channels(evaluated), scale)


def _frame_rotation(linear: np.ndarray, mode: str, channels, scale) -> np.ndarray:
    """`channel_frame` from linear = target_world⁻¹ · matrix_world's 3×3 (float64), the rotation
    channels and scale = (*scale, *delta_scale) as read from the evaluated object."""
    R = _channel_matrix(mode, channels)
    factors = np.array(scale, dtype=np.float64)
    with np.errstate(all="ignore"):
        frame = linear / (factors[:3] * factors[3:])[None, :] @ R.T
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


class ProbeKind:
    """Probes: any objects (normally Empties) whose motion drives the mesh."""

    def store_rest(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
                   only: list[int] | None = None) -> None:
        """Record the current poses of the probes (all, or those at indices `only`) as their rest."""
        if len(deformer.probes) == 0:
            raise BindError("The deformer has no probes: add at least one")
        items = list(deformer.probes) if only is None else [deformer.probes[i] for i in only]
        try:
            target_world = world_matrix(obj, depsgraph)
            rests = []
            for item in items:
                probe = item.object
                if probe is None:
                    raise BindError(f"Probe '{item.name or '?'}' has no object: remove it or pick one")
                if probe == obj:
                    raise BindError(f"'{obj.name}' cannot be a probe of itself")
                if not probe.users_scene:
                    raise BindError(f"Probe '{probe.name}' is not in any scene: link it back or remove it")
                rest = local_matrix(target_world, world_matrix(probe, depsgraph))
                if not np.all(np.isfinite(rest)) or np.linalg.det(rest[:3, :3].astype(np.float64)) == 0.0:
                    raise BindError(f"Probe '{probe.name}' has a zero scale or a non-finite transform: "
                                    "fix it before binding")
                rests.append(rest)
        except np.linalg.LinAlgError:
            raise BindError(f"'{obj.name}' has a zero scale: fix its transform before binding") from None
        for item, rest in zip(items, rests, strict=True):
            evaluated = item.object.evaluated_get(depsgraph)  # the channels as evaluated, like the matrix
            item.rest_matrix = rest.ravel().tolist()
            item.name = item.object.name
            item.rest_rotation_mode = evaluated.rotation_mode
            item.rest_rotation = rotation_channels(evaluated)

    def sparse_weights(self, obj: bpy.types.Object, deformer,
                       rest_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        rests = rest_matrices(deformer).astype(np.float64)
        scales = np.array([item.weight_scale for item in deformer.probes], dtype=np.float64)
        warning = ""
        dense = solved = None
        if deformer.weight_mode == "VERTEX_GROUPS":
            names = [probe_label(item) for item in deformer.probes]
            missing = [n for n in names if obj.vertex_groups.get(n) is None]
            if missing:
                warning = ("No vertex group named " + ", ".join(f"'{n}'" for n in missing)
                           + ": paint one per probe, named after it (those probes have no influence)")
            dense = nodes.vertex_group_weights(obj, names)
        elif deformer.weight_mode == "SURFACE":
            result = harmonic_surface_weights(obj.data, rest_points, rests[:, :3, 3])
            dense, solved = result.weights, result.solved
            warning = surface_warning(result, [probe_label(item) for item in deformer.probes])
        indices, values = weights.probe_weights(
            rest_points, rests[:, :3, 3], mode=deformer.weight_mode, radius=deformer.radius,
            exponent=deformer.exponent, normalize=deformer.normalize, k=deformer.max_influences,
            scales=scales, dense=dense, solved=solved)
        return indices, values, warning

    def current_motions(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Motions:
        probes = deformer.probes
        m = len(probes)
        rests = rest_matrices(deformer)
        rest_modes = [item.rest_rotation_mode for item in probes]
        flat = np.empty(m * 4, dtype=np.float32)
        if m:
            probes.foreach_get("rest_rotation", flat)
        rest_rotations = flat.reshape(-1, 4).astype(np.float64)
        target_world = world_matrix(obj, depsgraph)
        if not finite_transform(target_world):
            return Motions.invalid(m, f"'{obj.name}' has a non-finite transform (NaN or infinity): the mesh "
                                   "shows its rest shape")
        # Everything the probes share in one bytes object, which caches its hash: each probe's key
        # holds it plus its index, instead of hashing its own copies of the rest data per update.
        shared = b"".join((target_world.tobytes(), rests.tobytes(), flat.tobytes(),
                           "\0".join(rest_modes).encode()))
        rows: list[_ProbeRow] = []
        for i, item in enumerate(probes):
            probe = item.object
            if probe is None:
                return Motions.invalid(m, f"Probe '{item.name or '?'}' was deleted or unassigned: "
                                       "remove it from the deformer or pick another object")
            if not in_a_scene(probe):
                return Motions.invalid(m, f"Probe '{probe.name}' is not in any scene (deleted?): "
                                       "remove it from the deformer or link it back")
            if probe == obj:  # kept here too: a message set when it was picked must not be wiped
                return Motions.invalid(m, f"'{obj.name}' cannot be a probe of itself: pick another object "
                                       f"for probe {i + 1}")
            evaluated = probe.evaluated_get(depsgraph)
            world = np.array(evaluated.matrix_world, dtype=np.float64)
            mode = evaluated.rotation_mode
            channels = rotation_channels(evaluated, mode)
            scale = (*evaluated.scale, *evaluated.delta_scale)
            key = (shared, i, world.tobytes(), mode, _bits(channels + scale))
            row = _rows.get(key)
            if row is None:
                row = _probe_row(target_world, world, channels, mode, scale, rests[i], rest_modes[i],
                                 rest_rotations[i])
                if len(_rows) >= ROW_MEMO_SIZE:
                    _rows.clear()
                _rows[key] = row
            if row.error:
                return Motions.invalid(m, row.error.format(probe=probe.name, target=obj.name))
            rows.append(row)
        if m == 0:
            return Motions(np.zeros((0, 4, 4)), np.zeros(0, dtype=bool), "", rest_modes, rest_rotations, [],
                           rest_rotations.copy(), np.zeros((0, 3, 3)), np.zeros((0, 3)))
        return Motions(np.stack([r.matrix for r in rows]), np.array([r.at_rest for r in rows]), "",
                       rest_modes, rest_rotations, [r.mode for r in rows],
                       np.array([r.rotation for r in rows], dtype=np.float64),
                       np.stack([r.frame for r in rows]), np.stack([r.pivot for r in rows]))


def mesh_triangles(mesh: bpy.types.Mesh) -> np.ndarray:
    """The mesh's tessellation (T, 3) int32 vertex indices (Blender's loop triangles: every face,
    n-gons included), read with one foreach_get."""
    if hasattr(mesh, "calc_loop_triangles"):
        mesh.calc_loop_triangles()
    triangles = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    if triangles.size:
        mesh.loop_triangles.foreach_get("vertices", triangles)
    return triangles.reshape(-1, 3)


#: Recent harmonic solves keyed on their exact inputs (rest positions, triangles, probe rest
#: positions): re-weighting with another exponent, normalisation, influence count or weight scale
#: reuses the solve instead of repeating it. Bounded; recomputable.
SURFACE_MEMO_SIZE = 4
_surface_memo: dict[bytes, surface.HarmonicWeights] = {}


def harmonic_surface_weights(mesh: bpy.types.Mesh, rest_points: np.ndarray,
                             centers: np.ndarray) -> surface.HarmonicWeights:
    """core.surface.harmonic_weights of probes at `centers` (m, 3) on the mesh's rest shape
    `rest_points` (N, 3) and its loop triangles (memoised on the exact inputs)."""
    triangles = mesh_triangles(mesh)
    points = np.ascontiguousarray(rest_points, dtype=np.float64)
    centers = np.ascontiguousarray(centers, dtype=np.float64)
    digest = hashlib.blake2b(digest_size=16)
    for array in (points, triangles, centers):
        digest.update(str(array.shape).encode())
        digest.update(array.tobytes())
    key = digest.digest()
    result = _surface_memo.get(key)
    if result is None:
        result = surface.harmonic_weights(points, triangles, centers)
        if len(_surface_memo) >= SURFACE_MEMO_SIZE:
            _surface_memo.pop(next(iter(_surface_memo)))
        _surface_memo[key] = result
    return result


def surface_warning(result: surface.HarmonicWeights, names: list[str]) -> str:
    """The status note of a 'SURFACE' weighting: loose parts that fell back to inverse distance, and
    probes that own no surface ('' when neither)."""
    notes = []
    if result.loose_parts:
        parts = "1 loose part" if result.loose_parts == 1 else f"{result.loose_parts} loose parts"
        notes.append(f"Surface weights: {parts} ({result.loose_vertices} vertices) without a probe near "
                     "them use inverse-distance weights")
    if result.unanchored:
        listed = ", ".join(f"'{names[i]}'" for i in result.unanchored)
        notes.append(f"Surface weights: {listed} share the nearest surface with another probe and have "
                     "no surface influence")
    return "; ".join(notes)


def in_a_scene(obj: bpy.types.Object) -> bool:
    """`bool(obj.users_scene)` without its cost in the common case: users_scene lists every object of
    every scene (O(objects) per call); a lookup by name finds the object directly, and only a miss
    (e.g. a linked object sharing a local one's name) takes the full scan."""
    name = obj.name
    for scene in bpy.data.scenes:
        if scene.objects.get(name) == obj:
            return True
    return bool(obj.users_scene)


@dataclass(frozen=True)
class _ProbeRow:
    """What one probe contributes to `Motions`, a pure function of the values it is keyed on in `_rows`.

    error: '' or a message with {probe} / {target} placeholders (the names are not part of the key).
    The arrays are shared between updates: never modify them.
    """

    matrix: np.ndarray  # (4, 4) float64, A = C · C_rest⁻¹ (identity at rest)
    at_rest: bool
    mode: str
    rotation: tuple[float, ...]  # the control's current rotation channels (4,)
    frame: np.ndarray  # (3, 3) channel frame
    pivot: np.ndarray  # (3,) current origin in the target's space
    error: str = ""


#: Per-probe memo: a probe whose inputs (its and the target's world matrix, its channels and scales,
#: its rest data) are bitwise unchanged gets its previous `_ProbeRow` back instead of redoing the
#: solves and polar splits. Keys hold every input, so the result never depends on update history.
#: Bounded: cleared when full (a rig with more probes than this just recomputes).
ROW_MEMO_SIZE = 4096
_rows: dict[tuple, _ProbeRow] = {}


def forget() -> None:
    """Drop the per-probe and surface-weight memos (they only hold recomputable values)."""
    _rows.clear()
    _surface_memo.clear()


#: Blender clamps an infinite location or scale to ±3.4e38 (the float32 maximum): entries beyond this
#: are treated as not finite, instead of sending the mesh there.
MAX_COORDINATE = 1e30


def finite_transform(matrix: np.ndarray) -> bool:
    """Whether every entry of `matrix` is finite and below MAX_COORDINATE in magnitude (NaN fails too)."""
    return bool(np.all(np.abs(matrix) < MAX_COORDINATE))


def _bits(values: tuple[float, ...]) -> bytes:
    """The exact float64 bits of a short tuple of numbers (−0.0 and NaN payloads included)."""
    return struct.pack(f"{len(values)}d", *values)


def _probe_row(target_world: np.ndarray, world: np.ndarray, channels: tuple[float, ...], mode: str,
               scale: tuple[float, ...], rest: np.ndarray, rest_mode: str,
               rest_rotation: np.ndarray) -> _ProbeRow:
    """The `_ProbeRow` of one probe from its world matrix (float64), rotation channels and mode,
    (*scale, *delta_scale), and its rest matrix (float32) and channels."""
    identity = np.eye(4)
    rotation = tuple(float(c) for c in channels) + (0.0,) * (4 - len(channels))
    if not finite_transform(world):
        return _ProbeRow(identity, False, mode, rotation, np.eye(3), np.zeros(3),
                         "Probe '{probe}' has a non-finite transform (NaN or infinity): the mesh shows its "
                         "rest shape")
    try:
        current, solved = _local_solve(target_world, world)
    except np.linalg.LinAlgError:
        return _ProbeRow(identity, True, mode, rotation, np.eye(3), np.zeros(3),
                         "'{target}' is scaled to zero: the mesh shows its rest shape")
    frame = _frame_rotation(solved[:, :3], mode, channels, scale)
    pivot = current[:3, 3].astype(np.float64)
    # At rest = the same matrix AND the same channels (a full turn changes only the channels).
    if (np.array_equal(current, rest) and mode == rest_mode
            and np.array_equal(np.float32(np.array(rotation)), np.float32(rest_rotation))):
        return _ProbeRow(identity, True, mode, rotation, frame, pivot)
    try:
        with np.errstate(all="ignore"):
            matrix = relative_motion(current.astype(np.float64), rest.astype(np.float64))
    except np.linalg.LinAlgError:
        return _ProbeRow(identity, False, mode, rotation, frame, pivot,
                         "Probe '{probe}' has a singular rest matrix: rebind")
    try:
        aff3.validate_affine(matrix)
    except ValueError:
        if not np.all(np.isfinite(matrix)):
            reason = "has a non-finite transform (NaN or infinity)"
        elif np.linalg.det(matrix[:3, :3]) < 0.0:
            reason = "is mirrored (negative scale)"
        else:
            reason = "is scaled to zero"
        return _ProbeRow(identity, False, mode, rotation, frame, pivot,
                         "Probe '{probe}' " + reason + ": the mesh shows its rest shape")
    return _ProbeRow(matrix, False, mode, rotation, frame, pivot)


# cage_kind builds on the helpers above, so it is imported once they exist.
from .cage_kind import CageKind  # noqa: E402

KINDS: dict[str, ProbeKind | CageKind] = {"PROBE": ProbeKind(), "CAGE": CageKind()}
