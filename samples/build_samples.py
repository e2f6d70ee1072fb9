"""Rebuild every sample scene (.blend) from code, deterministically.

Run with the Blender 4.2 LTS venv, so the files open in 4.2 and newer (`make samples`, or
`.venv42/bin/python samples/build_samples.py [--samples NAME...]`); `.venv/bin/python` works too but
saves files that only Blender 5.0+ opens.

Each sample has a camera, a light, simple materials, keyframed controls and a frame range, and is
bound to the Affine Deformers extension, so it plays in Blender with no further setup:

- probe_bend      a bar bent, twisted and scaled by three probes (course notes, fig. 18)
- probe_vortex    a disc swirled by one probe turning through 450° (fig. 19; multi-turn twists)
- cage_deform     a blob figure inside a coarse closed quad cage animated by shape keys (fig. 20)
- comparison      the same end twist of a bar (±90°, then ±150°): 'LINEAR' blend (candy-wrapper
                  collapse), Blender's Armature with Preserve Volume (dual quaternions: no collapse, but
                  the short way round past 180° of twist) and the Aff+(3) log blend
- stack           a production stack: shape key → Armature → Affine probes → Subdivision
- bone_tail       a six-bone tail (wave, a non-uniformly scaled bone, then its tip twisting 0° → 450°):
                  Blender's Armature with Preserve Volume (the short way round past 180°) and our bone
                  deformer converted from the same Armature modifier, on the same mesh and vertex groups
- shape_pass      one bar bent by two probes, the per-vertex field beside Preserve Shape
- made_cage       Suzanne with a cage deformer added with no cage selected: the add operator makes her
                  cage; its shape keys lean her head, lift her ears and squash her

The extension is installed from the built .zip into an isolated Blender user directory, so the
artist's own Blender configuration is never touched. `bpy` must not be imported before
`start_blender()` has set BLENDER_USER_RESOURCES, hence the function-level imports of bpy.

Every sample records what the renderer and the tests need as custom properties: the scene's
`affdef_key_frames` (frames worth looking at; the first is the rest pose) and, on each deformed
object, `affdef_sample_target` (the deformation method it shows).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import subprocess
import sys
import tomllib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SAMPLES_DIR = ROOT / "samples"
DIST_DIR = ROOT / "dist"
DEFAULT_USER_DIR = ROOT / "out" / ".blender_user"
EXTENSION_ID = "affine_deformers"
ADDON_MODULE = f"bl_ext.user_default.{EXTENSION_ID}"

# Colours are linear RGB.
PROBE_RED = (0.8, 0.03, 0.02)
BACKGROUND = (0.32, 0.36, 0.42)


# --------------------------------------------------------------------------------------------------
# Blender session: isolated user directory + the built extension
# --------------------------------------------------------------------------------------------------


def package_path() -> Path | None:
    """The extension .zip `make build` produced for the manifest's current version (this machine's
    platform package, or the all-platform one without the compiled kernel), None when there is none."""
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text(encoding="utf-8"))
    built = sorted(DIST_DIR.glob(f"{manifest['id']}-{manifest['version']}*.zip"))
    return built[-1] if built else None


def _newest_source_mtime() -> float:
    sources = [ROOT / "blender_manifest.toml", ROOT / "__init__.py"]
    sources += list((ROOT / EXTENSION_ID).rglob("*.py"))
    return max(p.stat().st_mtime for p in sources if p.exists())


def ensure_package() -> Path:
    """Return the extension .zip, building it first when it is missing or older than the sources."""
    zip_path = package_path()
    stale = zip_path is not None and zip_path.stat().st_mtime < _newest_source_mtime()
    if zip_path is None or stale:
        print(f"building the extension package ({'stale' if stale else 'missing'})")
        subprocess.run(
            [sys.executable, str(ROOT / "tools" / "build_extension.py"), "--output-dir", str(DIST_DIR)],
            check=True,
            cwd=ROOT,
        )
        zip_path = package_path()
    if zip_path is None:
        raise SystemExit(f"extension package not found in {DIST_DIR} after building")
    return zip_path


def start_blender(user_dir: Path, package: Path) -> None:
    """Import bpy with an isolated user directory and install + enable the extension package.

    BLENDER_USER_RESOURCES is read when bpy initialises, so it has to be set before the first
    `import bpy` in this process; a second call with another directory is an error.
    """
    user_dir = Path(user_dir).resolve()
    if "bpy" in sys.modules:
        current = os.environ.get("BLENDER_USER_RESOURCES")
        if current is None or Path(current).resolve() != user_dir:
            raise RuntimeError(
                f"bpy was imported before start_blender(); its user directory is {current!r}, not {user_dir}"
            )
    user_dir.mkdir(parents=True, exist_ok=True)
    os.environ["BLENDER_USER_RESOURCES"] = str(user_dir)
    import bpy

    result = bpy.ops.extensions.package_install_files(
        filepath=str(package), repo="user_default", enable_on_install=True
    )
    enabled = {addon.module for addon in bpy.context.preferences.addons}
    if "FINISHED" not in result or ADDON_MODULE not in enabled:
        raise RuntimeError(f"installing {package} failed ({result}); enabled add-ons: {sorted(enabled)}")


def operator_available(idname: str) -> bool:
    """True when an operator class such as 'OBJECT_OT_affine_probe_deformer_add' is registered."""
    import bpy

    return hasattr(bpy.types, idname)


# --------------------------------------------------------------------------------------------------
# Scene furniture: scene settings, camera, lights, materials
# --------------------------------------------------------------------------------------------------


@dataclass
class SampleInfo:
    """What a builder reports back: frames worth rendering and anything left undone."""

    key_frames: list[int]
    todo: list[str] = field(default_factory=list)


def new_scene(name: str, frame_end: int) -> object:
    """Start from an empty file (the extension stays enabled) and set up render/playback defaults."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.name = name
    scene.frame_start = 1
    scene.frame_end = frame_end
    scene.frame_current = 1
    scene.render.fps = 24
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 64
    scene.cycles.use_denoising = True
    scene.render.resolution_x = 960
    scene.render.resolution_y = 640
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "AgX"
    # Look names differ between colour-management configurations; the default look is fine too.
    with contextlib.suppress(TypeError):
        scene.view_settings.look = "AgX - Punchy"
    world = bpy.data.worlds.new(f"{name}.World")
    if world.node_tree is None:
        world.use_nodes = True
    background = world.node_tree.nodes.get("Background")
    background.inputs["Color"].default_value = (*BACKGROUND, 1.0)
    background.inputs["Strength"].default_value = 0.8
    scene.world = world
    return scene


def link(obj: object) -> object:
    import bpy

    bpy.context.scene.collection.objects.link(obj)
    return obj


