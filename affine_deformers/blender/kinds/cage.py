"""The cage kind: a closed mesh whose faces drive the target (course notes 8.3.2, MATH.md §9, §10).

Everything is expressed in the target's local space. With C = target_world⁻¹ · cage_world (rounded
to float32 like the probes' matrices) and q the cage's vertex positions in its own object space:

* bind stores, on the deformer item, C_rest (`cage_rest_matrix`), the rest cage
  p_rest = C_rest · q_rest (ID property `cage_rest_points`, float64, V·3) and the topology it was
  bound with (`cage_loop_vertices`, `cage_loop_start`, `cage_loop_total`, int32). These are ID
  properties of the target object, so they are saved in the .blend with the bind weights, survive
  undo, work with a cage linked from a library (nothing is written to the cage) and let re-weighting
  (exponent, half-space, influences, mask) run from rest data alone;
* per frame the cage is read from the EVALUATED depsgraph (shape keys, armature and other modifiers,
  object animation, edit-mode edits). Its motion is split into the object-level part
  G = C · C_rest⁻¹, applied exactly as a matrix after the blend, and the shape change
  p̃ = C_rest · q, whose per-face motions A_f (p_rest → p̃, core.cage.face_motions) are blended:

      v' = G · φ(Σ_f w_f P_f) v.

  Moving, rotating, scaling or shearing the cage OBJECT maps the target by exactly G without any
  per-face work; an affine map applied to the cage's vertices gives every face that map (core.cage's
  'NEIGHBOURS' apex), so it is reproduced exactly too. Only the faces the shape change can reach
  (core.cage.affected_faces) get parameters; the others are exactly at rest.

At a strength s other than 1 the target gets φ(s·ψ(G)), where the branch of ψ's rotation log matters
once the cage object has turned past 180°: as for probes (params.motions_to_params), bind stores the
cage's own rotation channels and each frame carries the reference rotation vector read from them and
the cage's origin, so a cage keyed 0 → 720° at s = 0.5 turns the target by 0 → 360° continuously.

The cage is read only when the depsgraph evaluates it: the deformer's modifier names it as an input
(relations.py), so it is evaluated while that modifier is enabled even when it is disabled in
viewports or renders.

A face that collapses in the current pose (zero area or non-finite) is skipped: its weight goes to
the vertex's other faces (blend.redistribute, or the node's other faces) and the status names how
many faces are skipped.

Weights (`cage_weights` option, `weight_mode`):

* 'HARMONIC' (default): harmonic face weights solved on a grid over the rest cage
  (core.cage.harmonic). The controls the target blends are then the grid nodes around it, not the
  faces: bind stores the used nodes' positions (`cage_node_points`, float64, G·3) and their face
  weights (`cage_node_weights`, float32, G·F) on the deformer item, and each vertex's 8 trilinear
  node weights as the usual weight attributes (K = 8). Per frame the faces' motions become node
  parameters (core.cage.harmonic.node_params, blended about each node), only for nodes with weight
  on a face that moved; the others are exactly at rest. For the 'LINEAR' blend the nodes' matrices
  are the linear blend of the face matrices, I + Σ_f W_cf (A_f − I).
* 'INVERSE_DISTANCE' (the weights of 0.1): inverse distance to each face, the half-space rule (a
  continuous ramp), Max Influences faces per vertex (continuous truncation): the faces are the
  controls. Files bound before the option existed keep these weights until rebound or switched.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatVectorProperty, IntProperty, PointerProperty

from ... import accel
from ...core.cage import (
    CageTopology,
    cage_weights,
    check_cage,
    signed_volume,
)
from ...core.cage import pool as cage_pool
from ...core.cage.harmonic import harmonic_weights, outside_points
from .. import caches
from ..files import nodes, storage
from ..update.validation import (
    MAX_WEIGHT,
    coordinates_problem,
    settings_problem,
    stored_array,
    values_problem,
)
from . import cage_binding, cage_motion, cage_tools
from .base import (
    IDENTITY16,
    INTERFACE,
    OVERRIDABLE,
    PREVIEW,
    READ_BY_KIND,
    REWEIGHTS,
    ROTATION_MODES,
    Adopted,
    BindError,
    DeformerKind,
    KindProperty,
    Motions,
    ignored_note,
    single_selected,
)
from .services import control_picker, on_preview_option, on_weight_option
from .transforms import (
    control_evaluated,
    in_a_scene,
    local_matrix,
    rotation_channels,
    transform_problem,
    want_resync,
    world_matrix,
)

CAGE = "CAGE"  # the kind's id
REST_POINTS = cage_tools.REST_POINTS
LOOP_VERTICES = "cage_loop_vertices"
LOOP_START = "cage_loop_start"
LOOP_TOTAL = "cage_loop_total"
BIND_KEYS = (REST_POINTS, LOOP_VERTICES, LOOP_START, LOOP_TOTAL)
NODE_POINTS = "cage_node_points"
NODE_WEIGHTS = "cage_node_weights"
NODE_KEYS = (NODE_POINTS, NODE_WEIGHTS)


# (target session_uid, deformer uid) -> (inputs, Motions) of the last evaluation: a cache, not bind data.
_last_motions: dict[tuple[int, str], tuple[tuple, Motions]] = {}



class NodeBind(NamedTuple):
    """A 'HARMONIC' bind as the blend uses it: node points (G, 3), node weights (G, F) float64 with
    rows summing to 1, and the node totals Σ_f W_cf valid_f per set of valid faces (None: all), which
    every update with that set needs (`accel.cage_nodes`); the last two sets are kept."""

    points: np.ndarray
    weights: np.ndarray
    totals: dict[bytes | None, np.ndarray]


# (target session_uid, deformer uid) -> (bind generation, NodeBind).
_node_data: dict[tuple[int, str], tuple[int, NodeBind]] = {}
# (vertex count, loop arrays' bytes) -> the validated CageTopology (`rest_cage`), oldest first.
_topologies: dict[tuple, CageTopology] = {}
_TOPOLOGIES_KEPT = 8
# (rest cage and topology bytes, exponent, half-space) -> the 'INVERSE_DISTANCE' weights' pooled
# nodes as mixes of the faces (core.cage.pool.pool_mixes), oldest first.
_pool_mixes: dict[tuple, np.ndarray] = {}
_POOL_MIXES_KEPT = 4


@caches.register
def _forget(key: caches.Key | None) -> None:
    """The motions and node data per deformer; the topologies, keyed on their content, at a full forget."""
    caches.drop(_last_motions, key)
    caches.drop(_node_data, key)
    if key is None:
        _topologies.clear()
        _pool_mixes.clear()


def _get_cage_weights(self) -> int:
    # Unset: 'HARMONIC' (0), except for a deformer bound before the option existed, whose stored
    # weights are inverse-distance ones (no grid nodes): it keeps them until switched or rebound.
    value = self.get("cage_weights_mode")
    if value is None:
        return 1 if self.bound_flag and self.kind == CAGE and NODE_POINTS not in self else 0
    return int(value)


def _set_cage_weights(self, value: int) -> None:
    self["cage_weights_mode"] = int(value)


def _poll_cage(self, candidate: bpy.types.Object) -> bool:
    return candidate.type == "MESH" and candidate != self.id_data


def weight_mode(deformer) -> str:
    """The deformer's cage weight mode (`props.AffineDeformer.cage_weights`)."""
    return deformer.cage_weights


