"""The bone kind: the pose bones of an Armature object drive the mesh — an affine skin.

Every motion is expressed as the Armature modifier does, in the armature's space carried into the
target's: with P = target_world⁻¹ · armature_world (both evaluated), bone i's pose matrix B_i and its
rest matrix R_i (`Bone.matrix_local`, Edit Mode's rest, both in armature space),

    A_i = P · B_i · R_i⁻¹ · P⁻¹,

so moving the armature object alone does not move the mesh (as with the Armature modifier), and a
bone's full affine motion — scale and the shear a scaled parent gives its children included, which
the Armature modifier's linear and dual-quaternion blends drop or distort — is followed exactly
where a vertex belongs to one bone. Bendy-bone segments are not followed (a bendy bone moves as a
straight bone).

Blend (MATH.md §14, core.hierarchy): down the bone hierarchy. Each bone's local motion
L_i = A_parent⁻¹ A_i (its parent: the nearest ancestor among the deformer's bones) is weighted by
the vertex's weight on it and on every bone below it, and the factors φ(Σ W ψ(L)) multiply from the
roots down: a vertex between a forearm and its upper arm gets the upper arm's motion and part of
the forearm's own turn about the elbow, however far the upper arm has moved.

Rotation-log branch (MATH.md §8): L_i's log is taken on the branch nearest the bone's own turn, read
from its pose channels (its rest channels are the identity) and carried into the target's rest space
by its rest frame rot(P · R_i), about its rest head; bones between it and its parent that do not drive
the mesh add their turns. Deterministic: it depends on the current frame's channels only.

Weights: the vertex groups named after the bones ('VERTEX_GROUPS', what the Armature modifier
reads), or from the bones' rest segments head → tail stored in the target's space at bind
('INVERSE_DISTANCE', 'FALLOFF': distance to the segment; 'SURFACE': harmonic, anchored at the
segments' midpoints).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import bpy
import numpy as np
from bpy.props import CollectionProperty, IntProperty, PointerProperty

from ...core import aff3, hierarchy, unwrap
from .. import caches
from ..files import storage
from . import armature_convert, bone_tools
from .base import (
    INTERFACE,
    OVERRIDABLE,
    READ_BY_KIND,
    Adopted,
    BindError,
    Chain,
    DeformerKind,
    KindProperty,
    Motions,
    ignored_note,
    single_selected,
)
from .batching import Batch, BatchedKind, keep_rows
from .bone_tools import DEFAULT_INFLUENCES, REST_SEGMENTS, deform_bones, stored_segments
from .services import control_picker, on_preview_option
from .transforms import (
    MAX_COORDINATE,
    StaleControls,
    finite_transform,
    frame_rotation,
    in_a_scene,
    inverse3,
    motion_problem,
    ordered_matmul,
    rotation_channels,
    transform_problem,
)
from .weighting import control_weights, draw_weight_options, weight_settings_problem

#: A bone whose pose matrix differs from its rest by at most this (relative to the bone's scale of
#: motion: entries of B·R⁻¹ − I) counts as at rest, so a rest pose gives the mesh exactly back.
AT_REST_TOL = 1e-6

_IDENTITY_CHANNELS = {"QUATERNION": (1.0, 0.0, 0.0, 0.0), "AXIS_ANGLE": (0.0, 0.0, 1.0, 0.0)}


def settings_problem(deformer) -> str:
    """The first weight setting of `deformer` or of a bone (its Weight Scale) that is refused, with
    what the update does ('' when none; kinds/weighting.py `weight_settings_problem`)."""
    bones = deformer.bones
    return weight_settings_problem(deformer, bones, lambda i: f"Bone '{bones[i].name}'")


def identity_channels(mode: str) -> tuple[float, float, float, float]:
    """A pose bone's rotation channels at rest in `mode` (layout of props.AffineDeformerProbe)."""
    return _IDENTITY_CHANNELS.get(mode, (0.0, 0.0, 0.0, 0.0))


def _poll_armature(_deformer, candidate: bpy.types.Object) -> bool:
    return candidate.type == "ARMATURE"


