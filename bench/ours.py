"""Our deformers inside Blender, driven like a user would: install the built .zip, run the add operators.

The per-update time is measured from outside (`common.time_updates`), so it contains everything an artist
waits for: the depsgraph pass that moves the control, our @persistent handler, and Blender's
re-evaluation of the Geometry Nodes modifier that adds our offsets.

The split of that time comes from `Instrument`, which needs no cooperation from the layer:
- the handler total is measured by wrapping our entries in `bpy.app.handlers` (exact);
  whole update − handler = Blender's own work (depsgraph passes, Geometry Nodes);
- inside the handler, the layer's stage functions listed in `STAGE_POINTS` (reading the controls'
  transforms, reading rest positions and weights, ψ, the per-vertex kernel, writing the offsets) are
  wrapped for the duration of a case, each timed exclusive of the others nested in it; the rest of the
  handler is reported as glue. A renamed function simply drops out of its stage into glue.
"""

from __future__ import annotations

import contextlib
import functools
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from native import Rig, move_cage_vertex, move_object

REPO = "user_default"
EXT_ID = "affine_deformers"
PKG = f"bl_ext.{REPO}.{EXT_ID}"
INNER = f"{PKG}.affine_deformers"

PROBE_OP = "object.affine_probe_deformer_add"
CAGE_OP = "object.affine_cage_deformer_add"
BONE_OP = "object.affine_bone_deformer_add"
BIND_OP = "object.affine_deformer_bind"

# Where the stages of our handler live, for the split when the layer keeps no counters of its own:
# (module under the package, function or Class.method, stage). Missing names are skipped; whatever is not
# covered shows up as "glue" (handler − covered stages).
STAGE_POINTS = (
    ("blender.kinds", "*.current_motions", "read"),  # every kind class registered in kinds.KINDS
    ("blender.files.storage", "read_positions", "read mesh"),
    ("blender.files.storage", "read_weights", "read mesh"),
    ("blender.update.params", "motions_to_params", "psi"),
    ("blender.update.params", "chain_params", "psi"),  # bones: ψ of the local motions
    ("core.aff3", "params_from_matrices", "psi"),
    ("core.aff3", "matrices_from_params", "psi"),
    ("core.cage", "affected_faces", "psi"),  # cage: which faces moved, then their tetrahedra → params
    ("core.cage", "face_motions", "psi"),
    ("core.cage.harmonic", "node_params", "psi"),  # harmonic cage weights: the nodes' blended faces
    ("core.cage.harmonic", "node_matrices_linear", "psi"),
    ("accel", "cage_faces", "psi"),  # the same two steps in the compiled kernel
    ("accel", "cage_nodes", "psi"),
    ("core.deform", "deform_points_params", "kernel"),
    ("core.deform", "deform_points_params_rows", "kernel"),
    ("core.deform", "blend_linear_sparse", "kernel"),
    ("core.deform", "deform_points", "kernel"),
    ("accel", "deform_points_params", "kernel"),  # the compiled kernel's dispatch (numpy fallback inside)
    ("accel", "deform_points_params_rows", "kernel"),
    ("core.deform", "vertex_motions", "kernel"),
    ("accel", "vertex_motions", "kernel"),
    ("accel", "chain_points", "kernel"),  # bones: the blend down the hierarchy
    ("accel", "chain_motions", "kernel"),
    ("blender.files.storage", "write_offsets", "write"),
    ("blender.files.storage", "write_motions", "write"),
    ("blender.files.storage", "write_offsets_unchecked", "write"),
)


# --------------------------------------------------------------------------------------------------
# Installing and finding the extension


def install(zip_path: Path) -> str | None:
    """Install and enable the built extension; None (with a printed reason) when that is impossible."""
    if not zip_path.is_file():
        print(f"[ours] {zip_path} not found — run `make build` first; our side is skipped")
        return None
    result = bpy.ops.extensions.package_install_files(
        filepath=str(zip_path), repo=REPO, enable_on_install=True
    )
    if "FINISHED" not in result or PKG not in sys.modules:
        print(f"[ours] installing {zip_path.name} failed ({result}); our side is skipped")
        return None
    accel = sys.modules.get(f"{PKG}.{EXT_ID}.accel")
    if accel is not None and hasattr(accel, "warm_up"):
        # What registration does: load the kernel and run each entry once, so no timed update pays
        # for loading it.
        t0 = time.perf_counter()
        print(f"[ours] kernel warm-up: {accel.warm_up()}, {time.perf_counter() - t0:.1f} s")
    return PKG