def look_at(obj: object, location: Sequence[float], target: Sequence[float]) -> None:
    """Place obj at location with its -Z axis towards target and +Y up (cameras and lights)."""
    from mathutils import Vector

    obj.location = location
    direction = Vector(target) - Vector(location)
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def add_camera(location: Sequence[float], target: Sequence[float], lens: float = 50.0) -> object:
    import bpy

    camera = link(bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera")))
    camera.data.lens = lens
    look_at(camera, location, target)
    bpy.context.scene.camera = camera
    return camera


def add_lights(target: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
    """A warm key sun from the upper left front and a cool fill area light from the right."""
    import bpy
    from mathutils import Vector

    sun = link(bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN")))
    sun.data.energy = 3.5
    sun.data.angle = math.radians(8.0)
    sun.data.color = (1.0, 0.95, 0.88)
    look_at(sun, Vector(target) + Vector((-6.0, -8.0, 10.0)), target)
    fill = link(bpy.data.objects.new("Fill", bpy.data.lights.new("Fill", "AREA")))
    fill.data.energy = 400.0
    fill.data.size = 6.0
    fill.data.color = (0.8, 0.88, 1.0)
    look_at(fill, Vector(target) + Vector((9.0, -6.0, 3.0)), target)


def _principled(material: object) -> object:
    if material.node_tree is None:
        material.use_nodes = True
    return material.node_tree.nodes.get("Principled BSDF")


def plain_material(name: str, color: Sequence[float], roughness: float = 0.5) -> object:
    import bpy

    material = bpy.data.materials.new(name)
    bsdf = _principled(material)
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    material.diffuse_color = (*color, 1.0)
    return material


def checker_material(
    name: str,
    color1: Sequence[float],
    color2: Sequence[float],
    scale: Sequence[float],
    polar: bool = False,
    polar_axis: str = "Z",
) -> object:
    """A checker on the rest coordinates (point attribute REST_ATTRIBUTE), so it sticks to the surface.

    With polar=True the checker runs on (angle/2π, radius, z) of the rest position: sectors and rings,
    which make a swirl easy to read. polar_axis='X' measures the angle about the X axis instead
    (atan2(z, y)) and runs the third coordinate along x: stripes along a limb lying on X, which make a
    twist about it easy to read.
    """
    if polar_axis not in ("X", "Z"):
        raise ValueError(f"polar_axis must be 'X' or 'Z', not {polar_axis!r}")
    import bpy

    material = bpy.data.materials.new(name)
    bsdf = _principled(material)
    tree = material.node_tree
    nodes, links = tree.nodes, tree.links
    attribute = nodes.new("ShaderNodeAttribute")
    attribute.attribute_type = "GEOMETRY"
    attribute.attribute_name = REST_ATTRIBUTE
    coordinates = attribute.outputs["Vector"]
    if polar:
        split = nodes.new("ShaderNodeSeparateXYZ")
        links.new(coordinates, split.inputs[0])
        angle = nodes.new("ShaderNodeMath")
        angle.operation = "ARCTAN2"
        # atan2(second, first) of the two coordinates across the axis.
        across = ("Y", "X") if polar_axis == "Z" else ("Z", "Y")
        links.new(split.outputs[across[0]], angle.inputs[0])
        links.new(split.outputs[across[1]], angle.inputs[1])
        turns = nodes.new("ShaderNodeMath")
        turns.operation = "DIVIDE"
        links.new(angle.outputs[0], turns.inputs[0])
        turns.inputs[1].default_value = 2.0 * math.pi
        radius = nodes.new("ShaderNodeVectorMath")
        radius.operation = "LENGTH"
        links.new(coordinates, radius.inputs[0])
        combine = nodes.new("ShaderNodeCombineXYZ")
        links.new(turns.outputs[0], combine.inputs["X"])
        links.new(radius.outputs["Value"], combine.inputs["Y"])
        links.new(split.outputs[polar_axis], combine.inputs["Z"])
        coordinates = combine.outputs[0]
    # A small offset keeps checker cell borders off the flat faces at integer coordinates.
    mapping = nodes.new("ShaderNodeMapping")
    mapping.inputs["Scale"].default_value = scale
    mapping.inputs["Location"].default_value = (0.013, 0.017, 0.011)
    links.new(coordinates, mapping.inputs["Vector"])
    checker = nodes.new("ShaderNodeTexChecker")
    checker.inputs["Color1"].default_value = (*color1, 1.0)
    checker.inputs["Color2"].default_value = (*color2, 1.0)
    checker.inputs["Scale"].default_value = 1.0
    links.new(mapping.outputs["Vector"], checker.inputs["Vector"])
    links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = 0.45
    material.diffuse_color = (*color1, 1.0)
    return material


def add_ground(z: float, size: float = 40.0) -> object:
    import bpy

    mesh = bpy.data.meshes.new("Ground")
    half = size / 2.0
    mesh.from_pydata(
        [(-half, -half, z), (half, -half, z), (half, half, z), (-half, half, z)], [], [(0, 1, 2, 3)]
    )
    ground = link(bpy.data.objects.new("Ground", mesh))
    ground.data.materials.append(plain_material("Ground", (0.3, 0.3, 0.3), roughness=0.8))
    ground.hide_select = True
    return ground


def add_label(text: str, location: Sequence[float], size: float = 0.3, align: str = "CENTER") -> object:
    """A text object standing upright and facing -Y (towards the cameras of the samples)."""
    import bpy

    curve = bpy.data.curves.new(f"Label.{text}", "FONT")
    curve.body = text
    curve.size = size
    curve.align_x = align
    curve.align_y = "CENTER"
    label = link(bpy.data.objects.new(f"Label.{text}", curve))
    label.location = location
    label.rotation_euler = (math.radians(90.0), 0.0, 0.0)
    label.data.materials.append(plain_material(f"Label.{text}", (0.02, 0.02, 0.025)))
    label.hide_select = True
    return label


def frame_viewports_through_camera() -> None:
    """Make the 3D views of the saved file look through the scene camera and show materials."""
    import bpy

    for screen in bpy.data.screens:
        for area in screen.areas:
            if area.type != "VIEW_3D":
                continue
            for space in area.spaces:
                if space.type == "VIEW_3D":
                    space.region_3d.view_perspective = "CAMERA"
                    space.shading.type = "MATERIAL"


# --------------------------------------------------------------------------------------------------
# Geometry (numpy / bmesh; these build sample meshes once, they are not the deformer's hot path)
# --------------------------------------------------------------------------------------------------

REST_ATTRIBUTE = "sample_rest_position"


def mesh_from_bmesh(name: str, bm: object) -> object:
    import bpy

    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def box_bmesh(
    size: Sequence[float], cuts: Sequence[int], center: Sequence[float] = (0.0, 0.0, 0.0)
) -> object:
    """A closed all-quad box with outward normals and cuts[a] segments along axis a."""
    import bmesh
    from mathutils import Matrix, Vector

    bm = bmesh.new()
    transform = Matrix.Translation(center) @ Matrix.Diagonal((*size, 1.0))
    bmesh.ops.create_cube(bm, size=1.0, matrix=transform)
    for axis in range(3):
        normal = Vector((0.0, 0.0, 0.0))
        normal[axis] = 1.0
        for k in range(1, cuts[axis]):
            point = Vector(center)
            point[axis] += size[axis] * (k / cuts[axis] - 0.5)
            geometry = bm.verts[:] + bm.edges[:] + bm.faces[:]
            bmesh.ops.bisect_plane(bm, geom=geometry, dist=1e-7, plane_co=point, plane_no=normal)
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces[:])
    return bm


def polar_disc_mesh(name: str, radius: float, rings: int, segments: int) -> object:
    """A flat disc in the XY plane: a centre vertex, `rings` rings of `segments` vertices each."""
    import bpy

    radii = radius * np.arange(1, rings + 1) / rings
    angles = 2.0 * np.pi * np.arange(segments) / segments
    ring_xy = radii[:, None, None] * np.stack([np.cos(angles), np.sin(angles)], axis=-1)[None]
    vertices = np.zeros((1 + rings * segments, 3))
    vertices[1:, :2] = ring_xy.reshape(-1, 2)
    j = np.arange(segments)
    j_next = (j + 1) % segments
    fan = np.stack([np.zeros(segments, dtype=int), 1 + j, 1 + j_next], axis=1)
    ring = np.arange(rings - 1)[:, None]
    inner, outer = 1 + ring * segments, 1 + (ring + 1) * segments
    quads = np.stack([inner + j, outer + j, outer + j_next, inner + j_next], axis=-1).reshape(-1, 4)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices.tolist(), [], [*fan.tolist(), *quads.tolist()])
    mesh.validate()
    return mesh


def blob_figure_bmesh() -> object:
    """A character-like figure from overlapping ellipsoids in a T-pose; eyes use material index 1."""
    import bmesh
    from mathutils import Matrix

    bm = bmesh.new()

    def ellipsoid(center: Sequence[float], radii: Sequence[float], along_x: bool = False) -> list:
        # UV-sphere rings run along the pole axis; putting the poles on the limb's long axis gives the
        # limbs many rings along their length, so they bend smoothly.
        rotate = Matrix.Rotation(math.radians(90.0), 4, "Y") if along_x else Matrix.Identity(4)
        scale = Matrix.Diagonal((radii[2], radii[1], radii[0], 1.0) if along_x else (*radii, 1.0))
        transform = Matrix.Translation(center) @ rotate @ scale
        result = bmesh.ops.create_uvsphere(bm, u_segments=24, v_segments=16, radius=1.0, matrix=transform)
        return list({face for vertex in result["verts"] for face in vertex.link_faces})

    ellipsoid((0.0, 0.0, 1.25), (0.55, 0.42, 0.62))  # body
    ellipsoid((0.0, 0.0, 2.12), (0.36, 0.34, 0.36))  # head
    for side in (-1.0, 1.0):
        ellipsoid((side * 0.98, 0.0, 1.52), (0.55, 0.15, 0.15), along_x=True)  # arm
        ellipsoid((side * 0.27, 0.0, 0.45), (0.17, 0.17, 0.47))  # leg
        for face in ellipsoid((side * 0.13, -0.3, 2.2), (0.06, 0.06, 0.06)):  # eye
            face.material_index = 1
    return bm


def store_rest_attribute(mesh: object) -> None:
    """Copy the rest positions into a point attribute that the checker materials read."""
    coordinates = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", coordinates)
    attribute = mesh.attributes.new(REST_ATTRIBUTE, "FLOAT_VECTOR", "POINT")
    attribute.data.foreach_set("vector", coordinates)


def add_mesh_object(name: str, mesh: object, material: object | Iterable[object]) -> object:
    import bpy

    store_rest_attribute(mesh)
    materials = [material] if not isinstance(material, list | tuple) else material
    for item in materials:
        mesh.materials.append(item)
    for polygon in mesh.polygons:
        polygon.use_smooth = False
    return link(bpy.data.objects.new(name, mesh))


# --------------------------------------------------------------------------------------------------
# Controls: probes (Empties with a visible marker), keyframes, deformers
# --------------------------------------------------------------------------------------------------


def add_probe(name: str, location: Sequence[float], marker_axis: str = "X", size: float = 0.35) -> object:
    """An Empty probe plus a small red arrow parented to it, so renders show the probe's motion.

    The arrow is not selectable: clicking in the viewport picks the Empty, which is the control.
    """
    import bmesh
    import bpy
    from mathutils import Matrix

    probe = link(bpy.data.objects.new(name, None))
    probe.empty_display_type = "ARROWS"
    probe.empty_display_size = size * 1.4
    probe.location = location
    probe.rotation_mode = "XYZ"

    bm = bmesh.new()
    to_axis = {
        "X": Matrix.Rotation(math.radians(-90.0), 4, "Y"),
        "Y": Matrix.Rotation(math.radians(90.0), 4, "X"),
        "Z": Matrix.Identity(4),
    }[marker_axis]
    # The shaft starts at the probe's origin; the head sits at the far end of the shaft.
    bmesh.ops.create_cone(
        bm,
        cap_ends=True,
        segments=12,
        radius1=0.05 * size / 0.35,
        radius2=0.05 * size / 0.35,
        depth=size,
        matrix=to_axis @ Matrix.Translation((0.0, 0.0, size / 2.0)),
    )
    bmesh.ops.create_cone(
        bm,
        cap_ends=True,
        segments=16,
        radius1=0.14 * size / 0.35,
        radius2=0.0,
        depth=0.3 * size,
        matrix=to_axis @ Matrix.Translation((0.0, 0.0, size * 1.15)),
    )
    bmesh.ops.create_uvsphere(bm, u_segments=16, v_segments=8, radius=0.09 * size / 0.35)
    mesh = mesh_from_bmesh(f"{name}.marker", bm)
    mesh.materials.append(probe_material())
    marker = link(bpy.data.objects.new(f"{name}.marker", mesh))
    marker.parent = probe
    marker.hide_select = True
    return probe


def probe_material() -> object:
    import bpy

    existing = bpy.data.materials.get("Probe")
    if existing is not None:
        return existing
    material = plain_material("Probe", PROBE_RED, roughness=0.35)
    bsdf = _principled(material)
    bsdf.inputs["Emission Color"].default_value = (*PROBE_RED, 1.0)
    bsdf.inputs["Emission Strength"].default_value = 0.6
    return material


def key_transforms(obj: object, frames: dict[int, dict[str, Sequence[float]]]) -> None:
    """Keyframe location / rotation_euler (degrees) / scale of obj (or a pose bone) at the given frames."""
    for frame, channels in sorted(frames.items()):
        for channel, value in channels.items():
            if channel == "rotation_euler":
                obj.rotation_euler = [math.radians(v) for v in value]
            else:
                setattr(obj, channel, value)
            obj.keyframe_insert(channel, frame=frame)


def fcurves(id_data: object) -> list:
    """The F-curves animating an ID (layered actions of Blender 4.4+, or a legacy action's list)."""
    animation = id_data.animation_data
    if animation is None or animation.action is None:
        return []
    action = animation.action
    legacy = getattr(action, "fcurves", None)
    if legacy is not None and len(legacy):
        return list(legacy)
    from bpy_extras import anim_utils

    channelbag = anim_utils.action_get_channelbag_for_slot(action, animation.action_slot)
    return list(channelbag.fcurves) if channelbag is not None else []


def make_linear(id_data: object) -> None:
    """Constant-speed motion between keys (the default Bézier keys ease in and out)."""
    for curve in fcurves(id_data):
        for point in curve.keyframe_points:
            point.interpolation = "LINEAR"


def select_only(active: object, others: Sequence[object]) -> None:
    import bpy

    for obj in bpy.context.view_layer.objects:
        obj.select_set(False)
    for obj in (active, *others):
        obj.select_set(True)
    bpy.context.view_layer.objects.active = active


def configure_deformer(target: object, index: int, settings: dict[str, object], todo: list[str]) -> None:
    """Set deformer properties that exist (and enum values that are valid); report the rest."""
    deformer = target.affine_deformers[index]
    properties = deformer.bl_rna.properties
    for name, value in settings.items():
        if name not in properties:
            todo.append(f"{target.name}: deformer has no property {name!r} (wanted {value!r})")
            continue
        prop = properties[name]
        if prop.type == "ENUM" and value not in prop.enum_items:
            todo.append(f"{target.name}: {name}={value!r} is not one of {list(prop.enum_items.keys())}")
            continue
        setattr(deformer, name, value)


def add_deformer(
    kind: str, target: object, controls: Sequence[object], settings: dict[str, object], todo: list[str]
) -> bool:
    """Add and bind a 'probe' or 'cage' deformer the way scripts do, at the current frame (the rest pose).

    Active object = target; selected = target + controls (the probe Empties, or the cage mesh).
    """
    import bpy

    operator = f"affine_{kind}_deformer_add"
    if not operator_available(f"OBJECT_OT_{operator}"):
        todo.append(f"{target.name}: {kind} deformer operator missing; saved WITHOUT a deformer (TODO)")
        return False
    select_only(target, controls)
    with bpy.context.temp_override(
        active_object=target,
        object=target,
        selected_objects=[target, *controls],
        selected_editable_objects=[target, *controls],
    ):
        result = getattr(bpy.ops.object, operator)()
    if "FINISHED" not in result:
        raise RuntimeError(f"{operator} on {target.name} returned {result}")
    # Weight options re-weight a bound deformer at once, from the rest data stored at bind.
    configure_deformer(target, len(target.affine_deformers) - 1, settings, todo)
    return True


def mark_target(obj: object, method: str) -> None:
    obj["affdef_sample_target"] = method


# --------------------------------------------------------------------------------------------------
# The samples
# --------------------------------------------------------------------------------------------------


def build_probe_bend() -> SampleInfo:
    """A bar bent into a U, then an S, twisted and bulged by three probes (notes, fig. 18)."""
    todo: list[str] = []
    scene = new_scene("probe_bend", frame_end=72)
    bar = add_mesh_object(
        "Bar",
        mesh_from_bmesh("Bar", box_bmesh(size=(8.0, 0.8, 0.8), cuts=(64, 6, 6))),
        checker_material("Bar", (0.8, 0.32, 0.04), (0.9, 0.88, 0.82), scale=(2.5, 2.5, 2.5)),
    )
    left = add_probe("Probe.Left", (-4.0, 0.0, 0.0))
    middle = add_probe("Probe.Middle", (0.0, 0.0, 0.0), marker_axis="Z")
    right = add_probe("Probe.Right", (4.0, 0.0, 0.0))
    key_transforms(
        left,
        {
            1: {"location": (-4.0, 0.0, 0.0), "rotation_euler": (0, 0, 0)},
            24: {"location": (-3.6, 0.0, 1.6), "rotation_euler": (0, 50, 0)},
            48: {"location": (-3.6, 0.0, 1.6), "rotation_euler": (0, 50, 0)},
            72: {"location": (-4.0, 0.0, 0.0), "rotation_euler": (0, 0, 0)},
        },
    )
    key_transforms(
        middle,
        {
            1: {"location": (0.0, 0.0, 0.0), "rotation_euler": (0, 0, 0), "scale": (1, 1, 1)},
            24: {"location": (0.0, 0.0, 0.0), "rotation_euler": (0, 0, 0), "scale": (1, 1, 1)},
            48: {"location": (0.0, 0.0, -0.4), "rotation_euler": (60, 0, 0), "scale": (1.7, 1.7, 1.7)},
            72: {"location": (0.0, 0.0, 0.0), "rotation_euler": (90, 0, 0), "scale": (1, 1, 1)},
        },
    )
    key_transforms(
        right,
        {
            1: {"location": (4.0, 0.0, 0.0), "rotation_euler": (0, 0, 0), "scale": (1, 1, 1)},
            24: {"location": (3.6, 0.0, 1.6), "rotation_euler": (0, -50, 0), "scale": (1, 1, 1)},
            48: {"location": (3.6, 0.0, 1.6), "rotation_euler": (0, -50, 0), "scale": (1, 1, 1)},
            72: {"location": (3.5, 0.0, -1.4), "rotation_euler": (0, 60, 0), "scale": (0.5, 0.5, 0.5)},
        },
    )
    scene.frame_set(1)
    add_deformer("probe", bar, [left, middle, right], {"blend_mode": "AFFINE_LOG"}, todo)
    mark_target(bar, "AFFINE_LOG")
    add_ground(-2.6)
    add_camera((0.0, -11.8, 2.6), (0.0, 0.0, 0.1), lens=40.0)
    add_lights()
    return SampleInfo(key_frames=[1, 24, 48, 72], todo=todo)


def build_probe_vortex() -> SampleInfo:
    """A disc swirled by a centre probe turning 450° about Z over the timeline (notes, fig. 19)."""
    todo: list[str] = []
    scene = new_scene("probe_vortex", frame_end=97)
    disc = add_mesh_object(
        "Disc",
        polar_disc_mesh("Disc", radius=3.0, rings=30, segments=120),
        checker_material("Disc", (0.08, 0.2, 0.6), (0.9, 0.92, 0.95), scale=(16.0, 2.0, 1.0), polar=True),
    )
    probe = add_probe("Probe.Vortex", (0.0, 0.0, 0.0), marker_axis="X", size=0.8)
    # Constant speed: 150° every 32 frames, so the key frames 1, 33, 65, 97 show 0°, 150°, 300°, 450°.
    key_transforms(probe, {1: {"rotation_euler": (0, 0, 0)}, 97: {"rotation_euler": (0, 0, 450)}})
    make_linear(probe)
    scene.frame_set(1)
    # Unnormalised falloff: vertices beyond the radius keep weight 0 and stay put, the centre turns
    # with the probe, and the rings in between turn by their weight times the probe's angle.
    add_deformer(
        "probe",
        disc,
        [probe],
        {"weight_mode": "FALLOFF", "radius": 2.7, "normalize": "NONE", "blend_mode": "AFFINE_LOG"},
        todo,
    )
    mark_target(disc, "AFFINE_LOG")
    add_ground(-0.05)
    add_camera((0.0, -7.2, 6.6), (0.0, -0.2, 0.0), lens=40.0)
    add_lights()
    return SampleInfo(key_frames=[1, 33, 65, 97], todo=todo)


CAGE_SHAPES: dict[str, Callable[[np.ndarray], np.ndarray]] = {}


def _cage_shape(name: str) -> Callable:
    def register(function: Callable[[np.ndarray], np.ndarray]) -> Callable:
        CAGE_SHAPES[name] = function
        return function

    return register


@_cage_shape("RaiseArm")
def _raise_right_arm(co: np.ndarray) -> np.ndarray:
    """Lift the cage's right end above the hips, pivoting about the shoulder."""
    out = co.copy()
    lifted = (co[:, 0] > 0.5) & (co[:, 2] > 0.5)
    reach = np.clip((co[:, 0] - 0.5) / 1.2, 0.0, 1.0)
    out[lifted, 2] += 1.1 * reach[lifted]
    out[lifted, 0] -= 0.3 * reach[lifted]
    return out


@_cage_shape("Lean")
def _lean(co: np.ndarray) -> np.ndarray:
    """Shear the upper cage sideways (more at the top), the feet stay."""
    out = co.copy()
    out[:, 0] += 0.55 * np.clip((co[:, 2] - 0.3) / 2.45, 0.0, 1.0) ** 2
    return out


def squashed(co: np.ndarray, height: float, bulge: float) -> np.ndarray:
    """`co` squashed vertically to `height` times its height about its base, widened `bulge` times."""
    out = co.copy()
    base = co[:, 2].min()
    out[:, 2] = base + height * (co[:, 2] - base)
    out[:, :2] *= bulge
    return out


@_cage_shape("Squash")
def _squash(co: np.ndarray) -> np.ndarray:
    """Squash vertically and bulge sideways, about the cage's base."""
    return squashed(co, 0.72, 1.25)


def build_cage_deform() -> SampleInfo:
    """A blob figure inside a coarse closed quad cage whose shape keys raise an arm, lean, squash."""
    import bpy

    todo: list[str] = []
    scene = new_scene("cage_deform", frame_end=72)
    figure = add_mesh_object(
        "Figure",
        mesh_from_bmesh("Figure", blob_figure_bmesh()),
        [
            plain_material("Figure", (0.85, 0.32, 0.12), roughness=0.4),
            plain_material("Eyes", (0.01, 0.01, 0.01), roughness=0.2),
        ],
    )
    for polygon in figure.data.polygons:
        polygon.use_smooth = True
    cage_mesh = mesh_from_bmesh("Cage", box_bmesh(size=(3.4, 1.3, 2.9), cuts=(4, 1, 3), center=(0, 0, 1.3)))
    cage = link(bpy.data.objects.new("Cage", cage_mesh))
    cage.display_type = "WIRE"
    # Hidden in renders as artists do; the deformer's modifier references the cage, so Blender still
    # evaluates it (shape keys included) in the render depsgraph.
    cage.hide_render = True
    basis = cage.shape_key_add(name="Basis", from_mix=False)
    rest = np.empty(len(cage_mesh.vertices) * 3)
    basis.data.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)
    for name, shape in CAGE_SHAPES.items():
        block = cage.shape_key_add(name=name, from_mix=False)
        block.data.foreach_set("co", shape(rest).ravel())
    values = {
        "RaiseArm": {1: 0.0, 24: 1.0, 48: 1.0, 72: 0.0},
        "Lean": {1: 0.0, 24: 0.0, 48: 1.0, 72: 0.0},
        "Squash": {1: 0.0, 24: 0.0, 48: 0.0, 72: 1.0},
    }
    for name, keys in values.items():
        block = cage_mesh.shape_keys.key_blocks[name]
        for frame, value in keys.items():
            block.value = value
            block.keyframe_insert("value", frame=frame)
    # The cage is hidden in renders; a linked duplicate sharing its mesh (and so its shape keys) shows
    # it as thin tubes without touching the cage's own evaluated geometry.
    wire = link(bpy.data.objects.new("Cage.wire", cage_mesh))
    modifier = wire.modifiers.new("Wireframe", "WIREFRAME")
    modifier.thickness = 0.025
    modifier.use_replace = True
    modifier.material_offset = 0
    wire_material = plain_material("CageWire", (0.05, 0.12, 0.45), roughness=0.3)
    wire.data.materials.append(wire_material)
    wire.hide_select = True
    wire.hide_viewport = True
    scene.frame_set(1)
    add_deformer("cage", figure, [cage], {"blend_mode": "AFFINE_LOG"}, todo)
    mark_target(figure, "AFFINE_LOG")
    add_ground(-0.16)
    add_camera((1.2, -9.5, 3.6), (0.0, 0.0, 1.35), lens=40.0)
    add_lights(target=(0.0, 0.0, 1.3))
    return SampleInfo(key_frames=[1, 24, 48, 72], todo=todo)


