"""Issue 47's pipeline matrix: every kind of deformer at every usual stack position, and behind every
modifier that changes the vertex count or order, in every context the add-on serves, measured
against the asset file's own result. Used by tests/blender/test_pipeline_matrix.py, which `make
pipeline` runs to write the tables into docs/pipeline.md.

The plan is a list of bodies (one small rig each, see pipeline_matrix_scene.py); four fresh bpy
processes measure them all: the asset (built once, with the reference), the contexts (local,
appended, linked and overridden, saved as the shot), the shot reopened, and the shot's background
animation render. A cell is a body in a context: the largest error over its vertices at frames 1, 12
and 24, or the status that says why the deformer could not run there.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FRAMES = (1, 12, 24)
#: A right cell is within this of the asset's positions: ~20 float32 ulps at the bodies' extent
#: (|x| ≤ 4, ulp 4.8e-7), room for the float32 paths (the carrier's attributes, the node tree's
#: arithmetic) to round differently from the asset's; a torn or stale mesh is off by 0.01 to 1.
TOLERANCE = 1e-5
KINDS = ("probe", "cage", "bone")
CONTEXTS = ("local", "appended", "overridden", "reopened", "render", "bare_asset", "bare_shot")
CONTEXT_TITLES = {
    "local": "local",
    "appended": "appended",
    "overridden": "linked and overridden",
    "reopened": "overridden, saved, reopened",
    "render": "`-a` render of the reopened shot",
    "bare_asset": "asset without the add-on",
    "bare_shot": "shot without the add-on",
}
#: The prefix of the statuses that hold a body's modifiers' warnings (pipeline_matrix_scene.WARNINGS).
WARNINGS_KEY = "warnings"
#: Contexts where the add-on is not installed: a cell's "status" is the modifier's warning there.
WITHOUT_ADDON = ("bare_asset", "bare_shot")
#: The first Blender with the Warning node (frame_check.py): before it, a modifier without the add-on
#: can only show its input, without a message.
WARNING_NODE_SINCE = (4, 4)

_MIRROR = {"type": "MIRROR", "settings": {"use_mirror_merge": True}}
_SUBSURF = {"type": "SUBSURF", "settings": {"levels": 1, "render_levels": 1}}
#: Stack positions: (row, what the body has around our deformer).
POSITIONS = (
    ("first", {}),
    ("after Mirror", {"before": [_MIRROR]}),
    ("after Mirror + Subdivision", {"before": [_MIRROR, _SUBSURF]}),
    ("after Armature", {"before": [{"type": "ARMATURE"}]}),
    ("after shape keys", {"shape_keys": True}),
    ("before Subdivision", {"after": [_SUBSURF]}),
    ("Preserve Shape on", {"preserve_shape": True}),
)
#: Modifiers before ours that change the vertex count or order: (row, the modifier, extra body
#: settings); the last row is the shape-preserving pass behind one.
MODIFIERS = (
    ("Mirror, merge on", _MIRROR, {}),
    ("Mirror, merge off", {"type": "MIRROR", "settings": {"use_mirror_merge": False}}, {}),
    ("Subdivision Surface", _SUBSURF, {}),
    ("Array", {"type": "ARRAY", "settings": {"count": 2}}, {}),
    ("Solidify", {"type": "SOLIDIFY", "settings": {"thickness": 0.1}}, {}),
    ("Bevel", {"type": "BEVEL", "settings": {"width": 0.1, "segments": 2, "limit_method": "ANGLE"}}, {}),
    ("Weld", {"type": "WELD"}, {"weld_seam": True}),
    ("Mirror, Preserve Shape on", _MIRROR, {"preserve_shape": True}),
)


@dataclass(frozen=True)
class Body:
    """One rig of the asset: a row of a table for one kind. `spec` is what pipeline_matrix_scene.py
    builds: the modifiers before and after our deformer, shape keys, Preserve Shape, a Weld seam."""

    table: str
    row: str
    kind: str
    spec: dict = field(hash=False)

    @property
    def name(self) -> str:
        return f"{self.kind.title()} {self.row}"

    @property
    def count_changes(self) -> bool:
        """A modifier before ours changes the vertex count (the case issue 47 is about)."""
        return any(mod["type"] != "ARMATURE" for mod in self.spec.get("before", ()))


def plan() -> list[Body]:
    """Every body: the stack positions, then the modifiers before ours, each for every kind."""
    bodies = [Body("positions", row, kind, spec) for row, spec in POSITIONS for kind in KINDS]
    bodies += [Body("modifiers", row, kind, {"before": [mod], **extra})
               for row, mod, extra in MODIFIERS for kind in KINDS]
    return bodies


def _plan_json(bodies: list[Body]) -> str:
    """The plan as pipeline_matrix_scene.py reads it: each body's name, kind and spec."""
    return json.dumps([{"name": body.name, "kind": body.kind, **body.spec} for body in bodies])