def kernel_backend() -> str:
    """Which per-vertex kernel our installed package uses ('C kernel (…), N threads' or 'numpy (…)')."""
    accel = sys.modules.get(f"{PKG}.{EXT_ID}.accel")
    return accel.backend() if accel is not None else "n/a"


def forget_caches() -> None:
    """Drop our per-control memos and caches, so a case does not find the poses an earlier case
    computed (the move sequence is the same in every case): every timed update then meets new poses,
    as in an interactive drag."""
    evaluate = sys.modules.get(f"{PKG}.{EXT_ID}.blender.update.evaluate")
    if evaluate is not None:
        evaluate.forget()


def use_compiled_kernel(flag: bool) -> None:
    """Switch our kernel like the add-on preference does (compiled ↔ numpy); caches are dropped."""
    accel = sys.modules.get(f"{PKG}.{EXT_ID}.accel")
    evaluate = sys.modules.get(f"{PKG}.{EXT_ID}.blender.update.evaluate")
    if accel is not None and hasattr(accel, "set_enabled"):
        accel.set_enabled(flag)
    if evaluate is not None:
        evaluate.forget()


def operator_exists(idname: str) -> bool:
    category, name = idname.split(".")
    try:
        getattr(getattr(bpy.ops, category), name).get_rna_type()
    except (KeyError, AttributeError):
        return False
    return True


def call_operator(idname: str, active: bpy.types.Object, selected: list[bpy.types.Object], **props):
    """Run an object operator as if `active` were active and `selected` selected (works in background)."""
    category, name = idname.split(".")
    op = getattr(getattr(bpy.ops, category), name)
    accepted = set(op.get_rna_type().properties.keys())
    kwargs = {k: v for k, v in props.items() if k in accepted}
    view_layer = bpy.context.view_layer
    for ob in view_layer.objects:
        ob.select_set(ob in selected)
    view_layer.objects.active = active
    with bpy.context.temp_override(
        active_object=active,
        object=active,
        selected_objects=selected,
        selected_editable_objects=selected,
    ):
        result = op(**kwargs)
    if "FINISHED" not in result:
        raise RuntimeError(f"{idname} returned {result}")
    return result


def _enum_ids(owner: bpy.types.bpy_struct, prop: str) -> list[str]:
    rna = owner.bl_rna.properties.get(prop)
    return [item.identifier for item in rna.enum_items] if rna is not None and rna.type == "ENUM" else []


def _smooth_mode(deformer: bpy.types.bpy_struct) -> str | None:
    """The weight mode closest to the Hook modifier's Smooth falloff, if the property group has one."""
    ids = _enum_ids(deformer, "weight_mode")
    for wanted in ("SMOOTH", "FALLOFF"):
        for ident in ids:
            if wanted in ident:
                return ident
    return None


# --------------------------------------------------------------------------------------------------
# Building our rigs


@dataclass
class OurRig(Rig):
    deformer_index: int = 0
    settings: dict[str, object] = field(default_factory=dict)
    influences: tuple[int, float] | None = None  # (K slots, mean non-zero weights per vertex)


def probe_rig(target: bpy.types.Object, empties: list[bpy.types.Object], radius: float) -> OurRig:
    """Our probe deformer on `target` driven by `empties`, smooth falloff of `radius` where available.

    bind_seconds is the add operator (it binds at once) plus any re-weighting the settings cause.
    """
    t0 = time.perf_counter()
    call_operator(PROBE_OP, target, [target, *empties], radius=radius)
    index = len(target.affine_deformers) - 1
    deformer = target.affine_deformers[index]
    generation = getattr(deformer, "bind_generation", None)
    changed = False
    mode = _smooth_mode(deformer)
    if mode is not None and deformer.weight_mode != mode:
        deformer.weight_mode = mode  # re-weights from the stored rest data
        changed = True
    if hasattr(deformer, "radius") and abs(deformer.radius - radius) > 1e-6:
        deformer.radius = radius
        changed = True
    reweighted = generation is not None and getattr(deformer, "bind_generation", None) != generation
    if changed and not reweighted and operator_exists(BIND_OP):
        # This layer does not re-weight on property changes: bind again (nothing has moved yet).
        call_operator(BIND_OP, target, [target], index=index)
    bind = time.perf_counter() - t0
    bpy.context.view_layer.update()
    settings = {
        k: getattr(deformer, k)
        for k in ("weight_mode", "radius", "normalize", "max_influences", "blend_mode", "strength")
        if hasattr(deformer, k)
    }
    return OurRig(
        target,
        move_object(empties[0]),
        time.perf_counter() - t0,
        bind_seconds=bind,
        deformer_index=index,
        settings=settings,
    )


