"""One deformer update, read → A_i → ψ → kernel → write, and the loops over objects and scenes.

For each deformer on a mesh: take the update's inputs once (snapshot.take: the kind reads its
controls from the evaluated depsgraph — bpy.data is stale during renders — and forms
A_i = C_i · C_rest,i⁻¹ in the target's local space; the bind data; the output path); when their
signature equals the last one written, stop. Otherwise blend (blend.py: parameters P_i = ψ(A_i) with
the rotation-log branch from params.py, the one place for that; per vertex
φ(Σ_k w_vk P_idx(v,k))), and write the offsets or motions our Geometry Nodes modifier applies
(outputs.py). The result at frame f depends only on the inputs at frame f: every cache (caches.py)
holds values recomputable from them.

Bad input becomes the deformer's `status`, and the modifier passes its input through unchanged.

Nothing here knows the interface: what other parts of the add-on do beside an update (the weight
tools' bookkeeping) runs through the explicit hooks of hooks.py, before an object's deformers are
evaluated and once a deformer's inputs are read.
"""

from __future__ import annotations

import contextlib
import traceback
from collections.abc import Container
from dataclasses import dataclass

import bpy
import numpy as np

from ... import accel
from .. import binding, caches, kinds
from ..caches import forget
from ..files import carrier, storage
from . import blend, frame_check, hooks, output_store, outputs, registry, shape_pass, snapshot
from . import bound as bound_data
from .params import motions_to_params
from .params import prefetch as motions_params_prefetch
from .result import Result

__all__ = ["blocking_error", "evaluate_all", "evaluate_deformer", "evaluate_object", "forget",
           "motions_to_params", "run"]

_busy = False


def set_status(deformer, message: str) -> bool:
    """Set the deformer's status; only real changes are written (a write tags the object for update).
    True when it changed."""
    if deformer.status != message:
        deformer.status = message
        return True
    return False


def evaluate_deformer(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph,
                      read: bpy.types.Depsgraph | None = None) -> str:
    """Evaluate one deformer and write its output when it changed. Returns its status ('' = fine).

    `read`: a depsgraph to read the controls from instead of `depsgraph`, ahead of the frame's
    evaluation (read_ahead.py): then only a clean result is written (an error, a control it does not
    evaluate, is left to the update after the frame), and no status or hook is touched."""
    step = _begin(obj, deformer, depsgraph, read, None)
    return step if isinstance(step, str) else _finish(step)


@dataclass
class _Blended:
    """A deformer between its blend and its write (`_begin` → `_finish`): while its update's kernel
    batch has not run, `output` holds rows still to be computed."""

    obj: bpy.types.Object
    deformer: object
    depsgraph: bpy.types.Depsgraph
    ahead: bool
    snap: snapshot.Snapshot
    signature: tuple
    carried: bool
    create: bool
    output: np.ndarray | None
    rows: np.ndarray | None
    error: str


def _begin(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph, read: bpy.types.Depsgraph | None,
           batch: accel.KernelBatch | None) -> str | _Blended:
    """Everything of `evaluate_deformer` up to the blend: its status when the deformer is done (an
    error found before the blend, or the same inputs as the output written last), else the blend,
    whose kernel rows go into `batch` when one is given (accel.collecting)."""
    if obj.type != "MESH":
        error = snapshot.precheck(obj, deformer)
        set_status(deformer, error)
        return error
    carried = carrier.needs_carrier(obj)  # looked up once: the write and the stamp go by it too
    if obj.library is not None or carried:
        problem = carrier.problem(obj, deformer)
        if problem:
            key = (obj.session_uid, deformer.uid)
            if caches.errors.get(key) != problem:  # the console says it once per load, not per update
                print(f"Affine Deformers: {obj.name} / {deformer.name}: {problem}")
                caches.errors[key] = problem
                caches.signatures.pop(key, None)
            with contextlib.suppress(AttributeError, TypeError, RuntimeError):  # a linked ID may refuse
                set_status(deformer, problem)
            return problem
    ahead = read is not None
    snap = snapshot.take(obj, deformer, read if ahead else depsgraph)
    if ahead and snap.error:
        return deformer.status
    if not ahead:
        hooks.run_inputs_read(obj, deformer, snap, depsgraph)  # e.g. the controls' states (weight_groups.py)
    signature = snap.signature()
    create = depsgraph.mode != "RENDER"  # no ID is made during a render frame (on_render_start makes them)
    if caches.signatures.get((obj.session_uid, deformer.uid)) == signature:
        _stamp(obj, deformer, depsgraph, create, snap.modifier, carried)  # the same output, right now too
        return deformer.status
    output = rows = None
    error = snap.error
    if not error:
        output, rows, error = _compute(obj, deformer, snap, batch)
    return _Blended(obj, deformer, depsgraph, ahead, snap, signature, carried, create, output, rows, error)