def bone_parents(armature: bpy.types.Object, names: list[str]) -> np.ndarray:
    """Each bone's parent among `names` (its nearest ancestor there, −1 for none) (m,) intp, from the
    armature's bones, as the update's hierarchy takes them (`_hierarchy`, from the pose bones)."""
    index = {name: i for i, name in enumerate(names)}
    bones = armature.data.bones
    parents = np.full(len(names), -1, dtype=np.intp)
    for i, name in enumerate(names):  # a walk up per bone, never per vertex
        bone = bones.get(name)
        parent = bone.parent if bone is not None else None
        while parent is not None and parent.name not in index:
            parent = parent.parent
        if parent is not None:
            parents[i] = index[parent.name]
    return parents


def _pool_scales(deformer) -> np.ndarray:
    """The bones' weight scales (m,), which weigh the children in the pooled nodes' means
    (core.hierarchy.pool_mix)."""
    scales = np.empty(len(deformer.bones), dtype=np.float32)
    if len(scales):
        deformer.bones.foreach_get("weight_scale", scales)
    return scales.astype(np.float64)


#: core.hierarchy.pool_mix keyed on the parents' and scales' bits: per update otherwise, for a result
#: that changes only with the bone list or a weight scale. Bounded like `_rows`.
_pool_mixes: dict[bytes, np.ndarray] = {}


