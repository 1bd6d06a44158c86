"""Wheel-torque disturbance h_d(t) of eq. (49); d_i = B h_d enters eq. (4)."""

from __future__ import annotations

from math import cos, sin

import numpy as np


def paper_disturbance(t: float) -> np.ndarray:
    """h_d(t) of eq. (49), in N m (the 10^-2 factor applied)."""
    return 1e-2 * np.array(
        [
            1.0 + 2.0 * cos(0.3 * t),
            2.0 + 1.5 * sin(0.3 * t) + 3.0 * cos(0.3 * t),
            3.0 + 2.0 * sin(0.2 * t),
            2.5 + sin(0.1 * t),
        ]
    )


def make_disturbance(kind: str, scale: float, constant: tuple[float, ...]):
    """A function t -> h_d(t) (4 wheel torques) for the scenario's choice."""
    if kind == "none":
        zero = np.zeros(4)
        return lambda t: zero
    if kind == "constant":
        c = scale * np.array(constant, dtype=float)
        return lambda t: c
    if kind == "paper":
        return lambda t: scale * paper_disturbance(t)
    raise ValueError(f"unknown disturbance kind {kind!r}")
