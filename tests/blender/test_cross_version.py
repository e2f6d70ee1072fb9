"""Files cross Blender versions: a rig of every kind at every usual stack position, saved by an older
Blender (4.2, 4.5, 5.0) with the add-on, opens in the running Blender and plays, renders (`-a`), links
and overrides exactly as it did on the Blender that saved it; and opened here without the add-on it
shows its input with the warning, not a stale shape.

The pipeline matrix (pipeline_matrix.py) does the measuring: its asset process runs on the saving
Blender (the extension installed there afresh), every other process on this one, and each cell is
compared with the asset's own frames as the saving Blender computed them. A file saved by this
Blender and reopened here is the matrix's own "reopened" column (test_pipeline_matrix.py).

Which Blenders save: `AFFINE_SAVING_PYTHONS`, "4.2=/path/python,4.5=/path/python,…" (`make test` sets it
for every suite); only those older than the running Blender are used. Without it the test
skips.
"""

from __future__ import annotations

import os
import subprocess

import bpy
import pytest

from tests.blender import pipeline_matrix

SAVERS_ENV = "AFFINE_SAVING_PYTHONS"
pytestmark = pytest.mark.pipeline_matrix


def _savers() -> list[tuple[str, str]]:
    """(version label, interpreter) of every saving Blender named in the environment."""
    found = []
    for entry in filter(None, os.environ.get(SAVERS_ENV, "").split(",")):
        label, _, python = entry.partition("=")
        found.append((label.strip(), python.strip()))
    return found


def _older(label: str) -> bool:
    return tuple(int(n) for n in label.split(".")[:2]) < tuple(bpy.app.version[:2])


@pytest.mark.parametrize("saver", _savers() or [("none", "")], ids=lambda saver: f"saved-by-{saver[0]}")
def test_a_file_saved_by_an_older_blender_plays_here_as_it_did_there(bl, extension_zip, tmp_path, saver):
    label, python = saver
    if not python:
        pytest.skip(f"{SAVERS_ENV} is not set (`make test` sets it for every suite)")
    if not _older(label):
        pytest.skip(f"Blender {label} is not older than this one ({bpy.app.version_string})")
    if not os.path.exists(python):
        pytest.fail(f"{SAVERS_ENV} names {python} for Blender {label}, which does not exist")
    saver_user = tmp_path / "user_saver"
    saver_user.mkdir()

    def build_asset(script: str) -> subprocess.CompletedProcess:
        # The saving Blender gets the extension installed in a user folder of its own: its Python
        # differs from this one's, and so does where Blender keeps an extension's wheels.
        install = ("import bpy\n"
                   f"assert bpy.ops.extensions.package_install_files(filepath={str(extension_zip)!r}, "
                   "repo='user_default', enable_on_install=True) == {'FINISHED'}\n")
        return bl.run_blender(install + script, python=python,
                              env_extra={"BLENDER_USER_RESOURCES": str(saver_user)})

    bodies = [body for body in pipeline_matrix.plan() if body.table == "positions"]
    run = pipeline_matrix.run(bl.run_blender, tmp_path, bodies, build_asset=build_asset)
    assert run.blender.startswith(label), (run.blender, label)
    # The render's picture is not compared with the asset's: another Blender's Cycles may shade the
    # same meshes differently. The render cells compare the meshes that render evaluated.
    failed = (pipeline_matrix.asset_problems(run) + pipeline_matrix.failures(run)
              + pipeline_matrix.warning_problems(run))
    worst = max((c.error for body in bodies for context in ("local", "overridden", "reopened", "render")
                 if (c := pipeline_matrix.cell(run, body, context)).error is not None), default=0.0)
    print(f"saved by {run.blender}, opened by {bpy.app.version_string}: {len(bodies)} bodies, "
          f"largest difference from the saving Blender's frames {worst:.2g}")
    assert not failed, "\n".join(failed)
