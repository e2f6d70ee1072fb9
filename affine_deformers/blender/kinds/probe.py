"""The probe kind: any objects (normally Empties) whose motion drives the mesh.

Bind stores each probe's rest matrix C_rest (target space, float32) and its rotation channels on the
probe item; per update each probe's A = C · C_rest⁻¹ comes from the evaluated depsgraph, memoised per
probe on the exact bits of its inputs (`_rows`), with its channels for the rotation-log branch.
Weights: inverse distance, falloff, painted vertex groups or harmonic surface weights
(kinds/weighting.py). The probe items, their operators, list and states: kinds/probe_tools.py.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import bpy
import numpy as np
from bpy.props import CollectionProperty, IntProperty

from ... import accel
from ...core import aff3, weights
from .. import caches
from ..files import storage
from ..update.validation import (
    channels_problem,
    channels_usable,
    rest_matrices_usable,
    rest_matrix_problem,
    shown,
)
from . import probe_tools
from .base import (
    INTERFACE,
    OVERRIDABLE,
    READ_BY_KIND,
    Adopted,
    BindError,
    ChannelTurns,
    DeformerKind,
    KindProperty,
    Motions,
    ignored_note,
)
from .batching import Batch, BatchedKind, keep_rows
from .probe_tools import default_probes, group_names, probe_label, selected_probes
from .services import on_preview_option
from .transforms import (
    MAX_COORDINATE,
    StaleControls,
    finite_transform,
    frame_rotation,
    frame_rotations,
    in_a_scene,
    inverse3,
    local_matrix,
    local_solve,
    local_solves_rows,
    motion_problem,
    ordered_matmul,
    relative_motion,
    rotation_channels,
    transform_problem,
    world_matrix,
)
from .weighting import control_weights, draw_weight_options, weight_settings_problem

#: Max Influences of a new probe deformer (core.weights.PROBE_INFLUENCES; the property's default, 4,
#: stays for files of 0.1.0).
DEFAULT_INFLUENCES = weights.PROBE_INFLUENCES


def pool_coefficients(deformer) -> np.ndarray:
    """The coefficients a_i = s_i / Σ s of the truncation's pooled control (m,) from the probes'
    weight scales s (core.weights.pool_weights, MATH.md §12): where every probe is equally far, the
    untruncated weights are in proportion to the scales, and so is the pooled mix."""
    scales = np.empty(len(deformer.probes), dtype=np.float32)
    if not len(scales):
        return np.zeros(0)
    deformer.probes.foreach_get("weight_scale", scales)
    key = scales.tobytes()  # per update otherwise: a few small numpy calls on cold caches
    found = _pools.get(key)
    if found is None:
        found = weights.pool_weights(scales.astype(np.float64))
        found.flags.writeable = False  # shared between updates
        if len(_pools) >= ROW_MEMO_SIZE:
            _pools.clear()
        _pools[key] = found
    return found


def settings_problem(deformer) -> str:
    """The first weight setting of `deformer` or of a probe (its Weight Scale) that is refused, with
    what the update does ('' when none; kinds/weighting.py `weight_settings_problem`)."""
    probes = deformer.probes
    return weight_settings_problem(deformer, probes, lambda i: f"Probe '{probe_label(probes[i])}'")


def rest_matrices(deformer) -> np.ndarray:
    """Stored rest matrices (m, 4, 4) float32 (row-major, as written by store_rest)."""
    flat = np.empty(len(deformer.probes) * 16, dtype=np.float32)
    if len(deformer.probes):
        deformer.probes.foreach_get("rest_matrix", flat)
    return flat.reshape(-1, 4, 4)


class ProbeKind(BatchedKind, DeformerKind):
    """Probes: any objects (normally Empties) whose motion drives the mesh."""

    id = probe_tools.PROBE
    label = "Probe"
    menu_label = "Probes"
    description = "Driven by the motion of probe objects"
    icon = "EMPTY_AXIS"
    single_control = False
    add_description = ("Add a probe deformer to the active mesh; the selected Empties become its probes "
                       "(none selected: two new Empties at the ends of the mesh's longest axis). Their "
                       "current poses become the "
                       "rest pose")
    classes = probe_tools.CLASSES
    paints_groups = True

    @classmethod
    def properties(cls) -> dict[str, KindProperty]:
        return {
            "probes": KindProperty(CollectionProperty(type=probe_tools.AffineDeformerProbe,
                                                      override=OVERRIDABLE), READ_BY_KIND),
            "active_probe_index": KindProperty(
                IntProperty(name="Active Probe", default=0, min=0, update=on_preview_option), INTERFACE),
        }

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
                if not in_a_scene(probe):
                    raise BindError(f"Probe '{probe.name}' is not in any scene: link it back or remove it")
                rest = local_matrix(target_world, world_matrix(probe, depsgraph))
                reason = transform_problem(rest)  # a rest the update would refuse as damaged
                if not reason and np.linalg.det(rest[:3, :3].astype(np.float64)) == 0.0:
                    reason = "has a zero scale"
                if reason:
                    raise BindError(f"Probe '{probe.name}' {reason}: fix it before binding")
                rests.append(rest)
        except np.linalg.LinAlgError:
            raise BindError(f"'{obj.name}' has a zero scale: fix its transform before binding") from None
        for item, rest in zip(items, rests, strict=True):
            evaluated = item.object.evaluated_get(depsgraph)  # the channels as evaluated, like the matrix
            item.rest_matrix = rest.ravel().tolist()
            item.name = item.object.name
            item.rest_rotation_mode = evaluated.rotation_mode
            item.rest_rotation = rotation_channels(evaluated)

    def adopt_rest(self, source, deformer, relative: np.ndarray) -> bool:
        rests = rest_matrices(source).astype(np.float64)
        if len(rests) != len(deformer.probes):
            return False
        for item, rest, src in zip(deformer.probes, rests, source.probes, strict=True):
            item.rest_matrix = np.float32(relative @ rest).ravel().tolist()
            item.rest_rotation_mode, item.rest_rotation = src.rest_rotation_mode, tuple(src.rest_rotation)
        return True

    def sparse_weights(self, obj: bpy.types.Object, deformer,
                       rest_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        problem = settings_problem(deformer)
        if problem:
            raise BindError(problem)
        rests = rest_matrices(deformer).astype(np.float64)
        scales = np.array([item.weight_scale for item in deformer.probes], dtype=np.float64)
        names = group_names(obj, deformer)  # a renamed probe keeps its painted group
        labels = [probe_label(item) for item in deformer.probes]
        indices, values, warning = control_weights(obj, deformer, rest_points, rests[:, :3, 3], scales,
                                                   names, labels)
        if deformer.weight_mode == "VERTEX_GROUPS":
            missing = [n for n in names if obj.vertex_groups.get(n) is None]
            if missing:
                warning = ("No vertex group named " + ", ".join(f"'{n}'" for n in missing)
                           + ": paint one per probe, named after it (those probes have no influence)")
        return indices, values, warning

    def adopt_selection(self, context: bpy.types.Context, target: bpy.types.Object) -> Adopted:
        """The selected Empties; none selected: two new Empties at the ends of the mesh's longest axis."""
        probes, ignored = selected_probes(context, target)
        created = [] if probes else default_probes(context, target)
        return Adopted(probes or created, created, ignored_note("non-Empty", ignored))

    def set_up(self, deformer, adopted: Adopted) -> None:
        deformer.max_influences = DEFAULT_INFLUENCES
        for probe in adopted.controls:
            deformer.probes.add().object = probe

    def added_message(self, target: bpy.types.Object, deformer, adopted: Adopted) -> str:
        names = ", ".join(f"'{o.name}'" for o in adopted.created)
        made = f" (created {names})" if adopted.created else ""
        return f"Added a probe deformer to '{target.name}' with {len(adopted.controls)} probe(s){made}"

    def controls(self, obj: bpy.types.Object, deformer) -> list[bpy.types.Object]:
        probes = {item.object for item in deformer.probes if item.object is not None and item.object != obj}
        return sorted(probes, key=lambda o: o.name_full)

    def draw_settings(self, layout: bpy.types.UILayout, deformer) -> None:
        draw_weight_options(layout, deformer)

    def branch_rule_active(self, deformer) -> bool:
        """A linear blend of probes has no rotation branches."""
        return deformer.blend_mode == "AFFINE_LOG"

    def draw_controls(self, layout: bpy.types.UILayout, deformer, index: int) -> None:
        probe_tools.draw_controls(layout, deformer, index)

    def control_count(self, deformer) -> int:
        return len(deformer.probes)

    def pool_mix(self, deformer) -> np.ndarray | None:
        """The pooled column blends the probes by their weight scales (`pool_coefficients`)."""
        return pool_coefficients(deformer) if len(deformer.probes) else None

    def active_control(self, deformer) -> int:
        return deformer.active_probe_index

    def control_items(self, deformer) -> bpy.types.bpy_prop_collection:
        return deformer.probes

    def control_groups(self, deformer, complete: bool = False) -> list[str]:
        """Each probe's object's name (the group Weights → Vertex Groups writes is named after it)."""
        if complete:
            for i, item in enumerate(deformer.probes):
                if item.object is None:
                    raise BindError(f"Probe {i + 1} ('{item.name or '?'}') has no object: pick one or "
                                    "remove it")
        return [item.object.name for item in deformer.probes if item.object is not None]

    def groups_written(self, deformer, names: list[str]) -> None:
        """Each probe reads its new group by name (and is named after it)."""
        for item, name in zip(deformer.probes, names, strict=True):
            item.vertex_group = name
            item.name = name

    def follow_renames(self, obj: bpy.types.Object, deformer) -> None:
        probe_tools.follow_renames(obj, deformer)

    def record_states(self, obj: bpy.types.Object, deformer, motions: Motions | None, error: str,
                      depsgraph: bpy.types.Depsgraph) -> None:
        probe_tools.record_states(obj, deformer, motions, error, depsgraph)