def cage_rig(target: bpy.types.Object, cage: bpy.types.Object) -> OurRig:
    """Our cage deformer on `target` with `cage`; bind_seconds = the add operator (it binds at once)."""
    t0 = time.perf_counter()
    call_operator(CAGE_OP, target, [target, cage])
    bind = time.perf_counter() - t0
    bpy.context.view_layer.update()
    index = len(target.affine_deformers) - 1
    return OurRig(
        target, move_cage_vertex(cage), time.perf_counter() - t0, bind_seconds=bind, deformer_index=index
    )


def bone_rig(target: bpy.types.Object, arm: bpy.types.Object, move: Callable[[int], None]) -> OurRig:
    """Our bone deformer on `target` driven by `arm`'s bones through the vertex groups named after them
    (what the add operator picks when the groups exist); bind_seconds = the add operator (it binds)."""
    t0 = time.perf_counter()
    call_operator(BONE_OP, target, [target, arm])
    bind = time.perf_counter() - t0
    bpy.context.view_layer.update()
    index = len(target.affine_deformers) - 1
    deformer = target.affine_deformers[index]
    if deformer.weight_mode != "VERTEX_GROUPS":
        raise RuntimeError(f"the bone deformer weights by {deformer.weight_mode}, not the vertex groups")
    settings = {k: getattr(deformer, k) for k in ("weight_mode", "normalize", "max_influences", "blend_mode")}
    return OurRig(target, move, time.perf_counter() - t0, bind_seconds=bind, deformer_index=index,
                  settings=settings)


_BIND_ATTR = re.compile(r"^\.affdef_(?P<uid>.+)_(?P<kind>idx|w)(?P<k>\d+)$")


def _bind_columns(me: bpy.types.Mesh) -> list[tuple[str, str]] | None:
    """[(index attribute, weight attribute)] per top-K slot of the one deformer bound on `me`, or None."""
    found: dict[str, dict[str, dict[int, str]]] = {}
    for attr in me.attributes:
        m = _BIND_ATTR.match(attr.name)
        if m:
            found.setdefault(m["uid"], {}).setdefault(m["kind"], {})[int(m["k"])] = attr.name
    if len(found) != 1:
        return None
    (parts,) = found.values()
    ks = sorted(parts.get("idx", {}))
    if not ks or ks != sorted(parts.get("w", {})):
        return None
    return [(parts["idx"][k], parts["w"][k]) for k in ks]


def bound_weights(target: bpy.types.Object, empties: list[bpy.types.Object]) -> np.ndarray | None:
    """Dense (N, m) weights our bind stored on the mesh (top-K attributes), columns in `empties` order.

    None when the attributes are not where DEVELOPING.md says they are; the caller then falls back to
    the analytic smooth falloff. Dense on purpose (it feeds vertex groups): call it for small m only.
    """
    me = target.data
    columns = _bind_columns(me)
    probe_objects = [p.object for p in target.affine_deformers[len(target.affine_deformers) - 1].probes]
    if columns is None or not probe_objects:
        return None
    column = {i: empties.index(ob) for i, ob in enumerate(probe_objects) if ob in empties}
    cols = np.array([column.get(i, -1) for i in range(len(probe_objects))])
    n = len(me.vertices)
    dense = np.zeros((n, len(empties)))
    idx_buf = np.empty(n, np.int32)
    w_buf = np.empty(n, np.float32)
    for idx_name, w_name in columns:
        me.attributes[idx_name].data.foreach_get("value", idx_buf)
        me.attributes[w_name].data.foreach_get("value", w_buf)
        valid = (idx_buf >= 0) & (idx_buf < len(probe_objects))
        c = np.where(valid, cols[np.clip(idx_buf, 0, len(probe_objects) - 1)], -1)
        ok = c >= 0
        np.add.at(dense, (np.flatnonzero(ok), c[ok]), w_buf[ok])
    return dense


def mean_influences(target: bpy.types.Object) -> tuple[int, float] | None:
    """(K stored slots, mean number of non-zero weights per vertex) of our bind, or None."""
    me = target.data
    columns = _bind_columns(me)
    if columns is None:
        return None
    n = len(me.vertices)
    w_buf = np.empty(n, np.float32)
    nonzero = 0
    for _, w_name in columns:
        me.attributes[w_name].data.foreach_get("value", w_buf)
        nonzero += int(np.count_nonzero(w_buf))
    return len(columns), nonzero / max(n, 1)


# --------------------------------------------------------------------------------------------------
# Splitting the per-update time