#: Shape keys of the made cage in made_cage.blend: functions of the cage's rest vertices, so they fit
#: whatever cage the add operator makes.
MADE_CAGE_SHAPES: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
MADE_CAGE_TILT = 25.0  # degrees the top of the cage leans sideways by in its "Tilt" key


def _made_cage_shape(name: str) -> Callable:
    def register(function: Callable[[np.ndarray], np.ndarray]) -> Callable:
        MADE_CAGE_SHAPES[name] = function
        return function

    return register


@_made_cage_shape("Tilt")
def _tilt_top(co: np.ndarray) -> np.ndarray:
    """Lean the cage's top half sideways (about the Y axis through its middle height), by MADE_CAGE_TILT
    at the top and smoothly less down to the middle (the chin stays)."""
    middle, top = 0.5 * (co[:, 2].min() + co[:, 2].max()), co[:, 2].max()
    t = np.clip((co[:, 2] - middle) / (top - middle), 0.0, 1.0)
    angle = math.radians(MADE_CAGE_TILT) * t * t * (3.0 - 2.0 * t)
    out = co.copy()
    x, z = co[:, 0], co[:, 2] - middle
    out[:, 0] = np.cos(angle) * x + np.sin(angle) * z
    out[:, 2] = middle - np.sin(angle) * x + np.cos(angle) * z
    return out