def pool_mixes(deformer) -> np.ndarray:
    """(G, F): where the 'INVERSE_DISTANCE' weights' truncation pools weight (MATH.md §12), the
    pooled nodes F … F + G − 1 as mixes of the faces (core.cage.pool.pool_mixes of the stored rest
    cage and the weight options); memoised on their content. BindError when the bind data is
    damaged."""
    points, topology, loops, start, total = rest_cage(deformer)
    key = (points.tobytes(), loops.tobytes(), start.tobytes(), total.tobytes(), float(deformer.exponent),
           bool(deformer.half_space))
    mixes = _pool_mixes.get(key)
    if mixes is None:
        mixes = cage_pool.pool_mixes(points, topology, exponent=deformer.exponent,
                                     half_space=deformer.half_space)
        if len(_pool_mixes) >= _POOL_MIXES_KEPT:
            _pool_mixes.pop(next(iter(_pool_mixes)))
        _pool_mixes[key] = mixes
    return mixes


def cage_settings_problem(deformer) -> str:
    """The first refused setting that the cage's weights read (validation.py), with what the update
    does; '' when none. Exponent and Max Influences shape the 'INVERSE_DISTANCE' weights, and the
    Exponent their pooled nodes at every update (`pool_mixes`) while they are the stored ones;
    'HARMONIC' weights read neither."""
    if weight_mode(deformer) == "INVERSE_DISTANCE" or (deformer.is_bound and not bound_with_nodes(deformer)):
        return settings_problem(deformer, ("exponent", "max_influences"))
    return ""


