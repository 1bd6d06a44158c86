"""Small nonlinear maps shared by the estimator, the ESO and the controller.

The numpy forms take vectors of any size; the ``*_scalar`` forms act on one float
and serve the per-step hot path (``AgentCore.step``), where the vectors have 2 or
3 components and a numpy call costs more than the arithmetic it does.
"""

from __future__ import annotations

import numpy as np

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Vec4 = tuple[float, float, float, float]


def sig(x: np.ndarray, power: float) -> np.ndarray:
    """sig^r(x) = |x|^r sign(x), element-wise (Notation 1 of the paper)."""
    return np.abs(x) ** power * np.sign(x)


def sig_scalar(x: float, power: float) -> float:
    """:func:`sig` of one float: |x|^r sign(x) with sign(0) = 0 (NaN stays NaN)."""
    if x > 0.0:
        return x**power
    if x < 0.0:
        return -((-x) ** power)
    return x * 0.0


def smooth_norm(x: np.ndarray, eps: float) -> float:
    """||x||_eps = sqrt(||x||^2 + eps^2): a norm that is smooth at 0.

    Used where the paper divides by ||x|| with a negative power (eqs. 41-42).
    """
    return float(np.sqrt(float(x @ x) + eps * eps))