@_made_cage_shape("EarsUp")
def _ears_up(co: np.ndarray) -> np.ndarray:
    """Lift the cage around the ears (beyond the cheeks, |x| > 0.8) and spread it a little."""
    reach = np.clip((np.abs(co[:, 0]) - 0.8) / 0.6, 0.0, 1.0) ** 2
    out = co.copy()
    out[:, 2] += 0.5 * reach
    out[:, 0] += 0.15 * reach * np.sign(co[:, 0])
    return out


@_made_cage_shape("Squash")
def _squash_head(co: np.ndarray) -> np.ndarray:
    """Squash vertically about the cage's base and bulge sideways."""
    return squashed(co, 0.75, 1.18)


def suzanne_mesh(name: str, levels: int = 2) -> object:
    """Blender's Suzanne (size 2) with a Subdivision modifier of `levels` applied."""
    import bpy

    bpy.ops.mesh.primitive_monkey_add(size=2.0, location=(0.0, 0.0, 0.0))
    head = bpy.context.active_object
    modifier = head.modifiers.new("Subdivision", "SUBSURF")
    modifier.levels = modifier.render_levels = levels
    mesh = bpy.data.meshes.new_from_object(head.evaluated_get(bpy.context.evaluated_depsgraph_get()))
    primitive = head.data
    bpy.data.objects.remove(head, do_unlink=True)
    bpy.data.meshes.remove(primitive)
    mesh.name = name
    return mesh


