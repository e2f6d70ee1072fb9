"""Fuzz of the values a script or a damaged file can set (issue #47): every numeric setting and stored
datum of each kind, set to hostile values, gives either the correct shape or a status naming it —
never an exception, a traceback, a non-finite position or a vertex sent beyond the controls' reach.

Rigs: one small posed rig per kind — three probes with Preserve Shape on and Max Influences 2 (so
the pooled column is used), a harmonic cage moved, turned and sheared, two chained bones weighted by
distance.

Cases, each value of FLOATS (INTS for integer properties):
* every writable numeric property of the deformer item (enumerated from bl_rna: every kind's
  properties are on every deformer) and of one control item (a probe, a bone); a vector property
  in the elements ELEMENTS picks; each set both through RNA (`setattr`: the interface clamps to the
  property's range, NaN passes the clamp; update callbacks run, e.g. re-weighting) and as an ID
  property of the same type (`item[name] = value`: what a script or a damaged file does — no clamp,
  no callback);
* every stored per-control datum — one vertex's weight and index attributes, the file-format stamp,
  a cage's ID-property arrays, the bones' rest segments — set element-wise, the caches dropped
  first (what a file load does: an update trusts the bind data it has cached until then).
Each case runs the update through the handlers (scene.frame_set) and directly
(evaluate.evaluate_object), then restores the value (re-weighting when the case re-weighted) and
checks the rig is back at its baseline.

A case passes when
* no exception escapes, nothing prints a traceback and no status reports an internal error;
* every evaluated position is finite;
* no vertex moves farther than the controls' reach, 2·R(s) + 1e-4 (or than the correct shape moves,
  where that is more and the shape is known without the add-on: the baseline, the input). R(s) =
  max over the kind's control motions M(s) and rest vertices v of |M(s) v − v|, at the strength s
  in use (clamped to the interface's 0 … 10), M(s) = φ(s·ψ(A)) of each motion A as this test
  forms it from the scene and the stored rest data: a probe's
  C·C_rest⁻¹; a cage's G^s·A_f^s (G the cage object's motion, A_f each face's from the stored rest
  cage, core.cage.face_motions); a bone's chain of local motions L^s from its root (pose · rest⁻¹
  carried into the target's space). The factor 2 covers blending (pooled and harmonic nodes mix
  several controls) and Preserve Shape;
* and either the status names the setting — its interface label (the RNA name; NAMED_BY where the
  status words it otherwise), with the control's name for a per-control setting, or the key /
  attribute name of stored data — and the mesh shows its input exactly; or the shape is the correct
  one: the baseline for a property that is no input of this deformer (interface and preview state,
  another kind's properties), the input at strength 0, otherwise the shape of a from-scratch update
  of the same stored values (every cache dropped, re-weighted when the case re-weighted).

The counts (cases, statuses, failures) are printed per kind (pytest -s).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import bpy
import numpy as np
import pytest

from tests.blender.test_bone_deformer import _armature, _bar
from tests.blender.test_cage_deformer import add_cage_deformer, box_cage, cage_points, set_cage_points

FLOATS = (0.0, -1.0, 1e30, -1e30, math.inf, -math.inf, math.nan)
INTS = (0, -1, -(2**31), 2**31 - 1)
#: Elements set of vector properties: of a row-major 4×4 a diagonal entry, a translation, another
#: diagonal entry and the bottom row's first and last; of rotation channels the first two.
ELEMENTS = {16: (0, 3, 5, 12, 15), 4: (0, 1)}
#: What a status says for a setting whose label it does not repeat, and why that names it.
NAMED_BY = {
    # the pre-check: "The mesh has N vertices but was bound with M"
    "bound_vertex_count": "was bound with",
    "file_format": "file format",  # "Bound by a newer version of Affine Deformers (file format N, …)"
}
MARGIN, SLACK = 2.0, 1e-4


@dataclass
class Rig:
    """A posed deformer: its target, control item to fuzz (None for a cage) and that item's name,
    the input and baseline shapes and status, and the motions M(s) of its controls (module docstring)."""

    kind: str
    target: bpy.types.Object
    deformer: object
    item: object | None
    item_name: str
    motions: Callable[[float], list[np.ndarray]]
    rest: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    baseline: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    status: str = ""


@dataclass
class Fuzz:
    """The add-on's modules, the stderr capture, and the counts."""

    installed: object
    capfd: object
    reweights: list[int]
    cases: int = 0
    statuses: int = 0
    failures: list[str] = field(default_factory=list)

    def module(self, name: str):
        return importlib.import_module(f"{self.installed.package}.{name}")


