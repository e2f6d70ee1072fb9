"""A rig updated in its asset file after a shot overrode it: on reopening the shot, Blender resyncs the
override (its hierarchy changed: a new probe) and the shot plays the updated asset — the new probe
included, the shot's own posing kept — with every step in a fresh process and the files on disk."""

from __future__ import annotations

import json
import shutil

from tests.blender.test_overrides import _COMMON, _LINK, REOPEN_AND_MEASURE, TOLERANCE

_SHOT = _COMMON + _LINK + """
bpy.ops.wm.read_homefile(use_empty=True)
link_and_override({asset!r})
bpy.context.scene.frame_set(12)
override("Cage").location.y += 0.3  # the shot's own posing, to be kept through the resync
bpy.ops.wm.save_as_mainfile(filepath={shot!r})
"""

_UPDATE_ASSET = _COMMON + """
bpy.ops.wm.open_mainfile(filepath={asset!r}, load_ui=False)
scene = bpy.context.scene
rig = bpy.data.collections["Rig"]
p3 = bpy.data.objects.new("P3", None)
p3.location = (0.0, 0.0, 1.6)
rig.objects.link(p3)
for frame, z in ((1, 1.6), (24, 2.4)):
    p3.location.z = z
    p3.keyframe_insert("location", frame=frame)
scene.frame_set(1)
body = bpy.data.objects["ProbeBody"]
body.affine_deformers[0].probes.add().object = p3
with bpy.context.temp_override(active_object=body, object=body, selected_objects=[body]):
    assert bpy.ops.object.affine_deformer_bind(index=0) == {{"FINISHED"}}
scene.frame_set(5)
bpy.ops.wm.save_mainfile()
reference = {{}}
scene.frame_set(12)
bpy.data.objects["Cage"].location.y += 0.3  # as the shot posed it
for frame in (1, 12, 24):
    scene.frame_set(frame)
    for name in BODIES:
        reference[f"{{name}}_{{frame}}"] = positions(bpy.data.objects[name])
np.savez({reference!r}, **reference)
"""

_REOPEN = _COMMON + _LINK + REOPEN_AND_MEASURE + """
body = override("ProbeBody")
probes = [item.object.name if item.object else None for item in body.affine_deformers[0].probes]
local = [item.object.library is None for item in body.affine_deformers[0].probes if item.object]
json.dump({{"errors": errors, "statuses": statuses, "probes": probes, "local": local}}, open({out!r}, "w"))
"""


def test_a_shot_plays_the_updated_asset_after_the_override_resyncs(asset, tmp_path, bl):
    library = tmp_path / "asset.blend"
    shutil.copyfile(asset["asset"], library)  # the session's asset stays as it is for other tests
    shot, reference, out = tmp_path / "shot.blend", tmp_path / "reference.npz", tmp_path / "reopen.json"
    bl.run_blender(_SHOT.format(asset=str(library), shot=str(shot)))
    bl.run_blender(_UPDATE_ASSET.format(asset=str(library), reference=str(reference)))
    bl.run_blender(_REOPEN.format(shot=str(shot), reference=str(reference), out=str(out), prefix="",
                                  label=""))
    with open(out) as file:
        result = json.load(file)
    print("shot vs updated asset:", json.dumps(result["errors"], indent=1))
    assert set(result["statuses"].values()) == {""}, result["statuses"]
    assert result["probes"] == ["P1", "P2", "P3"], result["probes"]
    assert all(result["local"]), "the probes are the shot's overrides, not the linked objects"
    assert max(result["errors"].values()) <= TOLERANCE, result["errors"]
