"""The cage kind's motions per frame (kinds/cage.py reads the cage and its bind data; this module turns
them into the controls' motions): the cage object's own motion G = C · C_rest⁻¹ and its rotation
branch, the faces' motions A_f of the shape change (MATH.md §9), and for harmonic weights the grid
nodes' parameters blended from the faces' (MATH.md §10)."""

from __future__ import annotations

import bpy
import numpy as np

from ... import accel
from ...core import aff3
from ...core.cage import CageTopology, FaceMotions, affected_faces, face_motions
from ...core.cage.harmonic import node_matrices_linear
from ..update.validation import channels_problem, rest_matrix_problem
from .base import BindError, Motions
from .transforms import (
    channel_frame,
    finite_transform,
    local_matrix,
    motion_problem,
    reference_rotvecs,
    relative_motion,
    rotation_channels,
    transform_problem,
    world_matrix,
)

#: What a collapsed face's status adds.
COLLAPSE_NOTE = "their weight goes to the neighbouring faces"
#: The compiled node totals memo keeps this many validity patterns per bind.
TOTALS_KEPT = 2


def object_motion(obj: bpy.types.Object, cage: bpy.types.Object, cage_world: np.ndarray, stored: np.ndarray,
                  depsgraph: bpy.types.Depsgraph
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None] | str:
    """(target world matrix, C = target_world⁻¹ · cage_world (float32), the stored C_rest (float32),
    G = C · C_rest⁻¹ or None when C = C_rest), or the status when they cannot be used: a target or
    cage transform (`cage_world`) that is not finite or out of range, a target scaled to zero, a damaged
    stored rest matrix `stored` (Cage Rest Matrix), or a motion G outside Aff+(3) or out of range."""
    passes = "the mesh shows its rest shape"
    target_world = world_matrix(obj, depsgraph)
    for who, world in ((f"'{obj.name}'", target_world), (f"Cage '{cage.name}'", cage_world)):
        if not finite_transform(world):
            return f"{who} {transform_problem(world)}: {passes}"
    try:
        matrix = local_matrix(target_world, cage_world)
    except np.linalg.LinAlgError:
        return f"'{obj.name}' is scaled to zero: {passes}"
    damaged = rest_matrix_problem("Cage Rest Matrix", stored)
    if damaged:
        return f"{damaged}: {passes}; rebind the deformer"
    if np.array_equal(matrix, stored):
        return target_world, matrix, stored, None
    try:
        with np.errstate(all="ignore"):
            outer = relative_motion(matrix.astype(np.float64), stored.astype(np.float64))
    except np.linalg.LinAlgError:
        return f"Cage '{cage.name}' is scaled to zero as an object: {passes}"
    reason = motion_problem(outer)
    if reason:
        return f"Cage '{cage.name}' {reason} as an object: {passes}"
    return target_world, matrix, stored, outer


