"""The bpy layer: registration of properties, operators, panels and handlers.

Scripts: `update.evaluate.evaluate_object(obj, depsgraph)` / `update.evaluate.evaluate_all(scene, depsgraph)`.
"""

from __future__ import annotations

import traceback

import bpy

from . import kind_services, kinds, props
from .files import carrier, relations
from .tools import bake, weight_groups, weight_operators
from .ui import operators, panels, prefs
from .update import handlers, shape_pass

#: Every class to register, in order: the kinds' (their control item groups before the deformer's
#: property group, which refers to them), then the deformer's, the shared operators and the interface.
CLASSES = (*prefs.CLASSES, *kinds.CLASSES, *props.CLASSES, *operators.CLASSES, *bake.CLASSES,
           *weight_operators.CLASSES, *panels.CLASSES)

__all__ = ["CLASSES", "kind_services", "register", "unregister", "weight_groups"]


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    props.register_properties()
    bpy.types.VIEW3D_MT_object.append(panels.draw_object_menu)
    bpy.types.OBJECT_MT_modifier_add_deform.append(panels.draw_modifier_menu)
    handlers.register_handlers()
    prefs.apply(prefs.preferences())
    prefs.check_kernel()
    _upgrade_open_file()


def _upgrade_open_file() -> None:
    """Enabled with a file already open (no load_post): upgrade its node groups and control inputs."""
    if not isinstance(bpy.data, bpy.types.BlendData):  # restricted while Blender starts: load_post does it
        return
    try:
        relations.upgrade_all()
        if carrier.remap_controls():  # library overrides made while the add-on was disabled
            relations.upgrade_all()
    except Exception:  # odd data must not stop the add-on from registering
        traceback.print_exc()


def unregister() -> None:
    handlers.unregister_handlers()
    shape_pass.release_all()
    bpy.types.VIEW3D_MT_object.remove(panels.draw_object_menu)
    bpy.types.OBJECT_MT_modifier_add_deform.remove(panels.draw_modifier_menu)
    props.unregister_properties()
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
