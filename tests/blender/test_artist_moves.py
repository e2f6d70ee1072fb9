"""An artist's ordinary moves, checked against what Blender itself gives (issue 55): each case builds
the rig the way an artist does (the menu's defaults, the usual toggles) and compares with Blender's
own result for the same rig (its Armature modifier, Scene Time), never with the add-on's formula.

Here: Affine Bones added where the mesh already has an Armature modifier of that armature (it must
not deform the mesh twice), and the scene's frame mapped to time by Time Stretching (the output
stamp must agree with what Scene Time gives, or every frame shows the input).
"""

from __future__ import annotations

import itertools

import bpy
import numpy as np
import pytest

from tests.blender.test_bone_deformer import _armature, _bar, _paint, _ramp_weights


def _skinned_bar(bl):
    """The bar of test_bone_deformer skinned to a two-bone 'Rig' by an Armature modifier (Preserve
    Volume), as an artist's mesh arrives: painted groups, the modifier on."""
    bar = _bar(bl)
    arm = _armature([0.0, 2.0, 4.0])
    x = bl.rest_positions(bar)[:, 0].astype(np.float64)
    centers = [0.5 * (a + b) for a, b in itertools.pairwise([0.0, 2.0, 4.0])]
    _paint(bar, _ramp_weights(x, centers, centers[1] - centers[0]), ["B0", "B1"])
    native = bar.modifiers.new("Armature", "ARMATURE")
    native.object, native.use_deform_preserve_volume = arm, True
    return bar, arm, native


def _bend(arm, degrees: float = 60.0, name: str = "B1") -> None:
    bone = arm.pose.bones[name]
    bone.rotation_mode = "XYZ"
    bone.rotation_euler = (0.0, 0.0, np.radians(degrees))
    bpy.context.view_layer.update()


def _armature_alone(bl, bar, native) -> np.ndarray:
    """What Blender's Armature modifier gives the posed bar, with every deformer of ours off."""
    ours = [m for m in bar.modifiers if m.type == "NODES"]
    states = [(m.show_viewport, m.show_render) for m in ours]
    native_state = (native.show_viewport, native.show_render)
    for m in ours:
        m.show_viewport = False
    native.show_viewport = True
    bpy.context.view_layer.update()
    found = bl.evaluated_positions(bar).astype(np.float64)
    for m, (viewport, render) in zip(ours, states, strict=True):
        m.show_viewport, m.show_render = viewport, render
    native.show_viewport, native.show_render = native_state
    bpy.context.view_layer.update()
    return found


@pytest.mark.parametrize("selected", ["mesh only", "mesh and armature"])
def test_affine_bones_from_the_menu_does_not_deform_the_mesh_twice(bl, selected):
    bar, arm, native = _skinned_bar(bl)
    chosen = [bar] if selected == "mesh only" else [bar, arm]
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=chosen):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    assert not native.show_viewport and not native.show_render, "the Armature modifier is turned off"
    stack = [m.type for m in bar.modifiers]
    assert stack == ["ARMATURE", "NODES"], stack  # in the Armature modifier's place, as Convert puts it
    _bend(arm)
    ours = bl.evaluated_positions(bar).astype(np.float64)
    theirs = _armature_alone(bl, bar, native)
    rest = bl.rest_positions(bar).astype(np.float64)
    moved = np.abs(theirs - rest).max()
    assert moved > 1.0, moved
    # Once deformed: near what the Armature gives (they blend differently where the groups overlap),
    # where twice deformed was 1.97 off on this 4-unit bar.
    assert np.abs(ours - theirs).max() < 0.1 * moved, np.abs(ours - theirs).max()
    assert deformer.status == "", deformer.status
    # Back to the Armature modifier: the deformer's own button undoes the take-over.
    assert bl.run_op(bpy.ops.object.affine_armature_restore, bar, index=0) == {"FINISHED"}
    assert native.show_viewport and native.show_render and len(bar.affine_deformers) == 0


def test_an_armature_modifier_turned_back_on_beside_the_bone_deformer_is_named(bl):
    bar, arm, native = _skinned_bar(bl)
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    native.show_render = True  # on in renders again: a render would deform the mesh twice
    _bend(arm)
    bl.evaluated_positions(bar)
    assert f"'{native.name}'" in deformer.status and "twice" in deformer.status, deformer.status
    native.show_render = False
    _bend(arm, 50.0)
    bl.evaluated_positions(bar)
    assert deformer.status == "", deformer.status


