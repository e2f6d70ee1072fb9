"""The numerical core (numpy only, never bpy): the Aff+(3) maps, weights, cages and the deformer kernel.

Script contract (docs/DEVELOPING.md): `phi(X, Y)`, `psi(A)` and `deform_points(points, transforms, weights)`
are importable from here; `deform_points_params` / `blend_linear_sparse` are the sparse hot paths.
"""

from .aff3 import (
    matrices_from_params,
    params_from_matrices,
    phi,
    psi,
    validate_affine,
)
from .deform import blend_linear_sparse, deform_points, deform_points_params

__all__ = [
    "blend_linear_sparse",
    "deform_points",
    "deform_points_params",
    "matrices_from_params",
    "params_from_matrices",
    "phi",
    "psi",
    "validate_affine",
]
