"""Bake: the deformer's result as a PC2 cache (Mesh Cache modifier) or keyed shape keys, played back
without the add-on (fresh process, add-on never installed), through Alembic export + import, un-baked
back to the live deformer, and left untouched by failures and bad requests."""

from __future__ import annotations

import importlib
import struct

import bpy
import numpy as np
import pytest

FRAMES = (1, 10, 20)
TOL = 1e-5


def _module(installed, name: str):
    return importlib.import_module(f"{installed.package}.blender.{name}")


def _keyframe(obj, frame: int, location=None, rotation=None, scale=None) -> None:
    for path, value in (("location", location), ("rotation_euler", rotation), ("scale", scale)):
        if value is not None:
            setattr(obj, path, value)
            obj.keyframe_insert(path, frame=frame)


def _scene(bl, tmp_path, save: bool = True):
    """A small cube (152 vertices) bent and twisted by two animated probes over frames 1..20."""
    target = bl.grid_cube(cuts=4)
    a, b = bl.empty("A", (1.2, 0.0, 0.0)), bl.empty("B", (-1.2, 0.0, 0.0))
    deformer = bl.add_probe_deformer(target, [a, b], weight_mode="INVERSE_DISTANCE")
    _keyframe(a, 1, (1.2, 0, 0), (0, 0, 0), (1, 1, 1))
    _keyframe(a, 10, (1.5, 0.2, 0.3), (0.3, 0.0, 1.4), (1.4, 1, 1))
    _keyframe(a, 20, (1.0, -0.5, 0.2), (0.5, 0.2, 2.8), (1, 0.6, 1))
    _keyframe(b, 1, (-1.2, 0, 0), (0, 0, 0))
    _keyframe(b, 20, (-1.0, 0.3, -0.5), (-1.2, 0.3, 0))
    if save:
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "bake.blend"))
    return target, deformer


def _live(bl, target, frames=FRAMES) -> dict[int, np.ndarray]:
    out = {}
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        out[frame] = bl.evaluated_positions(target).copy()
    return out


def _bake(bl, target, **kwargs):
    return bl.run_op(bpy.ops.object.affine_deformer_bake, target, **kwargs)


def _stack(obj) -> list[tuple]:
    return [(m.name, m.type, m.show_viewport, m.show_render) for m in obj.modifiers]


# ------------------------------------------------------------------------------------------------ PC2


def _check_baked_equals_live(bl, target, live: dict, tmp_path) -> None:
    """The baked result equals the live one at FRAMES: in this process, in a fresh process without the
    add-on (after saving the open file), and after an Alembic round trip."""
    baked = _live(bl, target)
    for frame in FRAMES:
        assert np.abs(baked[frame] - live[frame]).max() <= TOL, f"in-process frame {frame}"

    bpy.ops.wm.save_mainfile()
    got = _play_back_without_addon(bl, tmp_path, tmp_path / "bake.blend")
    for frame in FRAMES:
        assert np.abs(got[f"blend{frame}"] - live[frame]).max() <= TOL, f"fresh process, frame {frame}"
        assert np.abs(got[f"abc{frame}"] - live[frame]).max() <= TOL, f"Alembic round trip, frame {frame}"


def test_pc2_file_layout_round_trip_and_atomic_writes(installed, tmp_path):
    pc2 = _module(installed, "tools.pc2")
    rng = np.random.default_rng(3)
    points = rng.normal(size=(4, 5, 3)).astype(np.float32)
    path = tmp_path / "c.pc2"
    pc2.write_pc2(path, points, start_frame=7.0, sample_rate=0.5)
    raw = path.read_bytes()
    assert len(raw) == 32 + 4 * 5 * 12
    assert struct.unpack("<12siiffi", raw[:32]) == (b"POINTCACHE2\0", 1, 5, 7.0, 0.5, 4)
    assert np.array_equal(np.frombuffer(raw[32:], "<f4").reshape(4, 5, 3), points)
    got, start, rate = pc2.read_pc2(path)
    assert (start, rate) == (7.0, 0.5) and np.array_equal(got, points)

    # An aborted or failed writer leaves the previous file byte-identical and no temporary behind.
    with pytest.raises(pc2.PC2Error, match="shape"), pc2.PC2Writer(path, 5) as writer:
        writer.add(points[0])
        writer.add(points[0, :3])
    assert path.read_bytes() == raw
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.pc2"]
    with pytest.raises(pc2.PC2Error, match="non-finite"), pc2.PC2Writer(path, 5) as writer:
        writer.add(np.full((5, 3), np.nan))
    assert path.read_bytes() == raw

    (tmp_path / "bad.pc2").write_bytes(b"POINTCACHE3\0" + raw[12:])
    with pytest.raises(pc2.PC2Error, match="signature"):
        pc2.read_pc2(tmp_path / "bad.pc2")
    (tmp_path / "short.pc2").write_bytes(raw[:-4])
    with pytest.raises(pc2.PC2Error, match="announces"):
        pc2.read_pc2(tmp_path / "short.pc2")