# ------------------------------------------------------------------------------------------ running


@dataclass
class Run:
    """What the processes measured: positions and statuses keyed "<label>|<body>|<frame>" (labels:
    "asset", "input" and the contexts), each body's vertex counts (its mesh, what reaches ours), the
    Blender version, the seconds each process took, and how the render's picture differs from the
    asset's render of the same frame ("frame", "max", "pixels", "blank")."""

    bodies: list[Body]
    positions: dict[str, np.ndarray]
    statuses: dict[str, str]
    counts: dict[str, list[int]]
    blender: str
    seconds: dict[str, float]
    picture: dict


def _script(call: str, addon: bool = True) -> str:
    """A subprocess script: import the scene module from this folder and run `call` there (with the
    add-on enabled, unless `addon` is False)."""
    return f"""
import sys
sys.path.insert(0, {str(HERE)!r})
{"enable_addon()" if addon else ""}
import pipeline_matrix_scene as scene
scene.{call}
"""


def _steps(plan_json: str, folder: Path) -> dict[str, str]:
    """The four processes' calls (pipeline_matrix_scene.py), each writing `folder`/<step>.npz/.json."""
    asset, shot, pictures = (repr(str(folder / name)) for name in ("asset.blend", "shot.blend", "picture_"))
    out = {step: repr(str(folder / step)) for step in ("asset", "contexts", "reopened", "render", "bare")}
    asset_picture = repr(str(folder / "picture_asset.png"))
    return {
        "asset": f"build_asset({plan_json!r}, {asset}, {out['asset']}, {pictures})",
        "contexts": f"measure_contexts({plan_json!r}, {asset}, {shot}, {out['contexts']}, {pictures})",
        "reopened": f"measure_reopened({plan_json!r}, {shot}, {out['reopened']})",
        "render": f"measure_render({plan_json!r}, {shot}, {out['render']}, {asset_picture})",
        "bare": f"measure_without_addon({plan_json!r}, {asset}, {shot}, {out['bare']})",
    }


def run(run_blender: Callable[..., object], folder: Path, bodies: list[Body] | None = None,
        build_asset: Callable[..., object] | None = None) -> Run:
    """Build the asset and measure every context in five fresh processes, one after the other (each
    needs the file the one before saved); `run_blender(script, env_extra=None)` runs a script in a
    fresh bpy process (conftest.run_blender): the last one with an empty user directory, where the
    add-on is not installed. `build_asset`, when given, runs the first process instead (another
    Blender saves the asset: test_cross_version.py)."""
    bodies = plan() if bodies is None else bodies
    steps = _steps(_plan_json(bodies), folder)
    seconds, positions, statuses = {}, {}, {}
    bare_user = folder / "user_without_addon"
    bare_user.mkdir(exist_ok=True)
    for step, call in steps.items():
        start = time.perf_counter()
        if step == "bare":
            run_blender(_script(call, addon=False), env_extra={"BLENDER_USER_RESOURCES": str(bare_user)})
        elif step == "asset" and build_asset is not None:
            build_asset(_script(call))
        else:
            run_blender(_script(call))
        seconds[step] = time.perf_counter() - start
        positions.update(np.load(folder / f"{step}.npz"))
        statuses.update(json.loads((folder / f"{step}.json").read_text()))
    meta = json.loads((folder / "asset_meta.json").read_text())
    picture = json.loads((folder / "render_picture.json").read_text())
    return Run(bodies, positions, statuses, meta["counts"], meta["blender"], seconds, picture)


