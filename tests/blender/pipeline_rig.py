"""The rig asset of test_overrides (conftest's `asset` fixture: a probe, a cage and a bone deformer with
keyed controls, built once per session in the running Blender, and each body's evaluated positions at
frames 1, 12 and 24 as the reference), opened in this process for the pipeline tests
(test_pipeline_*.py)."""

from __future__ import annotations

import shutil
from collections.abc import Callable

import bpy
import numpy as np

from tests.blender.test_overrides import BODIES, FRAMES, TOLERANCE, pose

__all__ = [
    "BODIES",
    "FRAMES",
    "TOLERANCE",
    "assert_plays_as",
    "body_positions",
    "by_name",
    "open_rig",
    "pose",
    "save_and_reopen",
]


def by_name(name: str) -> bpy.types.Object:
    return bpy.data.objects[name]


def open_rig(asset: dict, tmp_path) -> dict[str, np.ndarray]:
    """Open a copy of the asset file (the shared one is never saved over); returns the reference
    positions ("<body>_<frame>", and "posed_<body>_<frame>" after `pose`)."""
    path = tmp_path / "rig.blend"
    shutil.copyfile(asset["asset"], path)
    bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    reference = dict(np.load(asset["reference"]))
    for name in BODIES:
        assert np.abs(reference[f"{name}_12"] - reference[f"{name}_1"]).max() > 0.05, "the rig deforms"
    return reference


def save_and_reopen(path) -> None:
    """Save the open file as `path` and open it again (what the next session or a farm worker sees)."""
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)


def body_positions(bl, get: Callable[[str], bpy.types.Object] = by_name, frames=FRAMES,
                   statuses: bool = True) -> dict[str, np.ndarray]:
    """The evaluated positions of each body (`get(name)`) at `frames`, keyed "<body>_<frame>"; with
    `statuses`, every deformer's status is checked to be clean."""
    got = {}
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        for name in BODIES:
            obj = get(name)
            got[f"{name}_{frame}"] = bl.evaluated_positions(obj).copy()
            if statuses:
                assert all(d.status == "" for d in obj.affine_deformers), (obj.name, frame)
    return got


def assert_plays_as(got: dict, reference: dict, prefix: str = "", tolerance: float = TOLERANCE) -> None:
    """Each of `got` ("<body>_<frame>") within `tolerance` of reference[prefix + key]."""
    errors = {key: float(np.abs(value - reference[prefix + key]).max()) for key, value in got.items()}
    assert max(errors.values()) <= tolerance, errors
