"""The per-control steps on the compiled kernel: ψ of the controls that moved (`params_from_matrices`,
`polar_log`) and the cage's harmonic nodes (`node_params`), each the compiled form of a core function
(named in its docstring, which holds the contract) with scalar C code per control
(csrc/kernel_controls.c: one-sided Jacobi SVD, so3 log, V⁻¹).

A handful of controls move in an update: what these save is numpy's per-call overhead on a few 3×3
matrices. They run on the calling thread (`state._entry_call`); `polar_log` and
`params_from_matrices` return None when the kernel is not active (the caller then uses numpy).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core import aff3 as _aff3
from ..core.cage import harmonic as _harmonic
from .state import _FAILED, _NO_POINTS, _c, _entry_call, _usable
from .vertex import linear_maps

__all__ = ["node_params", "params_from_matrices", "polar_log"]

FloatArray = NDArray[np.float64]


def polar_log(M: ArrayLike) -> tuple[FloatArray, FloatArray] | None:
    """(R, Ŷ) (n, 3, 3) each with M = R exp(Ŷ), R = U Vᵀ, Ŷ = V diag(log σ) Vᵀ for the SVD
    M = U diag(σ) Vᵀ of each of the (n, 3, 3) matrices M (det > 0, checked by the caller), computed
    by the compiled kernel (`Kernel.polar_log`, agreeing with numpy's SVD to ~1e-15); None when the
    compiled kernel is not active now (the caller then uses numpy): the `polar` argument of
    `core.aff3.params_from_matrices`."""
    module = _usable()
    if module is None:
        return None
    m = _c(np.asarray(M, dtype=np.float64).reshape(-1, 3, 3), np.float64)
    R = np.empty_like(m)
    Yh = np.empty_like(m)
    if _entry_call("polar_log", lambda: module.polar_log(m, R, Yh)) is _FAILED:
        return None
    return R, Yh


def params_from_matrices(A: ArrayLike) -> FloatArray | None:
    """`core.aff3.params_from_matrices(A)` (the contract: ψ in the 12-number layout, A (..., 4, 4) ↦
    (..., 12), the same ValueError for a motion outside Aff+(3)) in one compiled call
    (`Kernel.psi_rows`; the same parameters to ~1e-15). None when the compiled kernel is not active
    now (the caller then uses the numpy function)."""
    module = _usable()
    if module is None:
        return None
    checked = _aff3.validate_affine(A)
    flat = checked.reshape(-1, 4, 4)
    rows = np.empty((flat.shape[0], 12))
    rows[:, :9] = flat[:, :3, :3].reshape(-1, 9)
    rows[:, 9:] = flat[:, :3, 3]
    bad = _entry_call("psi_rows", lambda: module.psi_rows(rows))
    if bad is _FAILED:
        return None
    if bad >= 0:  # numpy names the transform in its error (or finds the row finite after all)
        return _aff3.params_from_matrices(checked)
    return rows.reshape(*checked.shape[:-2], 12)


def node_params(node_points: ArrayLike, node_weights: ArrayLike, face_params: ArrayLike, *,
                faces: ArrayLike | None = None, valid: ArrayLike | None = None) -> FloatArray:
    """`core.cage.harmonic.node_params` (the contract; the same result to ~1e-15) with its per-face
    and per-node steps in the compiled kernel (`Kernel.node_pivot`): B_f = V(ω_f)⁻¹ (M_f − I) for
    the faces, the blend over the node's faces (`face_columns`, numpy), then u′ = u + B x +
    V(ω)⁻¹ (x − M x) for the nodes. The numpy version (with `linear_maps`) when the compiled kernel
    is not active now."""
    def numpy() -> FloatArray:
        return _harmonic.node_params(node_points, node_weights, face_params, faces=faces, valid=valid,
                                     maps=linear_maps)

    module = _usable()
    if module is None:
        return numpy()
    W = np.asarray(node_weights, dtype=np.float64)
    x = _c(node_points, np.float64)
    P = np.asarray(face_params, dtype=np.float64)
    faces = np.arange(W.shape[1]) if faces is None else np.asarray(faces, dtype=np.intp)
    face_rows = _c(P[faces], np.float64)
    B = np.empty((faces.size, 9))
    nodes = np.empty((x.shape[0], 12))

    def both_steps() -> None:
        module.node_pivot(False, face_rows, _NO_POINTS, B)
        blend = _harmonic.face_columns(W, faces, valid, np.concatenate([face_rows, B], axis=1))
        module.node_pivot(True, np.ascontiguousarray(blend), x, nodes)

    if _entry_call("node_pivot", both_steps) is _FAILED:
        return numpy()
    return nodes