def outer_branch(deformer, cage: bpy.types.Object, depsgraph: bpy.types.Depsgraph, target_world: np.ndarray,
                 matrix: np.ndarray, outer: np.ndarray | None, stored_channels: bool
                 ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """(outer, reference rotation vector (3,), pivot (3,)) for scaling the cage object's motion G.

    Only needed where the branch of log G matters: 'CHANNELS', a strength other than 0 and 1, and
    channels stored at bind (`stored_channels`). The reference is the cage's own turn since bind read
    from its rotation channels (transforms.reference_rotvecs, in the target's space), the pivot its
    current origin in the target's space. A cage back at its rest matrix after whole turns (its
    channels differ) gets G = identity so that the turns still count. ValueError when the channels
    cannot be unwrapped; BindError when the stored rest channels (Cage Rest Rotation) are damaged.
    """
    strength = deformer.strength
    if deformer.branch_rule != "CHANNELS" or strength in (0.0, 1.0) or not stored_channels:
        return outer, None, None
    evaluated = cage.evaluated_get(depsgraph)
    rest_mode, rest_channels = deformer.cage_rest_rotation_mode, tuple(deformer.cage_rest_rotation)
    damaged = channels_problem("Cage Rest Rotation", rest_channels)
    if damaged:
        raise BindError(f"{damaged}: the mesh shows its rest shape; rebind the deformer")
    mode, channels = evaluated.rotation_mode, rotation_channels(evaluated)
    if outer is None:
        if mode == rest_mode and np.array_equal(np.float32(channels), np.float32(rest_channels)):
            return None, None, None
        outer = np.eye(4)
    frame = channel_frame(evaluated, target_world)
    reference = reference_rotvecs([rest_mode], [rest_channels], [mode], [channels], frame[None])[0]
    return outer, reference, matrix[:3, 3].astype(np.float64)


def face_motions_of(rest: np.ndarray, current: np.ndarray, topology: CageTopology, linear: bool,
                  compiled: tuple[FaceMotions, np.ndarray, float] | None = None) -> Motions:
    """Motions of the faces the cage's shape change can reach (core.cage.affected_faces); all other
    faces are exactly at rest (zero parameters, so the vertices they alone drive stay bit-for-bit).
    The matrices φ(P_f) are formed only for the 'LINEAR' blend (`linear`), the only reader of them;
    otherwise they stay the identity and the parameters carry the motion. `compiled`: the result of
    `accel.cage_faces` for these cages (the same motions to ~1e-15), or None to compute them here."""
    F = topology.n_faces
    if compiled is not None:
        motion, face_moved, _ = compiled
    else:
        face_moved = affected_faces(rest, current, topology)
        motion = None
        if np.any(face_moved):
            motion = face_motions(rest, current, topology, faces=face_moved, polar=accel.polar_log)
    at_rest = ~face_moved
    params = np.zeros((F, 12))
    valid = np.ones(F, dtype=bool)
    warning = ""
    if motion is not None and np.any(face_moved):
        if compiled is not None:  # a fresh array, zero outside the faces reached
            params = motion.params
        else:
            params[face_moved] = motion.params[face_moved]
        valid = motion.valid | at_rest
        if motion.messages:
            warning = "; ".join(motion.messages) + f" ({COLLAPSE_NOTE})"
    matrices = np.broadcast_to(np.eye(4), (F, 4, 4)).copy()
    if linear and np.any(face_moved):
        matrices[face_moved] = aff3.matrices_from_params(params[face_moved])
    return Motions(matrices, at_rest, "", params=params, valid=valid, warning=warning)


def _identities(n: int) -> np.ndarray:
    """(n, 4, 4) identity matrices (a fresh array: Motions may be modified by their reader)."""
    return np.broadcast_to(np.eye(4), (n, 4, 4)).copy()


def node_motions(faces: Motions, bind, *, linear: bool = False) -> Motions:
    """The faces' motions as the grid nodes' ('HARMONIC' weights): node c's parameters are the
    pivoted blend of its faces' (core.cage.harmonic.node_params), computed for the nodes with weight
    on a face that moved; the others are exactly at rest (parameters 0). Collapsed faces are left
    out of each node's blend (their weight goes to the node's other faces), so every node is valid.
    matrices: with `linear` the nodes' linear blend of the face matrices (what the 'LINEAR' blend
    uses); otherwise the identity (the affine blend reads the parameters only). `bind`: the deformer's
    node data (kinds.cage.NodeBind: points, weights, and its totals memo, updated here)."""
    node_points, node_weights = bind.points, bind.weights
    G = len(node_points)
    moved = np.flatnonzero(~faces.at_rest)
    valid = None if faces.valid is None or np.all(faces.valid) else faces.valid
    compiled = None
    if not linear:
        which = None if valid is None else np.packbits(valid).tobytes()
        compiled = accel.cage_nodes(node_points, node_weights, faces.params, moved, valid,
                                    totals=bind.totals.get(which))
        if compiled is not None and which not in bind.totals:
            bind.totals[which] = compiled[2]
            while len(bind.totals) > TOTALS_KEPT:
                bind.totals.pop(next(iter(bind.totals)))
    if compiled is not None:  # the compiled kernel: every touched node in one call
        params, touched, _ = compiled
        return Motions(_identities(G), ~touched, "", params=params, warning=faces.warning)
    touched = np.zeros(node_weights.shape[1])
    touched[moved] = 1.0
    rows = np.flatnonzero(node_weights @ touched > 0.0)
    params = np.zeros((G, 12))
    matrices = _identities(G)
    if rows.size:
        # Most nodes (the usual case: harmonic weights reach far): every node is computed and the rows
        # kept, rather than copying those rows of the (G, F) weights (column-major: `node_data`).
        whole = 4 * rows.size >= G
        points, weights = (node_points, node_weights) if whole else (node_points[rows], node_weights[rows])
        pick = rows if whole else slice(None)
        params[rows] = accel.node_params(points, weights, faces.params, faces=moved, valid=valid)[pick]
        if linear:
            matrices[rows] = node_matrices_linear(weights, faces.matrices, faces=moved, valid=valid)[pick]
    at_rest = np.ones(G, dtype=bool)
    at_rest[rows] = False
    return Motions(matrices, at_rest, "", params=params, warning=faces.warning)