class Instrument:
    """Per-rep stage timings of our handler; see the module docstring for where each number comes from."""

    def __init__(self) -> None:
        self.acc: dict[str, float] = {}
        self._handler_patches: list[tuple[list, int, Callable]] = []
        self._func_patches: list[tuple[object, str, Callable]] = []
        self._stack: list[list[float]] = []
        self.source = "the layer's stage functions (STAGE_POINTS), wrapped by the benchmark"

    # -- patching ---------------------------------------------------------------------------------
    def __enter__(self) -> Instrument:
        self._wrap_handlers()
        self._wrap_stages()
        self.reset()
        return self

    def __exit__(self, *exc: object) -> None:
        for handler_list, pos, original in reversed(self._handler_patches):
            handler_list[pos] = original
        for owner, name, original in reversed(self._func_patches):
            setattr(owner, name, original)
        self._handler_patches.clear()
        self._func_patches.clear()

    def _timer(self, stage: str, fn: Callable) -> Callable:
        """`fn` timed into `stage`, exclusive of wrapped calls nested inside it (they count for their own
        stage): reading the cage, for instance, contains the per-face ψ."""

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            frame = [0.0]  # time spent in wrapped calls nested inside this one
            self._stack.append(frame)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - t0
                self._stack.pop()
                self.acc[stage] = self.acc.get(stage, 0.0) + elapsed - frame[0]
                if self._stack:
                    self._stack[-1][0] += elapsed

        return wrapper

    def _wrap_handlers(self) -> None:
        for handler_list in (bpy.app.handlers.depsgraph_update_post, bpy.app.handlers.frame_change_post):
            for pos, fn in enumerate(list(handler_list)):
                if (getattr(fn, "__module__", None) or "").startswith(PKG):

                    def wrapper(*args, _fn=fn):
                        t0 = time.perf_counter()
                        try:
                            return _fn(*args)
                        finally:
                            self.acc["handler"] = self.acc.get("handler", 0.0) + time.perf_counter() - t0

                    self._handler_patches.append((handler_list, pos, fn))
                    handler_list[pos] = wrapper

    def _wrap_stages(self) -> None:
        """Wrap each STAGE_POINTS entry wherever our modules hold a reference to it."""
        functions: dict[int, tuple[Callable, str]] = {}
        for modname, attr, stage in STAGE_POINTS:
            mod = sys.modules.get(f"{INNER}.{modname}")
            if mod is None:
                continue
            if attr.startswith("*."):
                method = attr[2:]
                kinds = getattr(mod, "KINDS", {})
                for cls in {type(k) for k in kinds.values()}:
                    fn = cls.__dict__.get(method)
                    if callable(fn):
                        self._func_patches.append((cls, method, fn))
                        setattr(cls, method, self._timer(stage, fn))
                continue
            fn = getattr(mod, attr, None)
            if callable(fn):
                functions.setdefault(id(fn), (fn, stage))
        wrappers = {key: self._timer(stage, fn) for key, (fn, stage) in functions.items()}
        for modname, mod in list(sys.modules.items()):
            if not modname.startswith(INNER) or mod is None:
                continue
            for name, value in list(vars(mod).items()):
                entry = functions.get(id(value))
                if entry is not None and value is entry[0]:
                    self._func_patches.append((mod, name, value))
                    setattr(mod, name, wrappers[id(value)])

    # -- reading ----------------------------------------------------------------------------------
    def reset(self) -> None:
        self.acc = {}

    def stages(self) -> dict[str, float]:
        """Seconds per stage since the last reset ('handler' = our whole handler, 'glue' = the part of
        it no wrapped stage covers)."""
        out = dict(self.acc)
        if "handler" in out:
            covered = sum(v for k, v in out.items() if k != "handler")
            out["glue"] = max(out["handler"] - covered, 0.0)
        return out

    def record(self, samples, total_key: str = "total") -> None:
        """Append this rep's stage times to `samples.extra` and start the next rep from zero."""
        stages = self.stages()
        stages[total_key] = samples.seconds[-1]
        if "handler" in stages:
            stages["Blender re-evaluation"] = max(samples.seconds[-1] - stages["handler"], 0.0)
        for key, value in stages.items():
            samples.extra.setdefault(key, []).append(value)
        self.reset()