# ------------------------------------------------------------------------------------------ cells


@dataclass(frozen=True)
class Cell:
    """A body in a context: the largest error against the asset at FRAMES (None when a vertex count
    differs), against what reaches our modifier ("input"), the statuses seen, the vertex counts
    (got, asset's) of the first frame whose count differs, and whether showing the input without a
    message is all that can be asked there (without the add-on, on a Blender without the Warning
    node)."""

    error: float | None
    input_error: float | None
    status: str
    torn: tuple[int, int] | None = None
    unsaid_input_ok: bool = False

    @property
    def verdict(self) -> str:
        """right: the asset's result. named: a status says why not and the mesh is what reaches our
        modifier. input, no message: the input where nothing can say why (`unsaid_input_ok`). The
        rest fail: torn (a vertex count differs), wrong behind a status (neither the asset's result
        nor the input), wrong and silent."""
        if self.torn is not None:
            return "torn"
        if self.error <= TOLERANCE:
            return "right"
        if not self.status:
            if self.unsaid_input_ok and self.input_error <= TOLERANCE:
                return "input, no message"
            return "wrong and silent"
        return "named" if self.input_error <= TOLERANCE else "wrong behind a status"

    @property
    def passes(self) -> bool:
        return self.verdict in ("right", "named", "input, no message")


def cell(run: Run, body: Body, context: str) -> Cell:
    """`body` in `context` against the asset's own frames (and its input, with our modifier off)."""
    errors, input_errors, statuses = [], [], []
    for frame in FRAMES:
        got = run.positions[f"{context}|{body.name}|{frame}"]
        expected = run.positions[f"asset|{body.name}|{frame}"]
        status = run.statuses[f"{context}|{body.name}|{frame}"]
        if status and status not in statuses:
            statuses.append(status)
        if got.shape != expected.shape:
            return Cell(None, None, " / ".join(statuses), (len(got), len(expected)))
        errors.append(float(np.abs(got - expected).max()))
        input_errors.append(float(np.abs(got - run.positions[f"input|{body.name}|{frame}"]).max()))
    unsaid = context in WITHOUT_ADDON and not has_warning_node(run.blender)
    return Cell(max(errors), max(input_errors), " / ".join(statuses), unsaid_input_ok=unsaid)


def has_warning_node(blender: str) -> bool:
    """Whether the Blender of version string `blender` ("4.2.23 LTS") has the Warning node."""
    major, minor = (int(part) for part in blender.split()[0].split(".")[:2])
    return (major, minor) >= WARNING_NODE_SINCE


def asset_problems(run: Run) -> list[str]:
    """What would make the matrix meaningless: a status in the asset itself, a body that does not
    deform between the frames, a modifier before ours that leaves the vertex count as it was."""
    problems = []
    for body in run.bodies:
        at = {frame: run.positions[f"asset|{body.name}|{frame}"] for frame in FRAMES}
        if any(run.statuses[f"asset|{body.name}|{frame}"] for frame in FRAMES):
            problems.append(f"{body.name}: a status in the asset")
        if min(np.abs(at[frame] - at[1]).max() for frame in FRAMES[1:]) < 0.05:
            problems.append(f"{body.name}: does not deform between frames {FRAMES}")
        mesh, reaching = run.counts[body.name]
        if body.count_changes and mesh == reaching:
            problems.append(f"{body.name}: the modifiers before ours keep {mesh} vertices")
    return problems


def failures(run: Run) -> list[str]:
    """Every cell that fails, as '<body> in <context>: <verdict> (...)'."""
    found = []
    for body in run.bodies:
        for context in CONTEXTS:
            found_cell = cell(run, body, context)
            if not found_cell.passes:
                found.append(f"{body.name} in {CONTEXT_TITLES[context]}: {found_cell.verdict} "
                             f"({_describe(found_cell)})")
    return found


