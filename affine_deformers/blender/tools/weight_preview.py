"""Weight preview: the viewport shows the stored weights of one deformer as vertex colours.

What the artist sees (Solid shading, Color ▸ Attribute): with `AffineDeformer.weight_preview`
'ACTIVE', the weight of the active probe (or of one cage face) on Blender's weight-paint ramp
(blue 0 → green 0.5 → red 1; with `weight_preview_fit` up to the largest weight shown instead of 1);
with 'ALL', each control's own colour mixed by its weights, dark grey for the share of a vertex that
no control moves (a mask, Normalize None).

How, without touching renders or the saved deformation:

* the colours are computed here from the stored sparse weights (storage.read_weights; the cage's
  node → face weights for 'HARMONIC' cages) and written as a hidden FLOAT_VECTOR point attribute
  `.affdef_<uid>_preview` — a vector, not a colour attribute, so it never becomes the mesh's active or
  render colour (a new colour attribute on a mesh without one would become its render colour);
* a Geometry Nodes modifier at the bottom of the stack, PREVIEW_MODIFIER, enabled in the viewport
  only (`show_render` off, so final renders, F12 and Cycles/EEVEE/Workbench, never evaluate it),
  stores that vector as a FLOAT_COLOR point attribute under the name the viewport draws: the mesh's
  active colour attribute when it has one (shown in its place, in the viewport only), else
  DISPLAY_NAME, which is then made the mesh's active colour name (a name without an attribute on the
  original mesh: renders see no colour attribute, as before). It moves no vertex, and it stays last
  so every deformer's output path is unchanged (outputs.output_path looks only above a deformer);
* turning the preview off removes the modifier, the attribute, the node group once unused, and puts
  the active colour name back (kept on the deformer item, RESTORE_KEY, so it survives save / load).

One deformer per object previews at a time (the viewport shows one active colour). `refresh` runs
before an object's deformers are evaluated (weight_groups.py's hook, hooks.before_object) and from
the preview options' update callbacks; it recomputes the colours only when what they show changed
(bind generation, mode, control), and never raises. What it shows of each kind (its control count,
active control, stored weights) comes from the kind (DeformerKind).
"""

from __future__ import annotations

import colorsys
import traceback

import bpy
import numpy as np

from .. import caches, kinds
from ..files import modifier_inputs, storage
from ..kinds import BindError
from ..ui.addressing import linked_mesh_problem

PREVIEW_MODIFIER = "Affine Weight Preview"
GROUP_NAME = ".AffineDeformer Weight Preview"
GROUP_MARK = "affine_deformers_preview_group"  # custom property identifying our group (value = version)
GROUP_VERSION = 1
SOURCE_SOCKET = "Colors"
DISPLAY_SOCKET = "Display"
DISPLAY_NAME = "Affine Weights"
#: ID property on the previewing deformer item: the mesh's active colour name before the preview set
#: it to DISPLAY_NAME (absent when the preview did not change it).
RESTORE_KEY = "weight_preview_restore"

#: Blender's weight-paint ramp (display values): 0 blue, 0.25 cyan, 0.5 green, 0.75 yellow, 1 red.
RAMP_STOPS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
RAMP_COLORS = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
#: Colour (linear) of the share of a vertex no control moves, in the 'ALL' map.
REST_COLOR = np.array([0.05, 0.05, 0.05])

#: (object session uid) → signature of the colours last written: a cache (the .blend holds the truth:
#: a missing or different entry only means the colours are recomputed and compared once; session
#: uids are never reused, and undo restores colours together with the options they were made from).
_written: dict[int, tuple] = {}


@caches.register
def _forget(key: caches.Key | None) -> None:
    """Everything at a full forget (entries are per object, not per deformer)."""
    if key is None:
        _written.clear()