@contextlib.contextmanager
def write_only_updates():
    """Replace our update (`evaluate.run`, which every handler calls) by one that only writes a
    constant offset per frame into each deformer's offset attribute, and the frame stamp (frame_check.py):
    no control is read, nothing is
    computed. What is left of a frame is the floor of this design — the handler's writes and
    Blender's re-evaluation of the meshes and of our Geometry Nodes modifier — which no faster
    computation can go below."""
    evaluate = sys.modules[f"{INNER}.blender.update.evaluate"]
    storage = sys.modules[f"{INNER}.blender.files.storage"]
    frame_check = sys.modules[f"{INNER}.blender.update.frame_check"]
    output_store = sys.modules[f"{INNER}.blender.update.output_store"]
    nodes = sys.modules[f"{INNER}.blender.files.nodes"]
    real = evaluate.run

    done: list = []

    def write_only(scene: bpy.types.Scene, _depsgraph, read=None) -> None:
        """Writes once a frame: ahead of its evaluation where the update would read ahead (`read`
        given: read_ahead.py), else after it."""
        if scene is None:
            return
        stamp = (scene.frame_current, scene.frame_subframe)
        if read is None and done and done[-1] == stamp:
            return
        done[:] = [stamp] if read is not None else []
        value = 1e-4 * (scene.frame_current % 97 + 1)
        for obj in scene.objects:
            mesh = obj.data if obj.type == "MESH" else None
            for deformer in getattr(obj, "affine_deformers", ()):
                # the floor of the attribute store: a position carrier must not show instead
                output_store.empty_carrier(obj, nodes.find_modifier(obj, storage.offset_name(deformer.uid)))
                offsets = np.full((len(mesh.vertices), 3), value, dtype=np.float32)
                storage.write_offsets_unchecked(mesh, deformer.uid, offsets)
                # the frame check's stamp, as every real update writes it (frame_check.py)
                storage.write_frame(mesh, deformer.uid, frame_check.scene_time(scene))

    evaluate.run = write_only
    try:
        yield
    finally:
        evaluate.run = real


def kernel_seconds(targets: list[bpy.types.Object], reps: int = 20) -> float | None:
    """Median seconds of our compiled per-vertex map (φ of the blended parameters) over all `targets`
    once, each with its own bind's weights and a rigid motion of every control (the (m) rigs' probes
    turn and shift), every vertex recomputed, all targets in one kernel batch as an update runs them:
    the kernel's share of a frame with little Python around it. None without the weights or the
    compiled kernel."""
    accel = sys.modules.get(f"{INNER}.accel")
    if accel is None or not accel.active():
        return None
    jobs = []
    for target in targets:
        columns = _bind_columns(target.data)
        if columns is None:
            return None
        n = len(target.data.vertices)
        idx = np.empty((len(columns), n), np.int32)
        val = np.empty((len(columns), n), np.float32)
        for k, (idx_name, w_name) in enumerate(columns):
            target.data.attributes[idx_name].data.foreach_get("value", idx[k])
            target.data.attributes[w_name].data.foreach_get("value", val[k])
        unused = idx < 0  # an empty slot
        idx[unused], val[unused] = 0, 0.0
        rows = int(idx.max()) + 1
        table = np.zeros((rows, 12))  # (ω, u, Y): a turn and a shift, rigid as the keyed probes' wiggles
        table[:, :3] = (0.2, -0.1, 0.15)
        table[:, 3:6] = (0.05, 0.02, -0.03)
        points = np.empty(n * 3, np.float32)
        target.data.vertices.foreach_get("co", points)
        jobs.append((points.reshape(-1, 3).astype(np.float64), table, np.ascontiguousarray(idx.T),
                     np.ascontiguousarray(val.T, dtype=np.float64), np.empty((n, 3))))
    rows = [np.arange(len(points)) for points, *_ in jobs]
    times = []
    for _ in range(reps + 2):
        t0 = time.perf_counter()
        batch = accel.KernelBatch()  # as an update runs them: one hand-over for all targets
        with accel.collecting(batch):
            for i, (points, table, idx, val, out) in enumerate(jobs):
                accel.deform_points_params_rows(points, table, idx, val, rows[i], out,
                                                 key=("bench kernel", i))  # checked once
        batch.run()
        times.append(time.perf_counter() - t0)
    return float(np.median(times[2:]))


BAKE_OP = "object.affine_deformer_bake"


def bake_to_pc2(targets: list[bpy.types.Object], frames: int, directory: Path) -> None:
    """Bake the first deformer of every target over frames 1..`frames` into a PC2 cache in
    `directory` (the operator mutes the live deformer and adds a Mesh Cache modifier)."""
    for target in targets:
        call_operator(BAKE_OP, target, [target], index=0, mode="PC2", frame_start=1, frame_end=frames,
                      filepath=str(directory / f"{target.name}.pc2"))
