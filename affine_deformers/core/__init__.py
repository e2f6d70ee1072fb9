"""The numerical core (numpy only, never bpy): the Aff+(3) maps, weights, cages and the deformer kernel.

Script contract (docs in ARCHITECTURE.md): `phi(X, Y)`, `psi(A)` and `deform_points(points, transforms,
weights)` are importable from here.
"""

from .aff3 import (
    matrices_from_params,
    params_from_matrices,
    phi,
    psi,
    validate_affine,
)

__all__ = [
    "matrices_from_params",
    "params_from_matrices",
    "phi",
    "psi",
    "validate_affine",
]
