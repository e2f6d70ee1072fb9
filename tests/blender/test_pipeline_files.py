"""Issue 38's pipeline cases that go through files, on the rig asset of test_overrides (a probe, a cage
and a bone deformer with keyed controls, and the asset's own positions at frames 1, 12, 24 as the
reference): File ▸ Append of the rig twice into one file; Alembic, USD and FBX exports of the live
deformers (no bake) read back and compared with the evaluated meshes; the modifier's Viewport /
Render toggles as a background render of the saved file sees them; and the rig's armature disabled in
viewports or renders (locally, in a background render, and on overrides), which the bone deformer
follows as the Armature modifier does."""

from __future__ import annotations

import bpy
import numpy as np
import pytest

from tests.blender.pipeline_rig import (
    BODIES,
    FRAMES,
    TOLERANCE,
    assert_plays_as,
    body_positions,
    by_name,
    open_rig,
    overridden,
    override_rig,
    pose,
    save_and_reopen,
)

# ------------------------------------------------------------------------------------------------ append


def test_the_rig_appended_twice_plays_as_the_asset_and_each_copy_on_its_own(asset, bl, tmp_path):
    """File ▸ Append of the rig collection twice: both copies (their own meshes, controls and actions;
    deformers of the same ids) play as the asset; posing the second leaves the first as it was; after
    save and reopen the same."""
    reference = dict(np.load(asset["reference"]))
    for _ in range(2):
        assert bpy.ops.wm.append(directory=asset["asset"] + "/Collection/", filename="Rig") == {"FINISHED"}
    assert {o.name for o in bpy.data.objects} >= {f"{n}{s}" for n in BODIES for s in ("", ".001")}

    def second(name):
        return bpy.data.objects[name + ".001"]

    assert_plays_as(body_positions(bl), reference)
    assert_plays_as(body_positions(bl, second), reference)
    bpy.context.scene.frame_set(12)
    pose(second)
    assert_plays_as(body_positions(bl), reference)
    assert_plays_as(body_positions(bl, second), reference, "posed_")
    save_and_reopen(tmp_path / "appended.blend")
    assert_plays_as(body_positions(bl), reference)
    assert_plays_as(body_positions(bl, second), reference, "posed_")


# ------------------------------------------------------------------------------------------------ exports


def _export(fmt: str, path, evaluation_mode: str) -> None:
    if fmt == "ALEMBIC":
        result = bpy.ops.wm.alembic_export(filepath=str(path), start=1, end=24, as_background_job=False,
                                           evaluation_mode=evaluation_mode)
    else:
        result = bpy.ops.wm.usd_export(filepath=str(path), export_animation=True,
                                       evaluation_mode=evaluation_mode)
    assert result == {"FINISHED"}


def _import(fmt: str, path) -> None:
    if fmt == "ALEMBIC":
        result = bpy.ops.wm.alembic_import(filepath=str(path), as_background_job=False)
    else:
        result = bpy.ops.wm.usd_import(filepath=str(path))
    assert result == {"FINISHED"}


@pytest.mark.parametrize("evaluation_mode", ["RENDER", "VIEWPORT", "RENDER, viewport off"])
@pytest.mark.parametrize(("fmt", "suffix"), [("ALEMBIC", "abc"), ("USD", "usdc")])
def test_an_animated_export_without_baking_holds_the_evaluated_meshes(asset, bl, tmp_path, fmt, suffix,
                                                                       evaluation_mode):
    """Alembic and USD exports of the file with its deformers live (render or viewport evaluation; the
    cage is hidden in renders), imported back into an empty file: each body's points at frames 1, 12,
    24 are the evaluated deformed mesh's (the asset's reference). With our modifiers off in viewports
    (skipped by viewport updates), a render-mode export still evaluates them."""
    reference = open_rig(asset, tmp_path)
    assert_plays_as(body_positions(bl), reference)
    if evaluation_mode == "RENDER, viewport off":
        _set_modifiers("show_viewport", False)()
        evaluation_mode = "RENDER"
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end, scene.frame_step = 1, 24, 1  # USD exports the scene's range
    scene.frame_set(1)
    path = tmp_path / f"rig.{suffix}"
    _export(fmt, path, evaluation_mode)
    bpy.ops.wm.read_homefile(use_empty=True)
    _import(fmt, path)
    found = {}
    for frame in FRAMES:
        bpy.context.scene.frame_set(frame)
        for name in BODIES:
            imported = bl.evaluated_positions(bpy.data.objects[name])
            found[f"{name}/{frame}"] = float(np.abs(imported - reference[f"{name}_{frame}"]).max())
    print(fmt, "export vs evaluated:", found)
    assert max(found.values()) <= 1e-5, found


