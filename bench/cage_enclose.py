"""(e) Cages made for the mesh (issue #50): our cage deformer added with only the mesh selected makes its
cage. On Suzanne (subdivided twice), the Figure of samples/cage_deform.blend and that figure at 130k
vertices (the core test's mesh): the made cage's faces, stated margin, smallest distance and winding
numbers over every vertex, time to make; then one cage edit (the top half of each cage turned up to
45° about the vertical axis) with the made cage, with a hand-made cage (the sample's own cage; a box
cage for Suzanne) and with Blender's Mesh Deform bound to the same made cage, all in this process:
roughness, how closely the mesh follows the edit, edge distortion, torn edges and bind times.

The scenes, the edit and the metrics are tests/blender/cage_quality.py's (shared with
tests/blender/test_cage_made_quality.py, which asserts on them). A last table repeats the core test's
comparison without Blender (tests/core/enclose_quality.py: the made cage against a box cage of about
the same face count, a common affine motion and a 45° step twist of the cage's upper half).
"""

from __future__ import annotations

import importlib
import math
import sys
import traceback
from pathlib import Path

import numpy as np
import ours
from common import Table

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from tests.blender import cage_quality as cq  # the cases, the edit and the metrics
from tests.core import enclose_quality as eq  # the core-level comparison (numpy only)

FIXTURES = Path(__file__).resolve().parent.parent / "tests" / "fixtures"
BOX_CUTS = 7  # the box cage of the core comparison: 7 × 7 quads per side, 294 quads


def part_e(plan, have_ours: bool, report) -> None:
    cases = plan.e_cases
    print(f"(e) made cages: {', '.join(cases)}", flush=True)
    if not (have_ours and ours.operator_exists(ours.CAGE_OP)):
        report.notes.append(f"(e) `{ours.CAGE_OP}` is not registered: the made-cage part was skipped")
        return
    results: list[cq.CaseResult] = []
    for case in cases:
        try:
            r = cq.measure_case(case, ours.INNER, repeats=plan.e_repeats, precision=plan.precision)
        except Exception as exc:  # one broken case must not hide the others
            traceback.print_exc()
            report.problems.append(f"(e) {case}: {type(exc).__name__}: {exc}")
            continue
        results.append(r)
        print(f"  {cq.LABELS[case]}: {r.faces} faces, make {r.make_median:.2f} s (median of "
              f"{len(r.make_seconds)}), Mesh Deform bind {r.bind.get('mesh_deform', math.nan):.2f} s",
              flush=True)
        _check(r, report)
    if not results:
        return
    made = Table("(e) cages made for the mesh: the cage deformer added with no cage selected",
                 cq.MADE_HEADER)
    for row in cq.made_rows(results):
        made.add(*row)
    made.notes.append(
        "stated margin: the distance the maker promises between every vertex and the cage "
        "(EnclosingCage.margin; in brackets ÷ the mesh's largest extent); smallest distance and "
        "winding numbers over every vertex of the mesh, both diagonals of every quad: check = the "
        "add-on's check_enclosure on the cage the operator made, brute = an independent brute-force "
        "pass (solid angles, point–triangle distances) of tests/blender/cage_quality.py over every "
        f"vertex up to {cq.BRUTE_ALL_VERTICES:,}, over an even sample above")
    made.notes.append(
        f"make: the core's enclosing_cage at the operator's budget ({_budget()} faces; its own check "
        f"included), median of {plan.e_repeats} runs with the range; add: the add operator as an artist "
        "runs it (read the mesh, make, build the cage object, bind)")
    edit = Table("(e) a cage edit with the made cage, a hand-made cage and Mesh Deform on the made cage",
                 cq.EDIT_HEADER)
    for row in cq.edit_rows(results):
        edit.add(*row)
    edit.notes.append(
        f"the edit: every cage vertex turned about the vertical axis through the mesh's bounding-box "
        f"centre by {math.degrees(cq.TWIST_ANGLE):.0f}° × smoothstep(t), t = (z − z_mid) ÷ (z_top − "
        "z_mid) clipped to [0, 1] (the mesh's middle and top heights): the top half of every cage "
        "turns, the lower half stays; the same map for every cage, so the rows of one mesh compare")
    edit.notes.append(
        "roughness p99: 99th percentile over vertices of |d − mean of d over the edge neighbours| ÷ "
        "max |d| (d = deformed − rest, the measure of tests/core/enclose_quality.py); follow RMS: RMS of "
        "|deformed − the edit applied to the mesh directly| ÷ the mesh's largest extent; edge Δl/l: "
        "|edge length change| ÷ rest length over all edges, max and mean; torn: edges longer than "
        f"{cq.TEAR_STRETCH}× the longer of their rest length and their length under the edit applied "
        "directly, or with a non-finite end")
    edit.notes.append(
        "bind: ours, made cage = Rebind (affine_deformer_bind) of the deformer the add operator made; "
        "ours, hand-made cage = the add operator with the cage selected; Mesh Deform: meshdeform_bind "
        f"at precision {plan.precision}, on a copy of the made cage (same vertices and faces)")
    edit.notes.append(
        "hand-made cages: the 38-quad cage of samples/cage_deform.blend (object Cage, rest shape) for "
        "both figures; for Suzanne the 384-quad box cage of tests/blender/cage_field.py")
    report.tables += [made, edit]
    report.summary.append(_summary(results))
    try:
        report.tables.append(_core_table())
    except Exception as exc:
        traceback.print_exc()
        report.problems.append(f"(e) core comparison: {type(exc).__name__}: {exc}")


