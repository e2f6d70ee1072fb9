"""Blend parameters of the controls' motions: ψ(A_i) with the rotation-log branch, in ONE place.

The update pipeline asks this module, and only it, for parameters: `motions_to_params` for the
controls a vertex blends, `outer_at_strength` for a motion applied after the blend (a cage object's).
Both go through `lifted_params`, ψ followed by the branch lift (MATH.md §8). (core.cage lifts each
face's corner tetrahedra towards the face's own mean rotation: a different, per-face reference.)

Parameter rows are memoised on the exact bits of everything they depend on (`_param_rows`), so a
control that did not move costs a dictionary lookup; every row of ψ and of the lift is computed
independently of the others (tests/core/test_psi_batch.py), so the memo never changes a result.
"""

from __future__ import annotations

import numpy as np

from ... import accel
from ...core import aff3, unwrap
from .. import caches
from ..kinds import ChannelTurns, Motions
from ..kinds.transforms import reference_rotvecs

# Branch lift tolerances for Blender's float32 matrices (relative noise ~1e-7); core.unwrap's defaults
# suit exact input. Near a full turn the principal rotation is tiny, so its axis is noise/θ, which the
# lift multiplies by 2πk: below LIFT_AXIS_TOL radians the channels' axis is used instead (dropping at
# most that much genuine off-axis rotation). And V(ω) loses its in-plane gain there, so the float32
# residual of the translation (~1e-7·|pivot|) is divided by it: LIFT_DAMPING bounds the gain by
# 1/(2·LIFT_DAMPING). A probe turned 359.999° / 360° / 720° about a tilted axis, 6 units from the target's
# origin, was off by 3.5e-3 / 0.65 units with the core defaults, by < 2e-5 with these.
LIFT_AXIS_TOL = 3e-3
LIFT_DAMPING = 1e-3

#: Per-control memo of `motions_to_params` (see the module docstring). Bounded: cleared when full.
PARAM_MEMO_SIZE = 4096
_param_rows: dict[tuple, np.ndarray] = {}


@caches.register
def forget(key: caches.Key | None = None) -> None:
    """Drop the parameter memo at a full forget (its rows are keyed on their inputs, right for every
    deformer, so forgetting one deformer keeps them)."""
    if key is None:
        _param_rows.clear()


def lifted_params(matrices: np.ndarray, reference: np.ndarray | None,
                  pivots: np.ndarray | None) -> np.ndarray:
    """ψ(A) (m, 12) for motions (m, 4, 4), each rotation log lifted to the branch nearest its
    reference rotation vector (m, 3) about its pivot (m, 3) (core.unwrap.lift_params) when a
    reference is given; the principal branch (|ω| ≤ π) otherwise. ψ runs in the compiled kernel when
    it is active (accel.params_from_matrices), in numpy otherwise. ValueError from core.aff3 for a
    motion outside Aff+(3)."""
    params = accel.params_from_matrices(matrices)
    if params is None:
        params = np.asarray(aff3.params_from_matrices(matrices), dtype=np.float64)
    if reference is None:
        return params
    return unwrap.lift_params(params, reference, pivots, damping=LIFT_DAMPING, axis_tol=LIFT_AXIS_TOL)


