"""Small nonlinear maps shared by the estimator, the ESO and the controller.

The numpy forms take vectors of any size (the reference forms of the equations); the
``*_scalar`` forms act on one float, as the compiled law (agents/law_kernel.pyx) does.
"""

from __future__ import annotations

import numpy as np

from agents.law_kernel import sig_of

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Vec4 = tuple[float, float, float, float]


def sig(x: np.ndarray, power: float) -> np.ndarray:
    """sig^r(x) = |x|^r sign(x), element-wise (Notation 1 of the paper)."""
    return np.abs(x) ** power * np.sign(x)


def sig_scalar(x: float, power: float) -> float:
    """:func:`sig` of one float: |x|^r sign(x) with sign(0) = 0 (NaN stays NaN); the
    compiled law's own (agents/law_kernel.pyx)."""
    return sig_of(x, power)


def smooth_norm(x: np.ndarray, eps: float) -> float:
    """||x||_eps = sqrt(||x||^2 + eps^2): a norm that is smooth at 0.

    Used where the paper divides by ||x|| with a negative power (eqs. 41-42).
    """
    return float(np.sqrt(float(x @ x) + eps * eps))