def build_made_cage() -> SampleInfo:
    """Suzanne with a cage deformer added with no cage selected, so the add operator makes her cage
    (issue #50); the made cage's shape keys lean her head, lift her ears and squash her."""
    import bpy

    todo: list[str] = []
    scene = new_scene("made_cage", frame_end=72)
    head = add_mesh_object(
        "Suzanne",
        suzanne_mesh("Suzanne", levels=1),
        plain_material("Suzanne", (0.85, 0.32, 0.12), roughness=0.4),
    )
    head.data.polygons.foreach_set("use_smooth", np.ones(len(head.data.polygons), dtype=bool))
    scene.frame_set(1)
    # Only the mesh selected: the add operator makes the cage "Suzanne Cage" around it and binds.
    if not add_deformer("cage", head, [], {"blend_mode": "AFFINE_LOG"}, todo):
        return SampleInfo(key_frames=[1, 24, 48, 72], todo=todo)
    mark_target(head, "AFFINE_LOG")
    cage = head.affine_deformers[len(head.affine_deformers) - 1].cage
    if cage is None or cage == head:
        raise RuntimeError("the cage deformer added with no cage selected has no cage")
    cage_mesh = cage.data
    basis = cage.shape_key_add(name="Basis", from_mix=False)
    rest = np.empty(len(cage_mesh.vertices) * 3)
    basis.data.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)
    for name, shape in MADE_CAGE_SHAPES.items():
        block = cage.shape_key_add(name=name, from_mix=False)
        block.data.foreach_set("co", shape(rest).ravel())
    values = {
        "Tilt": {1: 0.0, 24: 1.0, 48: 1.0, 72: 0.0},
        "EarsUp": {1: 0.0, 24: 0.0, 48: 1.0, 72: 0.0},
        "Squash": {1: 0.0, 48: 0.0, 72: 1.0},
    }
    for name, keys in values.items():
        block = cage_mesh.shape_keys.key_blocks[name]
        for frame, value in keys.items():
            block.value = value
            block.keyframe_insert("value", frame=frame)
    # The made cage is hidden in renders; as in cage_deform.blend, a linked duplicate sharing its mesh
    # (and so its shape keys) shows it as thin tubes.
    wire = link(bpy.data.objects.new(f"{cage.name}.wire", cage_mesh))
    modifier = wire.modifiers.new("Wireframe", "WIREFRAME")
    modifier.thickness = 0.018
    modifier.use_replace = True
    modifier.material_offset = 0
    cage_mesh.materials.append(plain_material("CageWire", (0.05, 0.12, 0.45), roughness=0.3))
    wire.hide_select = True
    wire.hide_viewport = True
    # Subdivision after ours smooths the renders (the viewport shows the mesh the cage deforms).
    smooth = head.modifiers.new("Subdivision", "SUBSURF")
    smooth.levels, smooth.render_levels = 0, 1
    scene.frame_set(1)
    add_ground(-1.25)
    add_camera((2.3, -7.6, 1.8), (0.0, 0.0, 0.3), lens=50.0)
    add_lights()
    return SampleInfo(key_frames=[1, 24, 48, 72], todo=todo)