# ------------------------------------------------------------------------------------------ motions


def _power(fz: Fuzz, matrices: np.ndarray, s: float) -> np.ndarray:
    """φ(s·ψ(A)) of motions (n, 4, 4) (the script contract's ψ and φ in the 12-number layout)."""
    core = fz.module("core")
    return core.matrices_from_params(s * core.params_from_matrices(np.asarray(matrices, dtype=np.float64)))


def _world(obj) -> np.ndarray:
    return np.array(obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).matrix_world, dtype=np.float64)


def _probe_motions(fz: Fuzz, target, deformer) -> Callable[[float], list[np.ndarray]]:
    def motions(s: float) -> list[np.ndarray]:
        tw = _world(target)
        out = []
        for item in deformer.probes:
            rest = np.array(item.rest_matrix, dtype=np.float64).reshape(4, 4)
            out.append(np.linalg.inv(tw) @ _world(item.object) @ np.linalg.inv(rest))
        return list(_power(fz, np.stack(out), s))
    return motions


def _cage_motions(fz: Fuzz, target, deformer, cage) -> Callable[[float], list[np.ndarray]]:
    cage_core = fz.module("core.cage")

    def motions(s: float) -> list[np.ndarray]:
        stored = np.array(deformer.cage_rest_matrix, dtype=np.float64).reshape(4, 4)
        outer = np.linalg.inv(_world(target)) @ _world(cage) @ np.linalg.inv(stored)
        rest = np.asarray(deformer["cage_rest_points"], dtype=np.float64).reshape(-1, 3)
        topology = cage_core.CageTopology.from_arrays(
            *(np.asarray(deformer[k], dtype=np.int32) for k in ("cage_loop_vertices", "cage_loop_start",
                                                                 "cage_loop_total")), len(rest))
        current = cage_points(cage) @ stored[:3, :3].T + stored[:3, 3]
        faces = fz.module("core").matrices_from_params(cage_core.face_motions(rest, current, topology).params)
        return list(_power(fz, outer[None], s)[0] @ _power(fz, faces, s))
    return motions


def _bone_motions(fz: Fuzz, target, deformer, arm) -> Callable[[float], list[np.ndarray]]:
    def motions(s: float) -> list[np.ndarray]:
        frame = np.linalg.inv(_world(target)) @ _world(arm)
        pose = arm.evaluated_get(bpy.context.evaluated_depsgraph_get()).pose
        out = []
        for item in deformer.bones:
            chain, bone = [], pose.bones[item.name]
            while bone is not None:  # root last
                moved = np.array(bone.matrix) @ np.linalg.inv(np.array(bone.bone.matrix_local))
                parent = bone.parent
                below = (np.array(parent.matrix) @ np.linalg.inv(np.array(parent.bone.matrix_local))
                         if parent is not None else np.eye(4))
                chain.append(frame @ np.linalg.inv(below) @ moved @ np.linalg.inv(frame))
                bone = parent
            total = np.eye(4)
            for local in reversed(chain):
                total = total @ _power(fz, local[None], s)[0]
            out.append(total)
        return out
    return motions


# --------------------------------------------------------------------------------------------- rigs


def _probe_rig(bl, fz: Fuzz) -> Rig:
    target = bl.grid_cube(cuts=3)
    probes = [bl.empty("A", (0.0, 0.0, 1.3)), bl.empty("B", (1.3, 0.0, 0.0)), bl.empty("C", (0.0, 0.0, -1.3))]
    deformer = bl.add_probe_deformer(target, probes, max_influences=2, preserve_shape=True)
    probes[1].rotation_euler.x = 0.6
    probes[1].location.y = 0.3
    probes[2].scale = (1.2, 1.0, 1.0)
    return Rig("PROBE", target, deformer, deformer.probes[1], "B", _probe_motions(fz, target, deformer))