def _core_table() -> Table:
    """tests/core/test_cage_enclose.py's edit comparison on its fixtures, with the add-on's core."""
    enclose = importlib.import_module(f"{ours.INNER}.core.cage.enclose")
    t = Table("(e) the same without Blender: made cage vs a box cage (tests/core/enclose_quality.py)",
              ["mesh", "cage", "faces", "affine error", "twist roughness p99", "twist rigid residual"])
    for name, label in (("suzanne", "Suzanne (not subdivided)"), ("figure", "Figure")):
        data = np.load(FIXTURES / f"cage_{name}.npz")
        points, triangles = data["points"].astype(np.float64), data["triangles"].astype(np.intp)
        made = enclose.enclosing_cage(points, triangles)
        lo, hi = points.min(axis=0), points.max(axis=0)
        pad = 0.06 * float((hi - lo).max())
        box = eq.box_cage(lo - pad, hi + pad, BOX_CUTS)
        for cage, (x, quads) in (("made", (made.vertices, made.quads)), ("box", box)):
            m = eq.edit_quality(points, triangles, x, quads)
            t.add(f"{label}, {len(points):,} vertices", cage, len(quads), f"{m['affine']:.1e}",
                  f"{m['roughness']:.4f}", f"{m['residual']:.5f}")
    t.notes.append(
        "the add-on's core alone (harmonic weights, face motions, blend): affine error = max |x′ − (M x "
        "+ t)| ÷ size for one shear + stretch + shift of every cage vertex; twist: the cage vertices "
        "above the mesh's centre turned 45° (a step at the centre, not the smooth edit above); roughness "
        "p99 as above (triangle edges); rigid residual: RMS of the best rigid fit ÷ size over the top "
        f"quarter of the mesh; box cage: the mesh's box plus 6% of its size, {BOX_CUTS} × {BOX_CUTS} quads "
        "per side")
    return t


def _budget() -> int | str:
    try:
        return importlib.import_module(f"{ours.INNER}.blender.kinds.cage_tools").DEFAULT_FACES
    except (ImportError, AttributeError):
        return "?"


def _check(r: cq.CaseResult, report) -> None:
    """What must hold for every made cage: anything else makes the run exit 1."""
    label = f"(e) {cq.LABELS[r.case]}"
    if r.problems:
        report.problems.append(f"{label}: the made cage fails its check: {'; '.join(r.problems)}")
    for name, numbers in (("check", r.check), ("brute force", r.brute)):
        if not (abs(numbers["winding_min"] - 1.0) < 1e-6 and abs(numbers["winding_max"] - 1.0) < 1e-6):
            report.problems.append(f"{label}: a vertex is not inside the made cage ({name})")
        if not numbers["smallest"] >= r.margin:
            report.problems.append(f"{label}: a vertex is nearer than the stated margin ({name})")
    if not r.same_as_core:
        report.notes.append(f"{label}: the operator's cage differs from enclosing_cage at the default budget")
    for name, status in r.status.items():
        if status:
            report.notes.append(f"{label}, {cq.METHOD_LABELS[name]}: the deformer reported “{status}”")
    for name, error in r.errors.items():
        report.notes.append(f"{label}, {cq.METHOD_LABELS[name]}: {error}")


def _summary(results: list[cq.CaseResult]) -> str:
    made = "; ".join(f"{cq.LABELS[r.case]} {r.faces} faces in {r.make_median:.2f} s" for r in results)
    ratios = []
    for r in results:
        mine, hand = r.edit.get("ours_made"), r.edit.get("ours_hand")
        md = r.edit.get("mesh_deform")
        if mine and hand:
            rough = mine["roughness_p99"] / hand["roughness_p99"]
            text = (f"{cq.LABELS[r.case]}: roughness made ÷ hand-made {rough:.2f}×, follow RMS "
                    f"{mine['follow_rms']:.4f} vs {hand['follow_rms']:.4f}")
            if md:
                text += (f", Mesh Deform on the made cage: roughness {md['roughness_p99']:.4f} vs ours "
                         f"{mine['roughness_p99']:.4f}, follow RMS {md['follow_rms']:.4f}")
            ratios.append(text)
    inside = all(abs(r.check["winding_min"] - 1) < 1e-6 and abs(r.check["winding_max"] - 1) < 1e-6
                 and r.check["smallest"] >= r.margin for r in results)
    return (f"(e) made cages (median time to make): {made}; "
            + ("every vertex inside with the stated margin" if inside else "NOT every vertex inside")
            + ". Cage edit: " + "; ".join(ratios) + ".")