def twist_weights(x: np.ndarray, half_length: float) -> np.ndarray:
    """Weight of the right-hand control along a bar: smoothstep from 0 at the left end to 1 at the right."""
    s = np.clip((x + half_length) / (2.0 * half_length), 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def add_twist_groups(bar: object, left: str, right: str, half_length: float) -> None:
    """Vertex groups named after the left/right controls with complementary smoothstep weights."""
    co = np.empty(len(bar.data.vertices) * 3)
    bar.data.vertices.foreach_get("co", co)
    w_right = twist_weights(co.reshape(-1, 3)[:, 0], half_length)
    left_group, right_group = bar.vertex_groups.new(name=left), bar.vertex_groups.new(name=right)
    # Vertex group API takes one weight for a list of indices; group vertices by distinct weight.
    for weight in np.unique(w_right):
        indices = np.flatnonzero(w_right == weight).tolist()
        right_group.add(indices, float(weight), "REPLACE")
        left_group.add(indices, float(1.0 - weight), "REPLACE")


TWIST_KEYS = {1: 0.0, 24: 45.0, 48: 90.0, 72: 150.0}


def build_comparison() -> SampleInfo:
    """One ±90° (then ±150°) end twist, three ways: linear blend, dual quaternions, Aff+(3) log blend."""
    import bpy

    todo: list[str] = []
    scene = new_scene("comparison", frame_end=72)
    half_length, gap = 2.0, 1.9
    # Each end turns by at most 150°, so every control stays on the principal rotation-log branch.
    rows = [
        ("LINEAR", "linear", gap),
        ("DQS", "dual quat", 0.0),
        ("AFFINE_LOG", "Aff+(3)", -gap),
    ]
    colors = {"LINEAR": (0.7, 0.12, 0.1), "DQS": (0.15, 0.45, 0.15), "AFFINE_LOG": (0.1, 0.3, 0.75)}
    for method, caption, z in rows:
        bar = add_mesh_object(
            f"Bar.{method}",
            mesh_from_bmesh(f"Bar.{method}", box_bmesh(size=(2 * half_length, 0.55, 0.55), cuts=(48, 4, 4))),
            checker_material(f"Bar.{method}", colors[method], (0.95, 0.93, 0.88), scale=(3.0, 3.6, 3.6)),
        )
        bar.location = (0.0, 0.0, z)
        add_label(caption, (-half_length - 0.7, 0.0, z), size=0.42, align="RIGHT")
        mark_target(bar, method)
        left_name, right_name = f"{method}.Left", f"{method}.Right"
        add_twist_groups(bar, left_name, right_name, half_length)
        keys_left = {f: {"rotation_euler": (-a, 0, 0)} for f, a in TWIST_KEYS.items()}
        keys_right = {f: {"rotation_euler": (a, 0, 0)} for f, a in TWIST_KEYS.items()}
        if method == "DQS":
            armature = bpy.data.armatures.new("Twist")
            rig = link(bpy.data.objects.new("Twist.Rig", armature))
            rig.location = bar.location
            bpy.context.view_layer.objects.active = rig
            bpy.ops.object.mode_set(mode="EDIT")
            for name, head, tail in ((left_name, -half_length, 0.0), (right_name, 0.0, half_length)):
                bone = armature.edit_bones.new(name)
                bone.head, bone.tail, bone.roll = (head, 0.0, 0.0), (tail, 0.0, 0.0), 0.0
            bpy.ops.object.mode_set(mode="OBJECT")
            armature.display_type = "STICK"
            # Both bones point along +X, so a turn about a bone's own Y axis is the probes' turn about X.
            for name, keys in ((left_name, keys_left), (right_name, keys_right)):
                pose_bone = rig.pose.bones[name]
                pose_bone.rotation_mode = "XYZ"
                key_transforms(
                    pose_bone,
                    {f: {"rotation_euler": (0, v["rotation_euler"][0], 0)} for f, v in keys.items()},
                )
            bar.parent = rig
            bar.location = (0.0, 0.0, 0.0)
            modifier = bar.modifiers.new("Armature", "ARMATURE")
            modifier.object = rig
            modifier.use_deform_preserve_volume = True
            modifier.use_vertex_groups = True
            continue
        offset = half_length + 0.25
        left = add_probe(left_name, (-offset, 0.0, z), marker_axis="Z", size=0.4)
        right = add_probe(right_name, (offset, 0.0, z), marker_axis="Z", size=0.4)
        key_transforms(left, keys_left)
        key_transforms(right, keys_right)
        scene.frame_set(1)
        # The same weights as the Armature: the vertex groups named after the two controls.
        settings = {"blend_mode": method, "weight_mode": "VERTEX_GROUPS", "normalize": "SUM"}
        add_deformer("probe", bar, [left, right], settings, todo)
    add_camera((1.6, -9.8, 2.2), (-1.0, 0.0, 0.0), lens=40.0)
    add_lights(target=(-0.5, 0.0, 0.0))
    return SampleInfo(key_frames=[1, 24, 48, 72], todo=todo)


def build_stack() -> SampleInfo:
    """The deformer in a production stack: shape key → Armature → Affine probes → Subdivision. A bar
    bulges (shape key, frame 24), its right half twists 90° (Armature with Preserve Volume, frame 48),
    and our probes bend the bulged, twisted bar into a U (frame 72); Subdivision smooths it in renders."""
    import bpy

    todo: list[str] = []
    scene = new_scene("stack", frame_end=72)
    half_length = 3.0
    bar = add_mesh_object(
        "Bar",
        mesh_from_bmesh("Bar", box_bmesh(size=(2 * half_length, 0.7, 0.7), cuts=(48, 4, 4))),
        checker_material("Bar", (0.15, 0.45, 0.6), (0.93, 0.9, 0.84), scale=(3.0, 3.0, 3.0)),
    )
    # 1. A shape key: the middle bulges.
    bar.shape_key_add(name="Basis", from_mix=False)
    bulge = bar.shape_key_add(name="Bulge", from_mix=False)
    co = np.empty(len(bar.data.vertices) * 3, dtype=np.float32)
    bar.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    grow = 1.0 + 0.8 * np.exp(-((co[:, 0] / 1.1) ** 2))
    bulge.data.foreach_set("co", (co * np.stack([np.ones_like(grow), grow, grow], 1)).ravel())
    for frame, value in ((1, 0.0), (24, 1.0)):
        bulge.value = value
        bulge.keyframe_insert("value", frame=frame)
    # 2. An Armature twists the right half (bones along +X, turned about their own Y axis).
    armature = bpy.data.armatures.new("Stack")
    rig = link(bpy.data.objects.new("Stack.Rig", armature))
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    for name, head, tail in (("Left", -half_length, 0.0), ("Right", 0.0, half_length)):
        bone = armature.edit_bones.new(name)
        bone.head, bone.tail, bone.roll = (head, 0.0, 0.0), (tail, 0.0, 0.0), 0.0
    bpy.ops.object.mode_set(mode="OBJECT")
    armature.display_type = "STICK"
    rig.hide_render = True
    add_twist_groups(bar, "Left", "Right", half_length)
    right_bone = rig.pose.bones["Right"]
    right_bone.rotation_mode = "XYZ"
    key_transforms(right_bone, {1: {"rotation_euler": (0, 0, 0)}, 24: {"rotation_euler": (0, 0, 0)},
                                48: {"rotation_euler": (0, 90, 0)}})
    skin = bar.modifiers.new("Armature", "ARMATURE")
    skin.object = rig
    skin.use_deform_preserve_volume = True
    # 3. Our probes bend the result into a U.
    left = add_probe("Probe.Left", (-half_length, 0.0, 0.0))
    middle = add_probe("Probe.Middle", (0.0, 0.0, 0.0), marker_axis="Z")
    right = add_probe("Probe.Right", (half_length, 0.0, 0.0))
    for probe, sign in ((left, -1.0), (right, 1.0)):
        rest = {"location": (sign * half_length, 0.0, 0.0), "rotation_euler": (0, 0, 0)}
        key_transforms(probe, {1: rest, 48: rest,
                               72: {"location": (sign * (half_length - 0.5), 0.0, 1.8),
                                    "rotation_euler": (0, -sign * 55, 0)}})
    scene.frame_set(1)
    add_deformer("probe", bar, [left, middle, right], {}, todo)
    mark_target(bar, "AFFINE_LOG")
    # 4. Subdivision after ours, in renders (the viewport shows the cage of the stack).
    smooth = bar.modifiers.new("Subdivision", "SUBSURF")
    smooth.levels, smooth.render_levels = 0, 1
    add_ground(-2.2)
    add_camera((0.0, -11.5, 2.4), (0.0, 0.0, 0.3), lens=40.0)
    add_lights()
    return SampleInfo(key_frames=[1, 24, 48, 72], todo=todo)


TAIL_LENGTH = 5.0
TAIL_BONES = 6
#: Frames 1 → 21: the chain swings into a wave (each bone but the root and the tip turns about its own
#: X axis, degrees; + curls up) and the middle bone scales non-uniformly (its X is the tail's depth,
#: its Z the height); by frame 41 the tail is straight again and the tip starts to twist about its own
#: axis at constant speed, 10° a frame up to 450° at frame 86: the key frames 56, 68 and 86 show 150°,
#: 270° and 450°, and the tip passes 180° at frame 59. The twist runs on a straight chain so that its
#: cross-sections compare directly with the Armature modifier's (a bent chain twists as cleanly: the
#: bar test of tests/blender/test_bone_deformer.py measures that).
TAIL_WAVE = {1: (0.0, 0.0, 0.0, 0.0), 21: (10.0, 10.0, -10.0, -10.0), 41: (0.0, 0.0, 0.0, 0.0)}
TAIL_SCALE = {1: (1.0, 1.0, 1.0), 21: (1.2, 1.0, 1.7)}
TAIL_TWIST = {1: 0.0, 41: 0.0, 86: 450.0}
TAIL_SCALED_BONE = 2


def tail_mesh(name: str, length: float, rings: int, segments: int) -> object:
    """A tapering tail along +X from 0 to `length`: an elliptical tube (twice as tall as it is deep, so
    a twist shows in its silhouette), `rings` + 1 rings of `segments` vertices, a flat cap at the root
    and a pointed one at the tip."""
    import bpy

    x = length * np.arange(rings + 1) / rings
    height = 0.45 * (1.0 - 0.5 * x / length)  # half-height; the half-depth is half of it
    angles = 2.0 * np.pi * np.arange(segments) / segments
    ring = np.stack([np.broadcast_to(x[:, None], (rings + 1, segments)),
                     0.5 * height[:, None] * np.cos(angles)[None],
                     height[:, None] * np.sin(angles)[None]], axis=-1).reshape(-1, 3)
    root, tip = ring.shape[0], ring.shape[0] + 1
    vertices = np.concatenate([ring, [[0.0, 0.0, 0.0], [length + 0.8 * height[-1], 0.0, 0.0]]])
    j = np.arange(segments)
    j_next = (j + 1) % segments
    k = np.arange(rings)[:, None] * segments
    # Winding chosen so that every face's normal points out of the tail.
    quads = np.stack([k + j, k + j_next, k + segments + j_next, k + segments + j], axis=-1).reshape(-1, 4)
    root_fan = np.stack([np.full(segments, root), j_next, j], axis=1)
    last = rings * segments
    tip_fan = np.stack([np.full(segments, tip), last + j, last + j_next], axis=1)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices.tolist(), [], [*root_fan.tolist(), *quads.tolist(), *tip_fan.tolist()])
    mesh.validate()
    return mesh


