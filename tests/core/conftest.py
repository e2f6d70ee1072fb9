"""Shared inputs for the core tests: a fixed adversarial set of Aff+(3) matrices and seeded random ones.

The adversarial set is the cross product of
* rotation angles 0, 1e-12, 1e-8, 1e-5, 0.5, π/2, 2, π − 1e-6, π − 1e-9, π about several axes,
* stretch spectra (singular values of the linear part): uniform (triple), two equal, gaps
  1e-1 … 1e-12 (and 0) in either pair, anisotropy up to 1e3 : 1e-3,
* shears and translations from 0 to 1e3,
built exactly from their factors so every case has a known ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import scipy.linalg as sl

ANGLES = (0.0, 1e-12, 1e-8, 1e-5, 0.5, np.pi / 2, 2.0, np.pi - 1e-6, np.pi - 1e-9, np.pi)
AXES = (
    np.array([1.0, 0.0, 0.0]),
    np.array([0.0, 0.0, 1.0]),
    np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5]),
    np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0),
)
GAPS = (1e-1, 1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 0.0)
TRANSLATIONS = (
    np.zeros(3),
    np.array([1e-3, 0.0, -2e-3]),
    np.array([1.0, 2.0, -3.0]),
    np.array([1e3, -1e3, 5e2]),
)


def spectra() -> list[tuple[float, float, float]]:
    """Singular values of the stretch: repeated, clustered at every gap, strongly anisotropic."""
    out: list[tuple[float, float, float]] = [
        (1.0, 1.0, 1.0),
        (2.0, 2.0, 2.0),
        (1e-3, 1e-3, 1e-3),
        (1e3, 1e3, 1e3),
    ]
    out += [(1.0, 1.0, 3.0), (0.5, 2.0, 2.0)]
    for g in GAPS:
        out += [(1.0, 1.0 + g, 2.0), (0.3, 1.7, 1.7 + g), (1.0, 1.0 + g, 1.0 + 2.0 * g)]
    out += [(1e-3, 1.0, 1e3), (1e-3, 1e-3, 1e3), (1e-3, 1e3, 1e3), (0.1, 1.0, 10.0)]
    return out


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Exact-as-possible rotation matrix from Rodrigues with library trig (no series involved)."""
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


#: A fixed orthonormal frame for the stretch axes (so the stretch is not axis-aligned).
STRETCH_FRAME = rotation(np.array([0.6, 0.0, 0.8]), 0.9)


@dataclass(frozen=True)
class AffCase:
    """One adversarial matrix with its generating factors: A = [[R(axis, angle) · S, t], [0, 1]]."""

    name: str
    axis: np.ndarray
    angle: float
    sigma: tuple[float, float, float]
    shear: float
    t: np.ndarray

    @property
    def stretch(self) -> np.ndarray:
        S = STRETCH_FRAME @ np.diag(self.sigma) @ STRETCH_FRAME.T
        return 0.5 * (S + S.T)

    @property
    def matrix(self) -> np.ndarray:
        A = np.eye(4)
        M = rotation(self.axis, self.angle) @ self.stretch
        if self.shear:
            M = M @ np.array([[1.0, self.shear, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        A[:3, :3] = M
        A[:3, 3] = self.t
        return A


def adversarial_cases() -> list[AffCase]:
    cases: list[AffCase] = []
    sp = spectra()
    for i, angle in enumerate(ANGLES):
        for j, axis in enumerate(AXES):
            for k, sigma in enumerate(sp):
                if (i + j + k) % 3:  # a third of the full product keeps every pairing of factors
                    continue
                t = TRANSLATIONS[(i + k) % len(TRANSLATIONS)]
                cases.append(
                    AffCase(f"angle={angle!r} axis={j} sigma={sigma} t={t[0]:g}", axis, angle, sigma, 0.0, t)
                )
    for shear in (0.5, 10.0):
        for angle in (0.0, 1e-8, 2.0, np.pi - 1e-9):
            cases.append(
                AffCase(
                    f"shear={shear} angle={angle!r}", AXES[2], angle, (1.0, 2.0, 0.5), shear, TRANSLATIONS[2]
                )
            )
    return cases


def random_affine(
    rng: np.random.Generator, n: int, log_scale: float = 1.0, t_scale: float = 10.0
) -> np.ndarray:
    """n random matrices in Aff+(3): rotation · stretch (log-normal) · rotation, plus translation."""
    A = np.zeros((n, 4, 4))
    A[:, 3, 3] = 1.0
    for i in range(n):
        Q1, Q2 = (sl.qr(rng.normal(size=(3, 3)))[0] for _ in range(2))
        Q1 *= np.sign(np.linalg.det(Q1))
        Q2 *= np.sign(np.linalg.det(Q2))
        A[i, :3, :3] = Q1 @ np.diag(np.exp(rng.normal(scale=log_scale, size=3))) @ Q2
        A[i, :3, 3] = rng.normal(scale=t_scale, size=3)
    return A


@pytest.fixture(scope="session")
def adversarial() -> list[AffCase]:
    return adversarial_cases()


@pytest.fixture(scope="session")
def random_1000() -> np.ndarray:
    return random_affine(np.random.default_rng(20130), 1000)
