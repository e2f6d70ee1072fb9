"""The bpy layer: registration of properties, operators, panels and handlers.

Scripts: `evaluate.evaluate_object(obj, depsgraph)` / `evaluate.evaluate_all(scene, depsgraph)`.
"""

from __future__ import annotations

import bpy

from . import bake, evaluate, operators, panels, props

CLASSES = (*props.CLASSES, *operators.CLASSES, *bake.CLASSES, *panels.CLASSES)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    props.register_properties()
    bpy.types.VIEW3D_MT_object.append(panels.draw_object_menu)
    evaluate.register_handlers()


def unregister() -> None:
    evaluate.unregister_handlers()
    bpy.types.VIEW3D_MT_object.remove(panels.draw_object_menu)
    props.unregister_properties()
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