def _cage_rig(bl, fz: Fuzz) -> Rig:
    target = bl.grid_cube(cuts=3)
    cage = box_cage()
    deformer = add_cage_deformer(target, cage)
    cage.location = (0.2, 0.1, 0.0)
    cage.rotation_euler.z = 0.3
    points = cage_points(cage)
    points[:, 0] += 0.15 * points[:, 2]  # a shear: every face moves
    set_cage_points(cage, points)
    return Rig("CAGE", target, deformer, None, "", _cage_motions(fz, target, deformer, cage))


def _bone_rig(bl, fz: Fuzz) -> Rig:
    bar = _bar(bl, cuts=5)
    arm = _armature([0.0, 2.0, 4.0])
    bpy.context.view_layer.objects.active = bar
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar, arm]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    assert deformer.weight_mode == "INVERSE_DISTANCE"  # no painted groups: Radius and Exponent are read
    for name, angle in (("B0", 0.2), ("B1", 0.5)):
        bone = arm.pose.bones[name]
        bone.rotation_mode = "XYZ"
        bone.rotation_euler.z = angle
    return Rig("BONE", bar, deformer, deformer.bones[1], "B1", _bone_motions(fz, bar, deformer, arm))


def _ready(bl, fz: Fuzz, build: Callable) -> Rig:
    """The rig `build` makes, with its input, baseline shape and status."""
    rig = build(bl, fz)
    rig.rest = bl.rest_positions(rig.target).copy()
    rig.baseline, rig.status = _update(fz, rig)
    fz.capfd.readouterr()
    return rig


# -------------------------------------------------------------------------------------------- cases


def _update(fz: Fuzz, rig: Rig) -> tuple[np.ndarray, str]:
    """The update through the handlers, then directly; the evaluated positions and the status."""
    scene = bpy.context.scene
    scene.frame_set(2 if scene.frame_current == 1 else 1)
    fz.module("blender.update.evaluate").evaluate_object(rig.target, bpy.context.evaluated_depsgraph_get())
    co = _positions(rig.target)
    return co, rig.deformer.status


def _positions(obj) -> np.ndarray:
    mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _fresh(fz: Fuzz, rig: Rig, reweighted: bool) -> np.ndarray:
    """A from-scratch update of the stored values (every cache dropped; re-weighted first when the
    case re-weighted). ValueError / BindError from re-weighting propagate."""
    if reweighted:
        fz.module("blender.binding").reweight(rig.target, rig.deformer)
    fz.module("blender.update.evaluate").forget()
    fz.module("blender.update.evaluate").evaluate_object(rig.target, bpy.context.evaluated_depsgraph_get())
    return _positions(rig.target)


def _reach(rig: Rig, strength: float) -> float:
    """R(s) of the module docstring (NaN when the motions cannot be formed from the stored data)."""
    s = float(np.clip(strength, 0.0, 10.0)) if math.isfinite(strength) else 10.0
    try:
        motions = np.stack(rig.motions(s))
    except (ValueError, np.linalg.LinAlgError):
        return math.nan
    points = np.c_[rig.rest.astype(np.float64), np.ones(len(rig.rest))]
    with np.errstate(all="ignore"):
        moved = np.einsum("mij,nj->mni", motions[:, :3], points)
    return float(np.linalg.norm(moved - rig.rest[None], axis=2).max())


def _check(fz: Fuzz, rig: Rig, names: tuple[str, ...], no_input: bool, reweighted: bool) -> list[str]:
    """Run the update and judge it (module docstring); the problems found."""
    problems = []
    got, status = _update(fz, rig)
    if "Internal error" in status:
        problems.append(f"internal error: {status}")
    if not np.isfinite(got).all():
        return [*problems, "non-finite positions"]
    named = all(name in status for name in names)
    moved = float(np.abs(got - rig.rest).max())
    if named:
        fz.statuses += 1
        if not np.array_equal(got, rig.rest):
            problems.append(f"status names it but the mesh moved {moved:.3g}: {status!r}")
        return problems
    strength = rig.deformer.strength
    if no_input:
        expected = rig.baseline
    elif strength == 0.0:
        expected = rig.rest
    else:
        try:
            expected = _fresh(fz, rig, reweighted)
        except Exception as exc:  # the stored values cannot even be re-weighted, yet nothing said so
            return [*problems, f"not named in {status!r}, and a fresh update refuses it: {exc}"]
    if not np.allclose(got, expected, rtol=0.0, atol=1e-5):
        problems.append(f"not named in {status!r} and the shape is off by "
                        f"{float(np.abs(got - expected).max()):.3g}")
    distance = float(np.linalg.norm(got.astype(np.float64) - rig.rest, axis=1).max())
    allowed = MARGIN * _reach(rig, strength)
    if no_input or strength == 0.0:  # a shape known without the add-on: its own displacement is allowed
        allowed = max(allowed, float(np.linalg.norm(expected - rig.rest, axis=1).max()))
    if distance > 0.0 and not distance <= allowed + SLACK:
        problems.append(f"a vertex moved {distance:.3g}, beyond the controls' reach {allowed:.3g}")
    return problems