def _describe(found: Cell) -> str:
    parts = []
    if found.torn is not None:
        parts.append(f"{found.torn[0]} vertices, the asset {found.torn[1]}")
    else:
        parts.append(f"error {found.error:.3g}, against the input {found.input_error:.3g}")
    if found.status:
        parts.append(f"status {found.status!r}")
    return "; ".join(parts)


# ------------------------------------------------------------------------------------------ tables


class Notes:
    """The statuses quoted in the tables, numbered in order of first appearance."""

    def __init__(self) -> None:
        self.numbers: dict[str, int] = {}

    def ref(self, status: str) -> str:
        number = self.numbers.setdefault(status, len(self.numbers) + 1)
        return f"[{number}]"


def cell_text(found: Cell, notes: Notes) -> str:
    """A cell as the tables show it (see `markdown` for the legend)."""
    note = f" {notes.ref(found.status)}" if found.status else ""
    verdict = found.verdict
    if verdict == "torn":
        return f"**torn** {found.torn[0]} vs {found.torn[1]} vertices{note}"
    if verdict == "right":
        return ("0" if found.error == 0 else f"{found.error:.1e}") + note
    if verdict == "named":
        return f"input, warning{note}" if found.unsaid_input_ok or "not running" in found.status \
            else f"status{note}"
    if verdict == "input, no message":
        return "input (no Warning node)"
    if verdict == "wrong and silent":
        return f"**wrong, silent** {found.error:.2g}"
    return f"**wrong** {found.error:.2g}{note}"