def colors_name(uid: str) -> str:
    """The hidden attribute holding deformer `uid`'s preview colours (linear RGB, FLOAT_VECTOR)."""
    return f".affdef_{uid}_preview"


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB display values in [0, 1] → linear (IEC 61966-2-1), so the viewport (view transform
    Standard) shows exactly the ramp's display colours."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def ramp_colors(weights: np.ndarray) -> np.ndarray:
    """Linear RGB (N, 3) float32 of weights (N,) on the weight-paint ramp (clamped to [0, 1])."""
    w = np.clip(np.nan_to_num(np.asarray(weights, dtype=np.float64)), 0.0, 1.0)
    display = np.stack([np.interp(w, RAMP_STOPS, RAMP_COLORS[:, c]) for c in range(3)], axis=1)
    return srgb_to_linear(display).astype(np.float32)


def control_palette(m: int) -> np.ndarray:
    """One distinct linear colour per control (m, 3): hues spaced by the golden ratio (neighbouring
    indices far apart on the colour wheel), bright and saturated."""
    hues = (np.arange(m) * 0.6180339887498949) % 1.0
    display = np.array([colorsys.hsv_to_rgb(h, 0.75, 0.95) for h in hues]).reshape(m, 3)
    return srgb_to_linear(display)


def mix_colors(indices: np.ndarray, values: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """Per vertex Σ_k w_k · palette[idx_k] plus the leftover 1 − Σ_k w_k in REST_COLOR, divided by
    max(1, Σ_k w_k) (weights summing above 1 keep their mix), linear RGB (N, 3) float32."""
    total = values.sum(axis=1)
    mixed = np.einsum("nk,nkc->nc", values, palette[indices])
    mixed += np.maximum(1.0 - total, 0.0)[:, None] * REST_COLOR
    mixed /= np.maximum(total, 1.0)[:, None]
    return mixed.astype(np.float32)


# ------------------------------------------------------------------------------------------ weights


def control_count(deformer) -> int:
    """The number of controls the preview can show (DeformerKind.control_count: probes, bones, the
    bound cage's faces; 0 for a kind this version does not have)."""
    kind = kinds.get(deformer.kind)
    return kind.control_count(deformer) if kind is not None else 0


def preview_control(deformer) -> int:
    """The control 'ACTIVE' shows (DeformerKind.active_control: the active probe or bone, or the cage
    face `weight_preview_face`, -1 meaning the cage mesh's active face), clamped to the controls
    there are (-1 when there are none)."""
    m = control_count(deformer)
    if m == 0:
        return -1
    index = kinds.get(deformer.kind).active_control(deformer)
    return int(min(max(index, 0), m - 1))


def _stored(obj: bpy.types.Object, deformer) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(indices (N, K), values (N, K) float64, node → control weights (G, m) or None): the deformer's
    stored weights (DeformerKind.stored_weights; for a 'HARMONIC' cage the indices are grid nodes,
    each with face weights). Raises storage.StorageError / BindError when the bind data is missing or
    damaged."""
    kind = kinds.get(deformer.kind)
    if kind is None:
        raise BindError(f"{deformer.kind.title()} deformers are not available in this version")
    return kind.stored_weights(obj, deformer)


def control_weights(obj: bpy.types.Object, deformer, control: int) -> np.ndarray:
    """The stored weight (N,) float64 of one control (probe index, or cage face) at every vertex —
    exactly the value the deformation uses (the mask included, the strength not)."""
    indices, values, node_weights = _stored(obj, deformer)
    if node_weights is not None:  # a vertex blends 8 grid nodes, each node blends the faces
        return np.einsum("nk,nk->n", values, node_weights[:, control][indices])
    return np.where(indices == control, values, 0.0).sum(axis=1)


def preview_colors(obj: bpy.types.Object, deformer) -> np.ndarray:
    """The colours (N, 3) float32, linear RGB, the preview shows for `deformer` (see module doc);
    with `weight_preview_fit` the ramp runs from 0 to the largest weight shown."""
    if deformer.weight_preview == "ACTIVE":
        weights = control_weights(obj, deformer, preview_control(deformer))
        top = float(weights.max(initial=0.0))
        if deformer.weight_preview_fit and top > 0.0:
            weights = weights / top
        return ramp_colors(weights)
    indices, values, node_weights = _stored(obj, deformer)
    palette = control_palette(control_count(deformer))
    if node_weights is not None:
        palette = node_weights @ palette  # each node's colour: its faces' colours by their weights
    return mix_colors(indices, values, palette)


# ------------------------------------------------------------------------------- Geometry Nodes


def _is_our_group(ng: bpy.types.NodeTree | None) -> bool:
    return ng is not None and ng.library is None and ng.get(GROUP_MARK) == GROUP_VERSION


def _socket_identifier(ng: bpy.types.NodeTree, name: str) -> str:
    for item in ng.interface.items_tree:
        if getattr(item, "item_type", "") == "SOCKET" and item.in_out == "INPUT" and item.name == name:
            return item.identifier
    raise LookupError(name)


def ensure_group() -> bpy.types.NodeTree:
    """The shared preview group: Named Attribute (vector, input "Colors") → Store Named Attribute
    (colour, point, name input "Display") where the source exists."""
    for ng in bpy.data.node_groups:
        if _is_our_group(ng):
            return ng
    ng = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    ng[GROUP_MARK] = GROUP_VERSION
    ng.is_modifier = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    for name in (SOURCE_SOCKET, DISPLAY_SOCKET):
        socket = ng.interface.new_socket(name, in_out="INPUT", socket_type="NodeSocketString")
        socket.hide_in_modifier = True  # set by the add-on
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = ng.nodes, ng.links
    group_in, group_out = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    group_in.location, group_out.location = (-500, 0), (300, 0)
    named = nodes.new("GeometryNodeInputNamedAttribute")
    named.data_type = "FLOAT_VECTOR"
    named.location = (-250, -150)
    store = nodes.new("GeometryNodeStoreNamedAttribute")
    store.data_type, store.domain = "FLOAT_COLOR", "POINT"
    store.location = (50, 0)
    links.new(group_in.outputs[SOURCE_SOCKET], named.inputs["Name"])
    links.new(group_in.outputs[DISPLAY_SOCKET], store.inputs["Name"])
    links.new(group_in.outputs[0], store.inputs["Geometry"])
    links.new(named.outputs["Exists"], store.inputs["Selection"])
    links.new(named.outputs["Attribute"], store.inputs["Value"])
    links.new(store.outputs["Geometry"], group_out.inputs[0])
    return ng


def find_modifier(obj: bpy.types.Object) -> bpy.types.NodesModifier | None:
    """The preview modifier on `obj` (found by its node group, so a renamed one still counts)."""
    for mod in obj.modifiers:
        if mod.type == "NODES" and _is_our_group(mod.node_group):
            return mod
    return None


def _set_input(mod: bpy.types.NodesModifier, name: str, value: str) -> bool:
    return modifier_inputs.set_value(mod, _socket_identifier(mod.node_group, name), value)


def _ensure_modifier(obj: bpy.types.Object, source: str, display: str) -> bpy.types.NodesModifier:
    """The preview modifier reading `source` and writing `display`, last in the stack, viewport only."""
    mod = find_modifier(obj)
    if mod is None:
        mod = obj.modifiers.new(PREVIEW_MODIFIER, "NODES")
        mod.node_group = ensure_group()
        mod.show_render = False  # never in final renders
        mod.show_in_editmode = False
        mod.show_expanded = False
    changed = _set_input(mod, SOURCE_SOCKET, source)
    changed = _set_input(mod, DISPLAY_SOCKET, display) or changed
    if changed:
        mod.node_group = mod.node_group  # assigning an ID property does not tag the modifier
    index = list(obj.modifiers).index(mod)
    if index != len(obj.modifiers) - 1:  # a deformer added later goes below: keep the preview last
        obj.modifiers.move(index, len(obj.modifiers) - 1)
    if mod.show_render:
        mod.show_render = False
    return mod


# ---------------------------------------------------------------------------------- on / off


def _display_name(mesh: bpy.types.Mesh, deformer) -> str:
    """The colour attribute name the viewport draws, made so if needed: the mesh's active colour
    attribute when it has one, else DISPLAY_NAME set as its active colour name (the name it had is
    kept in RESTORE_KEY for `_restore_active_color`)."""
    colors = mesh.color_attributes
    active = colors.active_color_name
    if active and active != DISPLAY_NAME and colors.get(active) is not None:
        return active
    if active != DISPLAY_NAME:
        if RESTORE_KEY not in deformer:  # the name from before the preview, not one set meanwhile
            deformer[RESTORE_KEY] = active
        colors.active_color_name = DISPLAY_NAME
    return DISPLAY_NAME


def _restore_active_color(mesh: bpy.types.Mesh | None, deformer) -> None:
    previous = deformer.get(RESTORE_KEY)
    if previous is None:
        return
    del deformer[RESTORE_KEY]
    if mesh is not None and mesh.color_attributes.active_color_name == DISPLAY_NAME:
        mesh.color_attributes.active_color_name = str(previous)


def _write_colors(mesh: bpy.types.Mesh, name: str, colors: np.ndarray) -> None:
    """Write colours (N, 3) float32 into the hidden vector attribute `name` unless it holds them."""
    flat = np.ascontiguousarray(colors, dtype=np.float32).ravel()
    attr = mesh.attributes.get(name)
    if attr is not None and (attr.data_type != "FLOAT_VECTOR" or attr.domain != "POINT"):
        mesh.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = mesh.attributes.new(name, "FLOAT_VECTOR", "POINT")
    else:
        current = np.empty(flat.size, dtype=np.float32)
        attr.data.foreach_get("vector", current)
        if np.array_equal(current, flat):
            return
    attr.data.foreach_set("vector", flat)
    mesh.update_tag()


def remove(obj: bpy.types.Object, deformer=None) -> None:
    """Turn the preview of `obj` off without a trace: the modifier, every preview attribute, the
    node group when no modifier uses it, and the active colour name of `deformer` (None: of every
    deformer that changed it)."""
    _written.pop(obj.session_uid, None)
    mod = find_modifier(obj)
    if mod is not None:
        obj.modifiers.remove(mod)
    mesh = obj.data if obj.type == "MESH" else None
    editable = mesh is not None and mesh.library is None
    if editable:
        stale = [a.name for a in mesh.attributes
                 if a.name.startswith(".affdef_") and a.name.endswith("_preview")]
        for name in stale:
            mesh.attributes.remove(mesh.attributes[name])
        if stale:
            mesh.update_tag()
    deformers = [deformer] if deformer is not None else list(obj.affine_deformers)
    for item in deformers:
        _restore_active_color(mesh if editable else None, item)
    for ng in [g for g in bpy.data.node_groups if _is_our_group(g) and g.users == 0]:
        bpy.data.node_groups.remove(ng)


def previewing(obj: bpy.types.Object):
    """The deformer of `obj` whose weights are shown (the first with show_weights), or None."""
    for deformer in obj.affine_deformers:
        if deformer.show_weights:
            return deformer
    return None


def refresh(obj: bpy.types.Object, force: bool = False) -> None:
    """Bring the preview of `obj` in line with its deformers' `show_weights` (never raises: a failure
    turns into the deformer's status). Cheap when nothing changed."""
    try:
        _refresh(obj, force)
    except Exception as exc:  # a handler must never raise; the artist gets the reason
        traceback.print_exc()
        deformer = previewing(obj)
        if deformer is not None:
            message = f"Weight preview failed: {exc}"
            if deformer.status != message:
                deformer.status = message


def _refresh(obj: bpy.types.Object, force: bool) -> None:
    deformer = previewing(obj)
    if deformer is None:
        if obj.session_uid in _written or find_modifier(obj) is not None:
            remove(obj)
        return
    if obj.type != "MESH" or obj.library is not None or obj.data.library is not None or obj.mode == "EDIT":
        return
    mesh = obj.data
    if not deformer.is_bound:
        # nothing to show yet: no colours (the modifier would show the stale ones of an older bind)
        if find_modifier(obj) is not None or obj.session_uid in _written:
            remove(obj, deformer)
        return
    source = colors_name(deformer.uid)
    display = _display_name(mesh, deformer)
    _ensure_modifier(obj, source, display)
    signature = (mesh.session_uid, deformer.uid, deformer.bind_generation, len(mesh.vertices),
                 deformer.weight_preview, deformer.weight_preview_fit,
                 preview_control(deformer) if deformer.weight_preview == "ACTIVE" else None,
                 control_count(deformer))
    if not force and _written.get(obj.session_uid) == signature and mesh.attributes.get(source) is not None:
        return
    for attr in [a.name for a in mesh.attributes if a.name.startswith(".affdef_")
                 and a.name.endswith("_preview") and a.name != source]:
        mesh.attributes.remove(mesh.attributes[attr])  # a former deformer's (or uid's) colours
    try:
        colors = preview_colors(obj, deformer)
    except (storage.StorageError, BindError):
        # The deformer's status already says what is wrong with its bind data: show nothing.
        colors = None
    if colors is None:
        existing = mesh.attributes.get(source)
        if existing is not None:
            mesh.attributes.remove(existing)
            mesh.update_tag()
    else:
        _write_colors(mesh, source, colors)
    _written[obj.session_uid] = signature


def on_show_weights(deformer) -> None:
    """`show_weights` update: one previewing deformer per object; on → shown now, off → no trace."""
    obj = deformer.id_data
    if not isinstance(obj, bpy.types.Object):
        return
    try:
        if deformer.show_weights and obj.type == "MESH" and obj.library is None:
            problem = linked_mesh_problem(obj, "show its weights")
            if problem:  # the colours would have to be written to a mesh this file cannot change
                deformer["show_weights"] = False  # an item write runs no update callback
                deformer.status = problem
                print(f"Affine Deformers: Show Weights refused: {problem}")
                return
        if deformer.show_weights:
            for other in obj.affine_deformers:
                if other.show_weights and other.uid != deformer.uid:
                    other.show_weights = False  # its own update removes its preview
            refresh(obj, force=True)
        else:
            remove(obj, deformer)
            if previewing(obj) is not None:
                refresh(obj, force=True)
    except Exception as exc:  # an update callback must not leave the artist with a traceback only
        traceback.print_exc()
        deformer.status = f"Weight preview failed: {exc}"


def on_option(deformer) -> None:
    """Preview option or active probe changed: redraw the preview of the deformer's object."""
    obj = deformer.id_data
    if isinstance(obj, bpy.types.Object) and deformer.show_weights:
        refresh(obj)


def release(obj: bpy.types.Object, deformer) -> None:
    """A deformer being removed takes its preview with it (binding.remove)."""
    if deformer.show_weights or RESTORE_KEY in deformer:
        try:
            remove(obj, deformer)
        except Exception:  # removing the deformer must go on
            traceback.print_exc()


# --------------------------------------------------------------------------------------------- UI


def _viewport_shading(context) -> bpy.types.View3DShading | None:
    """The shading of the first 3D view of the current screen (None without a screen)."""
    screen = getattr(context, "screen", None)
    for area in getattr(screen, "areas", ()):
        if area.type == "VIEW_3D":
            return area.spaces.active.shading
    return None


def draw(layout: bpy.types.UILayout, context, deformer) -> None:
    """The preview toggle and options, and a hint when the 3D view does not show attribute colours."""
    row = layout.row(align=True)
    row.prop(deformer, "show_weights", text="Show Weights", icon="COLOR", toggle=True)
    sub = row.row(align=True)
    sub.active = deformer.show_weights
    sub.prop(deformer, "weight_preview", text="")
    if deformer.weight_preview == "ACTIVE":
        kind = kinds.get(deformer.kind)
        if kind is not None:
            kind.draw_preview_options(sub, deformer)
        sub.prop(deformer, "weight_preview_fit", text="", icon="FULLSCREEN_ENTER")
    if not deformer.show_weights:
        return
    shading = _viewport_shading(context)
    if shading is not None and (shading.type != "SOLID" or shading.color_type != "VERTEX"):
        hint = layout.row(align=True)
        hint.label(text="Viewport: Solid, Color Attribute", icon="INFO")
        hint.prop(shading, "type", text="", expand=False)
        hint.prop(shading, "color_type", text="")