# ------------------------------------------------------------------------------------------ time


def blender_scene_time() -> np.float32:
    """What Blender's own Scene Time node gives as Frame at the current frame (a throw-away object
    whose Geometry Nodes modifier stores it), to compare the add-on's stamp with."""
    ng = bpy.data.node_groups.new(".scene time probe", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    group_in, group_out = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    store = ng.nodes.new("GeometryNodeStoreNamedAttribute")
    store.data_type, store.domain = "FLOAT", "POINT"
    store.inputs["Name"].default_value = "scene_time"
    ng.links.new(group_in.outputs[0], store.inputs["Geometry"])
    ng.links.new(ng.nodes.new("GeometryNodeInputSceneTime").outputs["Frame"], store.inputs["Value"])
    ng.links.new(store.outputs[0], group_out.inputs[0])
    mesh = bpy.data.meshes.new(".scene time probe")
    mesh.vertices.add(1)
    obj = bpy.data.objects.new(".scene time probe", mesh)
    obj.modifiers.new("Scene Time", "NODES").node_group = ng
    bpy.context.scene.collection.objects.link(obj)
    try:
        evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
        value = np.empty(1, np.float32)
        evaluated.attributes["scene_time"].data.foreach_get("value", value)
    finally:
        bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(mesh)
        bpy.data.node_groups.remove(ng)
    return value[0]


def _rising_probe_rig(bl):
    """A cube following one probe keyed to rise from 0 to 4 over frames 1 to 41 (one probe: the mesh
    moves exactly as the probe, as Blender evaluates it)."""
    target = bl.grid_cube(cuts=3)
    probe = bl.empty("Lift", (0.0, 0.0, 0.0))
    deformer = bl.add_probe_deformer(target, [probe])
    for frame, z in ((1, 0.0), (41, 4.0)):
        probe.location.z = z
        probe.keyframe_insert("location", index=2, frame=frame)
    return target, probe, deformer


def _probe_rise(probe) -> float:
    return probe.evaluated_get(bpy.context.evaluated_depsgraph_get()).matrix_world.translation.z


@pytest.mark.parametrize("old_new", [(100, 50), (50, 100), (25, 40)], ids=["slower", "faster", "odd"])
def test_time_stretching_plays_every_frame(bl, old_new):
    target, probe, deformer = _rising_probe_rig(bl)
    scene = bpy.context.scene
    scene.render.frame_map_old, scene.render.frame_map_new = old_new
    rest = bl.rest_positions(target).astype(np.float64)
    for frame, subframe in ((5, 0.0), (9, 0.0), (2, 0.5), (7, 0.25), (5, 0.0)):
        scene.frame_set(frame, subframe=subframe)
        rise = _probe_rise(probe)
        assert rise > 0.0, "the probe has risen (Blender evaluates its action at the stretched time)"
        got = bl.evaluated_positions(target).astype(np.float64)
        assert np.abs(got - rest - (0.0, 0.0, rise)).max() < 1e-5, (frame, subframe, rise)
        assert deformer.status == "", deformer.status


def test_the_stamp_agrees_with_blenders_scene_time(bl, installed):
    """The stamp is compared with Scene Time by the node group: they must agree at every time mapping
    (else every frame looks stale and shows the input)."""
    import importlib

    check = importlib.import_module(f"{installed.package}.blender.update.frame_check")
    scene = bpy.context.scene
    for old, new in ((100, 50), (50, 100), (30, 70), (100, 100)):
        scene.render.frame_map_old, scene.render.frame_map_new = old, new
        for frame, subframe in ((5, 0.0), (13, 0.25), (1, 0.5)):
            scene.frame_set(frame, subframe=subframe)
            found = blender_scene_time()
            ours = check.scene_time(scene)
            assert abs(float(ours) - float(found)) <= check.TOLERANCE, (old, new, frame, subframe, found)


# ------------------------------------------------------------------------------------------ cages


def test_a_cage_whose_faces_were_flipped_after_binding_is_called_inside_out(bl):
    import bmesh

    from tests.blender.test_cage_deformer import add_cage_deformer, box_cage

    target = bl.grid_cube(cuts=4)
    cage = box_cage()
    deformer = add_cage_deformer(target, cage)
    bm = bmesh.new()
    bm.from_mesh(cage.data)
    bmesh.ops.reverse_faces(bm, faces=bm.faces[:2])
    bm.to_mesh(cage.data)
    bm.free()
    cage.data.update()
    bl.evaluated_positions(target)
    status = deformer.status
    assert "turned the other way" in status and "changed topology" not in status, status
    assert f"2 of {len(cage.data.polygons)} faces" in status, status


# ------------------------------------------------------------------------------- degenerate controls


def _two_probe_bar(bl):
    """The bar of test_bone_deformer (x from 0 to 4) with probes at its ends, Falloff weights of radius
    2.5 (so the far end holds no weight of the near probe), the end probe moved and turned."""
    bar = _bar(bl)
    start, end = bl.empty("Start", (0.0, 0.0, 0.0)), bl.empty("End", (4.0, 0.0, 0.0))
    deformer = bl.add_probe_deformer(bar, [start, end], weight_mode="FALLOFF", radius=2.5)
    end.location = (4.0, 0.5, 1.0)
    end.rotation_euler = (0.4, 0.0, 0.3)
    bpy.context.view_layer.update()
    return bar, start, end, deformer


def _held(bl, bar, deformer, index: int) -> np.ndarray:
    """Which vertices the probe `index` holds any weight of."""
    return bl.dense_weights(bar, deformer)[:, index] > 0.0


@pytest.mark.parametrize("scale", [(1.0, 1.0, 0.0), (0.0, 0.0, 0.0), (0.0, 1.0, 1.0)],
                         ids=["one axis", "all axes", "x axis"])
def test_a_probe_scaled_to_zero_collapses_what_it_holds_and_nothing_else(bl, scale):
    bar, start, _end, deformer = _two_probe_bar(bl)
    before = bl.evaluated_positions(bar).astype(np.float64)
    held = _held(bl, bar, deformer, 0)
    assert 0 < held.sum() < len(held)
    start.scale = tuple(s if s else 1e-6 for s in scale)
    bpy.context.view_layer.update()
    near = bl.evaluated_positions(bar).astype(np.float64)
    start.scale = scale
    bpy.context.view_layer.update()
    at_zero = bl.evaluated_positions(bar).astype(np.float64)
    size = np.ptp(before, axis=0).max()
    assert np.abs(at_zero - near).max() <= 0.01 * size, "scale 0 is the limit of the nearby scales"
    assert np.array_equal(at_zero[~held], before[~held]), "vertices it does not hold stay where they were"
    assert np.abs(at_zero[held] - before[held]).max() > 0.05, "what it holds collapses"
    assert "Probe 'Start' is scaled to zero" in deformer.status, deformer.status
    start.scale = (1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert np.array_equal(bl.evaluated_positions(bar).astype(np.float64), before) and deformer.status == ""


@pytest.mark.parametrize("how", ["mirrored", "deleted"])
def test_a_mirrored_or_deleted_probe_hands_its_vertices_to_the_others(bl, how):
    bar, start, _end, deformer = _two_probe_bar(bl)
    before = bl.evaluated_positions(bar).astype(np.float64)
    held = _held(bl, bar, deformer, 0)
    only_start = held & ~_held(bl, bar, deformer, 1)
    if how == "mirrored":
        start.scale = (-1.0, 1.0, 1.0)
    else:
        bpy.data.objects.remove(start)
    bpy.context.view_layer.update()
    got = bl.evaluated_positions(bar).astype(np.float64)
    rest = bl.rest_positions(bar).astype(np.float64)
    assert np.array_equal(got[~held], before[~held]), "vertices it does not hold stay where they were"
    assert np.array_equal(got[only_start], rest[only_start]), "held by it alone: nothing moves them"
    shared = held & ~only_start
    assert shared.any() and np.abs(got[shared] - rest[shared]).max() > 0.05, "shared ones follow 'End'"
    assert np.isfinite(got).all() and np.abs(got - rest).max() < 3.0, "nothing is flung"
    assert "'Start'" in deformer.status and "follow the other probes" in deformer.status, deformer.status


def test_a_bone_scaled_to_zero_collapses_its_vertices_as_the_armature_modifier_does(bl):
    bar, arm, native = _skinned_bar(bl)
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    _bend(arm, 30.0)
    before = bl.evaluated_positions(bar).astype(np.float64)
    arm.pose.bones["B1"].scale = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    ours = bl.evaluated_positions(bar).astype(np.float64)
    theirs = _armature_alone(bl, bar, native)
    x = bl.rest_positions(bar)[:, 0]
    only_b0, only_b1 = x <= 1.0, x >= 3.0  # the ramps of _skinned_bar: one bone's alone there
    assert np.array_equal(ours[only_b0], before[only_b0]), "the other bone's vertices stay"
    assert np.abs(ours[only_b1] - theirs[only_b1]).max() < 1e-4, "its own collapse onto its head"
    # Nothing is flung: every vertex stays by what is left of the rig, bone B0 (x from 0 to 2 on the X
    # axis) with B1 shrunk onto its head; the cross-section's half diagonal is 0.28. Between the bones
    # the blend of logarithms collapses more than Armature's linear blend (s^w, not w·s): the limit of
    # the nearby scales, as the probe test checks.
    along = np.clip(ours[:, 0], 0.0, 2.0)
    off_rig = np.hypot(ours[:, 0] - along, np.hypot(ours[:, 1], ours[:, 2]))
    assert np.isfinite(ours).all() and off_rig.max() < 0.3, off_rig.max()
    assert "Bone 'B1' is scaled to zero" in deformer.status, deformer.status
    # The limit of the nearby scales, flattened along the bone: its rotation is still in its matrix.
    # (Scaled to zero on every axis, a turned bone's matrix holds no rotation, and its blend with
    # the parent turns as the unturned one: 0.13 on this bar, 3 %; not yet followed, see the issue.)
    arm.pose.bones["B1"].scale = (1.0, 1e-6, 1.0)
    bpy.context.view_layer.update()
    near = bl.evaluated_positions(bar).astype(np.float64)
    arm.pose.bones["B1"].scale = (1.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    flat = bl.evaluated_positions(bar).astype(np.float64)
    assert np.abs(near - flat).max() <= 0.01 * 4.0, "scale 0 is the limit of the nearby scales"
    assert np.array_equal(flat[only_b0], before[only_b0]) and "'B1'" in deformer.status


@pytest.mark.parametrize("where", ["beside", "around half"])
def test_a_cage_that_does_not_hold_the_mesh_says_how_many_vertices_are_outside(bl, where):
    from tests.blender.test_cage_deformer import add_cage_deformer, box_cage

    target = bl.grid_cube(cuts=6)  # the cube from −1 to 1
    cage = box_cage()
    if where == "beside":
        cage.location.x = 5.0
    else:
        cage.location.x = 1.4  # the box cage of test_cage_deformer spans ±1.5: x < −0.1 is outside
    bpy.context.view_layer.update()
    deformer = add_cage_deformer(target, cage)
    rest = bl.rest_positions(target).astype(np.float64)
    world_x = rest[:, 0]
    lo = cage.location.x - 1.5
    expected = int(np.count_nonzero(world_x < lo - 0.05))
    status = deformer.status
    assert "lie outside cage 'Cage'" in status, status
    counted = int(status.split(" of ")[0])
    assert expected <= counted <= int(np.count_nonzero(world_x < lo + 0.05)), (counted, expected)
    # Turning the cage's top half 45° (as issue 55's artist did): the vertices it does not hold move no
    # more than 1.5 × the cage's own largest vertex move (Mesh Deform leaves them where they are).
    from tests.blender.test_cage_deformer import cage_points, set_cage_points

    points = cage_points(cage)
    top = points[:, 2] > 0.0
    c, s = np.cos(np.radians(45.0)), np.sin(np.radians(45.0))
    turned = points.copy()
    turned[top] = points[top] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    set_cage_points(cage, turned)
    cage_move = np.abs(turned - points).max()
    moved = np.abs(bl.evaluated_positions(target) - rest).max()
    assert moved <= 1.5 * cage_move, (moved, cage_move)
    set_cage_points(cage, points)
    bpy.context.scene.frame_set(3)
    assert "lie outside cage" in deformer.status, "it keeps saying it"
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    assert "lie outside cage" in deformer.status
    cage.location.x = 0.0  # it holds the mesh now: Rebind clears the warning
    bpy.context.view_layer.update()
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    assert deformer.status == "", deformer.status


def test_time_stretching_in_an_animation_render(bl, tmp_path):
    """`-a` of a time-stretched shot: at every rendered frame the render's own evaluation of the mesh
    follows the probe as that render evaluates it (Blender's Scene Time, not the add-on's formula)."""
    target, probe, deformer = _rising_probe_rig(bl)
    scene = bpy.context.scene
    scene.render.frame_map_old, scene.render.frame_map_new = 100, 50
    scene.frame_start, scene.frame_end = 2, 4
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    camera.location = (0.0, -8.0, 2.0)
    camera.rotation_euler = (np.radians(80.0), 0.0, 0.0)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.device = 1, "CPU"
    scene.render.resolution_x = scene.render.resolution_y = 16
    scene.render.filepath = str(tmp_path / "frame_")
    rest = bl.rest_positions(target).astype(np.float64)
    seen: dict[int, float] = {}

    def capture(scene, depsgraph=None):
        if depsgraph is None or depsgraph.mode != "RENDER":
            return
        depsgraph.update()  # the pass the render runs after the handlers (pipeline_matrix_scene)
        rise = probe.evaluated_get(depsgraph).matrix_world.translation.z
        mesh = target.evaluated_get(depsgraph).data
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        seen[scene.frame_current] = float(np.abs(co.reshape(-1, 3) - rest - (0.0, 0.0, rise)).max())
        seen[-scene.frame_current] = rise

    capture.__name__ = "artist_moves_render_capture"
    handlers = bpy.app.handlers.frame_change_post
    handlers.append(capture)  # after the add-on's handler, which writes the deformation
    try:
        assert bpy.ops.render.render(animation=True) == {"FINISHED"}
    finally:
        handlers.remove(capture)
    assert sorted(k for k in seen if k > 0) == [2, 3, 4], seen
    assert all(seen[-f] > 0.0 for f in (2, 3, 4)), "the probe has risen at every rendered frame"
    assert all(seen[f] < 1e-5 for f in (2, 3, 4)), seen
    assert deformer.status == ""


# ------------------------------------------------------------------------------------------ a rigger's edits


@pytest.mark.parametrize("modifier", ["kept", "removed"])
def test_a_renamed_bone_is_followed_and_rebind_keeps_the_painted_weights(bl, modifier):
    """B1 → Forearm (issue 57): Blender renames the vertex group where the mesh uses the armature (an
    Armature modifier, even off); the deformer follows, renaming the group itself where Blender did
    not; the shape stays, and Rebind gives the same shape from the renamed group."""
    bar, arm, native = _skinned_bar(bl)
    with bpy.context.temp_override(active_object=bar, object=bar, selected_objects=[bar]):
        assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}
    deformer = bar.affine_deformers[0]
    if modifier == "removed":
        bar.modifiers.remove(native)
    _bend(arm, 40.0)
    before = bl.evaluated_positions(bar).copy()
    arm.data.bones["B1"].name = "Forearm"
    bpy.context.view_layer.update()
    assert [item.name for item in deformer.bones] == ["B0", "Forearm"], deformer.status
    assert bar.vertex_groups.get("Forearm") is not None and bar.vertex_groups.get("B1") is None
    assert deformer.status == "" and np.array_equal(bl.evaluated_positions(bar), before)
    _bend(arm, 0.0, "Forearm")
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, bar, index=0) == {"FINISHED"}
    _bend(arm, 40.0, "Forearm")
    assert deformer.status == "" and np.abs(bl.evaluated_positions(bar) - before).max() < 1e-5


@pytest.mark.parametrize("kind", ["probe", "cage", "bone"])
def test_copy_modifiers_while_posed_deforms_the_copy_as_the_source(bl, installed, kind):
    """Ctrl+L ▸ Copy Modifiers from a posed rig onto an identical mesh (issue 57): the copy binds at
    the source's rest poses, so it shows the source's deformation at once and its rest when the
    controls go back, where it used to bind at the posed controls (no deformation, then a wrong one)."""
    import importlib

    copies = importlib.import_module(f"{installed.package}.blender.files.copies")
    from tests.blender.test_cage_deformer import add_cage_deformer, box_cage, cage_points, set_cage_points

    if kind == "bone":
        source, arm, native = _skinned_bar(bl)
        source.modifiers.remove(native)
        with bpy.context.temp_override(active_object=source, object=source, selected_objects=[source, arm]):
            assert bpy.ops.object.affine_bone_deformer_add() == {"FINISHED"}

        def pose(on):
            _bend(arm, 50.0 if on else 0.0)
    elif kind == "cage":
        source = bl.grid_cube(cuts=4)
        cage = box_cage()
        add_cage_deformer(source, cage)
        rest_cage = cage_points(cage)

        def pose(on):
            set_cage_points(cage, rest_cage + (rest_cage[:, 2:3] > 0) * np.array([0.4, 0.0, 0.3]) * on)
    else:
        source = bl.grid_cube(cuts=4)
        probe = bl.empty("P", (1.5, 0.0, 0.0))
        bl.add_probe_deformer(source, [probe, bl.empty("Q", (-1.5, 0.0, 0.0))])

        def pose(on):
            probe.location = (1.5, 0.0, 0.7 * on)
            probe.rotation_euler = (0.0, 0.5 * on, 0.0)
            bpy.context.view_layer.update()

    twin = bpy.data.objects.new("Twin", source.data.copy())  # the vertex groups come with the mesh
    bpy.context.scene.collection.objects.link(twin)
    pose(True)
    ours = [m for m in source.modifiers if m.type == "NODES"]
    with bpy.context.temp_override(active_object=source, object=source, selected_objects=[source, twin],
                                   selected_editable_objects=[source, twin]):
        assert bpy.ops.object.make_links_data(type="MODIFIERS") == {"FINISHED"}
    bpy.context.evaluated_depsgraph_get()
    copies.bind_adopted()  # the timer Blender runs after the handler (none runs in a bpy module)
    assert len(twin.affine_deformers) == 1 and twin.affine_deformers[0].status == "", ours
    expected = bl.evaluated_positions(source).astype(np.float64)
    assert np.abs(expected - bl.rest_positions(source)).max() > 0.1, "the source is posed"
    assert np.abs(bl.evaluated_positions(twin) - expected).max() < 1e-5, "it shows what the source shows"
    pose(False)
    assert np.abs(bl.evaluated_positions(twin) - bl.rest_positions(twin)).max() < 1e-5, "and rests with it"


def test_remake_cage_refuses_to_throw_a_posed_cage_away(bl):
    """Remake Cage after the made cage was posed (issue 57): refused with the reason, the edit and the
    deformation kept; after Rebind (the pose is the rest now) it remakes."""
    from tests.blender.test_cage_deformer import cage_points, set_cage_points

    target = bl.uv_sphere(segments=16, rings=8)
    with bpy.context.temp_override(active_object=target, object=target, selected_objects=[target]):
        assert bpy.ops.object.affine_cage_deformer_add() == {"FINISHED"}
    deformer = target.affine_deformers[0]
    cage = deformer.cage
    points = cage_points(cage)
    set_cage_points(cage, points + (points[:, 2:3] > 0.0) * np.array([0.3, 0.0, 0.0]))
    edited = cage_points(cage)
    posed = bl.evaluated_positions(target).copy()
    assert np.abs(posed - bl.rest_positions(target)).max() > 0.1
    with pytest.raises(RuntimeError, match=r"is posed or edited .*moved up to 0\.3"):
        bl.run_op(bpy.ops.object.affine_cage_remake, target, index=0)
    assert np.array_equal(cage_points(cage), edited), "the edit is kept"
    assert np.array_equal(bl.evaluated_positions(target), posed), "the deformation is kept"
    assert bl.run_op(bpy.ops.object.affine_deformer_bind, target, index=0) == {"FINISHED"}
    assert bl.run_op(bpy.ops.object.affine_cage_remake, target, index=0) == {"FINISHED"}
    assert deformer.status == ""


def test_a_deleted_probe_whose_name_holds_braces_is_named(bl):
    bar, start, _end, deformer = _two_probe_bar(bl)
    start.name = "Start{0}"
    bpy.context.view_layer.update()
    deformer.probes[0].name = "Start{0}"
    bpy.data.objects.remove(start)
    bpy.context.view_layer.update()
    assert np.isfinite(bl.evaluated_positions(bar)).all()
    assert "Probe 'Start{0}' was deleted" in deformer.status, deformer.status