_PLAYBACK = """
    import numpy as np
    assert not hasattr(bpy.types.Object, "affine_deformers"), "the add-on must not be present"
    bpy.ops.wm.open_mainfile(filepath={blend!r}, load_ui=False)
    assert not hasattr(bpy.types.Object, "affine_deformers")
    def positions(obj):
        mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        return co.reshape(-1, 3)
    result = {{}}
    for frame in (20, 1, 10):
        bpy.context.scene.frame_set(frame)
        result[f"blend{{frame}}"] = positions(bpy.data.objects["Cube"])
    bpy.ops.wm.alembic_export(filepath={abc!r}, start=1, end=20, evaluation_mode="RENDER",
                              as_background_job=False)
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 20
    bpy.ops.wm.alembic_import(filepath={abc!r}, as_background_job=False)
    imported = bpy.data.objects["Cube"]
    assert any(m.type == "MESH_SEQUENCE_CACHE" for m in imported.modifiers)
    for frame in (20, 1, 10):
        bpy.context.scene.frame_set(frame)
        result[f"abc{{frame}}"] = positions(imported)
    np.savez({out!r}, **result)
"""


def _play_back_without_addon(bl, tmp_path, blend) -> dict:
    """Open `blend` in a fresh bpy whose user directory never had the add-on; positions at FRAMES from
    the .blend and from an Alembic export of it, imported back."""
    empty_user = tmp_path / "plain_user"
    empty_user.mkdir()
    out = tmp_path / "playback.npz"
    bl.run_blender(_PLAYBACK.format(blend=str(blend), abc=str(tmp_path / "bake.abc"), out=str(out)),
                   env_extra={"BLENDER_USER_RESOURCES": str(empty_user)})
    return dict(np.load(out))


def test_pc2_bake_plays_back_without_the_addon_and_through_alembic(bl, installed, tmp_path):
    target, deformer = _scene(bl, tmp_path)
    all_frames = range(1, 21)
    live = _live(bl, target, all_frames)
    assert np.abs(live[10] - live[1]).max() > 0.2, "the scene must actually deform"
    live_mod = target.modifiers[0]
    bpy.context.scene.frame_set(7)

    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        # As the panel button runs it; without a window, invoke runs the bake to the end at once.
        assert bpy.ops.object.affine_deformer_bake("INVOKE_DEFAULT", index=0, mode="PC2") == {"FINISHED"}

    assert bpy.context.scene.frame_current == 7, "the original frame is restored"
    assert "affdef" not in "".join(o.name for o in bpy.data.objects), "capture object removed"
    cache_path = tmp_path / "Cube_Probe_Deformer.pc2"
    samples, start, rate = _module(installed, "tools.pc2").read_pc2(cache_path)
    assert samples.shape == (20, len(target.data.vertices), 3) and (start, rate) == (1.0, 1.0)
    for frame in all_frames:
        assert np.abs(samples[frame - 1] - live[frame]).max() <= TOL, f"sample of frame {frame}"

    cache = target.modifiers[0]
    assert [m.type for m in target.modifiers] == ["MESH_CACHE", "NODES"], "cache placed where ours was"
    assert target.modifiers[1] == live_mod and not live_mod.show_viewport and not live_mod.show_render
    assert not deformer.show_viewport and not deformer.show_render
    assert (cache.cache_format, cache.filepath, cache.deform_mode) == ("PC2", "//Cube_Probe_Deformer.pc2",
                                                                        "OVERWRITE")
    assert (cache.play_mode, cache.time_mode, cache.frame_start) == ("SCENE", "FRAME", 1.0)
    state = _module(installed, "tools.bake").bake_state(deformer)
    assert state["mode"] == "PC2" and (state["frame_start"], state["frame_end"]) == (1, 20)

    # With the add-on still enabled the cache replaces the live result exactly.
    _check_baked_equals_live(bl, target, live, tmp_path)