def bound_with_nodes(deformer) -> bool:
    """Whether the stored weights are 'HARMONIC' ones (grid nodes are the controls)."""
    return all(key in deformer for key in NODE_KEYS)


def node_data(obj: bpy.types.Object, deformer, n_faces: int) -> NodeBind:
    """The NodeBind (node weights' rows renormalised to 1 in float64) of a 'HARMONIC' bind, cached
    per bind generation; BindError when the stored arrays are damaged."""
    key = (obj.session_uid, deformer.uid)
    cached = _node_data.get(key)
    if cached is not None and cached[0] == deformer.bind_generation and cached[1].weights.shape[1] == n_faces:
        return cached[1]
    points, problem = stored_array(deformer, NODE_POINTS, integer=False)
    if not problem:
        weights, problem = stored_array(deformer, NODE_WEIGHTS, integer=False)
    if not problem and (points.size % 3 or weights.size != (points.size // 3) * n_faces):
        problem = (f"'{NODE_POINTS}' and '{NODE_WEIGHTS}' hold {points.size} and {weights.size} values "
                   f"for {n_faces} faces")
    if not problem:
        problem = (coordinates_problem(f"'{NODE_POINTS}'", points)
                   or values_problem(f"'{NODE_WEIGHTS}'", weights, 0.0, MAX_WEIGHT))
    if problem:
        raise BindError(damaged(problem))
    points = points.reshape(-1, 3)
    weights = weights.reshape(len(points), n_faces)
    total = weights.sum(axis=1, keepdims=True)
    weights = np.where(total > 0.0, weights / np.where(total > 0.0, total, 1.0), 0.0)
    # Column-major: an update gathers the columns of the faces that moved (core.cage.harmonic).
    weights = np.asfortranarray(weights)
    bind = NodeBind(points, weights, {})
    _node_data[key] = (deformer.bind_generation, bind)
    return bind


def damaged(problem: str) -> str:
    """The status of a cage deformer whose bind data is damaged (`problem` says how)."""
    return f"The cage bind data is damaged ({problem}): rebind the deformer"


def _stored_cage_arrays(deformer) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The stored rest cage (V·3,) float64 and its loop arrays (int32), each checked for its type and
    the points for finite, bounded coordinates; BindError naming what is damaged."""
    arrays = []
    for key in BIND_KEYS:
        array, problem = stored_array(deformer, key, integer=key != REST_POINTS)
        if problem:
            raise BindError(damaged(problem))
        arrays.append(array)
    points = arrays[0]
    problem = (f"'{REST_POINTS}' holds {points.size} values, not 3 per vertex" if points.size % 3
               else coordinates_problem(f"'{REST_POINTS}'", points))
    if problem:
        raise BindError(damaged(problem))
    return arrays[0], arrays[1], arrays[2], arrays[3]


class CageUnavailableError(Exception):
    """The cage cannot be read now (the message says why and what to do)."""


@dataclass(frozen=True)
class CageState:
    """The cage as evaluated: vertex positions in its object space, topology, world matrix."""

    points: np.ndarray  # (V, 3) float32
    loop_vertices: np.ndarray  # (L,) int32
    loop_start: np.ndarray  # (F,) int32
    loop_total: np.ndarray  # (F,) int32
    matrix_world: np.ndarray  # (4, 4) float64

    def topology(self) -> CageTopology:
        """Validated core topology (ValueError when malformed, e.g. a face with < 3 corners)."""
        return CageTopology.from_arrays(self.loop_vertices, self.loop_start, self.loop_total,
                                        len(self.points))


def cage_problem(target: bpy.types.Object, cage: bpy.types.Object | None) -> str:
    """Why `cage` cannot drive `target` (object level, not geometry), or ''."""
    if cage is None:
        return "The cage deformer has no cage object: pick a closed mesh in the Cage field and rebind"
    if cage == target:
        return f"'{target.name}' cannot be its own cage"
    if cage.type != "MESH":
        return f"Cage '{cage.name}' is not a mesh ({cage.type.title()}): pick a closed mesh"
    if not in_a_scene(cage):
        return f"Cage '{cage.name}' is not in any scene (deleted?): link it back or pick another cage"
    return ""


def read_cage(cage: bpy.types.Object, depsgraph: bpy.types.Depsgraph, related: bool = False) -> CageState:
    """The evaluated cage (modifiers, shape keys, edit-mode edits and object animation included);
    `related` as in `transforms.control_evaluated`."""
    evaluated = cage.evaluated_get(depsgraph)
    if not control_evaluated(cage, evaluated, depsgraph, related):
        if not related:
            want_resync()
        raise CageUnavailableError(
            f"Cage '{cage.name}' is not evaluated (it is disabled in viewports or renders, and the "
            "deformer is off there): enable the deformer, or show the cage")
    # to_mesh, not .data: an evaluated mesh in Edit Mode may be a wrapper without vertex arrays.
    mesh = evaluated.to_mesh()
    try:
        points = storage.read_positions(mesh).copy()
        loops = storage.corner_vertices(mesh)
        start, total = storage.face_corners(mesh)
    finally:
        evaluated.to_mesh_clear()
    return CageState(points, loops, start, total, np.array(evaluated.matrix_world, dtype=np.float64))


def _evaluated(obj: bpy.types.Object, deformer, cage: bpy.types.Object,
               depsgraph: bpy.types.Depsgraph) -> bool:
    """Whether `depsgraph` evaluates the cage for this deformer (nodes.evaluates)."""
    return nodes.evaluates(obj, storage.offset_name(deformer.uid), cage, depsgraph)


def to_target(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rows of `points` (V, 3) mapped by the affine 4×4 `matrix`, float64 (the single definition, so
    bind and evaluation round identically)."""
    m = np.asarray(matrix, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]


def store_array(owner, key: str, array: np.ndarray) -> None:
    """owner[key] = array (an ID property array, via the buffer protocol).

    The old property is deleted first: assigning a buffer to an existing ID property array of another
    length keeps the old length (Blender 4.2 and 5.0), and a shorter buffer corrupts memory."""
    if key in owner:
        del owner[key]
    owner[key] = np.ascontiguousarray(array)


def rest_matrix(deformer) -> np.ndarray:
    """C_rest (4, 4) float32 as stored."""
    return np.array(deformer.cage_rest_matrix, dtype=np.float32).reshape(4, 4)


def has_rest_channels(deformer) -> bool:
    """Whether bind stored the cage's rotation channels (files bound before they were stored: no)."""
    return deformer.is_property_set("cage_rest_rotation")


def rest_cage(deformer) -> tuple[np.ndarray, CageTopology, np.ndarray, np.ndarray, np.ndarray]:
    """Stored (p_rest (V, 3) float64, topology, loop_vertices, loop_start, loop_total); BindError when
    the bind data is missing or damaged."""
    if any(key not in deformer for key in BIND_KEYS):
        raise BindError("The cage bind data is missing: rebind the deformer")
    points, loops, start, total = _stored_cage_arrays(deformer)
    points = points.reshape(-1, 3)
    # Validated once per distinct topology (every update reads it), and kept with the derived arrays
    # it caches (corner triples, fans), which then need not be rebuilt per update either.
    key = (len(points), loops.tobytes(), start.tobytes(), total.tobytes())
    topology = _topologies.get(key)
    if topology is None:
        try:
            topology = CageTopology.from_arrays(loops, start, total, len(points))
        except ValueError as exc:
            raise BindError(damaged(f"its faces, '{LOOP_VERTICES}', '{LOOP_START}', '{LOOP_TOTAL}': {exc}")
                            ) from None
        _topologies[key] = topology
        while len(_topologies) > _TOPOLOGIES_KEPT:
            _topologies.pop(next(iter(_topologies)))
    return points, topology, loops, start, total


class CageKind(DeformerKind):
    """A closed mesh with outward normals; each face is a control."""

    id = CAGE
    label = "Cage"
    description = "Driven by the faces of a cage mesh"
    icon = "MESH_CUBE"
    single_control = True
    add_description = ("Add a cage deformer to the active mesh; the other selected mesh is the cage "
                       "(closed, normals outward; none selected: a cage is made around the mesh). Its "
                       "current shape becomes the rest shape")
    classes = cage_tools.CLASSES
    groups_note = "their controls are cage faces (hundreds of groups); Show Weights shows them"

    @classmethod
    def properties(cls) -> dict[str, KindProperty]:
        return {
            "cage": KindProperty(PointerProperty(
                name="Cage", override=OVERRIDABLE, type=bpy.types.Object, poll=_poll_cage,
                update=control_picker(cls.id, "cage", "the new cage"),
                description="Closed mesh with outward normals whose faces drive the target (a new pick is "
                            "bound at its current shape)"), READ_BY_KIND),
            "cage_rest_matrix": KindProperty(FloatVectorProperty(
                name="Cage Rest Matrix", size=16, default=IDENTITY16,
                description="Cage object matrix at bind, in the target's local space (row-major 4x4)"),
                READ_BY_KIND),
            "cage_rest_rotation_mode": KindProperty(EnumProperty(
                name="Cage Rest Rotation Mode", items=ROTATION_MODES, default="XYZ",
                description="Rotation mode of the cage object at bind"), READ_BY_KIND),
            "cage_rest_rotation": KindProperty(FloatVectorProperty(
                name="Cage Rest Rotation", size=4, default=(0.0, 0.0, 0.0, 0.0),
                description="Rotation channels of the cage object at bind: quaternion WXYZ, axis-angle "
                            "(angle, X, Y, Z) or Euler XYZ (unset in files bound before they were stored: "
                            "the cage's turns then take the shortest way)"), READ_BY_KIND),
            "half_space": KindProperty(BoolProperty(
                name="Half-Space Rule", default=True, update=on_weight_option,
                description="A cage face has no influence on vertices outside it (in its outer "
                            "half-space): keeps opposite sides of a thin part apart"), REWEIGHTS),
            "cage_weights": KindProperty(EnumProperty(
                name="Cage Weights", get=_get_cage_weights, set=_set_cage_weights, update=on_weight_option,
                items=[("HARMONIC", "Harmonic",
                        "Smooth, local weights solved inside the cage on a grid (like Mesh Deform): a "
                        "local edit of the cage moves the mesh near it smoothly", 0),
                       ("INVERSE_DISTANCE", "Inverse Distance",
                        "Inverse distance to each face with the half-space rule, Exponent and Max "
                        "Influences (the weights of version 0.1)", 1)],
                description="How the cage's faces are weighted on the target (changing it re-weights)"),
                REWEIGHTS),
            "cage_faces": KindProperty(IntProperty(
                name="Cage Faces", default=cage_tools.DEFAULT_FACES, min=10, max=20000,
                description="The face budget of a cage made around the mesh (Remake Cage): at most this "
                            "many quads"), INTERFACE),
            "weight_preview_face": KindProperty(IntProperty(
                name="Preview Face", default=-1, min=-1, update=on_preview_option,
                description="Cage face whose weights the preview shows (-1: the cage mesh's active face, "
                            "picked in its Edit Mode)"), PREVIEW),
        }

    def adopt_selection(self, context: bpy.types.Context, target: bpy.types.Object) -> Adopted:
        """The one other selected mesh (the cage); none selected: a cage made around the mesh
        (cage_tools.py)."""
        selected = [o for o in (getattr(context, "selected_objects", None) or [])
                    if o.type == "MESH" and o != target]
        if not selected:
            made = cage_tools.make_cage(context, target)
            return Adopted([made], [made], "")
        cage, ignored = single_selected(context, target, "MESH", "other mesh as the cage")
        return Adopted([cage], [], ignored_note("non-mesh", ignored))

    def set_up(self, deformer, adopted: Adopted) -> None:
        deformer.cage = adopted.controls[0]
        deformer.max_influences = 8
        if adopted.created:
            deformer.cage_faces = len(adopted.created[0].data.polygons)

    def added_message(self, target: bpy.types.Object, deformer, adopted: Adopted) -> str:
        faces = len(deformer[LOOP_TOTAL])
        made = ""
        if adopted.created:
            margin = adopted.created[0].data.get(cage_tools.MARGIN_KEY, 0.0)
            made = (f" (made around the mesh, every vertex at least {margin:.3g} inside: Remake Cage makes "
                    "it again at another budget)")
        return (f"Added a cage deformer to '{target.name}' driven by '{adopted.controls[0].name}' "
                f"({faces} faces){made}")

    def controls(self, obj: bpy.types.Object, deformer) -> list[bpy.types.Object]:
        cage = deformer.cage
        return [cage] if cage is not None and cage != obj else []

    def draw_settings(self, layout: bpy.types.UILayout, deformer) -> None:
        layout.prop(deformer, "cage")
        layout.prop(deformer, "cage_weights")
        if deformer.cage_weights == "INVERSE_DISTANCE":
            layout.prop(deformer, "exponent")
            layout.prop(deformer, "half_space")
            layout.prop(deformer, "max_influences")  # harmonic weights: always 8 grid nodes

    def branch_rule_active(self, deformer) -> bool:
        """The cage object's motion is scaled in the log space in both blend modes, and its branch
        only matters at a strength other than 1."""
        return deformer.strength != 1.0

    def draw_controls(self, layout: bpy.types.UILayout, deformer, index: int) -> None:
        """A cage is one object, picked in the settings."""

    def draw_actions(self, layout: bpy.types.UILayout, deformer, index: int) -> None:
        cage_tools.draw_actions(layout, deformer, index)

    def draw_preview_options(self, layout: bpy.types.UILayout, deformer) -> None:
        layout.prop(deformer, "weight_preview_face", text="Face")

    def control_count(self, deformer) -> int:
        """The bound cage's faces (0 before a bind)."""
        return len(deformer[LOOP_TOTAL]) if LOOP_TOTAL in deformer else 0

    def active_control(self, deformer) -> int:
        """The face `weight_preview_face`, or with -1 the cage mesh's active face."""
        index = deformer.weight_preview_face
        cage = deformer.cage
        if index < 0:
            index = cage.data.polygons.active if cage is not None and cage.type == "MESH" else 0
        return index

    def pool_mix(self, deformer) -> np.ndarray | None:
        """'INVERSE_DISTANCE': the pooled nodes' mixes of the faces (`pool_mixes`); None unbound."""
        return pool_mixes(deformer) if self.control_count(deformer) else None

    def stored_weights(self, obj: bpy.types.Object,
                       deformer) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """'HARMONIC' weights index grid nodes, each with its face weights (`node_data`);
        'INVERSE_DISTANCE' ones faces and the pooled nodes (`pool_mixes`)."""
        if not bound_with_nodes(deformer):
            return super().stored_weights(obj, deformer)
        node_weights = node_data(obj, deformer, self.control_count(deformer)).weights
        indices, values = storage.read_weights(obj.data, deformer.uid, len(node_weights))
        return indices, values, node_weights

    def store_rest(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
                   only: list[int] | None = None) -> None:
        """Record the cage's current evaluated shape and placement as its rest (`only` is ignored: a
        cage is bound as a whole). Refuses (BindError, nothing stored) an open, non-manifold,
        inconsistently oriented or inside-out cage, or one with zero-area faces."""
        cage = deformer.cage
        problem = cage_problem(obj, cage)
        if problem:
            raise BindError(problem)
        try:
            target_world = world_matrix(obj, depsgraph)
            state = read_cage(cage, depsgraph, _evaluated(obj, deformer, cage, depsgraph))
            matrix = local_matrix(target_world, state.matrix_world)
        except np.linalg.LinAlgError:
            raise BindError(f"'{obj.name}' has a zero scale: fix its transform before binding") from None
        except CageUnavailableError as exc:
            raise BindError(str(exc)) from None
        reason = transform_problem(matrix)  # a rest the update would refuse as damaged
        det = np.linalg.det(matrix[:3, :3].astype(np.float64)) if not reason else 0.0
        if reason or det == 0.0:
            raise BindError(f"Cage '{cage.name}' {reason or 'has a zero scale'}: fix it first")
        try:
            topology = state.topology()
        except ValueError as exc:
            raise BindError(f"Cage '{cage.name}' cannot be bound: {exc}") from None
        points = to_target(matrix, state.points)
        report = check_cage(points, topology)
        if not report.ok:
            hint = " (its object has a negative scale, which flips the normals)" if det < 0.0 else ""
            raise BindError(f"Cage '{cage.name}' cannot be bound{hint}: " + "; ".join(report.problems))
        deformer.cage_rest_matrix = matrix.ravel().tolist()
        evaluated = cage.evaluated_get(depsgraph)  # the channels as evaluated, like the matrix
        deformer.cage_rest_rotation_mode = evaluated.rotation_mode
        deformer.cage_rest_rotation = rotation_channels(evaluated)
        store_array(deformer, REST_POINTS, points.ravel())
        store_array(deformer, LOOP_VERTICES, state.loop_vertices)
        store_array(deformer, LOOP_START, state.loop_start)
        store_array(deformer, LOOP_TOTAL, state.loop_total)

    def adopt_rest(self, source, deformer, relative: np.ndarray) -> bool:
        try:
            points, _topology, loops, start, total = rest_cage(source)
        except BindError:
            return False
        matrix = np.asarray(source.cage_rest_matrix, dtype=np.float64).reshape(4, 4)
        deformer.cage_rest_matrix = np.float32(relative @ matrix).ravel().tolist()
        deformer.cage_rest_rotation_mode = source.cage_rest_rotation_mode
        deformer.cage_rest_rotation = tuple(source.cage_rest_rotation)
        store_array(deformer, REST_POINTS, (points @ relative[:3, :3].T + relative[:3, 3]).ravel())
        for key, array in ((LOOP_VERTICES, loops), (LOOP_START, start), (LOOP_TOTAL, total)):
            store_array(deformer, key, array)
        return True

    def sparse_weights(self, obj: bpy.types.Object, deformer,
                       rest_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        """From the stored rest cage only. 'HARMONIC': each vertex's 8 trilinear grid-node weights
        (core.cage.harmonic.harmonic_weights), the nodes' face weights stored on the deformer;
        'INVERSE_DISTANCE': inverse distance^exponent to each face polygon, half-space ramp,
        continuous top-K, rows summing to 1 (core.cage.cage_weights)."""
        problem = cage_settings_problem(deformer)
        if problem:
            raise BindError(problem)
        points, topology, *_ = rest_cage(deformer)
        _node_data.pop((obj.session_uid, deformer.uid), None)
        outside = outside_points(rest_points, points, topology)
        warning = cage_binding.outside_warning(deformer, outside)
        if weight_mode(deformer) == "HARMONIC":
            weights = harmonic_weights(rest_points, points, topology)
            store_array(deformer, NODE_POINTS, weights.node_points.ravel())
            store_array(deformer, NODE_WEIGHTS, weights.node_weights.ravel())
            indices, values = weights.indices, weights.values
        else:
            indices, values = cage_weights(rest_points, points, topology, exponent=deformer.exponent,
                                           half_space=deformer.half_space, k=deformer.max_influences)
            for key in NODE_KEYS:  # the weights now index faces
                if key in deformer:
                    del deformer[key]
        return indices, cage_binding.faded_outside(values, rest_points, outside, points, topology), warning

    def current_motions(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Motions:
        try:
            rest, topology, loops, start, total = rest_cage(deformer)
        except BindError as exc:
            return Motions.invalid(0, str(exc))
        F = topology.n_faces
        cage = deformer.cage
        problem = cage_problem(obj, cage) or cage_settings_problem(deformer)
        if problem:
            return Motions.invalid(F, problem)
        try:
            state = read_cage(cage, depsgraph, _evaluated(obj, deformer, cage, depsgraph))
        except CageUnavailableError as exc:
            return Motions.invalid(F, f"{exc}: the mesh shows its rest shape")
        same = (len(state.points) == len(rest) and np.array_equal(state.loop_vertices, loops)
                and np.array_equal(state.loop_start, start) and np.array_equal(state.loop_total, total))
        if not same:
            flipped = cage_binding.flipped_faces(loops, start, total, state.loop_vertices, state.loop_start,
                                     state.loop_total)
            if flipped:
                return Motions.invalid(
                    F, f"Cage '{cage.name}' has {flipped} of {F} faces turned the other way since bind (its "
                       "normals were flipped): the cage is inside out there and the mesh shows its rest "
                       "shape; flip them back (Recalculate Outside), or rebind")
            return Motions.invalid(
                F, f"Cage '{cage.name}' changed topology since bind ({len(rest)} → {len(state.points)} "
                   f"vertices, {F} → {len(state.loop_total)} faces): the mesh shows its rest shape; rebind")
        placed = cage_motion.object_motion(obj, cage, state.matrix_world, rest_matrix(deformer), depsgraph)
        if isinstance(placed, str):
            return Motions.invalid(F, placed)
        target_world, matrix, stored, outer = placed
        try:
            outer, reference, pivot = cage_motion.outer_branch(
                deformer, cage, depsgraph, target_world, matrix, outer, has_rest_channels(deformer))
        except BindError as exc:  # its stored rest rotation is damaged
            return Motions.invalid(F, str(exc))
        except ValueError as exc:
            return Motions.invalid(F, f"The motion of cage '{cage.name}' cannot be blended ({exc}): the "
                                      "mesh shows its rest shape")
        nodes = None
        if bound_with_nodes(deformer):
            try:
                nodes = node_data(obj, deformer, F)
            except BindError as exc:
                return Motions.invalid(F, str(exc))
        # Every depsgraph update re-evaluates; the motions are a pure function of these inputs.
        linear = deformer.blend_mode == "LINEAR"
        key = (rest.tobytes(), loops.tobytes(), start.tobytes(), total.tobytes(), stored.tobytes(),
               state.points.tobytes(), None if nodes is None else deformer.bind_generation, linear,
               accel.active())  # the compiled polar split and numpy's agree to ~1e-15, not bitwise
        cached = _last_motions.get((obj.session_uid, deformer.uid))
        if cached is not None and cached[0] == key:
            controls = cached[1]
        else:
            current = to_target(stored, state.points)
            # The compiled kernel does the faces and the volume in one call (None: numpy does them).
            compiled = accel.cage_faces(rest, current, topology)
            volume = signed_volume(current, topology) if compiled is None else compiled[2]
            if np.isfinite(volume) and volume <= 0.0:  # non-finite vertices: collapsed faces, below
                # Mirrored vertices (an animated inside-out cage) or a collapse to a plane or point:
                # every face motion would be mirrored or singular, so nothing of it is blended.
                controls = Motions.invalid(F, f"Cage '{cage.name}' is turned inside out or collapsed in its "
                                              "current shape (its volume is not positive): the mesh shows "
                                              "its rest shape")
            else:
                controls = cage_motion.face_motions_of(rest, current, topology, linear, compiled)
                if nodes is not None:
                    controls = cage_motion.node_motions(controls, nodes, linear=linear)
            _last_motions[(obj.session_uid, deformer.uid)] = (key, controls)
        pool = None
        if nodes is None and not controls.error:  # faces: their pooled nodes (MATH.md §12)
            try:
                pool = pool_mixes(deformer)
            except BindError as exc:
                return Motions.invalid(F, str(exc))
        return dataclasses.replace(controls, outer=outer, outer_reference=reference, outer_pivot=pivot,
                                   pool=pool)