def _case(fz: Fuzz, rig: Rig, what: str, names: tuple[str, ...], apply: Callable[[], None],
          undo: Callable[[], None], *, no_input: bool = False, stored: bool = False) -> None:
    """One case: apply, (drop the caches for stored data), update and judge, undo, check the baseline."""
    fz.cases += 1
    before = len(fz.reweights)
    problems = []
    try:
        apply()
        if stored:
            fz.module("blender.update.evaluate").forget()
        problems += _check(fz, rig, names, no_input, len(fz.reweights) > before)
    except Exception as exc:
        problems.append(f"raised {type(exc).__name__}: {exc}")
    finally:
        undo()
        if len(fz.reweights) > before:
            fz.module("blender.binding").reweight(rig.target, rig.deformer)
        if stored:
            fz.module("blender.update.evaluate").forget()
    err = fz.capfd.readouterr().err
    if "Traceback" in err:
        problems.append("printed a traceback: " + err.strip().splitlines()[-1])
    got, status = _update(fz, rig)
    if status != rig.status or not np.allclose(got, rig.baseline, rtol=0.0, atol=1e-6):
        problems.append(f"not restored ({status!r})")
        fz.module("blender.update.evaluate").forget()
        fz.module("blender.binding").reweight(rig.target, rig.deformer)
    fz.capfd.readouterr()
    if problems:
        fz.failures.append(f"{rig.kind} {what}: " + "; ".join(problems))


def _rna_cases(fz: Fuzz, rig: Rig, item, owner: str, no_input: Callable[[str], bool]) -> list[str]:
    """Every writable numeric property of `item` (a deformer or control item), set through RNA and as
    an ID property; returns the properties skipped, with why."""
    skipped = []
    for prop in item.bl_rna.properties:
        name = prop.identifier
        if prop.type not in ("INT", "FLOAT"):
            continue  # booleans, enums, strings, pointers, collections: no number to break
        if prop.is_readonly:
            skipped.append(f"{name}: read-only")
            continue
        label = NAMED_BY.get(name, prop.name or name)
        names = (label, f"'{owner}'") if owner else (label,)
        values = INTS if prop.type == "INT" else FLOATS
        elements = ELEMENTS[prop.array_length] if prop.array_length else (None,)
        for j in elements:
            for value in values:
                for way in ("rna", "id"):
                    what = f"{name}{'' if j is None else f'[{j}]'} = {value} ({way})"
                    apply, undo = _setter(item, name, j, value, way)
                    _case(fz, rig, what, names, apply, undo, no_input=no_input(name))
    return skipped


def _setter(item, name: str, j: int | None, value, way: str) -> tuple[Callable[[], None], Callable[[], None]]:
    """(apply, undo) of one value of property `name` (element `j` of a vector) of `item`, through RNA
    (`way` 'rna') or as an ID property of the property's own type ('id')."""
    old = getattr(item, name) if way == "rna" or name not in item else None  # the value RNA shows
    old = list(old) if j is not None and old is not None else old
    had = name in item
    stored = (list(item[name]) if j is not None else item[name]) if had else None

    def apply() -> None:
        if way == "rna":
            if j is None:
                setattr(item, name, value)
            else:
                setattr(item, name, [value if i == j else v for i, v in enumerate(old)])
        elif j is None:
            item[name] = value
        else:
            if name not in item:
                item[name] = list(old)
            item[name][j] = value

    def undo() -> None:
        if way == "rna":
            setattr(item, name, old)
        elif not had:
            del item[name]
        elif j is None:
            item[name] = stored
        else:  # element-wise: the array keeps its element type
            item[name][j] = stored[j]

    return apply, undo