def motions_to_params(motions: Motions, branch_rule: str) -> np.ndarray:
    """Blend parameters (m, 12) of the controls' motions: ψ(A_i) in the layout of docs/DEVELOPING.md.

    Controls exactly at rest get exactly zero parameters. Kinds that give their own parameters (cage
    faces average several tetrahedra) have them used as they are.

    The rotation log is multivalued (ω + 2πk·ω/|ω|); ψ as printed takes |ω| ≤ π, so a control turned
    past 180° flips the blend. With `branch_rule` 'CHANNELS' each ω is lifted to the branch nearest the
    control's own rotation channels (kinds.transforms.reference_rotvecs: Rotation Z keyed 0 → 720°
    gives 720°; turns from parents or constraints take the nearest branch) and u is recomputed about
    the control's origin (core.unwrap.lift_params). The reference comes from the current frame alone,
    so any frame evaluates the same in any order or process. 'SHORTEST' keeps the principal branch.
    """
    m = len(motions.matrices)
    if m == 0:
        return np.zeros((0, 12))
    if motions.params is not None:
        params = np.array(motions.params, dtype=np.float64)
        params[motions.at_rest] = 0.0
        return params
    lift = branch_rule == "CHANNELS" and motions.turns is not None and len(motions.turns.modes) == m
    keys = _param_keys(motions, lift)
    params = np.empty((m, 12))
    missing = []
    for i, key in enumerate(keys):
        row = _param_rows.get(key)
        if row is None:
            missing.append(i)
        else:
            params[i] = row
    if missing:
        params[missing] = _params_of_rows(motions, np.array(missing), lift)
        if len(_param_rows) + len(missing) > PARAM_MEMO_SIZE:
            _param_rows.clear()
        for i in missing:
            _param_rows[keys[i]] = params[i].copy()
    return params


def prefetch(items: list[tuple[Motions, str]]) -> None:
    """Fill the parameter memo for the rows of several deformers' motions ((motions, branch rule)
    each), the rows that miss it computed in one batch per branch treatment: the later
    `motions_to_params` of each deformer finds them (every row is computed on its own, so the batch
    gives each the bits it would get alone). Rows whose ψ fails are left to that call, which names
    the control."""
    # (lift, lifted to given references) -> entries
    groups: dict[tuple[bool, bool], list[tuple[Motions, list[int], list[tuple]]]] = {}
    for motions, branch_rule in items:
        if motions.chain is not None:
            motions = _chain_motions(motions)
        m = len(motions.matrices)
        if m == 0 or motions.params is not None:
            continue
        lift = branch_rule == "CHANNELS" and motions.turns is not None and len(motions.turns.modes) == m
        keys = _param_keys(motions, lift)
        missing = [i for i, key in enumerate(keys) if key not in _param_rows]
        if missing:
            given = lift and motions.turns.references is not None
            groups.setdefault((lift, given), []).append((motions, missing, keys))
    for (lift, _given), entries in groups.items():
        stacked = _stacked_rows(entries, lift)
        try:
            rows = _params_of_rows(stacked, np.arange(len(stacked.matrices)), lift)
        except ValueError:
            continue
        keys = [keys[i] for _, missing, keys in entries for i in missing]
        if len(_param_rows) + len(keys) > PARAM_MEMO_SIZE:
            _param_rows.clear()
        for key, row in zip(keys, rows, strict=True):
            _param_rows[key] = row.copy()


def _stacked_rows(entries: list[tuple[Motions, list[int], list[tuple]]], lift: bool) -> Motions:
    """The rows `missing` of each entry's motions as one Motions (with their channel turns when
    `lift`)."""
    matrices = np.concatenate([motions.matrices[missing] for motions, missing, _ in entries])
    at_rest = np.concatenate([motions.at_rest[missing] for motions, missing, _ in entries])
    turns = None
    if lift:
        parts = [(motions.turns, missing) for motions, missing, _ in entries]
        given = parts[0][0].references is not None  # the same for every entry of a group
        references = np.concatenate([t.references[missing] for t, missing in parts]) if given else None
        turns = ChannelTurns([t.rest_modes[i] for t, missing in parts for i in missing],
                             np.concatenate([t.rest_rotations[missing] for t, missing in parts]),
                             [t.modes[i] for t, missing in parts for i in missing],
                             np.concatenate([t.rotations[missing] for t, missing in parts]),
                             np.concatenate([t.frames[missing] for t, missing in parts]),
                             np.concatenate([t.pivots[missing] for t, missing in parts]),
                             references)
    return Motions(matrices, at_rest, turns=turns)


def chain_params(motions: Motions, branch_rule: str) -> np.ndarray:
    """Blend parameters (m, 12) of the local motions of a hierarchy (Motions.chain, MATH.md §14):
    ψ(L_i) as `motions_to_params` gives it (exactly zero at rest, memoised per row), the rotation
    log lifted with 'CHANNELS' to the branch nearest the control's own turn about its rest pivot."""
    return motions_to_params(_chain_motions(motions), branch_rule)


