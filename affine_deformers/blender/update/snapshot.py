"""The inputs of one deformer update, taken once; every cache key of the update derives from them.

`take` reads everything an update depends on — the pre-checks, the kind's current motions, the bind
data, the output path, the deformer's settings and the kernel backend — into a `Snapshot`:

* `Snapshot.signature()` is the update's key: equal signatures mean the written output is already
  right (evaluate.evaluate_deformer returns at once);
* `Snapshot.result_state()` is what a cached result was computed with (result.Result.state): a
  result is reused incrementally only under the same state;
* the per-control parameter memo (params.py) is keyed on the bits of `Snapshot.motions` rows.

Every property of a deformer item is either read into the snapshot or declared below with the reason
it does not need to be (tests/blender/test_structure.py changes each one and checks).

A setting that is not a finite number in its range (validation.py; a script or a damaged file
bypasses the interface's clamp) is the snapshot's error, naming it: Strength here, the settings the
weights read (Radius, Exponent, Max Influences, each control's Weight Scale) by the kind when it
reads its controls, Preserve Shape's by the pass (shape_pass.py); the mesh then shows its input.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import bpy
import numpy as np

from ... import accel
from .. import kinds
from ..files import nodes, storage
from ..kinds import Motions
from ..kinds.base import PREVIEW, REWEIGHTS
from . import bound as bound_data
from . import outputs
from .bound import BindRecord
from .validation import settings_problem

#: Deformer properties the update reads itself: their values are in `Snapshot.settings`.
SETTINGS = ("strength", "blend_mode", "branch_rule", "bind_generation", "preserve_shape", "shape_iterations",
            "shape_anchor")

#: Deformer properties an update does not read directly, and why that is safe: the common ones here,
#: each kind's own with its properties (kinds.base.KindProperty).
DECLARED = {
    # Re-weighting (binding.reweight) runs when one of these changes and bumps bind_generation.
    "weight_mode": REWEIGHTS, "radius": REWEIGHTS, "exponent": REWEIGHTS, "normalize": REWEIGHTS,
    "mask_group": REWEIGHTS, "max_influences": REWEIGHTS,
    "bind_warning": "written by re-weighting: bind_generation",
    # Read by the pre-checks: their effect is in Snapshot.error.
    "kind": "pre-check: error", "is_bound": "pre-check: error", "bound_flag": "pre-check: error",
    "bound_vertex_count": "pre-check: error", "bound_topology": "checked with the bind data: error",
    # Not inputs of the deformation.
    "name": "a label", "uid": "names the attributes: part of the cache key itself",
    "status": "the update's output",
    "bake_record": "the bake's record for Un-bake (bake.py): no input of the deformation",
    "show_weights": "the viewport preview (weight_preview.py): no input of the deformation",
    "weight_preview": PREVIEW, "weight_preview_fit": PREVIEW,
    "show_viewport": "the modifier's own toggle (Blender skips a disabled modifier)",
    "show_render": "the modifier's own toggle (Blender skips a disabled modifier)",
    **kinds.declared(),
}


@dataclass(frozen=True)
class Snapshot:
    """The inputs of one update of one deformer (see the module docstring). `motions` and `bound` are
    carried for the computation; they enter the comparisons through `motions_key` and `serial`."""

    mesh: int  # the mesh's session uid
    serial: int | None  # the bind data entry read (bound.BindRecord.serial), None without one
    error: str
    path: str  # 'OFFSET' or 'MOTION' (outputs.output_path)
    settings: tuple  # values of SETTINGS
    motions_key: tuple | None  # Motions.key()
    backend: bool  # the compiled kernel is active (the kernels agree to ~1e-15, not bit for bit)
    reader: bool = True  # the modifier's group reads position carriers (a group replaced or downgraded
    # under an unchanged output must be written again, to the store it reads: output_store.py)
    faces: tuple | None = None  # Preserve Shape's system is built on the faces: (polygons, loops) counts,
    # so an edit of the faces alone (the bind kept) is recomputed (shape_pass.factor_for)
    motions: Motions | None = field(default=None, compare=False)
    bound: BindRecord | None = field(default=None, compare=False)
    modifier: bpy.types.Modifier | None = field(default=None, compare=False)  # the deformer's, looked up once

    def signature(self) -> tuple:
        return (self.mesh, self.serial, self.error, self.path, self.settings, self.motions_key, self.backend,
                self.reader, self.faces)

    def result_state(self) -> tuple:
        """What a result is computed with besides the parameters (the incremental update's key)."""
        strength, _blend, branch_rule, _generation, *_shape = self.settings
        return (self.path, strength, branch_rule, self.backend)


def precheck(obj: bpy.types.Object, deformer, mod: bpy.types.Modifier | None = None) -> str:
    """Why the deformer cannot be evaluated at all ('' when it can be); `mod`: its modifier, when
    the caller has looked it up (outputs.modifier) already."""
    if obj.type != "MESH":
        return f"'{obj.name}' is not a mesh: the deformer has no effect"
    if kinds.get(deformer.kind) is None:
        return f"Deformer kind '{deformer.kind}' is not available in this version"
    if not deformer.is_bound:
        return "Not bound: press Bind" + (f" ({deformer.bind_warning})" if deformer.bind_warning else "")
    stamped = storage.file_format(deformer)
    if stamped > storage.FILE_FORMAT:
        return (f"Bound by a newer version of Affine Deformers (file format {stamped}, this version reads "
                f"up to {storage.FILE_FORMAT}): update the add-on; the mesh passes through")
    if (mod if mod is not None else outputs.modifier(obj, deformer.uid)) is None:
        return "The deformer's modifier was removed or applied: Rebind to recreate it"
    n = len(obj.data.vertices)
    if n != deformer.bound_vertex_count:
        return (f"The mesh has {n} vertices but was bound with {deformer.bound_vertex_count}: "
                "the topology changed, rebind the deformer")
    return ""


def take(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> Snapshot:
    """Read the inputs of an update of `deformer` on `obj` (a mesh) from the evaluated `depsgraph`."""
    mod = outputs.modifier(obj, deformer.uid) if kinds.get(deformer.kind) is not None else None
    error = precheck(obj, deformer, mod)
    motions = bound = None
    path = "OFFSET"
    if not error:  # the blend scales every weight by it; a kind checks the settings its weights read
        error = settings_problem(deformer, ("strength",))
    if not error:
        motions = kinds.get(deformer.kind).current_motions(obj, deformer, depsgraph)
        error = motions.error
    if not error:
        try:
            pool = 1 if motions.pool is None else len(np.atleast_2d(motions.pool))  # nodes (MATH.md §12)
            bound = bound_data.bind_data(obj, deformer, len(motions.matrices), pool=pool)
        except storage.StorageError as exc:
            error = str(exc)
    if not error:
        path, error = outputs.output_path(obj, deformer, bound.rest32, mod)
    return Snapshot(
        obj.data.session_uid, None if bound is None else bound.serial, error, path,
        tuple(getattr(deformer, name) for name in SETTINGS),
        None if motions is None else motions.key(), accel.active(), nodes.reads_positions(mod),
        (len(obj.data.polygons), len(obj.data.loops)) if deformer.preserve_shape and obj.type == "MESH"
        else None, motions, bound, mod)
