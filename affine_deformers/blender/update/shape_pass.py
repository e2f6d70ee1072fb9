"""The shape-preserving pass in an update (Preserve Shape; core/arap, MATH.md §15).

With the option on, an update takes the per-vertex field as usual — each vertex's motion
x ↦ M_v x + t_v (blend.blend_motions) and its position y_v = M_v p_v + t_v — and then solves for the
positions x whose gradient on every triangle best matches the blended map there, with the vertices
nearest the controls held towards y:

    min_x Σ_t w_t ‖(F_t(x) − A_t) P_t‖² + Σ_v α_v |x_v − y_v|²,

A_t the mean of the field's linear parts M_v at the triangle's corners (the blend at its centroid to
second order in its size), α from the bound weights (core.arap.anchor_weights). The matrix depends only
on the bound rest shape, its triangles, the weights and the anchor strength: it is ordered and factored
once (accel.arap_bind) and each update is a right-hand side and a back-solve.

What the pass deforms: the bound rest shape. On the offset path the result is x − p; on the motion
path (something before the modifier changes the positions) each vertex's motion gets the pass's
correction as a translation, x ↦ M_v x + t_v + (x_v − y_v): exact at the bound rest shape, and applied
to whatever reaches the modifier as the per-vertex field is.

Factors are memoised on a digest of everything they are computed from (`_factors`), so an undo or a
file reload finds the factor it already has instead of factoring again; the per-deformer memo of that
digest (`_digests`) is an ordinary cache. Both hold values recomputable from the .blend.
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from dataclasses import dataclass

import bpy
import numpy as np

from ... import accel
from ...core import arap
from .. import caches
from .bound import BindRecord
from .validation import settings_problem

#: The deformer settings the pass reads (Iterations: `apply`; Anchor Strength: `factor_for`).
SETTINGS = ("shape_iterations", "shape_anchor")


class ShapePassError(Exception):
    """The pass cannot run on this mesh (degenerate triangles, a system that cannot be factored); the
    message names the fix. The deformer then passes its input through."""


@dataclass
class Factor:
    """A bound system's solver and what the panel reports about it."""

    elements: arap.Elements
    solver: object  # accel.arap_bind's: frame(motions, field, iterations), stats, close()
    seconds: float  # assembly + ordering + factorisation
    loose_parts: int
    corners: tuple[np.ndarray, ...] = ()  # the elements' corner columns, contiguous (for the gathers)

    def __post_init__(self) -> None:
        self.corners = tuple(np.ascontiguousarray(c) for c in self.elements.corners.T)

    def summary(self) -> str:
        stats = self.solver.stats
        size = stats.get("bytes")
        memory = f", {size / 2**20:.1f} MB" if size else ""
        backend = stats.get("backend", "C")
        return f"Factored {stats.get('n', 0):,} vertices in {self.seconds:.2f} s{memory} ({backend})"


#: Bytes of factors kept at most (least recently used ones are freed first; the one in use never).
FACTOR_MEMORY = 2 * 2**30
#: digest of the inputs → Factor (never stale: the digest covers every input).
_factors: OrderedDict[bytes, Factor] = OrderedDict()
#: (object session uid, deformer uid) → (bound serial, anchor strength, backend, digest).
_digests: dict[caches.Key, tuple] = {}


@caches.register
def forget(key: caches.Key | None = None) -> None:
    caches.drop(_digests, key)


def release_all() -> None:
    """Free every factor (the add-on is being disabled)."""
    while _factors:
        _factors.popitem()[1].solver.close()


def _triangles(mesh: bpy.types.Mesh) -> np.ndarray:
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3)


def _digest(*arrays: np.ndarray, extra: tuple = ()) -> bytes:
    h = hashlib.blake2b(repr(extra).encode(), digest_size=20)
    for a in arrays:
        h.update(np.ascontiguousarray(a).view(np.uint8).ravel())
    return h.digest()