@pytest.fixture
def fbx_addon():
    """The io_scene_fbx add-on enabled for one test (the bpy module ships it, disabled)."""
    import addon_utils

    if addon_utils.enable("io_scene_fbx", default_set=False) is None:
        pytest.skip("the io_scene_fbx add-on is not in this bpy module")
    yield
    addon_utils.disable("io_scene_fbx", default_set=False)


def test_an_fbx_export_without_baking_holds_the_evaluated_meshes(asset, bl, tmp_path, fbx_addon):
    """FBX (a mesh's modifiers applied at the current frame; FBX holds no per-vertex animation without
    shape keys): each body exported at frame 12 and imported into an empty file has the evaluated
    mesh's world positions."""
    reference = open_rig(asset, tmp_path)
    bpy.context.scene.frame_set(12)
    expected = {}
    for name in BODIES:
        obj = bpy.data.objects[name]
        obj.select_set(True)
        matrix = np.array(obj.matrix_world)
        expected[name] = reference[f"{name}_12"].astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        assert np.abs(bl.evaluated_positions(obj) - reference[f"{name}_12"]).max() <= TOLERANCE
    path = tmp_path / "rig.fbx"
    assert bpy.ops.export_scene.fbx(filepath=str(path), use_selection=True, object_types={"MESH"},
                                    use_mesh_modifiers=True, bake_anim=False) == {"FINISHED"}
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.import_scene.fbx(filepath=str(path)) == {"FINISHED"}
    found = {}
    for name in BODIES:
        obj = bpy.data.objects[name]
        matrix = np.array(obj.matrix_world)
        world = bl.evaluated_positions(obj).astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        found[name] = float(np.abs(world - expected[name]).max())
    print("FBX export vs evaluated:", found)
    assert max(found.values()) <= 1e-5, found


# ------------------------------------------------------------------------------------ render toggles


def _render_variants(bl, tmp_path, variants: dict) -> dict[str, np.ndarray]:
    """Save the open file once per variant (a function changing it, undone by reopening), render frame 12
    of each saved file in one fresh background process (`blender -b file.blend -a`), and return the
    images."""
    source = tmp_path / "source.blend"
    scene = bpy.context.scene
    scene.frame_start = scene.frame_end = 12
    scene.frame_set(5)
    bpy.ops.wm.save_as_mainfile(filepath=str(source))
    for label, change in variants.items():
        bpy.ops.wm.open_mainfile(filepath=str(source), load_ui=False)
        bpy.context.scene.render.filepath = str(tmp_path / f"{label}_")
        change()
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / f"{label}.blend"))
    bl.run_blender(f"""
        enable_addon()
        for label in {list(variants)!r}:
            bpy.ops.wm.open_mainfile(filepath={str(tmp_path)!r} + f"/{{label}}.blend", load_ui=False)
            bpy.ops.render.render(animation=True)
    """)
    images = {}
    for label in variants:
        image = bpy.data.images.load(str(tmp_path / f"{label}_0012.png"))
        pixels = np.empty(len(image.pixels), dtype=np.float32)
        image.pixels.foreach_get(pixels)
        images[label] = pixels
        bpy.data.images.remove(image)
    return images