def table(run: Run, which: str, notes: Notes) -> str:
    """The markdown table of the bodies of `which` ("positions" or "modifiers"): a row per body."""
    first = {"positions": "stack position", "modifiers": "modifier before ours"}[which]
    header = ["kind", first, "vertices", *(CONTEXT_TITLES[c] for c in CONTEXTS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for body in (b for b in run.bodies if b.table == which):
        mesh, reaching = run.counts[body.name]
        cells = [cell_text(cell(run, body, context), notes) for context in CONTEXTS]
        lines.append("| " + " | ".join([body.kind, body.row, f"{mesh} → {reaching}", *cells]) + " |")
    return "\n".join(lines)


def picture_problems(run: Run) -> list[str]:
    """The asset's render must show the rigs; and when every render cell is right, the render's
    picture must be the asset's: the measured meshes are then those the picture shows (a check on
    `RenderCapture`)."""
    found = ["the asset's render shows nothing"] if run.picture["blank"] else []
    right = all(cell(run, body, "render").verdict == "right" for body in run.bodies)
    if right and run.picture["max"] > 1e-6:
        found.append(f"every render cell is right, but {run.picture['pixels']} pixels of the render's "
                     f"frame {run.picture['frame']} differ from the asset's")
    return found


def warning_problems(run: Run) -> list[str]:
    """A warning icon on a modifier where the add-on runs and nothing is wrong: artists learn to ignore
    the icon, then miss the one that matters (the add-on not running). Any warning in a context with
    the add-on fails, whatever the cell's verdict."""
    found = []
    for key, text in run.statuses.items():
        label, _, rest = key.partition("|")
        if label != WARNINGS_KEY or not text:
            continue
        context, name, frame = rest.split("|")
        if context not in WITHOUT_ADDON and context != "input":
            found.append(f"{name} in {CONTEXT_TITLES.get(context, context)} at frame {frame}: a modifier "
                         f"warns \"{text}\"")
    return found


def problems(run: Run) -> list[str]:
    """Everything that fails: the asset's problems, the pictures', every failing cell and every warning
    where the add-on runs."""
    return asset_problems(run) + picture_problems(run) + failures(run) + warning_problems(run)


def markdown(run: Run, date: str, failed: list[str]) -> str:
    """The whole report: what is measured, both tables, the statuses they quote and what `failed`
    (`problems(run)`) beyond the bold cells of the tables."""
    notes = Notes()
    positions, modifiers = table(run, "positions", notes), table(run, "modifiers", notes)
    took = ", ".join(f"{step} {seconds:.0f} s" for step, seconds in run.seconds.items())
    cells = failures(run)
    beyond = [line for line in failed if line not in cells]
    lines = [
        "# Pipeline matrix: every context against the asset's own result",
        "",
        "Generated by `make pipeline` (tests/blender/test_pipeline_matrix.py, which writes this file",
        "when `AFFINE_PIPELINE_MARKDOWN` names it); do not edit by hand.",
        "",
        f"Blender {run.blender}, {date}; the run took {sum(run.seconds.values()):.0f} s ({took}).",
        "",
        *LEGEND,
        "",
        f"The render's picture of frame {run.picture['frame']} beside the asset's own render of it (same "
        f"camera and settings): {run.picture['pixels']} pixels differ (largest difference "
        f"{run.picture['max']:.2g}).",
        "",
        "## Stack positions",
        "",
        positions,
        "",
        "## Modifiers before ours that change the vertex count or order",
        "",
        modifiers,
        "",
    ]
    if notes.numbers:
        lines += ["## Statuses", "", *(f"{n}. {status}" for status, n in notes.numbers.items()), ""]
    lines += ["## Failures", "", f"{len(cells)} of {len(run.bodies) * len(CONTEXTS)} cells fail (in bold)."]
    lines += ["", *(f"- {line}" for line in beyond)] if beyond else []
    return "\n".join([*lines, ""])


LEGEND = """\
## What is measured

The asset file holds a collection "Rig" with one small rig per table row and kind: a gridded box of
218 vertices (x from -1 to 2: not symmetric about its mirror plane, with one grid line on it for
Mirror's merge) deformed by our deformer with keyed controls: probes, two keyed Empties; cage, a box
cage whose object and shape key are keyed (hidden in renders, as riggers hide cages); bones, an
armature of two keyed bones weighted by distance. *after Armature*: an Armature modifier with its own
keyed armature before ours; *after shape keys*: a keyed shape key value; *before Subdivision*: ours
first, Subdivision Surface after it; *Weld*: the box split along one grid line, which Weld merges,
its vertices sorted along x (so the merge shifts the indices after the seam).
The reference is the asset's own evaluated mesh at frames 1, 12 and 24, recorded in the process that
built it; the file is saved at frame 5. Column *vertices*: the mesh's vertex count → what reaches our
deformer.

Contexts (columns); the first four visit the frames in the order 24, 1, 12:

- *local*: the asset opened in a fresh process;
- *appended*: File ▸ Append of "Rig" into a new file (the same process);
- *linked and overridden*: "Rig" linked into a new file and overridden as Object ▸ Library Override ▸
  Make does (the same process), then saved at frame 5 as the shot;
- *overridden, saved, reopened*: the shot opened in a fresh process;
- *`-a` render*: the shot rendered in a fresh process as `blender -b shot.blend -a` does
  (`render.render(animation=True)`: frames 1 to 24, Cycles, 1 sample, 96 × 96 pixels). The meshes
  are read from the render's own depsgraph at frames 1, 12 and 24 (`RenderCapture` in
  tests/blender/pipeline_matrix_scene.py says how, and how that was checked against the pictures);
- *asset / shot without the add-on*: the asset and the reopened shot opened in a fresh process whose
  user directory has no add-on (a farm worker or a colleague without it). Every rig is animated and
  the files were saved at frame 5, so at frames 1, 12 and 24 nothing is right: each modifier must
  show its input, with its warning (the "status" there: `NodesModifier.node_warnings`) on Blender 4.4
  and newer — *input, warning [n]* — and without one on 4.2, which has no Warning node — *input (no
  Warning node)*.

A cell is the largest distance between a vertex and the asset's (object space, Blender units; the
boxes are 3 long) over frames 1, 12 and 24: right when at most 1e-5 (*0*: bit for bit). Otherwise:

- *status [n]* (*input, warning [n]* without the add-on): the deformer's status or the modifier's
  warning (listed below) says why it cannot run there, and the mesh is what reaches our modifier,
  passed on through the rest of the stack: allowed;
- **wrong, silent**: another mesh and no status: a failure;
- **wrong** *[n]*: a status, but the mesh is neither the asset's result nor the input: a failure;
- **torn**: another vertex count: a failure.\
""".splitlines()