def _finish(step: _Blended) -> str:
    """The rest of `evaluate_deformer` once the blend's rows are computed: the output checked, written
    where it goes with its stamp, and the status set (nothing but a clean result ahead of the frame)."""
    obj, deformer, snap, depsgraph = step.obj, step.deformer, step.snap, step.depsgraph
    error, output, rows = step.error, step.output, step.rows
    finite = outputs.finite_motions if snap.path == "MOTION" else outputs.finite_offsets
    # A result the blend proved bounded (result.Result.proven) needs no pass over its vertices.
    if not error and not snap.bound.result.proven and not finite(output, rows):
        error = "The deformation is not finite: the mesh shows its rest shape"
        snap.bound.result.forget()
    if step.ahead and error:
        return deformer.status
    path, bound = snap.path, snap.bound
    if error:
        # Zero offsets and no motions: the modifier passes its input through, wherever it stands.
        path, output, rows = "OFFSET", np.zeros((len(obj.data.vertices), 3)), None
        cached = bound_data.cached(obj, deformer)
        if cached is not None:
            cached.result.forget_written()  # written below without it
    _write(obj, deformer, snap.modifier, path, output, rows, None if error else bound, depsgraph, step.create,
           step.carried)
    warning = snap.motions.warning if snap.motions is not None else ""
    status = error or "; ".join(m for m in (warning, deformer.bind_warning) if m)
    set_status(deformer, status)
    key = (obj.session_uid, deformer.uid)
    caches.signatures[key] = step.signature
    caches.errors[key] = error
    return status


