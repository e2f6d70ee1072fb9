"""A cage made for the artist (issue #50): adding a cage deformer with no cage selected builds one around
the mesh (core.cage.enclosing_cage: closed, 2-manifold, outward, self-intersection free, every vertex
inside with a margin, following the shape, at most the deformer's Cage Faces, mirror-symmetric when
the mesh is), and Remake Cage builds it again at another budget and rebinds.

The cage is a mesh object "<target> Cage" in the target's collections, with the target's transform
(its vertices are made in the target's local space), shown as a wire and hidden in renders, as riggers
keep cages. It is made from the rest mesh (the mesh's own vertices and triangles, whatever its
modifiers), so any mesh gets one — open, non-manifold, with loose vertices; a mesh without vertices,
with all its vertices at one place or with non-finite ones is refused with a message and nothing is made.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.props import IntProperty

from ...core.cage.enclose import EnclosingCage, enclosing_cage
from ..files import storage
from ..ui.addressing import UNDOABLE, DeformerIndexed, addressed_deformer
from .base import BindError
from .services import services

#: The face budget of a made cage, unless the deformer's Cage Faces says otherwise.
DEFAULT_FACES = 300


def _triangles(mesh: bpy.types.Mesh) -> np.ndarray:
    """The mesh's triangles (T, 3) int32 (loop triangles, through their corners' vertices)."""
    mesh.calc_loop_triangles()
    loops = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("loops", loops)
    return storage.corner_vertices(mesh)[loops].reshape(-1, 3)


def made_cage(target: bpy.types.Object, faces: int) -> EnclosingCage:
    """The cage made around `target`'s rest mesh with at most `faces` quads, in its local space.
    BindError (nothing made) when no cage can be made, saying why."""
    mesh = target.data
    if target.type != "MESH":
        raise BindError(f"'{target.name}' is not a mesh: a cage is made around a mesh's vertices")
    if len(mesh.vertices) == 0:
        raise BindError(f"'{target.name}' has no vertices: there is nothing to make a cage around")
    points = storage.read_positions(mesh).astype(np.float64)
    if not np.all(np.isfinite(points)):
        raise BindError(f"'{target.name}' has vertices that are not finite (NaN or infinity): fix them first")
    if np.ptp(points, axis=0).max() == 0.0:
        raise BindError(f"All vertices of '{target.name}' are at one place: a cage needs a shape to follow")
    try:
        return enclosing_cage(points, _triangles(mesh) if len(mesh.polygons) else None, budget=faces)
    except ValueError as exc:
        raise BindError(f"No cage can be made around '{target.name}': {exc}") from None


#: The made cage's margin (every vertex of the mesh at least this far inside), kept on its mesh.
MARGIN_KEY = "affine_made_margin"


def fill_mesh(mesh: bpy.types.Mesh, made: EnclosingCage) -> None:
    """Give the empty `mesh` the made cage's vertices and quads, and its margin (MARGIN_KEY)."""
    mesh[MARGIN_KEY] = float(made.margin)
    mesh.vertices.add(len(made.vertices))
    mesh.vertices.foreach_set("co", made.vertices.astype(np.float32).ravel())
    mesh.loops.add(len(made.loop_vertices))
    mesh.loops.foreach_set("vertex_index", np.asarray(made.loop_vertices, dtype=np.int32))
    mesh.polygons.add(len(made.loop_start))
    mesh.polygons.foreach_set("loop_start", np.asarray(made.loop_start, dtype=np.int32))
    mesh.polygons.foreach_set("loop_total", np.asarray(made.loop_total, dtype=np.int32))
    mesh.update(calc_edges=True)
    mesh.validate(clean_customdata=False)


def cage_mesh(target: bpy.types.Object, faces: int, name: str) -> bpy.types.Mesh:
    """A new mesh datablock: the cage made around `target` (made_cage)."""
    made = made_cage(target, faces)
    result = bpy.data.meshes.new(name)
    fill_mesh(result, made)
    return result


def make_cage(context: bpy.types.Context, target: bpy.types.Object,
              faces: int = DEFAULT_FACES) -> bpy.types.Object:
    """A new cage object around `target` (module docstring)."""
    name = f"{target.name} Cage"
    cage = bpy.data.objects.new(name, cage_mesh(target, faces, name))
    cage.matrix_world = target.matrix_world
    cage.display_type = "WIRE"
    cage.hide_render = True
    collections = target.users_collection
    (collections[0] if collections else context.scene.collection).objects.link(cage)
    return cage