def _stored_cases(fz: Fuzz, rig: Rig) -> None:
    """Weight and index attributes (one vertex), the file-format stamp, and the kind's ID-property
    arrays, set element-wise with the caches dropped."""
    deformer, mesh = rig.deformer, rig.target.data
    moved = int(np.linalg.norm(rig.baseline - rig.rest, axis=1).argmax())  # a vertex the damage shows on
    for suffix, values in (("w0", FLOATS), ("idx0", INTS)):
        attr_name = f".affdef_{deformer.uid}_{suffix}"
        for value in values:
            apply, undo = _attribute_setter(mesh, attr_name, moved, value)
            _case(fz, rig, f"{attr_name}[{moved}] = {value}", (attr_name,), apply, undo, stored=True)
    for value in INTS:
        apply, undo = _setter(deformer, "file_format", None, value, "id")
        _case(fz, rig, f"file_format = {value}", (NAMED_BY["file_format"],), apply, undo, stored=True)
    arrays = {"CAGE": {"cage_rest_points": (0, 1), "cage_loop_vertices": (0,), "cage_loop_start": (0, 1),
                       "cage_loop_total": (0,), "cage_node_points": (0,), "cage_node_weights": (0,)},
              "BONE": {"bone_rest_segments": (0, 3)}}.get(rig.kind, {})
    for key, elements in arrays.items():
        integer = deformer[key].typecode == "i"
        for j in elements:
            for value in INTS if integer else FLOATS:
                apply, undo = _setter(deformer, key, j, value, "id")
                _case(fz, rig, f"{key}[{j}] = {value}", (key,), apply, undo, stored=True)


def _attribute_setter(mesh, name: str, vertex: int, value) -> tuple[Callable[[], None], Callable[[], None]]:
    attr = mesh.attributes[name]
    old = attr.data[vertex].value

    def apply() -> None:
        mesh.attributes[name].data[vertex].value = value

    def undo() -> None:
        mesh.attributes[name].data[vertex].value = old

    return apply, undo


# -------------------------------------------------------------------------------------------- tests


@pytest.fixture
def fuzz(installed, capfd, monkeypatch) -> Fuzz:
    binding = importlib.import_module(f"{installed.package}.blender.binding")
    calls: list[int] = []
    original = binding.reweight

    def counted(obj, deformer) -> None:  # which cases re-weighted (their reference re-weights too)
        calls.append(1)
        original(obj, deformer)

    monkeypatch.setattr(binding, "reweight", counted)
    return Fuzz(installed, capfd, calls)


@pytest.mark.parametrize("build", [_probe_rig, _cage_rig, _bone_rig], ids=["probe", "cage", "bone"])
def test_hostile_settings_and_stored_data(bl, fuzz, build):
    rig = _ready(bl, fuzz, build)
    assert np.abs(rig.baseline - rig.rest).max() > 0.05, "the rig deforms"
    reach = _reach(rig, rig.deformer.strength)
    moved = float(np.linalg.norm(rig.baseline - rig.rest, axis=1).max())
    assert moved <= MARGIN * reach, (moved, reach)  # the bound holds for the correct shape
    snapshot = fuzz.module("blender.update.snapshot")
    kinds = fuzz.module("blender.kinds")
    base = fuzz.module("blender.kinds.base")
    own = set(kinds.get(rig.kind).properties())
    others = set(kinds.properties()) - own

    def no_input(name: str) -> bool:  # interface or preview state, or another kind's property
        return name in others or snapshot.DECLARED.get(name) in (base.INTERFACE, base.PREVIEW)

    skipped = _rna_cases(fuzz, rig, rig.deformer, "", no_input)
    if rig.item is not None:
        skipped += _rna_cases(fuzz, rig, rig.item, rig.item_name, lambda _name: False)
    _stored_cases(fuzz, rig)
    with fuzz.capfd.disabled():
        print(f"\nfuzz {rig.kind.lower()}: {fuzz.cases} cases, {fuzz.statuses} statuses naming the value, "
              f"{len(fuzz.failures)} failures" + (f"; skipped {', '.join(skipped)}" if skipped else ""))
        for failure in fuzz.failures[:40]:
            print("  " + failure)
    assert not fuzz.failures, f"{len(fuzz.failures)} of {fuzz.cases} cases failed: {fuzz.failures[:5]}"


