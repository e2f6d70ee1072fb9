"""Affine Deformers: probe, cage and bone deformers blending motions in the Aff+(3) parameter space.

`affine_deformers.core` is the numpy-only numerical core; `affine_deformers.blender` is the bpy layer.
Importing this package imports neither, so the core stays usable without Blender.
"""