@caches.register
def _forget(_key: caches.Key | None) -> None:
    """The per-probe memos are keyed on their inputs, so shared by all deformers: any forget drops them."""
    _rows.clear()
    _rest_inverses.clear()
    _pools.clear()
    _batch.drop()


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
    #: A degenerate probe that still deforms (a status naming it, its vertices only affected):
    #: scaled to zero (collapsed onto it: aff3.nearest_positive) or skipped (mirrored, deleted: its
    #: weight goes to the vertex's other probes).
    warning: str = ""
    skip: bool = False


#: Per-probe memo: a probe whose inputs (its and the target's world matrix, its channels and scales,
#: its rest data, the kernel backend of the frames' polar split) are bitwise unchanged gets its
#: previous `_ProbeRow` back instead of redoing the solves and polar splits. Keys hold every input, so
#: the result never depends on update history.
#: Bounded: cleared when full (a rig with more probes than this just recomputes).
ROW_MEMO_SIZE = 4096
_rows: dict[tuple, _ProbeRow] = {}


def _bits(values: tuple[float, ...]) -> bytes:
    """The exact float64 bits of a short tuple of numbers (−0.0 and NaN payloads included)."""
    return struct.pack(f"{len(values)}d", *values)


@dataclass
class _Reading:
    """One deformer's probes as read for an update, before the rows that missed the memo are
    computed (`_fill`) and the motions assembled (`_finish`). Lives for one update only."""

    obj: bpy.types.Object
    deformer: object
    target_world: np.ndarray
    rests: np.ndarray  # (m, 4, 4) float32
    rest_modes: list[str]
    rest_rotations: np.ndarray  # (m, 4)
    rows: list[_ProbeRow | None]
    misses: list[tuple[int, tuple, np.ndarray, tuple, str, tuple]]
    problem: str


