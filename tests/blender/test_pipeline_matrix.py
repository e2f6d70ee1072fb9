"""Issue 47's pipeline matrix (tests/blender/pipeline_matrix.py): every kind at every usual stack
position, and behind every modifier that changes the vertex count or order, in every context the
add-on serves (local, appended, linked and overridden, reopened, a background `-a` render of the
reopened shot), against the asset file's own frames 1, 12 and 24. No cell may be wrong and silent,
torn, or wrong behind a status. The tables are printed (shown when the test fails, or with -s) and
written to a temporary file, or to the file `AFFINE_PIPELINE_MARKDOWN` names (`make pipeline`:
docs/pipeline.md).

Run it alone: `pytest -m pipeline_matrix tests/blender` (about half a minute on Blender 5.0).
"""

from __future__ import annotations

import datetime
import os
from pathlib import Path

import numpy as np
import pytest

from tests.blender import pipeline_matrix

MARKDOWN_ENV = "AFFINE_PIPELINE_MARKDOWN"
pytestmark = pytest.mark.pipeline_matrix


def test_every_context_gives_the_assets_result_or_says_why_not(bl, tmp_path):
    run = pipeline_matrix.run(bl.run_blender, tmp_path)
    failed = pipeline_matrix.problems(run)
    report = pipeline_matrix.markdown(run, datetime.date.today().isoformat(), failed)
    out = Path(os.environ.get(MARKDOWN_ENV) or tmp_path / "pipeline.md")
    out.write_text(report, encoding="utf-8")
    print(report)
    print(f"(written to {out})")
    assert not failed, "\n".join(failed)


def _one_cell(got, status: str = "") -> pipeline_matrix.Cell:
    """The cell of one body whose asset moves by 1 between frames and whose input stays at rest,
    measured as `got(frame, asset, input)` with `status`."""
    body = pipeline_matrix.Body("positions", "first", "probe", {})
    run = pipeline_matrix.Run([body], {}, {}, {body.name: [4, 4]}, "", {}, {})
    for frame in pipeline_matrix.FRAMES:
        asset = np.full((4, 3), float(frame != 1))
        rest = np.zeros((4, 3))
        run.positions.update({f"asset|{body.name}|{frame}": asset, f"input|{body.name}|{frame}": rest,
                              f"local|{body.name}|{frame}": got(frame, asset, rest)})
        run.statuses[f"local|{body.name}|{frame}"] = status
    return pipeline_matrix.cell(run, body, "local")


def test_a_cell_is_right_or_names_why_not_and_shows_its_input():
    """The cell rule the matrix applies (no Blender process): within the tolerance of the asset,
    or a status with the input shown; anything else fails, a status or not."""
    notes = pipeline_matrix.Notes()
    off = pipeline_matrix.TOLERANCE * 2
    cases = {
        "right": _one_cell(lambda frame, asset, rest: asset),
        "wrong and silent": _one_cell(lambda frame, asset, rest: asset + off),
        "named": _one_cell(lambda frame, asset, rest: rest, "linked without an override"),
        "wrong behind a status": _one_cell(lambda frame, asset, rest: asset + off, "stale"),
        "torn": _one_cell(lambda frame, asset, rest: np.zeros((5, 3)) if frame == 12 else asset),
    }
    for verdict, found in cases.items():
        assert found.verdict == verdict, (verdict, found)
        assert found.passes == (verdict in ("right", "named")), verdict
    assert pipeline_matrix.cell_text(cases["right"], notes) == "0"
    assert pipeline_matrix.cell_text(cases["named"], notes) == "status [1]"
    assert pipeline_matrix.cell_text(cases["torn"], notes) == "**torn** 5 vs 4 vertices"
    assert pipeline_matrix.cell_text(cases["wrong and silent"], notes) == "**wrong, silent** 2e-05"