def chain_weights(x: np.ndarray, heads: np.ndarray, reach: float = 1.5) -> np.ndarray:
    """(N, m) skin weights of a chain of bones heads[i] → heads[i + 1] along x, smooth (C¹) in x:
    bone i's raw weight is a smoothstep bump that is 1 at the bone's centre and 0 at `reach` bone
    lengths from it (1 before the first centre and after the last, so the ends are held by the end
    bones alone); the bumps are normalised to sum to 1. With reach 1.5 a point is shared by two or
    three bones, as a painted skin is."""
    centers = 0.5 * (heads[:-1] + heads[1:])
    lengths = np.diff(heads)
    f = np.clip(1.0 - np.abs(x[:, None] - centers[None, :]) / (reach * lengths[None, :]), 0.0, 1.0)
    bumps = f * f * (3.0 - 2.0 * f)  # flat at the centre, so the end clamps below keep it C¹
    bumps[x <= centers[0], 0] = 1.0
    bumps[x >= centers[-1], -1] = 1.0
    return bumps / bumps.sum(axis=1, keepdims=True)


def paint_groups(obj: object, names: Sequence[str], weights: np.ndarray) -> None:
    """Vertex groups `names` with the weights (N, m); zeros are left out of a group. VertexGroup.add
    takes one weight for a list of indices, so the vertices are added per distinct weight value."""
    for column, name in enumerate(names):
        group = obj.vertex_groups.new(name=name)
        for value in np.unique(weights[:, column]):
            if value > 0.0:
                group.add(np.flatnonzero(weights[:, column] == value).tolist(), float(value), "REPLACE")


def add_bone_chain(name: str, heads: np.ndarray, location: Sequence[float]) -> object:
    """An armature object at `location` with a chain of connected bones Tail.0, Tail.1, … along +X
    (roll 0: a bone's Y axis is +X, its X axis −Y, its Z axis +Z). The bone after the scaled one does
    not inherit scale, so the scale stays on that bone."""
    import bpy

    armature = bpy.data.armatures.new(name)
    rig = link(bpy.data.objects.new(name, armature))
    rig.location = location
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    previous = None
    for i in range(len(heads) - 1):
        bone = armature.edit_bones.new(f"Tail.{i}")
        bone.head, bone.tail, bone.roll = (float(heads[i]), 0.0, 0.0), (float(heads[i + 1]), 0.0, 0.0), 0.0
        if previous is not None:
            bone.parent, bone.use_connect = previous, True
        if i == TAIL_SCALED_BONE + 1:
            bone.inherit_scale = "NONE"
        previous = bone
    bpy.ops.object.mode_set(mode="OBJECT")
    armature.display_type = "STICK"
    return rig


def key_tail(rig: object) -> None:
    """Keyframe the tail's wave, the middle bone's scale and the tip's constant-speed twist."""
    bones = rig.pose.bones
    for pose_bone in bones:
        pose_bone.rotation_mode = "XYZ"
    for i in range(1, TAIL_BONES - 1):
        key_transforms(bones[i], {f: {"rotation_euler": (a[i - 1], 0, 0)} for f, a in TAIL_WAVE.items()})
    key_transforms(bones[TAIL_SCALED_BONE], {f: {"scale": s} for f, s in TAIL_SCALE.items()})
    tip = bones[TAIL_BONES - 1]
    # A bone's own axis is its local Y.
    key_transforms(tip, {f: {"rotation_euler": (0, a, 0)} for f, a in TAIL_TWIST.items()})
    for curve in fcurves(rig):  # constant speed (the twist's first two keys are both 0°)
        if curve.data_path.startswith(f'pose.bones["{tip.name}"]'):
            for point in curve.keyframe_points:
                point.interpolation = "LINEAR"