def _damaged(fz: Fuzz, rig: Rig, damage: Callable[[], None], repair: Callable[[], None], named: str) -> None:
    """`damage` the stored data (caches dropped, as a file load does): the status names `named`, the
    mesh shows its input, nothing prints a traceback; `repair` brings the baseline back."""
    damage()
    fz.module("blender.update.evaluate").forget()
    got, status = _update(fz, rig)
    assert named in status and np.array_equal(got, rig.rest), (named, status)
    assert "Traceback" not in fz.capfd.readouterr().err
    repair()
    fz.module("blender.update.evaluate").forget()
    got, status = _update(fz, rig)
    assert status == rig.status and np.allclose(got, rig.baseline, rtol=0.0, atol=1e-6), status


def _replacing(owner, key: str, bad) -> tuple[Callable[[], None], Callable[[], None]]:
    """(damage, repair) replacing the ID property `owner[key]` by `bad`, then restoring its array (same
    element type: numpy keeps the typecode's)."""
    saved = np.array(owner[key])

    def damage() -> None:
        del owner[key]
        owner[key] = bad

    def repair() -> None:
        del owner[key]
        owner[key] = saved

    return damage, repair


def test_stored_arrays_of_the_wrong_type_or_shape_are_named(bl, fuzz):
    """What the fuzz's values cannot do: a cage's ID-property array replaced by one of another element
    type, another length or no array at all."""
    rig = _ready(bl, fuzz, _cage_rig)
    deformer = rig.deformer
    for key, bad in (("cage_loop_start", [float(i) for i in deformer["cage_loop_start"]]),
                     ("cage_rest_points", "damaged"),
                     ("cage_rest_points", [0.0, 1.0]),
                     ("cage_node_weights", [0.5] * 7),
                     ("cage_node_points", {"x": 1.0})):
        _damaged(fuzz, rig, *_replacing(deformer, key, bad), key)


def test_weight_attributes_of_the_wrong_type_or_missing_are_named(bl, fuzz):
    rig = _ready(bl, fuzz, _probe_rig)
    mesh = rig.target.data
    name = f".affdef_{rig.deformer.uid}_w0"
    saved = np.empty(len(mesh.vertices), dtype=np.float32)
    mesh.attributes[name].data.foreach_get("value", saved)

    def retyped() -> None:
        mesh.attributes.remove(mesh.attributes[name])
        mesh.attributes.new(name, "INT", "POINT")

    def missing() -> None:
        mesh.attributes.remove(mesh.attributes[name])

    def repair() -> None:
        if mesh.attributes.get(name) is not None:
            mesh.attributes.remove(mesh.attributes[name])
        mesh.attributes.new(name, "FLOAT", "POINT").data.foreach_set("value", saved)

    _damaged(fuzz, rig, retyped, repair, f"'{name}' is INT on the POINT domain, not FLOAT on POINT")
    _damaged(fuzz, rig, missing, repair, f"'{name}' is missing")


def test_damaged_bone_rest_segments_are_named_by_the_update_and_by_re_weighting(bl, fuzz):
    """The segments are read by re-weighting; the update checks them too, so damage shows at once."""
    rig = _ready(bl, fuzz, _bone_rig)
    deformer = rig.deformer
    key = "bone_rest_segments"
    _damaged(fuzz, rig, *_replacing(deformer, key, [0.0] * 5), f"'{key}' holds 5 values for 2 bones")
    damage, repair = _replacing(deformer, key, np.where(np.arange(12) == 4, np.nan, np.array(deformer[key])))
    damage()
    deformer.radius = 2.0  # re-weights: refused, naming the segments
    assert f"'{key}' holds a non-finite value, nan at index 4" in deformer.status
    assert np.array_equal(_update(fuzz, rig)[0], rig.rest)
    repair()
    deformer.radius = 1.0
    got, status = _update(fuzz, rig)
    assert status == rig.status and np.allclose(got, rig.baseline, rtol=0.0, atol=1e-6), status