def _chain_motions(motions: Motions) -> Motions:
    """The local motions of `motions.chain` as Motions, their reference rotation vectors (if any) as
    the turns: what `chain_params` blends."""
    chain = motions.chain
    m = len(chain.locals)
    turns = None
    if chain.references is not None:
        modes = [""] * m  # the references are given: the channel fields are not read
        unused = np.zeros((m, 4))
        turns = ChannelTurns(modes, unused, modes, unused, np.broadcast_to(np.eye(3), (m, 3, 3)),
                             chain.pivots, chain.references)
    return Motions(chain.locals, chain.at_rest, turns=turns)


def _param_keys(motions: Motions, lift: bool) -> list[tuple]:
    """One hashable key per control holding the exact bits of everything its parameter row depends on."""
    m = len(motions.matrices)
    parts = [motions.matrices.reshape(m, 16), motions.at_rest.reshape(m, 1).astype(np.float64)]
    turns = motions.turns
    if lift and turns.references is not None:
        parts += [turns.references.reshape(m, 3), turns.pivots.reshape(m, 3)]
    elif lift:
        parts += [turns.rest_rotations.reshape(m, -1), turns.rotations.reshape(m, -1),
                  turns.frames.reshape(m, 9), turns.pivots.reshape(m, 3)]
    bits = np.ascontiguousarray(np.concatenate(parts, axis=1, dtype=np.float64))
    # The compiled ψ and numpy's agree to ~1e-15, not bit for bit: a row is kept per backend.
    compiled = accel.active()
    if not lift:
        return [(row.tobytes(), compiled) for row in bits]
    return [(row.tobytes(), compiled, rest_mode, mode)
            for row, rest_mode, mode in zip(bits, turns.rest_modes, turns.modes, strict=True)]


def _params_of_rows(motions: Motions, rows: np.ndarray, lift: bool) -> np.ndarray:
    """ψ(A_i), lifted to the channels' branch when `lift`, of the controls `rows` (zero at rest)."""
    reference = pivots = None
    if lift and motions.turns.references is not None:
        reference, pivots = motions.turns.references[rows], motions.turns.pivots[rows]
    elif lift:
        turns = motions.turns
        reference = reference_rotvecs([turns.rest_modes[i] for i in rows], turns.rest_rotations[rows],
                                      [turns.modes[i] for i in rows], turns.rotations[rows],
                                      turns.frames[rows])
        pivots = turns.pivots[rows]
    try:
        params = lifted_params(motions.matrices[rows], reference, pivots)
    except ValueError:
        # The core names the row within this batch of changed controls: name the control instead.
        for i in rows:
            try:
                aff3.params_from_matrices(motions.matrices[i : i + 1])
            except ValueError as exc:
                raise ValueError(f"control {int(i) + 1}: {exc}") from None
        raise
    params[motions.at_rest[rows]] = 0.0
    return params


def outer_at_strength(motions: Motions, strength: float, branch_rule: str) -> np.ndarray | None:
    """The motion applied after the blend, at strength s: φ(s·ψ(G)) (exactly G at s = 1; None when
    the kind has none).

    With `branch_rule` 'CHANNELS' and a reference from the kind (Motions.outer_reference: the cage
    object's own turn since bind), ψ(G) is lifted to the rotation-log branch nearest it about the
    object's origin, exactly as controls are (`motions_to_params`): a cage keyed 0 → 720° at s = 0.5
    turns the target 0 → 360° without a flip at 180°.
    """
    if motions.outer is None or strength == 1.0:
        return motions.outer
    lift = branch_rule == "CHANNELS" and motions.outer_reference is not None
    params = lifted_params(motions.outer[None], motions.outer_reference[None] if lift else None,
                           motions.outer_pivot[None] if lift and motions.outer_pivot is not None else None)
    return aff3.matrices_from_params(strength * params[0])