def _compute(obj: bpy.types.Object, deformer, snap: snapshot.Snapshot,
             batch: accel.KernelBatch | None) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(output, rows, error) of the blend for the snapshot's path — followed by the shape-preserving
    pass when it is on (shape_pass.py) — ; on an error the cached result is dropped, so the next update
    starts from a full recompute. The plain blend's kernel rows go into `batch` when one is given (the
    output is then read only after it ran); the pass reads its field at once, so it is computed here."""
    compute = blend.blend_motions if snap.path == "MOTION" else blend.blend_offsets
    shaped = deformer.preserve_shape and kinds.get(deformer.kind).shape_pass
    error = ""
    output = rows = None
    try:
        if shaped:
            field, _rows = blend.blend_motions(deformer, snap.motions, snap.bound, snap.result_state())
            controls = len(snap.motions.matrices)
            output, rows = shape_pass.apply(obj, deformer, snap.bound, controls, field, snap.path), None
            snap.bound.result.forget()  # the per-vertex caches must not meet the pass's output
        else:
            with accel.collecting(batch):
                output, rows = compute(deformer, snap.motions, snap.bound, snap.result_state())
    except (storage.StorageError, shape_pass.ShapePassError) as exc:
        error = str(exc)
    except ValueError as exc:  # core refuses to blend (e.g. a motion too degenerate for its log)
        error = f"The controls' motions cannot be blended ({exc}): the mesh shows its rest shape"
    if error:
        snap.bound.result.forget()
    return output, rows, error


def _write(obj: bpy.types.Object, deformer, mod: bpy.types.Modifier | None, path: str, output: np.ndarray,
           rows: np.ndarray | None, bound: bound_data.BindRecord | None, depsgraph: bpy.types.Depsgraph,
           create: bool, carried: bool) -> None:
    """Write the output of `path` and its frame stamp where it goes (output_store.py): a library
    override's carrier (attributes), else the mesh's attributes or the deformer's position carrier,
    whichever costs less; the store not chosen is emptied. Nothing is written to a linked mesh (Blender
    would drop it) or when there is nothing to write to: the modifier shows what is there. `carried`:
    carrier.needs_carrier(obj), as the update found it."""
    uid = deformer.uid
    stamp = _stamp_value(obj, deformer, depsgraph)
    result = bound.result if bound is not None else None
    if carried:
        _write_attributes(carrier.output_mesh(obj, create), uid, path, output, rows, result, stamp)
        return
    holder = None
    if output_store.choose(obj, uid, mod, path, depsgraph) == "POSITIONS":
        holder = output_store.ensure_carrier(obj, uid, mod, create)
    switched = output_store.switched(obj, uid, "ATTRIBUTES" if holder is None else "POSITIONS")
    if switched and result is not None:
        result.forget_written()  # what is remembered is the other store's
    if holder is None:
        output_store.empty_carrier(obj, mod)
        _write_attributes(obj.data, uid, path, output, rows, result, stamp)
        return
    store = output_store.PositionStore(holder.data)
    if output_store.drop_attributes(obj.data, uid) and result is not None:
        result.forget_written()
    if result is None:
        data = output
    else:
        data = (result.pending_motions(output, rows) if path == "MOTION"
                else result.pending_offsets(output, rows))
    if data is None:
        store.stamp(stamp)
    else:
        store.write(data, stamp)


def _write_attributes(mesh: bpy.types.Mesh | None, uid: str, path: str, output: np.ndarray,
                      rows: np.ndarray | None, result: Result | None, stamp: float) -> None:
    """The output and its stamp as attributes of `mesh` (the target's, or an override's carrier's),
    dropping the other path's attributes."""
    if mesh is None or mesh.library is not None or mesh.override_library is not None:
        if result is not None:
            result.forget_written()
        return
    if path == "MOTION":
        outputs.write_motions(mesh, uid, output, rows, result)
    else:
        if storage.remove_output(mesh, uid, keep="OFFSET") and result is not None:
            result.forget_written(motions_only=True)
        outputs.write_offsets(mesh, uid, output, rows, result)
    frame_check.stamp(mesh, uid, stamp)


def _stamp_value(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> np.float32:
    """The scene time the deformer's output is right for (frame_check.py): the depsgraph's time, or
    "every frame" when nothing it depends on changes with time."""
    kind = kinds.get(deformer.kind)
    controls = kind.controls(obj, deformer) if kind is not None else []
    if frame_check.right_at_every_frame(obj, controls):
        return np.float32(frame_check.STAMP_ALWAYS)
    return frame_check.scene_time(depsgraph.scene)


def _stamp(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph, create: bool,
           mod: bpy.types.Modifier | None, carried: bool) -> None:
    """Re-stamp an output that is right at a new time too, where it lives (`carried`: as _write)."""
    stamp = _stamp_value(obj, deformer, depsgraph)
    if carried:
        mesh = carrier.output_mesh(obj, create)
        if mesh is not None and mesh.library is None and mesh.override_library is None:
            frame_check.stamp(mesh, deformer.uid, stamp)
        return
    found = output_store.carrier_of(obj, mod)
    if found is not None and found.library is None and len(found.data.vertices):
        output_store.PositionStore(found.data).stamp(stamp)
    elif obj.data.library is None and obj.data.override_library is None:
        frame_check.stamp(obj.data, deformer.uid, stamp)


def blocking_error(obj: bpy.types.Object, deformer) -> str:
    """The error of the deformer's last evaluation ('' when it deformed, possibly with a warning)."""
    return caches.errors.get((obj.session_uid, deformer.uid), "")


def evaluate_object(obj: bpy.types.Object, depsgraph: bpy.types.Depsgraph | None = None,
                    skip: Container[tuple[int, str]] = (),
                    read: bpy.types.Depsgraph | None = None) -> list[str]:
    """Evaluate every deformer of `obj`; returns their statuses. Objects in Edit Mode are left alone
    (their mesh data is not in sync). For scripts: call `bpy.context.evaluated_depsgraph_get()`
    afterwards to see the written offsets in the evaluated mesh.

    `skip`: (object session uid, deformer uid) of deformers left as they are. The handlers' updates
    (`run`) skip those whose modifier is disabled in `depsgraph`'s mode (`disabled`: the Viewport or
    Render toggle; a baked deformer has both off): such a deformer keeps its last output and costs
    nothing, as a disabled modifier does; enabling it again is a depsgraph update, which evaluates
    it, and its signature (caches.signatures) says whether the kept output is still right."""
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    update = _Update(depsgraph, read)
    with caches.update_scope(), accel.pinned():
        try:
            return update.add(obj, skip)
        finally:
            update.finish()  # fills the statuses of the deformers it blended


class _Update:
    """One update of many deformers, in three passes so the kernel runs once for all of them: each
    deformer's inputs read and blended in turn (`_begin`), its kernel rows collected in one
    accel.KernelBatch; the batch run (one hand-over to the kernel's threads); then each deformer's
    output checked, written and its status set (`_finish`), in the same order. A deformer's result
    does not depend on the others in its batch (bit for bit)."""

    def __init__(self, depsgraph: bpy.types.Depsgraph, read: bpy.types.Depsgraph | None) -> None:
        self.depsgraph, self.read = depsgraph, read
        self.batch = accel.KernelBatch()
        #: (statuses of its object, index there, the blended deformer) waiting for the batch
        self.blended: list[tuple[list[str], int, _Blended]] = []

    def add(self, obj: bpy.types.Object, skip: Container[tuple[int, str]] = ()) -> list[str]:
        """Begin every deformer of `obj`; returns its statuses, those of deformers still blending
        filled in by `finish`."""
        if len(obj.affine_deformers):
            registry.add(obj)  # a deformer a script made without our operators is updated from now on
        if obj.mode == "EDIT":
            return [d.status for d in obj.affine_deformers]
        try:
            binding.separate_shared_ids(obj)  # linked duplicates must not share output attributes
        except Exception:  # never let it stop the evaluation; the ids stay shared and the next update retries
            traceback.print_exc()
        if self.read is None:
            hooks.run_before_object(obj)  # e.g. renamed controls' groups, the weight preview
        statuses: list[str] = []
        for deformer in obj.affine_deformers:
            if (obj.session_uid, deformer.uid) in skip:
                statuses.append(deformer.status)
                continue
            try:
                step = _begin(obj, deformer, self.depsgraph, self.read, self.batch)
            except Exception as exc:  # never let bad data take the handler (or Blender) down
                step = _failed(obj, deformer, exc, self.read is not None)
            if isinstance(step, _Blended):
                self.blended.append((statuses, len(statuses), step))
                step = deformer.status  # until `finish`
            statuses.append(step)
        return statuses

    def finish(self) -> None:
        """Run the batch, then finish every blended deformer. Should the batch fail, each deformer is
        blended again on its own from a full recompute (the rows it collected are undefined)."""
        blended, self.blended = self.blended, []
        try:
            self.batch.run()
        except Exception:
            traceback.print_exc()
            for _statuses, _index, step in blended:
                step.snap.bound.result.forget()
                if not step.error:
                    step.output, step.rows, step.error = _compute(step.obj, step.deformer, step.snap, None)
        for statuses, index, step in blended:
            try:
                statuses[index] = _finish(step)
            except Exception as exc:  # never let bad data take the handler (or Blender) down
                statuses[index] = _failed(step.obj, step.deformer, exc, step.ahead)


def _failed(obj: bpy.types.Object, deformer, exc: Exception, ahead: bool) -> str:
    """The status of a deformer whose update raised `exc`: ahead of the frame its current one (the
    update after the frame says what went wrong); otherwise an internal error, its output emptied so
    the modifier passes its input through."""
    if ahead:
        return deformer.status
    message = f"Internal error ({type(exc).__name__}: {exc}): the mesh shows its rest shape"
    if deformer.status != message:  # print once, not at every depsgraph update
        traceback.print_exception(exc)
    try:
        bound_data.forget((obj.session_uid, deformer.uid))  # its copy of the attribute is stale
        if obj.type == "MESH":  # a position carrier would go on showing its last output
            output_store.empty_carrier(obj, outputs.modifier(obj, deformer.uid))
        mesh = carrier.output_mesh(obj, create=False) if obj.type == "MESH" else None
        if mesh is not None and mesh.library is None and mesh.override_library is None:
            storage.remove_output(mesh, deformer.uid, keep="OFFSET")
            storage.write_offsets(mesh, deformer.uid, np.zeros((len(obj.data.vertices), 3)))
        set_status(deformer, message)
    except Exception:
        traceback.print_exc()
    return message


def disabled(obj: bpy.types.Object, deformer, depsgraph: bpy.types.Depsgraph) -> bool:
    """Whether the deformer's modifier exists and is disabled in `depsgraph`'s mode (a missing
    modifier is not: the update reports it). Never raises (a failure counts as enabled: the
    update's own checks then speak)."""
    try:
        mod = outputs.modifier(obj, deformer.uid) if obj.type == "MESH" else None
        return mod is not None and not (mod.show_render if depsgraph.mode == "RENDER" else mod.show_viewport)
    except Exception:
        traceback.print_exc()
        return False


def evaluate_all(scene: bpy.types.Scene | None = None, depsgraph: bpy.types.Depsgraph | None = None) -> None:
    """Evaluate every deformer in `scene` (default: the context scene and its evaluated depsgraph)."""
    if scene is None:
        scene = bpy.context.scene
    if depsgraph is None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    run(scene, depsgraph)


def run(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph | None,
        read: bpy.types.Depsgraph | None = None) -> None:
    """Evaluate every deformer in `scene` with `depsgraph`, unless an update is already running (our
    own writes trigger depsgraph updates while it runs); never raises. `read`: read the controls from
    this depsgraph, ahead of `depsgraph`'s evaluation (read_ahead.py; see evaluate_deformer)."""
    global _busy
    if _busy or scene is None or depsgraph is None:
        return
    _busy = True
    try:
        with caches.update_scope(), accel.pinned():  # one lookup, one backend for the whole update
            _run(scene, depsgraph, read)
    except Exception:
        traceback.print_exc()
    finally:
        _drop_prefetched()
        _busy = False


def _run(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph, read: bpy.types.Depsgraph | None) -> None:
    """`run`'s update, in order: the deformers it evaluates (the registry's objects of the scene,
    less those another scene shows and the disabled ones), their controls read and ψ of the moved
    ones for all (`_prefetch`), then `_Update`: each deformer blended, the kernel rows of all in one
    batch, each output written and status set."""
    if read is None:  # ahead of the frame `depsgraph` still lists the last evaluation's updates,
        # whose IDs may be gone since: only an evaluated depsgraph is asked what changed
        registry.note(depsgraph)  # objects added since (append, link, Shift+D, a script)
        output_store.note(depsgraph)
    shown = _shown_elsewhere(scene, depsgraph)
    objects = [obj for obj in registry.in_scene(scene) if not shown(obj)]
    if not objects:
        return
    off = {(obj.session_uid, deformer.uid) for obj in objects for deformer in obj.affine_deformers
           if disabled(obj, deformer, depsgraph)}
    _prefetch(objects, read or depsgraph, off)
    update = _Update(depsgraph, read)
    try:
        for obj in objects:
            update.add(obj, off)
    finally:
        update.finish()  # what was blended is written, even when a later object failed


def _prefetch(objects: list[bpy.types.Object], depsgraph: bpy.types.Depsgraph,
              off: Container[tuple[int, str]]) -> None:
    """Read the controls of every deformer this update evaluates, kind by kind in one batch
    (DeformerKind.prefetch), and fill the parameter memo for all of them at once (params.prefetch):
    with many deformed objects the per-control numpy work is shared instead of repeated per object.
    The results equal what each deformer would read alone (row by row, same bits); with one deformer
    there is nothing to share. Never raises: on a failure each deformer reads its own."""
    try:
        by_kind: dict[str, list] = {}
        for obj in objects:
            if obj.type != "MESH" or obj.mode == "EDIT":
                continue
            for deformer in obj.affine_deformers:
                if (deformer.is_bound and kinds.get(deformer.kind) is not None
                        and (obj.session_uid, deformer.uid) not in off):
                    by_kind.setdefault(deformer.kind, []).append((obj, deformer))
        if sum(len(pairs) for pairs in by_kind.values()) < 2:
            return
        read = []
        for kind_id, pairs in by_kind.items():
            read += kinds.get(kind_id).prefetch(pairs, depsgraph)
        motions_params_prefetch([(motions, deformer.branch_rule) for deformer, motions in read
                                 if deformer.blend_mode != "LINEAR"])
    except Exception:
        traceback.print_exc()
        _drop_prefetched()


def _drop_prefetched() -> None:
    for kind in kinds.KINDS.values():
        kind.drop_prefetched()


def running() -> bool:
    """Whether an update is running (its writes trigger the depsgraph handler again)."""
    return _busy


def _shown_elsewhere(scene: bpy.types.Scene, depsgraph: bpy.types.Depsgraph):
    """A test for objects whose viewport update from `scene` is skipped: those the context's scene
    shows too, when `scene` is another one. A deformer's output lives on the mesh, which holds one
    shape at a time, so two scenes at different frames would rewrite it on every alternate update;
    the scene the artist is in wins. Renders are never skipped."""
    active = getattr(bpy.context, "scene", None)
    if depsgraph.mode == "RENDER" or active is None or active == scene:
        return lambda _obj: False
    objects = active.objects
    return lambda obj: objects.get(obj.name) == obj
