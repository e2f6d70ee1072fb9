"""Add-on preferences: which per-vertex kernel evaluates the deformers.

The compiled kernel (affine_deformers.accel, numba bundled as wheels) is 2–5× faster per core than the
numpy kernel and uses every core; both give the same results to ~1e-15. Its first use compiles it
(several seconds, once: numba caches the machine code next to the add-on), so a session with the
interface starts that in a helper thread at registration instead of in the first update.
"""

from __future__ import annotations

import threading
import traceback

import bpy
from bpy.props import BoolProperty

from .. import accel
from . import evaluate

#: The add-on's module name (the extension's top-level package), which Blender keys preferences by.
ADDON_ID = __package__.removesuffix(".affine_deformers.blender")


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
            "Evaluate the deformers with the bundled compiled kernel (numba): several times faster and "
            "multi-threaded. Off: the numpy kernel (same results to 1e-15, slower). The first use on a "
            "machine compiles the kernel once, which takes a few seconds"
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


def start_warm_up() -> None:
    """Import numba and compile the kernel in a helper thread (interactive sessions only: a background
    job compiles on its first update anyway, and must not race its own exit). Updates meanwhile run
    on the numpy kernel (accel._usable), so the interface never waits for the compiler."""
    if bpy.app.background:
        return

    def work() -> None:
        try:
            accel.warm_up()
        except Exception:  # the dispatch falls back to numpy by itself; just leave a trace
            traceback.print_exc()

    threading.Thread(target=work, name="affine_deformers_warm_up", daemon=True).start()


CLASSES = (AFFINE_AddonPreferences,)