def _pool_mix(parents: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """`hierarchy.pool_mix(parents, scales)`, memoised (read-only: shared between updates)."""
    key = parents.astype(np.int64).tobytes() + scales.tobytes()
    found = _pool_mixes.get(key)
    if found is None:
        found = hierarchy.pool_mix(parents, scales)
        found.flags.writeable = False
        if len(_pool_mixes) >= ROW_MEMO_SIZE:
            _pool_mixes.clear()
        _pool_mixes[key] = found
    return found


def armature_problem(target: bpy.types.Object, armature: bpy.types.Object | None) -> str:
    """Why `armature` cannot drive `target` ('' when it can)."""
    if armature is None:
        return "No armature: pick the armature whose bones drive the mesh"
    if armature.type != "ARMATURE":
        return f"'{armature.name}' is not an armature"
    if not in_a_scene(armature):
        return f"Armature '{armature.name}' is not in any scene (deleted?): link it back or pick another"
    return ""


@dataclass(frozen=True)
class _BoneRow:
    """What one bone contributes to `Motions` (a pure function of the values it is keyed on)."""

    matrix: np.ndarray  # (4, 4) A_i (identity at rest)
    at_rest: bool
    unturned: bool  # its rotation channels are the identity
    turn: np.ndarray  # (3,) rot(P · R_i) · the channels' rotation vector: its own turn, target rest space
    head: np.ndarray  # (3,) its rest head, target space: the point its own turn is about
    error: str = ""
    warning: str = ""  # scaled to zero: it still deforms (aff3.nearest_positive), with a status


#: Per-bone memo keyed on the exact bits of every input of `_bone_row`. Bounded: cleared when full.
ROW_MEMO_SIZE = 4096
_rows: dict[tuple, _BoneRow] = {}


def _bits(values: tuple[float, ...]) -> bytes:
    return struct.pack(f"{len(values)}d", *values)


#: rot(P · R) per (P, R) bits: a bone's rest frame in the target's space changes only with the
#: objects' transforms, not with the pose. Bounded like `_rows`.
_rest_frames: dict[bytes, np.ndarray] = {}


def _rest_frame(rested: np.ndarray) -> np.ndarray:
    """rot(P · R) (3, 3), the polar rotation of a bone's rest matrix in the target's space."""
    key = rested.tobytes()
    frame = _rest_frames.get(key)
    if frame is None:
        frame = frame_rotation(rested[:3, :3], "XYZ", (0.0, 0.0, 0.0), (1.0,) * 6)
        if len(_rest_frames) >= ROW_MEMO_SIZE:
            _rest_frames.clear()
        _rest_frames[key] = frame
    return frame


def _bone_row(frame_matrix: np.ndarray, frame_inverse: np.ndarray, pose: np.ndarray, rest: np.ndarray,
              mode: str, channels: tuple[float, ...]) -> _BoneRow:
    """The `_BoneRow` of one pose bone: `frame_matrix` P and its inverse, its pose matrix B and rest
    matrix R (armature space, float64), its rotation mode and channels."""
    identity = np.eye(4)
    rotation = tuple(float(c) for c in channels) + (0.0,) * (4 - len(channels))
    rested = ordered_matmul(frame_matrix, rest)
    head = rested[:3, 3].copy()
    reason = transform_problem(pose, "pose") or transform_problem(ordered_matmul(frame_matrix, pose), "pose")
    if reason:
        return _BoneRow(identity, False, False, np.zeros(3), np.zeros(3),
                        "Bone '{bone}' " + reason + ": the mesh shows its input")
    try:
        with np.errstate(all="ignore"):
            local = ordered_matmul(pose, _inverse_affine(rest))
    except np.linalg.LinAlgError:
        return _BoneRow(identity, False, False, np.zeros(3), head,
                        "Bone '{bone}' has a zero-length rest: fix it in Edit Mode")
    width = 4 if mode in ("QUATERNION", "AXIS_ANGLE") else 3
    rest_frame = _rest_frame(rested)
    try:
        rotvec = unwrap.channel_rotvec(mode, np.array(identity_channels(mode)[:width]),
                                       np.array(rotation[:width], dtype=np.float64))
        turn = ordered_matmul(rest_frame, rotvec)
    except ValueError:
        turn = np.full(3, np.nan)  # reported only when the branch rule needs it (see current_motions)
    # At rest = the rest matrix AND identity channels (a full turn changes only the channels).
    unturned = np.array_equal(np.float32(rotation[:width]), np.float32(identity_channels(mode)[:width]))
    if unturned and np.max(np.abs(local - identity)) <= AT_REST_TOL:
        return _BoneRow(identity, True, True, turn, head)
    with np.errstate(all="ignore"):
        matrix = ordered_matmul(ordered_matmul(frame_matrix, local), frame_inverse)
    matrix[3] = (0.0, 0.0, 0.0, 1.0)
    reason = motion_problem(matrix, "pose")
    if reason == "is scaled to zero" or reason.startswith("is mirrored"):
        try:  # the limit of the nearby poses: what it holds collapses onto its head, as Armature's do
            collapsed = aff3.nearest_positive(matrix, head)
        except ValueError:
            pass
        else:
            return _BoneRow(collapsed, False, unturned, turn, head,
                            warning="Bone '{bone}' is scaled to zero: the vertices it holds collapse onto it")
    if reason:
        return _BoneRow(identity, False, unturned, turn, head,
                        "Bone '{bone}' " + reason + ": the mesh shows its input")
    return _BoneRow(matrix, False, unturned, turn, head)


@dataclass
class _Reading:
    """One deformer's bones as read for an update, before the rows that missed the memo are computed
    (`_fill`) and the motions assembled (`_finish`). Lives for one update only."""

    obj: bpy.types.Object
    deformer: object
    armature: bpy.types.Object
    frame: np.ndarray  # P = target_world⁻¹ · armature_world
    frame_inverse: np.ndarray
    pose: object  # the evaluated armature's pose
    rows: dict[str, _BoneRow | None]
    misses: list[tuple]
    missing: str  # a bone the armature does not have ('' when none)


def _read(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Motions | _Reading:
    """Read the deformer's bones from the evaluated `depsgraph` and look their rows up in the memo;
    Motions at once for a problem with the armature or the objects' transforms."""
    m = len(deformer.bones)
    armature = deformer.armature
    problem = armature_problem(obj, armature)
    if problem:
        return Motions.invalid(m, f"{problem}: the mesh shows its input")
    try:
        frame = _frame_matrix(obj, armature, depsgraph)
        frame_inverse = _inverse_affine(frame)
    except np.linalg.LinAlgError:
        return Motions.invalid(m, f"'{obj.name}' or armature '{armature.name}' is scaled to zero: the "
                               "mesh shows its input")
    if not finite_transform(frame):
        return Motions.invalid(m, f"'{obj.name}' or armature '{armature.name}' {transform_problem(frame)}: "
                               "the mesh shows its input")
    problem = settings_problem(deformer)
    if problem:
        return Motions.invalid(m, problem)
    _segments, problem = stored_segments(deformer)  # read by re-weighting: damage shows at once too
    if problem:
        return Motions.invalid(m, f"{problem}: the mesh shows its input; rebind the deformer")
    evaluated = armature.evaluated_get(depsgraph)
    if StaleControls(obj, storage.offset_name(deformer.uid), depsgraph, True).stale(armature, evaluated):
        return Motions.invalid(m, f"Armature '{armature.name}' is not evaluated (it is disabled in "
                               "viewports or renders, and the deformer is off there): enable the "
                               "deformer, or enable the armature and hide it with the eye icon")
    pose = evaluated.pose
    rows: dict[str, _BoneRow | None] = {}
    misses: list[tuple] = []
    missing = ""
    for item in deformer.bones:
        if not _chain_rows(item.name, pose, frame, rows, misses):
            missing = item.name
            break
    return _Reading(obj, deformer, armature, frame, frame_inverse, pose, rows, misses, missing)


def _fill(readings: list[_Reading]) -> None:
    """Compute the bones that missed the memo, of all `readings` in one batch (every row on its own,
    against its own deformer's frame: the same bits alone or in any batch), into the readings and
    the memo."""
    misses = [(reading, miss) for reading in readings for miss in reading.misses]
    if not misses:
        return
    computed = _bone_rows(np.stack([reading.frame for reading, _ in misses]),
                          np.stack([reading.frame_inverse for reading, _ in misses]),
                          np.stack([miss[2] for _, miss in misses]),
                          np.stack([miss[3] for _, miss in misses]), [miss[4] for _, miss in misses],
                          [miss[5] for _, miss in misses])
    keep_rows(_rows, ROW_MEMO_SIZE, misses, computed)


def _finish(reading: _Reading) -> Motions:
    """The motions of a reading whose rows are all known."""
    deformer, armature, rows = reading.deformer, reading.armature, reading.rows
    m = len(deformer.bones)
    # The first problem in the order the chains were walked; replace, not format: a bone name may
    # hold braces.
    for name, row in rows.items():
        if row.error:
            message = row.error.replace("{armature}", armature.name).replace("{bone}", name)
            return Motions.invalid(m, message)
    if reading.missing:
        return Motions.invalid(m, f"Armature '{armature.name}' has no bone named '{reading.missing}' "
                               "(deleted, or renamed where it could not be told apart): rename it back or "
                               "remove it from the deformer")
    chosen = [rows[item.name] for item in deformer.bones]
    if m == 0:
        return Motions(np.zeros((0, 4, 4)), np.zeros(0, dtype=bool))
    matrices = np.stack([r.matrix for r in chosen])
    chain = _hierarchy([item.name for item in deformer.bones], reading.pose, rows, matrices)
    if deformer.branch_rule == "CHANNELS" and not np.all(np.isfinite(chain.references)):
        bad = deformer.bones[int(np.flatnonzero(~np.isfinite(chain.references).all(axis=1))[0])].name
        return Motions.invalid(m, f"The rotation channels of bone '{bad}' (or of a parent) cannot be "
                               "unwrapped (non-finite or too many turns): the mesh shows its input")
    if deformer.branch_rule != "CHANNELS":
        chain.references = chain.pivots = None
    warnings = [row.warning.replace("{bone}", name) for name, row in rows.items() if row.warning]
    warnings.append(armature_convert.doubling_warning(reading.obj, armature))
    return Motions(matrices, np.array([r.at_rest for r in chosen]), chain=chain,
                   pool=_pool_mix(chain.parents, _pool_scales(deformer)),
                   warning="; ".join(w for w in warnings if w))


_batch = Batch(_read, _fill, _finish)


def _bone_rows(frame_matrix: np.ndarray, frame_inverse: np.ndarray, poses: np.ndarray, rests: np.ndarray,
               modes: list[str], channels: list[tuple[float, ...]]) -> list[_BoneRow]:
    """`_bone_row` of n pose bones at once (poses, rests (n, 4, 4) float64), in a few stacked numpy
    calls: every row is computed on its own (stacked products run matrix by matrix, the channel
    unwrap row by row), so a bone gets the same bits in any batch, alone included. Bones with a
    problem (non-finite pose, zero-length rest, a motion outside Aff+(3)) go through `_bone_row`,
    which words the message; a turn whose channels cannot be unwrapped is NaN, as there."""
    n = len(poses)
    # One frame for all rows, or each row its own deformer's (`_fill`): the same elementwise products.
    P = np.broadcast_to(frame_matrix, (n, 4, 4)) if np.ndim(frame_matrix) == 2 else frame_matrix
    P_inv = np.broadcast_to(frame_inverse, (n, 4, 4)) if np.ndim(frame_inverse) == 2 else frame_inverse
    rotations = [tuple(float(c) for c in ch) + (0.0,) * (4 - len(ch)) for ch in channels]
    rotation_array = np.array(rotations)
    identities = np.array([identity_channels(mode) for mode in modes])
    euler = np.array([mode not in ("QUATERNION", "AXIS_ANGLE") for mode in modes])
    with np.errstate(all="ignore"):
        rested = ordered_matmul(P, rests)
        finite = ((np.abs(poses) < MAX_COORDINATE).all(axis=(1, 2))
                  & (np.abs(ordered_matmul(P, poses)) < MAX_COORDINATE).all(axis=(1, 2)))
        inverses = [_rest_inverse(rest) for rest in rests]
        local = ordered_matmul(poses, np.stack([inverse for inverse, _ in inverses]))
        frames = np.stack([_rest_frame(r) for r in rested])
        try:
            rotvecs = unwrap.channel_rotvec(modes, identities, rotation_array)
        except ValueError:  # some row cannot be unwrapped: the others keep their (row-independent) turn
            rotvecs = np.stack([_channel_turn(mode, identities[i], rotation_array[i])
                                for i, mode in enumerate(modes)])
        turns = ordered_matmul(frames, rotvecs[:, :, None])[:, :, 0]
        # Euler channels compare three values, the others four (the fourth Euler slot is padding).
        same = np.float32(rotation_array) == np.float32(identities)
        unturned = same[:, :3].all(axis=1) & (euler | same[:, 3])
        at_rest = unturned & (np.abs(local - np.eye(4)).reshape(n, 16).max(axis=1) <= AT_REST_TOL)
        matrices = ordered_matmul(ordered_matmul(P, local), P_inv)
        matrices[:, 3] = (0.0, 0.0, 0.0, 1.0)
        motion_ok = ((np.abs(matrices) < MAX_COORDINATE).all(axis=(1, 2))
                     & (np.linalg.det(matrices[:, :3, :3]) > 0.0))
    out = []
    identity = np.eye(4)
    for i in range(n):
        if not (finite[i] and inverses[i][1] and (at_rest[i] or motion_ok[i])):
            out.append(_bone_row(P[i], P_inv[i], poses[i], rests[i], modes[i], channels[i]))
            continue
        head = rested[i, :3, 3].copy()
        if at_rest[i]:
            out.append(_BoneRow(identity, True, True, turns[i], head))
        else:
            out.append(_BoneRow(matrices[i], False, bool(unturned[i]), turns[i], head))
    return out


def _channel_turn(mode: str, rest: np.ndarray, current: np.ndarray) -> np.ndarray:
    """unwrap.channel_rotvec of one row (n = 1), NaN when its channels cannot be unwrapped."""
    try:
        return unwrap.channel_rotvec([mode], rest[None], current[None])[0]
    except ValueError:
        return np.full(3, np.nan)


#: Inverses of bones' rest matrices (armature space), keyed on their bits: the rest pose changes only
#: in Edit Mode. Bounded like `_rows`.
_rest_inverses: dict[bytes, tuple[np.ndarray, bool]] = {}


def _rest_inverse(rest: np.ndarray) -> tuple[np.ndarray, bool]:
    """(`_inverse_affine`(rest), whether it exists and is finite) of a rest matrix (4, 4) float64."""
    key = rest.tobytes()
    found = _rest_inverses.get(key)
    if found is None:
        try:
            inverse = _inverse_affine(rest)
            found = (inverse, bool(np.isfinite(inverse).all()))
        except np.linalg.LinAlgError:
            found = (np.eye(4), False)
        if len(_rest_inverses) >= ROW_MEMO_SIZE:
            _rest_inverses.clear()
        _rest_inverses[key] = found
    return found


class BoneKind(BatchedKind, DeformerKind):
    """An Armature object's pose bones (all deform bones, or a chosen set) drive the mesh."""

    batch = _batch

    id = bone_tools.BONE
    label = "Bone"
    menu_label = "Bones"
    description = "Driven by the pose bones of an armature (an affine skin)"
    icon = "BONE_DATA"
    single_control = True
    add_description = ("Add a bone deformer to the active mesh; the selected armature's deform bones drive "
                       "it, weighted by the vertex groups named after them (as the Armature modifier reads "
                       "them), or by distance to the bones when the mesh has none of those groups")
    classes = (*bone_tools.CLASSES, *armature_convert.CLASSES)
    paints_groups = True

    @classmethod
    def properties(cls) -> dict[str, KindProperty]:
        return {
            "armature": KindProperty(PointerProperty(
                name="Armature", override=OVERRIDABLE, type=bpy.types.Object, poll=_poll_armature,
                update=control_picker(cls.id, "armature", "the new armature"),
                description="Armature whose pose bones drive the target (its deform bones, at their rest "
                            "pose in Edit Mode, are the rest)"), READ_BY_KIND),
            "bones": KindProperty(CollectionProperty(type=bone_tools.AffineDeformerBone), READ_BY_KIND),
            "active_bone_index": KindProperty(
                IntProperty(name="Active Bone", default=0, min=0, update=on_preview_option), INTERFACE),
        }

    def adopt_selection(self, context: bpy.types.Context, target: bpy.types.Object) -> Adopted:
        """The one selected armature; none selected: the armature of the mesh's (first enabled) Armature
        modifier, as a built-in deformer takes its object."""
        selected = [o for o in (getattr(context, "selected_objects", None) or []) if o.type == "ARMATURE"]
        from_modifier = None if selected else armature_convert.modifier_armature(target)
        if from_modifier is not None:
            if not deform_bones(from_modifier):
                raise BindError(f"Armature '{from_modifier.name}' has no deform bones")
            return Adopted([from_modifier], [], "")
        if not selected:
            raise BindError(f"Select an armature with '{target.name}' active, or give '{target.name}' an "
                            "Armature modifier that names one: the bone deformer takes its bones")
        armature, ignored = single_selected(context, target, "ARMATURE", "armature")
        if not deform_bones(armature):
            raise BindError(f"Armature '{armature.name}' has no deform bones")
        return Adopted([armature], [], ignored_note("non-armature", ignored))

    def set_up(self, deformer, adopted: Adopted) -> None:
        armature = adopted.controls[0]
        deformer.armature = armature
        target = deformer.id_data
        names = deform_bones(armature)
        for name in names:
            deformer.bones.add().name = name
        painted = any(target.vertex_groups.get(name) is not None for name in names)
        deformer.weight_mode = "VERTEX_GROUPS" if painted else "INVERSE_DISTANCE"
        deformer.normalize = "SUM"  # as the Armature modifier: a vertex's bone weights sum to 1
        deformer.max_influences = DEFAULT_INFLUENCES
        replaced = armature_convert.doubling_modifiers(target, armature)
        if replaced and replaced[0].vertex_group and not replaced[0].invert_vertex_group:
            deformer.mask_group = replaced[0].vertex_group  # as Convert: the modifier's mask carries over

    def after_add(self, target: bpy.types.Object, deformer, adopted: Adopted) -> str:
        return armature_convert.take_over_doubling(target, deformer, adopted.controls[0])

    def added_message(self, target: bpy.types.Object, deformer, adopted: Adopted) -> str:
        weights_from = ("their vertex groups" if deformer.weight_mode == "VERTEX_GROUPS"
                        else "distance (the mesh has no groups named after them)")
        return (f"Added a bone deformer to '{target.name}' driven by {len(deformer.bones)} bones of "
                f"'{adopted.controls[0].name}', weighted by {weights_from}")

    def store_rest(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
                   only: list[int] | None = None) -> None:
        """Check the armature and its bones; record the bones' rest segments in the target's space
        (for distance weights). The rest pose itself is the armature's (Edit Mode) rest, read live."""
        armature = deformer.armature
        problem = armature_problem(obj, armature)
        if problem:
            raise BindError(problem)
        bones = armature.data.bones
        if len(deformer.bones) == 0 or not any(bones.get(item.name) for item in deformer.bones):
            deformer.bones.clear()  # a new armature: its deform bones
            for name in deform_bones(armature):
                deformer.bones.add().name = name
        if len(deformer.bones) == 0:
            raise BindError(f"Armature '{armature.name}' has no deform bones")
        missing = [item.name for item in deformer.bones if bones.get(item.name) is None]
        if missing:
            raise BindError(f"Armature '{armature.name}' has no bone named "
                            + ", ".join(f"'{n}'" for n in missing) + ": remove it from the deformer")
        try:
            frame = _frame_matrix(obj, armature, depsgraph)
        except np.linalg.LinAlgError:
            raise BindError(f"'{obj.name}' has a zero scale: fix its transform before binding") from None
        segments = np.empty((len(deformer.bones), 2, 3))
        for i, item in enumerate(deformer.bones):
            bone = bones[item.name]
            segments[i, 0] = frame[:3, :3] @ np.array(bone.head_local) + frame[:3, 3]
            segments[i, 1] = frame[:3, :3] @ np.array(bone.tail_local) + frame[:3, 3]
        if not np.all(np.isfinite(segments)):
            raise BindError(f"Armature '{armature.name}' has a non-finite transform: fix it before binding")
        if REST_SEGMENTS in deformer:  # never assign an array of another length over an ID property
            del deformer[REST_SEGMENTS]
        deformer[REST_SEGMENTS] = segments.ravel().tolist()

    def sparse_weights(self, obj: bpy.types.Object, deformer,
                       rest_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        problem = settings_problem(deformer)
        if problem:
            raise BindError(problem)
        names = [item.name for item in deformer.bones]
        segments, problem = stored_segments(deformer)
        if problem:
            raise BindError(f"{problem}: rebind the deformer")
        heads, tails = segments[:, 0], segments[:, 1]
        scales = np.array([item.weight_scale for item in deformer.bones], dtype=np.float64)
        # Weight the truncation pools (near ties of more bones than Max Influences) goes to a point on
        # the bones' tree, an ancestor of most of the vertex's weight or the mean of its children
        # (core.hierarchy.PoolPoint, MATH.md §12): indices m … 2m name those means.
        armature = deformer.armature
        parents = (bone_parents(armature, names) if armature is not None and armature.type == "ARMATURE"
                   else np.full(len(names), -1, dtype=np.intp))
        indices, values, warning = control_weights(obj, deformer, rest_points, heads, scales, names, names,
                                                   anchors=0.5 * (heads + tails), tails=tails,
                                                   pool=hierarchy.PoolPoint(parents),
                                                   floor=hierarchy.BONE_POOL_FLOOR)
        if deformer.weight_mode == "VERTEX_GROUPS":
            missing = [n for n in names if obj.vertex_groups.get(n) is None]
            if len(missing) == len(names):
                warning = ("No vertex group is named after a bone: paint groups named after the bones, "
                           "or choose distance weights")
        return indices, values, warning


    def controls(self, obj: bpy.types.Object, deformer) -> list[bpy.types.Object]:
        armature = deformer.armature
        return [armature] if armature is not None and armature != obj else []

    def draw_settings(self, layout: bpy.types.UILayout, deformer) -> None:
        layout.prop(deformer, "armature")
        draw_weight_options(layout, deformer)

    def branch_rule_active(self, deformer) -> bool:
        return deformer.blend_mode == "AFFINE_LOG"

    def draw_controls(self, layout: bpy.types.UILayout, deformer, index: int) -> None:
        bone_tools.draw_controls(layout, deformer, index)

    def draw_object(self, layout: bpy.types.UILayout, obj: bpy.types.Object) -> None:
        armature_convert.draw_convert(layout, obj)

    def draw_actions(self, layout: bpy.types.UILayout, deformer, index: int) -> None:
        armature_convert.draw_restore(layout, deformer, index)

    def control_count(self, deformer) -> int:
        return len(deformer.bones)

    def pool_mix(self, deformer) -> np.ndarray | None:
        """The pooled nodes m … 2m (core.hierarchy.pool_parents) as weights on the bones: the means
        of each bone's children and of the roots (core.hierarchy.pool_mix, exact as the blend takes
        them)."""
        names = [item.name for item in deformer.bones]
        if not names:
            return None
        armature = deformer.armature
        parents = (bone_parents(armature, names) if armature is not None and armature.type == "ARMATURE"
                   else np.full(len(names), -1, dtype=np.intp))
        return hierarchy.pool_mix(parents, _pool_scales(deformer))

    def active_control(self, deformer) -> int:
        return deformer.active_bone_index

    def control_items(self, deformer) -> bpy.types.bpy_prop_collection:
        return deformer.bones

    def control_groups(self, deformer, complete: bool = False) -> list[str]:
        """Each bone's name: the Armature modifier's convention, a group per bone name."""
        return [item.name for item in deformer.bones]

    def adopt_rest(self, source, deformer, relative: np.ndarray) -> bool:
        segments, problem = stored_segments(source)
        if problem or len(segments) != len(deformer.bones):
            return False
        deformer[REST_SEGMENTS] = (segments @ relative[:3, :3].T + relative[:3, 3]).ravel().tolist()
        return True

    def follow_renames(self, obj: bpy.types.Object, deformer) -> None:
        bone_tools.follow_renames(obj, deformer)


@caches.register
def _forget(_key: caches.Key | None) -> None:
    """The per-bone memos are keyed on their inputs, so shared by all deformers: any forget drops them."""
    _rows.clear()
    _rest_frames.clear()
    _rest_inverses.clear()
    _batch.drop()
    _pool_mixes.clear()


def _frame_matrix(obj: bpy.types.Object, armature: bpy.types.Object,
                  depsgraph: bpy.types.Depsgraph) -> np.ndarray:
    """P = target_world⁻¹ · armature_world (evaluated, float64); LinAlgError for a singular target."""
    target_world = np.array(obj.evaluated_get(depsgraph).matrix_world, dtype=np.float64)
    armature_world = np.array(armature.evaluated_get(depsgraph).matrix_world, dtype=np.float64)
    out = _inverse_affine(target_world) @ armature_world
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _inverse_affine(matrix: np.ndarray) -> np.ndarray:
    """The inverse (4, 4) of an affine matrix (bottom row 0 0 0 1): [[M⁻¹, −M⁻¹ t], [0, 1]];
    LinAlgError when M is singular."""
    linear = inverse3(matrix[:3, :3])
    out = np.eye(4)
    out[:3, :3] = linear
    out[:3, 3] = -ordered_matmul(linear, matrix[:3, 3])
    return out


def _chain_rows(name: str, pose, frame: np.ndarray, rows: dict[str, _BoneRow | None],
                misses: list[tuple]) -> bool:
    """Walk bone `name` and its parents (their turns add up) into `rows` (in walk order): a bone whose
    inputs are in the memo gets its `_BoneRow`, the others None and an entry (name, key, pose matrix,
    rest matrix, mode, channels) in `misses`. False when the armature has no bone `name`."""
    while name and name not in rows:
        pose_bone = pose.bones.get(name)
        if pose_bone is None:
            return False
        posed = np.array(pose_bone.matrix, dtype=np.float64)
        rest = np.array(pose_bone.bone.matrix_local, dtype=np.float64)
        mode = pose_bone.rotation_mode
        channels = rotation_channels(pose_bone, mode)
        key = (frame.tobytes(), posed.tobytes(), rest.tobytes(), mode, _bits(channels))
        row = _rows.get(key)
        if row is None:
            misses.append((name, key, posed, rest, mode, channels))
        rows[name] = row
        parent = pose_bone.parent
        name = parent.name if parent is not None else ""
    return True


def _hierarchy(names: list[str], pose, rows: dict[str, _BoneRow], matrices: np.ndarray) -> Chain:
    """The deformer's bones as a hierarchy (MATH.md §14): each bone's parent is its nearest ancestor
    among `names` (bones in between, not driving the mesh, count as part of its own motion), and its
    local motion L_i = A_parent⁻¹ A_i turns by its own channels and those of the bones in between:
    that sum, in the target's rest space, is L_i's reference rotation vector, about its rest head.
    A bone whose local motion is within AT_REST_TOL of the identity and which (with the bones in
    between) is unturned has L_i = I exactly, so a rigid chain moves rigidly."""
    index = {name: i for i, name in enumerate(names)}
    m = len(names)
    parents = np.full(m, -1, dtype=np.intp)
    references = np.zeros((m, 3))
    unturned = np.ones(m, dtype=bool)
    for i, name in enumerate(names):  # a pass per bone and its ancestors, never per vertex
        bone = name
        while bone:
            references[i] += rows[bone].turn
            unturned[i] &= rows[bone].unturned
            parent = pose.bones[bone].parent
            bone = parent.name if parent is not None else ""
            if bone in index:
                parents[i] = index[bone]
                break
    locals_ = hierarchy.local_motions(matrices, parents)
    still = unturned & (np.abs(locals_ - np.eye(4)).reshape(m, 16).max(axis=1, initial=0.0) <= AT_REST_TOL)
    locals_[still] = np.eye(4)
    pivots = np.stack([rows[name].head for name in names])
    return Chain(parents, locals_, still, references, pivots)