def factor_for(obj: bpy.types.Object, deformer, bound: BindRecord, controls: int) -> Factor:
    """The factor of `deformer`'s system, built when its inputs changed (ShapePassError when it
    cannot be). `controls`: the deformer's control count; bound weight columns at or past it are the
    truncation's pooled nodes (MATH.md §12), which anchor nothing."""
    key = (obj.session_uid, deformer.uid)
    strength = float(deformer.shape_anchor)
    mesh = obj.data
    # The faces are the system's, not the bind's: an edit of the faces alone (n-gon caps triangulated)
    # keeps the bind and must still rebuild the system (issue 57). Their counts catch such edits.
    state = (bound.serial, strength, accel.active(), len(mesh.polygons), len(mesh.loops))
    known = _digests.get(key)
    if known is not None and known[:-1] == state and known[-1] in _factors:
        _factors.move_to_end(known[-1])
        return _factors[known[-1]]
    triangles = _triangles(mesh)
    if not len(triangles):
        raise ShapePassError(f"'{obj.name}' has no faces: Preserve Shape needs a surface; turn it off")
    digest = _digest(bound.rest32, triangles, bound.indices, bound.values,
                     extra=(strength, accel.active(), controls))
    found = _factors.get(digest)
    if found is None:
        found = _build(bound, triangles, strength, controls)
        _factors[digest] = found
        _evict(keep=digest)
    _factors.move_to_end(digest)
    _digests[key] = (*state, digest)
    return found


def _build(bound: BindRecord, triangles: np.ndarray, strength: float, controls: int) -> Factor:
    start = time.perf_counter()
    try:
        elements = arap.triangle_elements(bound.points, triangles)
        anchors = arap.anchor_weights(elements, bound.indices, bound.values, strength=strength,
                                      controls=controls)
        system = arap.bind_system(elements, anchors)
        solver = accel.arap_bind(system)
    except ValueError as exc:  # degenerate triangles, a system that cannot be factored
        raise ShapePassError(f"Preserve Shape: {exc}") from None
    return Factor(elements, solver, time.perf_counter() - start, system.loose_parts)


def _evict(keep: bytes) -> None:
    total = sum(f.solver.stats.get("bytes", 0) for f in _factors.values())
    for digest in list(_factors):
        if total <= FACTOR_MEMORY:
            break
        if digest != keep:
            total -= _factors[digest].solver.stats.get("bytes", 0)
            _factors.pop(digest).solver.close()


def summary(obj: bpy.types.Object, deformer) -> str:
    """What the panel shows about the deformer's factor ('' when none is built)."""
    known = _digests.get((obj.session_uid, deformer.uid))
    found = _factors.get(known[-1]) if known is not None else None
    return found.summary() if found is not None else ""


def apply(obj: bpy.types.Object, deformer, bound: BindRecord, controls: int, motions: np.ndarray,
          path: str) -> np.ndarray:
    """The pass on the field's per-vertex motions (4, N, 3) (blend.blend_motions' columns M e_x, M e_y,
    M e_z, t): offsets x − p (N, 3) float64 for the 'OFFSET' path, motions with the correction in their
    translations (4, N, 3) float32 for 'MOTION'. Raises ShapePassError, also naming a setting of the
    pass that is not a finite number in its range (validation.py: NaN passes the interface's clamp, a
    script or a damaged file bypasses it)."""
    problem = settings_problem(deformer, SETTINGS)
    if problem:
        raise ShapePassError(problem)
    factor = factor_for(obj, deformer, bound, controls)
    M = np.asarray(motions, dtype=np.float64)
    p = bound.points
    y = M[0] * p[:, :1] + M[1] * p[:, 1:2] + M[2] * p[:, 2:3] + M[3]
    # (3, E, 3): the mean of the corners' columns, from the float32 motions (a shared motion's three
    # equal corners give exactly it back: float32 sums are exact in float64)
    rows = np.ascontiguousarray(np.asarray(motions)[:3].transpose(1, 0, 2)).reshape(len(p), 9)
    c0, c1, c2 = factor.corners
    mean = (np.take(rows, c0, axis=0).astype(np.float64) + np.take(rows, c1, axis=0)
            + np.take(rows, c2, axis=0)) / 3.0
    targets = mean.reshape(-1, 3, 3).transpose(1, 0, 2)
    x = factor.solver.frame(targets, y, int(deformer.shape_iterations))
    if path == "OFFSET":
        return x - p
    out = np.array(motions, dtype=np.float32)
    out[3] += (x - y).astype(np.float32)
    return out
