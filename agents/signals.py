"""Small nonlinear maps shared by the estimator, the ESO and the controller.

The numpy forms take vectors of any size: the reference forms of the equations, which the
tests check the compiled law (agents/law_kernel.pyx, its own scalar forms) against.
"""

from __future__ import annotations

import numpy as np

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Vec4 = tuple[float, float, float, float]


def sig(x: np.ndarray, power: float) -> np.ndarray:
    """sig^r(x) = |x|^r sign(x), element-wise (Notation 1 of the paper)."""
    return np.abs(x) ** power * np.sign(x)


def smooth_norm(x: np.ndarray, eps: float) -> float:
    """||x||_eps = sqrt(||x||^2 + eps^2): a norm that is smooth at 0.

    Used where the paper divides by ||x|| with a negative power (eqs. 41-42).
    """
    return float(np.sqrt(float(x @ x) + eps * eps))
