"""What every deformer kind gives the shared bind / update machinery, and what it gets back.

A kind is one kind of control (probe objects, the faces of a cage, …). The rest of the Blender layer
knows kinds only through `DeformerKind`: binding asks it for the rest data and the weights, the
update pipeline for the controls' current motions A_i = C_i · C_rest,i⁻¹ (`Motions`), relations for
the objects to evaluate with the target, the deformer's property group for the kind's own properties
(`properties`), registration for its classes (control items, operators, lists), the panel for its
part of the interface, and the weight tools for its control items, active control, painted groups
and stored weights. The update turns motions into blend parameters ψ(A_i) in one place (params.py);
a kind never does.

Matrices are expressed in the target's local space, C = target_world⁻¹ · control_world, and rounded
to float32 exactly like stored rest matrices, so a control whose current matrix is bitwise equal to
its rest matrix is recognised as "at rest" and contributes exactly the identity.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import bpy
import numpy as np

from ..files import storage

#: `override=` of the deformer's control pointers and of every collection holding them: a library
#: override of a rig then keeps them pointed at the overridden controls, and saves that.
OVERRIDABLE = {"LIBRARY_OVERRIDABLE"}  # a set: bpy.props refuses a frozenset
IDENTITY16 = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)

#: Items of the rest rotation mode properties (a control's rotation mode at bind).
ROTATION_MODES = [
    ("QUATERNION", "Quaternion", ""),
    ("XYZ", "XYZ Euler", ""),
    ("XZY", "XZY Euler", ""),
    ("YXZ", "YXZ Euler", ""),
    ("YZX", "YZX Euler", ""),
    ("ZXY", "ZXY Euler", ""),
    ("ZYX", "ZYX Euler", ""),
    ("AXIS_ANGLE", "Axis Angle", ""),
]

# Why the update need not read a deformer property itself (snapshot.DECLARED; tests/blender/
# test_structure.py changes each property and checks the reason holds).
#: Changing it re-weights the deformer (binding.reweight), which bumps bind_generation.
REWEIGHTS = "re-weights: bind_generation"
#: The kind reads it for the controls' motions, which are part of the snapshot.
READ_BY_KIND = "read by the kind: motions"
#: Interface state (e.g. the active item of a list).
INTERFACE = "interface only"
#: An option of the viewport weight preview (weight_preview.py).
PREVIEW = "the viewport preview: no input of the deformation"


class KindProperty(NamedTuple):
    """A property a kind adds to the deformer (`AffineDeformer`): its bpy.props definition, and why the
    update need not read it (one of the reasons above)."""

    prop: Any
    declared: str


class BindError(Exception):
    """Bind-time failure with a message meant for the artist."""


@dataclass
class ChannelTurns:
    """The controls' own rotation channels, for choosing the rotation-log branch (MATH.md §8).

    rest_modes / rest_rotations (m, 4): the channels at bind; modes / rotations (m, 4): now (layout
    of props.AffineDeformerProbe.rest_rotation: a quaternion, an axis-angle, or Euler angles and 0);
    frames (m, 3, 3): the rotation taking vectors of the frame each control's channels turn in (its
    parent frame) to the target's space (transforms.channel_frame); pivots (m, 3): the controls'
    current origins in the target's space, about which a lifted rotation keeps its translation;
    references (m, 3) or None: the reference rotation vectors themselves, when the kind forms them
    (a bone's turn adds up its chain's channels), else params.py reads them from the channels.
    """

    rest_modes: list[str]
    rest_rotations: np.ndarray
    modes: list[str]
    rotations: np.ndarray
    frames: np.ndarray
    pivots: np.ndarray
    references: np.ndarray | None = None


@dataclass
class Chain:
    """The controls' hierarchy, for blending down it (MATH.md §14, core.hierarchy; bones).

    parents (m,) intp: the nearest ancestor among the controls (−1: none); locals (m, 4, 4) float64:
    L_i = A_parent⁻¹ A_i (A_i for a root), exactly the identity where at_rest (m,) bool; references
    (m, 3) and pivots (m, 3), or None: L_i's reference rotation vector (the control's own turn, in
    the target's rest space) and the rest point it turns about, for the branch of ψ(L_i).
    """

    parents: np.ndarray
    locals: np.ndarray
    at_rest: np.ndarray
    references: np.ndarray | None = None
    pivots: np.ndarray | None = None

    def key(self) -> tuple:
        return tuple(None if a is None else a.tobytes()
                     for a in (self.parents, self.locals, self.at_rest, self.references, self.pivots))


@dataclass
class Motions:
    """Current motions of a deformer's controls: the common core every kind fills.

    matrices (m, 4, 4) float64: A_i in Aff+(3) (identity where at_rest); at_rest (m,) bool: control i
    is exactly at its rest pose (its parameters are exactly zero); error: '' or a message naming the
    first invalid control (the input then passes through unchanged); warning: a non-fatal status
    (the deformation is still shown).

    Optional parts, each None when a kind has no use for it:
    turns: the rotation channels of controls that have them (probes), for the branch of ψ;
    params (m, 12): blend parameters used instead of ψ(matrices), for controls whose parameters are
      not ψ of one matrix (a cage face averages its corner tetrahedra; matrices then hold φ(params)
      for the 'LINEAR' blend, the only reader of them, and may stay the identity otherwise);
    valid (m,) bool: False marks a control to skip — its weight goes to the vertex's other controls;
    outer (4, 4): a motion applied after the blend, v' = outer · blend(v) (a cage object's motion);
    outer_reference (3,) and outer_pivot (3,): the reference rotation vector and current origin of
      the object `outer` belongs to, for the branch of ψ(outer) when it is scaled by a strength;
    chain: the controls' hierarchy — the affine blend then goes down it (bones) and `turns` is unused;
    pool: the truncation's pooled nodes as mixes of the controls (MATH.md §12), which weights pointing
      at indices m … m + G − 1 blend: (m,) one node, the coefficients a_i of the probes' pooled
      control (core.weights.pool_weights); (G, m) a cage's pool nodes or a bone's children means
      (with `chain`: core.hierarchy.pool_mix, blended down the hierarchy); None: one, uniform.
    """

    matrices: np.ndarray
    at_rest: np.ndarray
    error: str = ""
    warning: str = ""
    turns: ChannelTurns | None = None
    params: np.ndarray | None = None
    valid: np.ndarray | None = None
    outer: np.ndarray | None = None
    outer_reference: np.ndarray | None = None
    outer_pivot: np.ndarray | None = None
    chain: Chain | None = None
    pool: np.ndarray | None = None

    @classmethod
    def invalid(cls, m: int, error: str) -> Motions:
        """m controls at rest with `error` (the update then shows the input unchanged)."""
        return cls(np.broadcast_to(np.eye(4), (m, 4, 4)).copy(), np.ones(m, dtype=bool), error)

    def key(self) -> tuple:
        """The exact bits of everything in these motions (a part of the update's input snapshot)."""
        turns = self.turns
        return (self.matrices.tobytes(), self.at_rest.tobytes(), self.error, self.warning,
                None if turns is None else (tuple(turns.modes), turns.rotations.tobytes(),
                                            turns.frames.tobytes(), turns.pivots.tobytes(),
                                            None if turns.references is None else turns.references.tobytes()),
                *(None if a is None else np.asarray(a).tobytes()
                  for a in (self.params, self.valid, self.outer, self.outer_reference, self.outer_pivot,
                            self.pool)),
                None if self.chain is None else self.chain.key())


@dataclass
class Adopted:
    """What a new deformer takes from the selection (DeformerKind.adopt_selection): its controls, the
    objects made for it (removed again when its bind fails) and a warning for the report."""

    controls: list
    created: list
    warning: str = ""


def single_selected(context: bpy.types.Context, target: bpy.types.Object, kind: str,
                    what: str) -> tuple[bpy.types.Object, list]:
    """(the one selected object of type `kind` other than `target`, the other selected objects);
    BindError naming `what` when there is not exactly one."""
    selected = list(getattr(context, "selected_objects", None) or [])
    found = [o for o in selected if o != target and o.type == kind]
    if len(found) != 1:
        names = ", ".join(f"'{o.name}'" for o in found)
        raise BindError(f"Select exactly one {what}, with the mesh to deform active "
                        + (f"(selected: {names})" if found else "(none selected)"))
    return found[0], [o for o in selected if o not in (target, found[0])]


def ignored_note(what: str, objects: list) -> str:
    """'Ignored selected <what> objects: A, B' ('' when there are none), for an add report."""
    return f"Ignored selected {what} objects: " + ", ".join(o.name for o in objects) if objects else ""




def _points_to_object(prop: bpy.types.Property) -> bool:
    fixed = getattr(prop, "fixed_type", None)
    return fixed is not None and fixed.identifier == "Object"


class DeformerKind(ABC):
    """The interface of a deformer kind (see kinds/__init__.py for how one is registered).

    id: the value of `AffineDeformer.kind` (and of kinds.KindId); label, description, icon and
    add_description (the add operator's tooltip): how the interface names it; single_control: the
    kind's controls are one object (named on the modifier's Object input, unless it is an armature;
    otherwise they go in its probe collection, relations.py). Every method receives the target object
    and its deformer item.

    A kind owns its properties, operators and panel part: `properties` (merged into the deformer's
    property group before it is registered: the names are RNA paths saved in .blend files and used by
    scripts, never rename one), `classes` (registered before the deformer's property group: its
    control items' PropertyGroup classes first, then its operators and lists), the draw methods. Its
    property updates and operators reach binding and the update through `kinds.services`.

    The methods below `draw_controls` have defaults for kinds without such parts."""

    id: ClassVar[str]
    label: ClassVar[str]
    #: How Add Modifier ▸ Deform names it after "Affine" (plural for kinds with many controls).
    menu_label: ClassVar[str] = ""
    description: ClassVar[str]
    icon: ClassVar[str]
    add_description: ClassVar[str]
    single_control: ClassVar[bool]
    #: The bpy classes the kind registers (control item PropertyGroups first).
    classes: ClassVar[tuple[type, ...]] = ()
    #: Whether its controls' weights can be painted vertex groups ('VERTEX_GROUPS', Weights → Vertex
    #: Groups, Update Painted Weights).
    paints_groups: ClassVar[bool] = False
    #: For a kind that does not paint groups: why not (ends the refusal of Weights → Vertex Groups).
    groups_note: ClassVar[str] = ""
    #: Whether Preserve Shape (shape_pass.py) applies to its deformers: it needs only the per-vertex
    #: motions and the bound weights, which every kind's update gives.
    shape_pass: ClassVar[bool] = True

    @classmethod
    def properties(cls) -> dict[str, KindProperty]:
        """The kind's own properties of the deformer, by name (see the class docstring)."""
        return {}

    # ------------------------------------------------------------------------------- adding one

    @abstractmethod
    def adopt_selection(self, context: bpy.types.Context, target: bpy.types.Object) -> Adopted:
        """The controls a new deformer of this kind on `target` gets from the selection (objects may
        be created, e.g. a probe when none is selected); BindError when the selection cannot make one,
        with nothing created."""

    @abstractmethod
    def set_up(self, deformer, adopted: Adopted) -> None:
        """Give a new, unbound deformer item its controls and the kind's defaults."""

    def adopt_rest(self, source, deformer, relative: np.ndarray) -> bool:
        """Give `deformer`, a copy of the bound `source` on another mesh (Copy Modifiers, Copy to
        Selected), the source's rest data carried into its target's space by `relative` (4, 4: the
        source target's space → this one's), instead of binding at the controls' current poses.
        False when the kind cannot (the copy then binds at the current poses)."""
        return False

    def after_add(self, target: bpy.types.Object, deformer, adopted: Adopted) -> str:
        """Finish a deformer just added and bound (the add operator's last step); returns what to add
        to its report ('' when nothing)."""
        return ""

    @abstractmethod
    def added_message(self, target: bpy.types.Object, deformer, adopted: Adopted) -> str:
        """The report after a new deformer of this kind was added and bound."""

    # ---------------------------------------------------------------------- bind and update

    @abstractmethod
    def store_rest(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
                   only: list[int] | None = None) -> None:
        """Record the controls' current poses (all, or those at indices `only`) as their rest, on the
        deformer item (saved in the .blend). BindError, with nothing stored, when they cannot be."""

    @abstractmethod
    def sparse_weights(self, obj: bpy.types.Object, deformer,
                       rest_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        """(indices (N, K) int32, values (N, K) float64, warning) for the rest vertices, from the
        stored rest data only (re-weighting never needs the current poses)."""

    @abstractmethod
    def current_motions(self, obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Motions:
        """The controls' motions now, read from the evaluated `depsgraph`; never raises for bad input
        (an invalid control is `Motions.invalid` with a message)."""

    def prefetch(self, pairs: list[tuple[bpy.types.Object, object]],
                 depsgraph: bpy.types.Depsgraph) -> list[tuple[object, Motions]]:
        """Optional: read the motions of several (object, deformer) pairs of this kind at once, ahead
        of the update's `current_motions` calls (which then return them), sharing work between
        objects; returns (deformer, motions) of those read. Never raises for bad input."""
        return []

    def drop_prefetched(self) -> None:  # noqa: B027 (optional)
        """Forget what `prefetch` read (the end of the update)."""

    @abstractmethod
    def controls(self, obj: bpy.types.Object, deformer) -> list[bpy.types.Object]:
        """The objects the target must be evaluated with (never `obj` itself)."""

    def control_pointers(self, deformer) -> list[tuple[Any, str]]:
        """(owner, property name) of every object pointer among the kind's own properties that is set:
        a property of the deformer, or one of the items of a collection property of it (a probe's
        `object`). What library overrides repoint at the overridden controls (carrier.remap_controls)
        and copies keep (copies.py); found from the registered RNA, so a kind needs no code for it."""
        found = []
        rna = deformer.bl_rna.properties
        for name in self.properties():
            prop = rna.get(name)
            if prop is None:
                continue
            if prop.type == "POINTER" and getattr(deformer, name) is not None and _points_to_object(prop):
                found.append((deformer, name))
            elif prop.type == "COLLECTION":
                for item in getattr(deformer, name):
                    found += [(item, p.identifier) for p in item.bl_rna.properties
                              if p.type == "POINTER" and _points_to_object(p)
                              and getattr(item, p.identifier) is not None]
        return found

    # ----------------------------------------------------------------------------------- panel

    @abstractmethod
    def draw_settings(self, layout: bpy.types.UILayout, deformer) -> None:
        """The kind's options in the deformer panel (between the header and the common options)."""

    @abstractmethod
    def branch_rule_active(self, deformer) -> bool:
        """Whether the branch rule changes anything with the deformer's current settings (the panel
        greys it out otherwise)."""

    @abstractmethod
    def draw_controls(self, layout: bpy.types.UILayout, deformer, index: int) -> None:
        """The kind's control list, below the common options (nothing for a single-object kind)."""

    def draw_object(self, layout: bpy.types.UILayout, obj: bpy.types.Object) -> None:  # noqa: B027 (optional)
        """The kind's buttons for the object as a whole, below the deformer list (e.g. converting an
        Armature modifier)."""

    def draw_actions(self, layout: bpy.types.UILayout, deformer, index: int) -> None:  # noqa: B027 (optional)
        """The kind's buttons above its settings (e.g. back to the Armature modifier it replaced)."""

    def draw_preview_options(self, layout: bpy.types.UILayout, deformer) -> None:  # noqa: B027 (optional)
        """The kind's options of the weight preview's 'ACTIVE' mode (e.g. which cage face)."""

    # ---------------------------------------------------------------------- the weight tools

    @abstractmethod
    def control_count(self, deformer) -> int:
        """The number of controls the stored weights are about (probes, bones, a cage's faces)."""

    @abstractmethod
    def active_control(self, deformer) -> int:
        """The control the weight tools show (the active item of the kind's list, a chosen face), not
        clamped to the controls there are."""

    def control_items(self, deformer) -> tuple | bpy.types.bpy_prop_collection:
        """The deformer's items of its controls (each with a `weight_scale`), or () for a kind whose
        controls are not items (a cage's faces)."""
        return ()

    def control_groups(self, deformer, complete: bool = False) -> list[str]:
        """The vertex group each control's weights go into under Weights → Vertex Groups, in control
        order. A control that names none now (a probe without an object) is left out, or, with
        `complete`, refused (BindError naming it)."""
        return []

    def groups_written(self, deformer, names: list[str]) -> None:  # noqa: B027 (optional)
        """After Weights → Vertex Groups wrote the groups `names` (one per control): point the
        controls at them where the kind records that (a probe's `vertex_group`)."""

    def pool_mix(self, deformer) -> np.ndarray | None:
        """The truncation's pooled nodes (indices m … m + G − 1 of the stored weights, MATH.md §12) as
        mixes of the controls (G, m), or None for a kind whose stored weights never index them.
        Default: one node, all controls alike."""
        m = self.control_count(deformer)
        return np.full((1, m), 1.0 / m) if m else None

    def stored_weights(self, obj: bpy.types.Object,
                       deformer) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(indices (N, K), values (N, K) float64, node weights (G, m) or None): the stored bind
        weights; when they index intermediate nodes (a 'HARMONIC' cage's grid nodes, or the pooled
        column: G = m + 1, the controls themselves then `pool_mix`), each node's weights on the
        controls. storage.StorageError / BindError when the bind data is damaged."""
        m = self.control_count(deformer)
        pool = self.pool_mix(deformer)
        pool = None if pool is None else np.atleast_2d(pool)
        indices, values = storage.read_weights(obj.data, deformer.uid, m + (0 if pool is None else len(pool)))
        if pool is not None and indices.size and int(indices.max()) >= m:
            return indices, values, np.vstack([np.eye(m), pool])
        return indices, values, None

    def follow_renames(self, obj: bpy.types.Object, deformer) -> None:  # noqa: B027 (optional)
        """Before an update: keep names the deformer stores in step with renamed controls (a renamed
        probe's painted group). Never raises."""

    def record_states(self, obj: bpy.types.Object, deformer, motions: Motions | None, error: str,  # noqa: B027 (optional)
                      depsgraph: bpy.types.Depsgraph) -> None:
        """After a deformer's inputs were read: show each control's state on its item (only changes
        are written). Never raises."""