def build_bone_tail() -> SampleInfo:
    """A six-bone tail that swings into a wave and scales its middle bone non-uniformly, then twists
    its tip 0° → 450°: the same mesh and vertex groups skinned by Blender's Armature modifier with
    Preserve Volume (top) and by our bone deformer, converted from an identical Armature modifier
    (bottom)."""
    import bpy

    todo: list[str] = []
    scene = new_scene("bone_tail", frame_end=max(TAIL_TWIST))
    heads = np.linspace(0.0, TAIL_LENGTH, TAIL_BONES + 1)
    names = [f"Tail.{i}" for i in range(TAIL_BONES)]
    rows = [
        ("DQS", "Armature modifier, Preserve Volume", 1.05, (0.15, 0.45, 0.15)),
        ("AFFINE_LOG", "Affine bone deformer (ours)", -0.95, (0.1, 0.3, 0.75)),
    ]
    for method, caption, z, color in rows:
        rig = add_bone_chain(f"Rig.{method}", heads, (-0.5 * TAIL_LENGTH, 0.0, z))
        key_tail(rig)
        tail = add_mesh_object(
            f"Tail.{method}",
            tail_mesh(f"Tail.{method}", TAIL_LENGTH, rings=150, segments=32),
            checker_material(f"Tail.{method}", color, (0.95, 0.93, 0.88), scale=(8.0, 0.0, 2.4), polar=True,
                             polar_axis="X"),
        )
        tail.data.polygons.foreach_set("use_smooth", np.ones(len(tail.data.polygons), dtype=bool))
        tail.parent = rig  # the rig's origin is the tail's: both see the bones where the mesh is
        x = np.empty(len(tail.data.vertices) * 3)
        tail.data.vertices.foreach_get("co", x)
        paint_groups(tail, names, chain_weights(x.reshape(-1, 3)[:, 0], heads))
        # Below the tail's root half: the wave lifts the tail, the bulge is above and below its middle.
        add_label(caption, (-0.5 * TAIL_LENGTH, 0.0, z - 0.74), size=0.24, align="LEFT")
        mark_target(tail, method)
        modifier = tail.modifiers.new("Armature", "ARMATURE")
        modifier.object = rig
        modifier.use_deform_preserve_volume = True
        modifier.use_vertex_groups = True
        modifier.use_bone_envelopes = False
        if method == "DQS":
            continue
        # Ours replaces an identical Armature modifier, which stays in the stack (disabled): toggle the
        # two to compare on the same object.
        scene.frame_set(1)
        if not operator_available("OBJECT_OT_affine_armature_convert"):
            todo.append(f"{tail.name}: armature convert operator missing; saved WITHOUT a deformer (TODO)")
            continue
        select_only(tail, [])
        with bpy.context.temp_override(active_object=tail, object=tail, selected_objects=[tail],
                                       selected_editable_objects=[tail]):
            result = bpy.ops.object.affine_armature_convert(modifier=modifier.name)
        if "FINISHED" not in result:
            raise RuntimeError(f"affine_armature_convert on {tail.name} returned {result}")
    add_camera((0.25, -9.2, 0.3), (0.25, 0.0, -0.12), lens=50.0)
    add_lights()
    return SampleInfo(key_frames=[1, 21, 56, 68, 86], todo=todo)


#: The right probe of shape_pass.blend turns the bar's right half about the middle by these angles.
BEND_KEYS = {1: 0.0, 24: 90.0, 48: 150.0, 72: 0.0}


def build_shape_pass() -> SampleInfo:
    """One bar bent 90° then 150° at its middle by two probes, twice: the per-vertex field (left) and
    with Preserve Shape (right), same weights."""
    todo: list[str] = []
    scene = new_scene("shape_pass", frame_end=72)
    half_length, offset = 2.0, 2.25
    rows = [("FIELD", "per-vertex field", -2.6, {}),
            ("PRESERVE_SHAPE", "Preserve Shape", 2.6, {"preserve_shape": True})]
    for method, caption, x, extra in rows:
        bar = add_mesh_object(
            f"Bar.{method}",
            mesh_from_bmesh(f"Bar.{method}", box_bmesh(size=(2 * half_length, 0.55, 0.55), cuts=(48, 5, 5))),
            checker_material(f"Bar.{method}", (0.1, 0.3, 0.75) if extra else (0.7, 0.12, 0.1),
                             (0.95, 0.93, 0.88), scale=(3.0, 3.6, 3.6)),
        )
        bar.location = (x, 0.0, 0.0)
        add_label(caption, (x, 0.0, -0.9), size=0.36, align="CENTER")
        mark_target(bar, method)
        left_name, right_name = f"{method}.Left", f"{method}.Right"
        add_twist_groups(bar, left_name, right_name, half_length)
        left = add_probe(left_name, (x - offset, 0.0, 0.0), marker_axis="Z", size=0.4)
        right = add_probe(right_name, (x + offset, 0.0, 0.0), marker_axis="Z", size=0.4)
        # The right half turns rigidly about the bar's middle, upwards (about −Y).
        key_transforms(right, {f: {"location": (x + offset * math.cos(math.radians(a)), 0.0,
                                                offset * math.sin(math.radians(a))),
                                   "rotation_euler": (0, -a, 0)} for f, a in BEND_KEYS.items()})
        scene.frame_set(1)
        settings = {"blend_mode": "AFFINE_LOG", "weight_mode": "VERTEX_GROUPS", "normalize": "SUM", **extra}
        add_deformer("probe", bar, [left, right], settings, todo)
    add_camera((0.0, -13.0, 1.0), (0.0, 0.0, 0.8), lens=40.0)
    add_lights()
    return SampleInfo(key_frames=[1, 24, 48], todo=todo)


SAMPLES: dict[str, Callable[[], SampleInfo]] = {
    "probe_bend": build_probe_bend,
    "probe_vortex": build_probe_vortex,
    "cage_deform": build_cage_deform,
    "comparison": build_comparison,
    "stack": build_stack,
    "bone_tail": build_bone_tail,
    "shape_pass": build_shape_pass,
    "made_cage": build_made_cage,
}


def build_sample(name: str, output_dir: Path) -> SampleInfo:
    """Build one sample into output_dir/<name>.blend (compressed, at frame 1)."""
    import bpy

    info = SAMPLES[name]()
    scene = bpy.context.scene
    scene["affdef_key_frames"] = info.key_frames
    scene.frame_set(scene.frame_start)
    frame_viewports_through_camera()
    path = output_dir / f"{name}.blend"
    path.unlink(missing_ok=True)  # no .blend1 backup of the previous build
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=True, relative_remap=True)
    return info


def build_samples(names: Sequence[str], output_dir: Path) -> dict[str, SampleInfo]:
    """Build the named samples (bpy must already be started with the extension enabled)."""
    output_dir.mkdir(parents=True, exist_ok=True)
    return {name: build_sample(name, output_dir) for name in names}


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description="Rebuild the sample .blend files from code.")
    parser.add_argument(
        "--samples",
        nargs="+",
        choices=list(SAMPLES),
        default=list(SAMPLES),
        metavar="NAME",
        help=f"samples to build (default: all of {', '.join(SAMPLES)})",
    )
    parser.add_argument("--output-dir", type=Path, default=SAMPLES_DIR, help="where the .blend files go")
    add_install_arguments(parser)
    return parser.parse_args(argv)


def add_install_arguments(parser: argparse.ArgumentParser) -> None:
    """--user-dir and --package: where and what `start_blender` installs (shared with render_samples)."""
    parser.add_argument(
        "--user-dir",
        type=Path,
        default=DEFAULT_USER_DIR,
        help="isolated Blender user directory the extension is installed into",
    )
    parser.add_argument(
        "--package",
        type=Path,
        default=None,
        help="extension .zip (default: dist/, built first when missing or stale)",
    )


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    package = args.package or ensure_package()
    start_blender(args.user_dir, package)
    output_dir = args.output_dir.resolve()
    infos = build_samples(args.samples, output_dir)
    for name, info in infos.items():
        print(f"{output_dir / (name + '.blend')}  key frames {info.key_frames}")
    todo = [item for info in infos.values() for item in info.todo]
    if todo:
        print("TODO / not built as intended:")
        for item in todo:
            print(f"  - {item}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