def _read(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Motions | _Reading:
    """Read the probes of `deformer` from the evaluated `depsgraph` and look their rows up in the
    memo; Motions at once when the target itself cannot be read."""
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
        return Motions.invalid(m, f"'{obj.name}' {transform_problem(target_world)}: the mesh shows its "
                               "rest shape")
    problem = settings_problem(deformer)
    if problem:
        return Motions.invalid(m, problem)
    # Everything the probes share in one bytes object, which caches its hash: each probe's key
    # holds it plus its index, instead of hashing its own copies of the rest data per update.
    shared = b"".join((target_world.tobytes(), rests.tobytes(), flat.tobytes(),
                       "\0".join(rest_modes).encode()))
    backend = accel.active()  # the compiled and numpy polar splits of the frames differ by ~1e-15
    rows: list[_ProbeRow | None] = []
    misses: list[tuple[int, tuple, np.ndarray, tuple, str, tuple]] = []
    problem = ""
    # Probes the modifier does not name are evaluated because they are enabled (relations.py);
    # each is checked, so a visibility change not synced yet is an error, not a stale pose.
    stale = StaleControls(obj, storage.offset_name(deformer.uid), depsgraph, bool(m))
    for i, item in enumerate(probes):
        probe = item.object
        gone = ""
        if probe is None:
            gone = (f"Probe '{item.name or '?'}' was deleted or unassigned: its vertices follow the other "
                    "probes; remove it from the deformer or pick another object")
        elif not in_a_scene(probe):
            gone = (f"Probe '{probe.name}' is not in any scene (deleted?): its vertices follow the other "
                    "probes; remove it from the deformer or link it back")
        if gone:  # only what it held changes: its weight goes to the other probes
            rows.append(_ProbeRow(np.eye(4), True, rest_modes[i], tuple(rest_rotations[i]), np.eye(3),
                                  np.zeros(3), warning=gone, skip=True))
            continue
        if probe == obj:  # kept here too: a message set when it was picked must not be wiped
            problem = f"'{obj.name}' cannot be a probe of itself: pick another object for probe {i + 1}"
        if problem:
            break
        evaluated = probe.evaluated_get(depsgraph)
        if stale.stale(probe, evaluated):
            problem = (f"Probe '{probe.name}' is not evaluated (it is disabled in viewports or "
                       "renders, and the deformer is off there): enable the deformer, or show the "
                       "probe")
            break
        world = np.array(evaluated.matrix_world, dtype=np.float64)
        mode = evaluated.rotation_mode
        channels = rotation_channels(evaluated, mode)
        scale = (*evaluated.scale, *evaluated.delta_scale)
        key = (shared, i, world.tobytes(), mode, _bits(channels + scale), backend)
        row = _rows.get(key)
        if row is None:
            misses.append((i, key, world, channels, mode, scale))
        rows.append(row)
    return _Reading(obj, deformer, target_world, rests, rest_modes, rest_rotations, rows, misses, problem)


def _fill(readings: list[_Reading]) -> None:
    """Compute the rows that missed the memo, of all `readings` in one batch (every row is computed
    on its own against its own target: the same bits alone or in any batch), into the readings and
    the memo."""
    misses = [(reading, miss) for reading in readings for miss in reading.misses]
    if not misses:
        return
    computed = _probe_rows(np.stack([reading.target_world for reading, _ in misses]),
                           np.stack([miss[2] for _, miss in misses]), [miss[3] for _, miss in misses],
                           [miss[4] for _, miss in misses], [miss[5] for _, miss in misses],
                           np.stack([reading.rests[miss[0]] for reading, miss in misses]),
                           [reading.rest_modes[miss[0]] for reading, miss in misses],
                           np.stack([reading.rest_rotations[miss[0]] for reading, miss in misses]))
    keep_rows(_rows, ROW_MEMO_SIZE, misses, computed)


def _finish(reading: _Reading) -> Motions:
    """The motions of a reading whose rows are all known."""
    obj, deformer, rows = reading.obj, reading.deformer, reading.rows
    m = len(deformer.probes)
    for i, row in enumerate(rows):  # the first probe in order with a problem names it
        if row.error:
            return Motions.invalid(m, row.error.format(probe=deformer.probes[i].object.name, target=obj.name))
    if reading.problem:
        return Motions.invalid(m, reading.problem)
    # replace, not format: a name may hold braces (and a deleted probe's message holds its name already)
    warnings = [row.warning.replace("{probe}", _probe_name(deformer.probes[i])).replace("{target}", obj.name)
                for i, row in enumerate(rows) if row.warning]
    skipped = np.array([row.skip for row in rows], dtype=bool)
    rest_modes, rest_rotations = reading.rest_modes, reading.rest_rotations
    if m == 0:
        return Motions(np.zeros((0, 4, 4)), np.zeros(0, dtype=bool),
                       turns=ChannelTurns(rest_modes, rest_rotations, [], rest_rotations.copy(),
                                          np.zeros((0, 3, 3)), np.zeros((0, 3))))
    turns = ChannelTurns(rest_modes, rest_rotations, [r.mode for r in rows],
                         np.array([r.rotation for r in rows], dtype=np.float64),
                         np.stack([r.frame for r in rows]), np.stack([r.pivot for r in rows]))
    return Motions(np.stack([r.matrix for r in rows]), np.array([r.at_rest for r in rows]), turns=turns,
                   pool=pool_coefficients(deformer), warning="; ".join(warnings),
                   valid=~skipped if skipped.any() else None)


def _probe_name(item) -> str:
    return item.object.name if item.object is not None else (item.name or "?")


_batch = ProbeKind.batch = Batch(_read, _fill, _finish)


def _probe_rows(target_world: np.ndarray, worlds: np.ndarray, channels: list[tuple[float, ...]],
                modes: list[str], scales: list[tuple[float, ...]], rests: np.ndarray, rest_modes: list[str],
                rest_rotations: np.ndarray) -> list[_ProbeRow]:
    """`_probe_row` of n probes at once (worlds (n, 4, 4) float64, rests (n, 4, 4) float32, the other
    arguments one entry per probe), in a few stacked numpy calls instead of a few dozen per probe.
    `target_world`: the target's world matrix (4, 4), or one per probe (n, 4, 4) when the probes of
    several deformers are computed together (`_fill`).

    Every row is computed on its own (stacked products and SVDs run matrix by matrix, the rest is
    elementwise), so a probe gets the same bits in any batch, alone included. C = target⁻¹ · world
    has the bits `local_matrix` gives (the at-rest test compares it with the stored rest matrix);
    A = C · C_rest⁻¹ with C_rest⁻¹ memoised per rest matrix (`_rest_inverse`). Probes with a problem
    (non-finite transform, singular rest, a motion outside Aff+(3)) and a target scaled to zero go
    through `_probe_row`, which words the message."""
    n = len(worlds)
    targets = np.broadcast_to(target_world, (n, 4, 4)) if np.ndim(target_world) == 2 else target_world
    with np.errstate(all="ignore"):
        finite = (np.abs(worlds) < MAX_COORDINATE).all(axis=(1, 2))
        current, solved, solvable = local_solves_rows(targets, worlds if finite.all()
                                                      else np.where(finite[:, None, None], worlds, 0.0))
        finite &= solvable  # a target scaled to zero: its probes get their message from `_probe_row`
        rotations = [tuple(float(c) for c in ch) + (0.0,) * (4 - len(ch)) for ch in channels]
        rotation_array = np.array(rotations)
        frames = frame_rotations(solved[:, :, :3], modes, rotation_array, np.array(scales, dtype=np.float64))
        at_rest = ((current.reshape(n, 16) == rests.reshape(n, 16)).all(axis=1)
                   & np.array([mode == rest for mode, rest in zip(modes, rest_modes, strict=True)])
                   & (np.float32(rotation_array) == np.float32(rest_rotations)).all(axis=1))
        inverses = [_rest_inverse(rest) for rest in rests]
        moved = current.astype(np.float64)
        lin = ordered_matmul(moved[:, :3, :3], np.stack([inverse for inverse, _ in inverses]))
        matrices = np.zeros((n, 4, 4))
        matrices[:, :3, :3] = lin
        rest_origins = rests[:, :3, 3].astype(np.float64)[:, :, None]
        matrices[:, :3, 3] = moved[:, :3, 3] - ordered_matmul(lin, rest_origins)[:, :, 0]
        matrices[:, 3, 3] = 1.0
        motion_ok = ((np.abs(matrices) < MAX_COORDINATE).all(axis=(1, 2)) & (np.linalg.det(lin) > 0.0)
                     & np.array([ok for _, ok in inverses]))
        # else `_probe_row` says why
        finite &= rest_matrices_usable(rests, mirrored=True) & channels_usable(rest_rotations)
    out = []
    identity = np.eye(4)
    for i in range(n):
        if not finite[i] or not (at_rest[i] or motion_ok[i]):
            out.append(_probe_row(targets[i], worlds[i], channels[i], modes[i], scales[i], rests[i],
                                  rest_modes[i], rest_rotations[i]))
            continue
        pivot = current[i, :3, 3].astype(np.float64)
        if at_rest[i]:
            out.append(_ProbeRow(identity, True, modes[i], rotations[i], frames[i], pivot))
        else:
            out.append(_ProbeRow(matrices[i], False, modes[i], rotations[i], frames[i], pivot))
    return out


#: Pool coefficients (`pool_coefficients`) keyed on the probes' weight scales' bits (recomputable).
_pools: dict[bytes, np.ndarray] = {}

#: Inverses of stored rest matrices' 3×3 parts, keyed on their bits (recomputable; cleared when full).
_rest_inverses: dict[bytes, tuple[np.ndarray, bool]] = {}


def _rest_inverse(rest: np.ndarray) -> tuple[np.ndarray, bool]:
    """(C_rest⁻¹'s 3×3 part (float64, the adjugate over the determinant), whether it is usable) of a
    stored rest matrix (4, 4) float32."""
    key = rest.tobytes()
    found = _rest_inverses.get(key)
    if found is None:
        try:
            inverse = inverse3(rest[:3, :3].astype(np.float64))
            found = (inverse, bool(np.isfinite(inverse).all()))
        except np.linalg.LinAlgError:
            found = (np.eye(3), False)
        if len(_rest_inverses) >= ROW_MEMO_SIZE:
            _rest_inverses.clear()
        _rest_inverses[key] = found
    return found


def _probe_row(target_world: np.ndarray, world: np.ndarray, channels: tuple[float, ...], mode: str,
               scale: tuple[float, ...], rest: np.ndarray, rest_mode: str,
               rest_rotation: np.ndarray) -> _ProbeRow:
    """The `_ProbeRow` of one probe from its world matrix (float64), rotation channels and mode,
    (*scale, *delta_scale), and its rest matrix (float32) and channels."""
    identity = np.eye(4)
    rotation = tuple(float(c) for c in channels) + (0.0,) * (4 - len(channels))
    damaged = (rest_matrix_problem("Probe '{probe}': Rest Matrix", rest, mirrored=True)
               or channels_problem("Probe '{probe}': Rest Rotation", rest_rotation.tolist()))
    if damaged:
        return _ProbeRow(identity, False, mode, rotation, np.eye(3), np.zeros(3),
                         damaged + ": the mesh shows its rest shape; rebind the deformer")
    if not finite_transform(world):
        return _ProbeRow(identity, False, mode, rotation, np.eye(3), np.zeros(3),
                         "Probe '{probe}' " + transform_problem(world) + ": the mesh shows its rest shape")
    try:
        current, solved = local_solve(target_world, world)
    except np.linalg.LinAlgError:
        return _ProbeRow(identity, True, mode, rotation, np.eye(3), np.zeros(3),
                         "'{target}' is scaled to zero: the mesh shows its rest shape")
    frame = frame_rotation(solved[:, :3], mode, channels, scale)
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
    reason = motion_problem(matrix)
    if reason.startswith("is mirrored"):
        dets = [float(np.linalg.det(m[:3, :3].astype(np.float64))) for m in (rest, current)]
        if dets[0] < 0.0:  # the rest is the mirrored one (an Empty scaled by −1 at bind, or damaged)
            reason = (f"is mirrored relative to its Rest Matrix (determinant {shown(dets[0])}, now "
                      f"{shown(dets[1])})")
    # A rest matrix mirrored against a probe that is not is bind data gone bad (or a probe mirrored at
    # bind and no longer): the deformer's own data, so the mesh shows its rest shape.
    if reason == "is scaled to zero" or reason == "is mirrored (negative scale)":
        try:  # the limit of the nearby poses: what it holds collapses onto it
            collapsed = aff3.nearest_positive(matrix, rest[:3, 3].astype(np.float64))
        except ValueError:  # mirrored: no valid pose is near, its weight goes to the other probes
            return _ProbeRow(identity, True, mode, rotation, frame, pivot,
                             warning="Probe '{probe}' " + reason + ": an affine blend cannot mirror, its "
                                     "vertices follow the other probes", skip=True)
        return _ProbeRow(collapsed, False, mode, rotation, frame, pivot,
                         warning="Probe '{probe}' is scaled to zero: the vertices it holds collapse onto it")
    if reason:
        return _ProbeRow(identity, False, mode, rotation, frame, pivot,
                         "Probe '{probe}' " + reason + ": the mesh shows its rest shape")
    return _ProbeRow(matrix, False, mode, rotation, frame, pivot)