#: ID property of a cage deformer: its rest cage's points (V, 3) in the target's space (kinds/cage.py).
REST_POINTS = "cage_rest_points"
#: A cage whose points left their rest by more than this share of its size holds an artist's edit.
EDITED = 1e-5


def _edited(obj: bpy.types.Object, deformer, cage: bpy.types.Object) -> str:
    """What an artist changed of the cage since it was bound — its mesh's points moved (Edit Mode, a
    script) or its vertex count — in words ('' when nothing): a remade cage would not keep it."""
    stored = deformer.get(REST_POINTS)
    if stored is None:
        return ""
    rest = np.asarray(stored, dtype=np.float64).reshape(-1, 3)
    mesh = cage.data
    if len(mesh.vertices) != len(rest):
        return f"its vertex count changed since binding ({len(rest)} → {len(mesh.vertices)})"
    co = np.empty(len(rest) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    try:
        relative = np.linalg.solve(np.array(obj.matrix_world), np.array(cage.matrix_world))
    except np.linalg.LinAlgError:
        return ""
    now = co.reshape(-1, 3).astype(np.float64) @ relative[:3, :3].T + relative[:3, 3]
    moved = float(np.abs(now - rest).max())
    size = float(np.ptp(rest, axis=0).max()) if len(rest) else 0.0
    return f"its vertices moved up to {moved:.3g} since binding" if moved > EDITED * max(size, 1e-9) else ""


class AFFINE_OT_cage_remake(DeformerIndexed, bpy.types.Operator):
    """Make the deformer's cage again around the mesh's rest shape with at most Cage Faces quads (the cage
    object and its mesh keep their names; a cage with shape keys, posed or edited is refused), and
    rebind"""

    bl_idname = "object.affine_cage_remake"
    bl_label = "Remake Cage"
    bl_options = UNDOABLE

    faces: IntProperty(name="Cage Faces", default=0, min=0, max=20000,
                       description="At most this many quads (0: the deformer's Cage Faces)")

    def execute(self, context: bpy.types.Context) -> set[str]:
        obj, deformer = addressed_deformer(self, context)
        if obj is None:
            return {"CANCELLED"}
        cage = deformer.cage
        if deformer.kind != "CAGE" or cage is None:
            self.report({"ERROR"}, f"'{deformer.name}' has no cage to remake")
            return {"CANCELLED"}
        if cage.library is not None or cage.data.library is not None:
            self.report({"ERROR"}, f"Cage '{cage.name}' is linked from a library: remake it in that file")
            return {"CANCELLED"}
        mesh = cage.data
        if mesh.shape_keys is not None:
            # A new cage has other vertices: the keys (a keyed cage edit) could not follow it.
            self.report({"ERROR"}, f"Cage '{cage.name}' has shape keys, which a remade cage would lose: "
                                   "remove them first, or add a new cage deformer")
            return {"CANCELLED"}
        edited = _edited(obj, deformer, cage)
        if edited:  # the deformation it makes would go with it (issue 57): refused, as for shape keys
            self.report({"ERROR"}, f"Cage '{cage.name}' is posed or edited ({edited}), which a remade cage "
                                   "would lose: bring it back to its rest shape, or Rebind to make this "
                                   "shape the rest, then remake it")
            return {"CANCELLED"}
        faces = self.faces or deformer.cage_faces
        try:
            made = made_cage(obj, faces)
        except BindError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        # Filled in place: the mesh keeps its name, and objects sharing it show the new cage too.
        mesh.clear_geometry()
        fill_mesh(mesh, made)
        cage.matrix_world = obj.matrix_world
        deformer.cage_faces = faces
        try:
            services().bind(obj, deformer, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        services().evaluate(obj, context.evaluated_depsgraph_get())
        self.report({"INFO"}, f"Made a cage of {len(mesh.polygons)} faces around '{obj.name}' (every vertex "
                              f"at least {made.margin:.3g} inside) and rebound")
        return {"FINISHED"}


def draw_actions(layout: bpy.types.UILayout, deformer, index: int) -> None:
    """Remake Cage, with the face budget beside it."""
    row = layout.row(align=True)
    row.prop(deformer, "cage_faces", text="Faces")
    row.operator(AFFINE_OT_cage_remake.bl_idname, icon="MESH_CUBE").index = index


CLASSES = (AFFINE_OT_cage_remake,)
