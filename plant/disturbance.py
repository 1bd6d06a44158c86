"""Wheel-torque disturbance h_d(t) of eq. (49); d_i = B h_d enters eq. (4).

The formula itself lives once, in the plant's kernel (plant/fleet_kernel.pyx), which
evaluates it inside the model plant's integration; :class:`Disturbance` names the
scenario's choice and evaluates it for the other plants (pybullet, the drive emulators).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plant.fleet_kernel import DISTURBANCE_KINDS, disturbance_at


@dataclass(frozen=True)
class Disturbance:
    """h_d(t), 4 wheel torques in N m: ``none``, a ``constant`` (``constant`` N m), or
    ``paper`` (eq. 49), times ``scale``."""

    kind: str
    scale: float = 1.0
    constant: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.kind not in DISTURBANCE_KINDS:
            raise ValueError(f"unknown disturbance kind {self.kind!r}; "
                             f"choose one of {', '.join(DISTURBANCE_KINDS)}")
        if len(self.constant) != 4:
            raise ValueError(f"a constant disturbance has 4 wheel torques, got {self.constant}")

    def __call__(self, t: float) -> np.ndarray:
        return disturbance_at(self.kind, self.scale, self.constant, t)


def make_disturbance(kind: str, scale: float, constant: tuple[float, ...]) -> Disturbance:
    """The scenario's disturbance (its [disturbance] table)."""
    padded = tuple(float(c) for c in constant) + (0.0,) * (4 - len(constant))
    return Disturbance(kind, float(scale), padded[:4] if kind == "constant" else (0.0,) * 4)


class StartedDisturbance:
    """The scenario's h_d on each robot's own clock: robot i feels h_d(t - start_i) from
    its start on, nothing before (start_i NaN). The model plant evaluates it in its
    kernel (plant/model_plant.py); called, it gives the (n, 4) rows at t, as a plant
    that takes any function of t does."""

    def __init__(self, disturbance: Disturbance, robots: int) -> None:
        self.disturbance = disturbance
        self.start = np.full(robots, np.nan)  # read by the kernel at every step

    def begin(self, row: int, t: float) -> None:
        """Robot ``row`` starts feeling h_d at time ``t`` (its first start counts)."""
        if np.isnan(self.start[row]):
            self.start[row] = t

    def __call__(self, t: float) -> np.ndarray:
        return np.array([np.zeros(4) if np.isnan(s) else self.disturbance(t - s)
                         for s in self.start])