@pytest.mark.attributes  # inspects the attribute store (conftest: skipped on POSITIONS)
def test_pc2_bake_keeps_modifiers_below_live_and_captures_only_our_deformer(bl, installed, tmp_path):
    target, deformer = _scene(bl, tmp_path)
    above = target.modifiers.new("Displace", "DISPLACE")
    above.strength = 0.3
    target.modifiers.move(len(target.modifiers) - 1, 0)
    below = target.modifiers.new("Subdivision", "SUBSURF")
    below.levels = 1
    bake = _module(installed, "tools.bake")
    job = bake.BakeJob(bpy.context, target, 0, "PC2", 1, 20, "")
    assert len(job.warnings) == 1 and "(Displace)" in job.warnings[0] and "Subdivision" not in job.warnings[0]

    above.show_viewport = above.show_render = False  # nothing above ours moves vertices: exact bake
    live = _live(bl, target)
    rest = bl.rest_positions(target)
    offsets = {}
    for frame in FRAMES:
        bpy.context.scene.frame_set(frame)
        offsets[frame] = installed.storage.read_offsets(target.data, deformer.uid).copy()
    above.show_viewport = above.show_render = True  # enabled again: its effect must not leak in
    assert _bake(bl, target, index=0, mode="PC2") == {"FINISHED"}
    samples, _start, _rate = _module(installed, "tools.pc2").read_pc2(tmp_path / "Cube_Probe_Deformer.pc2")
    for frame in FRAMES:
        assert np.abs(samples[frame - 1] - (rest + offsets[frame])).max() <= TOL, "only our deformer"
    assert [m.type for m in target.modifiers] == ["DISPLACE", "MESH_CACHE", "NODES", "SUBSURF"]

    above.show_viewport = above.show_render = False
    baked = _live(bl, target)
    for frame in FRAMES:
        assert len(live[frame]) > len(rest), "the subdivision below is evaluated"
        assert np.abs(baked[frame] - live[frame]).max() <= TOL, f"subdivided result, frame {frame}"


# ----------------------------------------------------------------------------------------- shape keys


def test_shape_key_bake_plays_back_without_the_addon_and_through_alembic(bl, installed, tmp_path):
    target, deformer = _scene(bl, tmp_path)
    mesh = target.data
    mesh.shape_keys or target.shape_key_add(name="Basis", from_mix=False)
    user_key = target.shape_key_add(name="Lift", from_mix=False)  # the artist's own key stays additive
    co = bl.rest_positions(target)
    co[:, 2] += 0.1
    user_key.data.foreach_set("co", co.ravel())
    user_key.value = 0.5
    live = _live(bl, target)
    bpy.context.scene.frame_set(4)

    assert _bake(bl, target, index=0, mode="SHAPE_KEYS") == {"FINISHED"}

    assert bpy.context.scene.frame_current == 4
    blocks = mesh.shape_keys.key_blocks
    names = [f"Probe Deformer f{f:04d}" for f in range(1, 21)]
    assert [b.name for b in blocks] == ["Basis", "Lift", *names]
    assert not deformer.show_viewport and not deformer.show_render
    scene = bpy.context.scene
    for frame, subframe, expected in ((10, 0.0, {9: 0, 10: 1, 11: 0}), (10, 0.5, {10: 0.5, 11: 0.5}),
                                      (1, 0.0, {1: 1, 2: 0}), (20, 0.0, {19: 0, 20: 1}),
                                      (-5, 0.0, {1: 1, 2: 0}), (30, 0.0, {19: 0, 20: 1})):
        scene.frame_set(frame, subframe=subframe)
        values = {f: blocks[names[f - 1]].value for f in range(1, 21)}
        for f, value in values.items():
            assert value == pytest.approx(expected.get(f, 0.0), abs=1e-6), (frame, subframe, f)
    _check_baked_equals_live(bl, target, live, tmp_path)


