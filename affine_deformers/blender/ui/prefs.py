"""Add-on preferences: which per-vertex kernel evaluates the deformers.

The compiled kernel (affine_deformers.accel: a C library bundled per platform) is 2–5× faster per
core than the numpy kernel and uses every core; both give the same results to ~1e-15. It loads in
milliseconds; registration runs each of its entries once (`check_kernel`), so a library that does not
work on this machine switches to numpy there, with the reason in the preferences, not in the middle
of the first update.
"""

from __future__ import annotations

import traceback

import bpy
from bpy.props import BoolProperty

from ... import accel
from ..update import evaluate

#: The add-on's module name (the extension's top-level package), which Blender keys preferences by.
ADDON_ID = __package__.rpartition(".affine_deformers.blender")[0]


def preferences() -> AFFINE_AddonPreferences | None:
    """This add-on's preferences, or None when it is not registered as an add-on (e.g. imported)."""
    addon = bpy.context.preferences.addons.get(ADDON_ID)
    return None if addon is None else addon.preferences


def _use_compiled_changed(prefs: AFFINE_AddonPreferences, _context: bpy.types.Context) -> None:
    apply(prefs)
    # Cached results came from the other kernel: recompute everything, then redraw the viewport.
    evaluate.forget()
    if bpy.context.scene is not None:
        evaluate.evaluate_all(bpy.context.scene)


def apply(prefs: AFFINE_AddonPreferences | None) -> None:
    """Hand the preference to the kernel dispatch (default: compiled kernel on)."""
    accel.set_enabled(True if prefs is None else prefs.use_compiled_kernel)


class AFFINE_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    use_compiled_kernel: BoolProperty(
        name="Compiled Kernel",
        description=(
            "Evaluate the deformers with the bundled compiled kernel (C): several times faster and "
            "multi-threaded. Off: the numpy kernel (same results to 1e-15, slower)"
        ),
        default=True,
        update=_use_compiled_changed,
    )

    def draw(self, _context: bpy.types.Context) -> None:
        layout = self.layout
        layout.prop(self, "use_compiled_kernel")
        row = layout.row()
        row.active = False
        row.label(text=f"Kernel in use: {accel.backend()}")


def check_kernel() -> None:
    """Load the compiled kernel and run each entry once on a tiny input (milliseconds): a library that
    fails here switches the process to numpy (the preferences say why) before the first update."""
    try:
        accel.warm_up()
    except Exception:  # the dispatch falls back to numpy by itself; just leave a trace
        traceback.print_exc()


CLASSES = (AFFINE_AddonPreferences,)
