"""Blender extension entry point: re-exports register/unregister of the add-on package."""

from .affine_deformers.blender import register, unregister

__all__ = ["register", "unregister"]