# ------------------------------------------------------------------------------------- un-bake, re-bake


@pytest.mark.parametrize("mode", ["PC2", "SHAPE_KEYS"])
def test_unbake_brings_the_live_deformer_back_and_rebake_replaces(bl, installed, tmp_path, mode):
    target, deformer = _scene(bl, tmp_path)
    live = _live(bl, target)
    stack = _stack(target)
    actions = set(bpy.data.actions.keys())
    assert _bake(bl, target, index=0, mode=mode) == {"FINISHED"}
    assert _bake(bl, target, index=0, mode=mode, frame_start=5, frame_end=12) == {"FINISHED"}  # re-bake
    state = _module(installed, "tools.bake").bake_state(deformer)
    assert (state["frame_start"], state["frame_end"]) == (5, 12)
    if mode == "PC2":
        assert [m.type for m in target.modifiers] == ["MESH_CACHE", "NODES"]
        assert len(_module(installed, "tools.pc2").read_pc2(tmp_path / "Cube_Probe_Deformer.pc2")[0]) == 8
    else:
        assert [b.name for b in target.data.shape_keys.key_blocks] == [
            "Basis", *(f"Probe Deformer f{f:04d}" for f in range(5, 13))]
        bpy.context.scene.frame_set(8)
        assert target.data.shape_keys.key_blocks["Probe Deformer f0008"].value == 1.0, "curves follow"
    baked = _live(bl, target, (10,))
    assert np.abs(baked[10] - live[10]).max() <= TOL

    assert bl.run_op(bpy.ops.object.affine_deformer_unbake, target, index=0) == {"FINISHED"}
    assert _stack(target) == stack and deformer.show_viewport and deformer.show_render
    assert target.data.shape_keys is None
    assert set(bpy.data.actions.keys()) == actions, "the action the bake created is gone"
    assert _module(installed, "tools.bake").bake_state(deformer) is None
    if mode == "PC2":
        assert (tmp_path / "Cube_Probe_Deformer.pc2").exists(), "the cache file stays on disk"
    after = _live(bl, target)
    for frame in FRAMES:
        assert np.array_equal(after[frame], live[frame]), f"live again, frame {frame}"
    with pytest.raises(RuntimeError, match="not baked"):
        bl.run_op(bpy.ops.object.affine_deformer_unbake, target, index=0)


# -------------------------------------------------------------------------------- failures and errors


@pytest.mark.parametrize("mode", ["PC2", "SHAPE_KEYS"])
def test_a_failure_mid_bake_leaves_the_object_as_it_was(bl, installed, tmp_path, monkeypatch, mode):
    target, deformer = _scene(bl, tmp_path)
    cache_path = tmp_path / "Cube_Probe_Deformer.pc2"
    cache_path.write_bytes(b"previous cache")
    bake = _module(installed, "tools.bake")
    real = bake._Capture.positions
    calls = []

    def failing(self, depsgraph):
        calls.append(1)
        if len(calls) == 6:
            raise RuntimeError("disk on fire")
        return real(self, depsgraph)

    monkeypatch.setattr(bake._Capture, "positions", failing)
    stack, objects = _stack(target), set(bpy.data.objects.keys())
    bpy.context.scene.frame_set(3)
    with pytest.raises(RuntimeError, match="disk on fire"):
        _bake(bl, target, index=0, mode=mode)
    assert len(calls) == 6
    assert bpy.context.scene.frame_current == 3
    assert _stack(target) == stack and deformer.show_viewport and deformer.show_render
    assert target.data.shape_keys is None and bake.bake_state(deformer) is None
    assert set(bpy.data.objects.keys()) == objects
    assert cache_path.read_bytes() == b"previous cache"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["Cube_Probe_Deformer.pc2", "bake.blend"]