def _set_modifiers(flag: str, value: bool):
    def change():
        for name in BODIES:
            setattr(bpy.data.objects[name].modifiers[0], flag, value)
    return change


def _remove_deformers(bl):
    def change():
        for name in BODIES:
            body = bpy.data.objects[name]
            assert bl.run_op(bpy.ops.object.affine_deformer_remove, body, index=0) == {"FINISHED"}
    return change


def test_a_background_render_respects_the_modifiers_viewport_and_render_toggles(asset, bl, tmp_path):
    """The saved file rendered in the background: with our modifiers off in viewports (on in renders)
    the frame is the same image as with everything on; off in renders, it is the image of the bodies
    with their deformers removed (their rest shapes), and the two differ."""
    open_rig(asset, tmp_path)
    images = _render_variants(bl, tmp_path, {
        "on": lambda: None,
        "viewport_off": _set_modifiers("show_viewport", False),
        "render_off": _set_modifiers("show_render", False),
        "removed": _remove_deformers(bl),
    })
    assert images["on"].std() > 0.01, "blank render"
    assert np.array_equal(images["viewport_off"], images["on"])
    assert np.array_equal(images["render_off"], images["removed"])
    assert np.abs(images["on"] - images["removed"]).max() > 0.05, "the render shows the deformation"


# ------------------------------------------------------------------------------- disabled armatures


def test_a_bone_deformer_whose_armature_is_disabled_in_viewports_plays(asset, bl, tmp_path):
    """Riggers disable rigs in viewports (the monitor icon); the Armature modifier still deforms, and
    so does ours: posed, and after save and reopen."""
    reference = open_rig(asset, tmp_path)
    bpy.data.objects["Arm"].hide_viewport = True
    assert_plays_as(body_positions(bl), reference)
    bpy.context.scene.frame_set(12)
    pose(by_name)
    assert_plays_as(body_positions(bl), reference, "posed_")
    save_and_reopen(tmp_path / "disabled.blend")
    assert_plays_as(body_positions(bl), reference, "posed_")


@pytest.mark.parametrize("where", ["shot", "asset"])
def test_an_overridden_rig_whose_armature_is_disabled_plays(asset, bl, tmp_path, where):
    """A shot overriding the rig, its armature disabled in viewports and renders there (on the
    override) or in the asset: the bodies play as the asset, posed, and after save and reopen."""
    source = asset["asset"]
    if where == "asset":
        reference = open_rig(asset, tmp_path)
        bpy.data.objects["Arm"].hide_viewport = bpy.data.objects["Arm"].hide_render = True
        source = str(tmp_path / "disabled_asset.blend")
        bpy.ops.wm.save_as_mainfile(filepath=source)
        bpy.ops.wm.read_homefile(use_empty=True)
    else:
        reference = dict(np.load(asset["reference"]))
    override_rig(source)
    if where == "shot":
        overridden("Arm").hide_viewport = overridden("Arm").hide_render = True
    assert overridden("Arm").hide_viewport
    assert_plays_as(body_positions(bl, overridden), reference)
    bpy.context.scene.frame_set(12)
    pose(overridden)
    assert_plays_as(body_positions(bl, overridden), reference, "posed_")
    save_and_reopen(tmp_path / "shot.blend")
    assert overridden("Arm").hide_viewport
    assert_plays_as(body_positions(bl, overridden), reference, "posed_")


def test_a_bone_deformer_whose_armature_is_disabled_in_renders_renders_as_shown(asset, bl, tmp_path):
    """A rig disabled in renders (the camera icon): the background render shows the posed bodies."""
    open_rig(asset, tmp_path)

    def disable_in_renders():
        bpy.data.objects["Arm"].hide_render = True

    images = _render_variants(bl, tmp_path, {"on": lambda: None, "rig_off": disable_in_renders})
    assert np.array_equal(images["rig_off"], images["on"])
