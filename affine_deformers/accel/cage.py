"""The cage's per-update path on the compiled kernel: its faces' motions (`cage_faces`: core.cage's
`face_motions`, `affected_faces` and `signed_volume` in one call) and its harmonic nodes' parameters
(`cage_nodes`: core.cage.harmonic.node_params for the nodes a moved face reaches), from
csrc/kernel_cage.c. Both return None when the compiled kernel is not active now (the caller then
uses the numpy functions, which hold the contract).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core import cage as _cage
from ..core import unwrap as _unwrap
from .state import _FAILED, _c, _entry_call, _usable

__all__ = ["cage_faces", "cage_nodes"]

FloatArray = NDArray[np.float64]


def cage_faces(rest: ArrayLike, current: ArrayLike, topology: _cage.CageTopology
               ) -> tuple[_cage.FaceMotions, NDArray[np.bool_], float] | None:
    """(`core.cage.face_motions(rest, current, topology, faces=reached)`, reached (F,) bool =
    `core.cage.affected_faces(rest, current, topology)`, `core.cage.signed_volume(current, topology)`)
    with the 'NEIGHBOURS' apex, in one compiled call (`Kernel.cage_faces`: corner frames, stencil
    apex, fold guard, ψ with the polar split of `polar_log`, the mean over each face's corners, for
    the faces reached only; agreeing with the numpy functions to ~1e-15). Faces whose corners need a
    lift onto the first corner's rotation branch (past a half turn from it) are lifted and averaged
    here with `unwrap.lift_params`, as face_motions does. None when the compiled kernel is not
    active now (the caller then uses the numpy functions)."""
    module = _usable()
    if module is None:
        return None
    tables = _cage.face_tables(rest, topology)
    cur = _c(np.asarray(current, dtype=np.float64), np.float64)
    if cur.shape != tables.rest.shape:
        raise ValueError(f"current must have shape {tables.rest.shape}, got {cur.shape}")
    F = topology.n_faces
    params = np.empty((F, 12))
    corner_params = np.empty((tables.triples.shape[0], 12))
    flags = np.empty(F, dtype=np.int64)
    moved = np.empty(cur.shape[0], dtype=np.bool_)
    volume = _entry_call("cage_faces", lambda: module.cage_faces(
        cur, tables.rest, tables.triples, tables.first, tables.usable, tables.weight, tables.rest_ok,
        tables.centres, tables.inverses, tables.stencil_vertices, tables.stencil_gamma,
        tables.stencil_moments, tables.stencil_spread, tables.stencil_active, tables.fan, moved,
        params, corner_params, flags))
    if volume is _FAILED:
        return None
    reached = (flags & module.FACE_REACHED) != 0
    has_corner = (flags & module.FACE_HAS_CORNER) != 0
    valid = has_corner & (((flags & module.FACE_VALID) != 0) | ~reached)
    lift = np.flatnonzero(flags & module.FACE_NEEDS_LIFT)
    for f in lift.tolist():  # rare: a face whose corners straddle a half turn
        span = np.arange(tables.first[f], tables.first[f + 1])
        rows = span[tables.usable[span]]
        lifted = _unwrap.lift_params(corner_params[rows], corner_params[rows[0], 0:3])
        params[f] = (tables.weight[rows, None] * lifted).sum(axis=0)
    return _cage.FaceMotions(params, valid, _cage.face_messages(has_corner, valid)), reached, float(volume)


def cage_nodes(node_points: ArrayLike, node_weights: ArrayLike, face_params: ArrayLike, reached: ArrayLike,
               valid: ArrayLike | None = None, totals: ArrayLike | None = None
               ) -> tuple[FloatArray, NDArray[np.bool_], FloatArray] | None:
    """(params (G, 12), touched (G,), totals (G,)): `core.cage.harmonic.node_params(node_points,
    node_weights, face_params, faces=reached, valid=valid)` for the nodes with weight on a reached
    face (touched), zeros for the others, in one compiled call (`Kernel.cage_nodes`; the same
    parameters to ~1e-15). node_weights (G, F), best column-major (its transpose is then read
    without a copy); reached: the indices of the faces that moved; valid (F,) bool or None (all
    valid). totals: the node sums Σ_f W_cf valid_f that an earlier call with the same node_weights
    and valid returned (what every update with them needs, so a caller keeps them), or None to
    compute them; passing them changes no bit of the result. None when the compiled kernel is not
    active now (the caller then uses `node_params`)."""
    module = _usable()
    if module is None:
        return None
    W = np.asarray(node_weights, dtype=np.float64)
    x = _c(node_points, np.float64)
    P = np.asarray(face_params, dtype=np.float64)
    reached = _c(reached, np.int64)
    G, F = W.shape
    keep = np.ones(F, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    faces = reached[keep[reached]]
    terms = np.empty((faces.size, 21))
    blend = np.empty((21, G))
    out = np.empty((G, 12))
    touched = np.empty(G, dtype=np.bool_)
    fill = totals is None
    sums = np.empty(G) if fill else _c(totals, np.float64)
    if sums.shape != (G,):
        raise ValueError(f"totals must have shape ({G},), got {sums.shape}")
    Wt, rows, keep64 = _c(W.T, np.float64), _c(P[faces], np.float64), keep.astype(np.float64)
    if _entry_call("cage_nodes", lambda: module.cage_nodes(
            Wt, reached, faces, rows, keep64, sums, fill, x, terms, blend, out, touched)) is _FAILED:
        return None
    return out, touched, sums