def test_bad_requests_are_refused_with_clear_messages_and_change_nothing(bl, installed, tmp_path):
    target, _deformer = _scene(bl, tmp_path, save=False)
    stack = _stack(target)
    with pytest.raises(RuntimeError, match="not saved"):
        _bake(bl, target, index=0, mode="PC2")
    with pytest.raises(RuntimeError, match=r"Bad frame range 10\.\.5"):
        _bake(bl, target, index=0, mode="SHAPE_KEYS", frame_start=10, frame_end=5)
    with pytest.raises(RuntimeError, match="no affine deformer #3"):
        _bake(bl, target, index=3, mode="SHAPE_KEYS")
    unbound = target.affine_deformers.add()
    unbound.name = "Loose"
    with pytest.raises(RuntimeError, match="'Loose' is not bound"):
        _bake(bl, target, index=1, mode="SHAPE_KEYS")
    target.affine_deformers.remove(1)

    # A probe with a non-finite scale at frame 6: the bake stops there instead of baking the rest
    # shape. (Scaled to zero it deforms, collapsing what it holds: that bakes as it shows.)
    probe = bpy.data.objects["B"]
    _keyframe(probe, 5, scale=(1, 1, 1))
    _keyframe(probe, 6, scale=(float("nan"), 1, 1))
    _keyframe(probe, 7, scale=(1, 1, 1))
    with pytest.raises(RuntimeError, match="Frame 6: Probe 'B' has a non-finite transform"):
        _bake(bl, target, index=0, mode="SHAPE_KEYS")
    assert target.data.shape_keys is None

    # An absolute path works in an unsaved file.
    absolute = tmp_path / "cache" / "abs.pc2"
    assert _bake(bl, target, index=0, mode="PC2", filepath=str(absolute), frame_start=1,
                 frame_end=4) == {"FINISHED"}
    assert len(_module(installed, "tools.pc2").read_pc2(absolute)[0]) == 4
    assert _stack(target) != stack and target.modifiers[0].filepath == str(absolute)


class _Recorder:
    """Stands in for a UILayout: records labels and operator buttons (with the properties set)."""

    def __init__(self, log: list) -> None:
        self.log = log

    def _child(self, *_args, **_kwargs) -> _Recorder:
        return _Recorder(self.log)

    row = column = box = _child

    def label(self, text: str = "", icon: str = "NONE") -> None:
        self.log.append(("label", text, icon))

    def operator(self, idname: str, **_kwargs):
        module, name = idname.split(".")
        props = type("Props", (), {})()
        props.rna = getattr(getattr(bpy.ops, module), name).get_rna_type()
        self.log.append(("operator", idname, props))
        return props


def test_bake_section_of_the_panel_follows_the_bake_state(bl, installed, tmp_path):
    target, deformer = _scene(bl, tmp_path)
    panels = _module(installed, "ui.panels")

    def draw():
        log = []
        panels.draw_bake(_Recorder(log), deformer, 0)
        for entry in log:
            if entry[0] == "operator":
                names = set(entry[2].rna.properties.keys())
                assert set(vars(entry[2])) - {"rna"} <= names, entry
        return log

    buttons = [(e[1], e[2].mode) for e in draw() if e[0] == "operator"]
    assert buttons == [("object.affine_deformer_bake", "PC2"), ("object.affine_deformer_bake", "SHAPE_KEYS")]
    assert _bake(bl, target, index=0, mode="PC2", frame_start=1, frame_end=3) == {"FINISHED"}
    log = draw()
    assert [e[1] for e in log if e[0] == "operator"] == ["object.affine_deformer_bake",
                                                          "object.affine_deformer_unbake"]
    labels = [(e[1], e[2]) for e in log if e[0] == "label"]
    assert labels == [("Baked to //Cube_Probe_Deformer.pc2, frames 1..3", "FILE_CACHE")]
    deformer.show_viewport = True  # the artist turns the live deformer back on by hand
    assert any(icon == "ERROR" and "twice" in text for kind, text, icon, *_ in draw() if kind == "label")
