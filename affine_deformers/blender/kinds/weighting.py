"""Weighting shared by the kinds whose controls are weighted by distance, surface or painted groups
(probes, bones): the weight options' panel part, and the weights themselves from the deformer's
options (core.weights.probe_weights; 'SURFACE': harmonic weights along the mesh, core.surface,
memoised on their exact inputs; 'VERTEX_GROUPS': the groups the kind names).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable

import bpy
import numpy as np

from ...core import surface, weights
from .. import caches
from ..files import nodes
from ..update.validation import items_problem, settings_problem


def draw_weight_options(layout: bpy.types.UILayout, deformer) -> None:
    """The weight options of kinds weighted by distance, surface or painted groups (probes, bones):
    radius only where it is a length scale, exponent where it sharpens."""
    layout.prop(deformer, "weight_mode")
    if deformer.weight_mode in ("INVERSE_DISTANCE", "FALLOFF"):
        layout.prop(deformer, "radius")
    if deformer.weight_mode in ("INVERSE_DISTANCE", "SURFACE"):
        layout.prop(deformer, "exponent")
    layout.prop(deformer, "normalize")
    layout.prop(deformer, "max_influences")


#: The deformer settings each weight mode reads (core.weights.probe_weights): Radius as the distance
#: scale (and, for 'SURFACE', on loose parts without a control), Exponent as the power; every mode
#: keeps the Max Influences largest.
MODE_SETTINGS = {
    "INVERSE_DISTANCE": ("radius", "exponent", "max_influences"),
    "FALLOFF": ("radius", "max_influences"),
    "VERTEX_GROUPS": ("max_influences",),
    "SURFACE": ("radius", "exponent", "max_influences"),
}


def weight_settings_problem(deformer, items, label: Callable[[int], str]) -> str:
    """The first setting the weights of `deformer` read that is refused (validation.py: not a finite
    number in its range), with what the update does: its weight mode's settings (`MODE_SETTINGS`),
    then each control item's Weight Scale (`items`, named by `label(i)`); '' when all are fine. Checked
    by every update (the scales also weigh the pooled nodes; a damaged setting shows at once, not at
    the next re-weighting) and by re-weighting."""
    return (settings_problem(deformer, MODE_SETTINGS.get(deformer.weight_mode, ()))
            or items_problem(items, "weight_scale", label))


def control_weights(obj: bpy.types.Object, deformer, rest_points: np.ndarray, heads: np.ndarray,
                    scales: np.ndarray, groups: list[str], labels: list[str], *,
                    anchors: np.ndarray | None = None,
                    tails: np.ndarray | None = None,
                    pool: weights.PoolColumns | None = None,
                    floor: float = weights.POOL_FLOOR) -> tuple[np.ndarray, np.ndarray, str]:
    """(indices (N, K), values (N, K), warning) of controls at `heads` (m, 3) (segments heads → tails
    for the distance modes when `tails` is given) with weight scales `scales` (m,), by the deformer's
    weight options: 'VERTEX_GROUPS' reads the vertex groups `groups` (one per control; a missing one
    reads as 0, the kind words that warning), 'SURFACE' solves harmonic weights anchored at `anchors`
    (default: the heads), whose loose parts and unanchored controls (named by `labels`) are the
    warning. `pool` and `floor`: where the truncation's pooled weight goes and its divisor's floor
    (core.weights.probe_weights; bones pass their tree's, MATH.md §12)."""
    mode = deformer.weight_mode
    warning = ""
    dense = solved = None
    if mode == "VERTEX_GROUPS":
        dense = nodes.vertex_group_weights(obj, groups)
    elif mode == "SURFACE":
        result = harmonic_surface_weights(obj.data, rest_points, heads if anchors is None else anchors)
        dense, solved = result.weights, result.solved
        warning = surface_warning(result, labels)
    indices, values = weights.probe_weights(
        rest_points, heads, mode=mode, radius=deformer.radius, exponent=deformer.exponent,
        normalize=deformer.normalize, k=deformer.max_influences, scales=scales, dense=dense,
        solved=solved, tails=tails if mode in ("INVERSE_DISTANCE", "FALLOFF") else None, pool=pool,
        floor=floor)
    return indices, values, warning


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


@caches.register
def _forget(_key: caches.Key | None) -> None:
    """The surface solves are keyed on their inputs, so shared by all deformers: any forget drops them."""
    _surface_memo.clear()
