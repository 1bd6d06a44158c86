"""Plants that integrate robots in-process: the model plant (eq. 4) and the
kinematic plant (q_dot = commanded velocity, what the authors' script simulates).

Both hold every robot's state and advance it by one control period with the
command held constant (zero-order hold). Pure numerics; the node that puts a
plant on the wire lives elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from plant.disturbance import Disturbance, StartedDisturbance
from plant.fleet_kernel import FleetDynamics
from plant.interface import DEFAULT_SUBSTEPS
from plant.mecanum import MecanumModel

DisturbanceFn = Callable[[float], np.ndarray]


class ModelPlant:
    """Integrates q_ddot = -A0 q_dot - A1 + B (u + h_d(t)) with RK4 sub-steps.

    Every robot is integrated in one call of the plant's kernel
    (plant/fleet_kernel.pyx, ``FleetDynamics``): eq. (4) on C doubles, the disturbance
    evaluated inside when it is the scenario's (:class:`Disturbance`); any other
    function of t (the drive emulators' armed disturbance, tests) is evaluated here at
    the stages' times and handed over.
    """

    kind = "model"

    def __init__(
        self,
        models: Sequence[MecanumModel],
        q: np.ndarray,
        q_dot: np.ndarray,
        disturbance: DisturbanceFn,
        substeps: int = DEFAULT_SUBSTEPS,
    ) -> None:
        self.models = list(models)
        self.q = np.array(q, dtype=float)
        self.q_dot = np.array(q_dot, dtype=float)
        self.disturbance = disturbance
        self.substeps = substeps
        # the scenario's h_d, whole or from each robot's own start, is evaluated in the
        # kernel; any other function of t here, at the stages' times (what that costs: a
        # fleet emulator's robots, staged here, took 50 µs a step against 3 in the kernel)
        self._start = disturbance.start if isinstance(disturbance, StartedDisturbance) else None
        known = (disturbance if isinstance(disturbance, Disturbance) else
                 disturbance.disturbance if isinstance(disturbance, StartedDisturbance) else
                 Disturbance("none"))
        self._dynamics = FleetDynamics(self.models, known.kind, known.scale, known.constant,
                                       substeps)
        self._other = None if isinstance(disturbance, Disturbance | StartedDisturbance) \
            else disturbance

    def _stage_disturbances(self, t: float, dt: float) -> np.ndarray:
        """h_d at the RK4 stages' times t + k h + (0, h/2, h), one (n, 4) block each."""
        n, h = len(self.models), dt / self.substeps
        times = [t + k * h + half for k in range(self.substeps) for half in (0.0, 0.5 * h)]
        times.append(t + self.substeps * h)
        return np.ascontiguousarray(
            [np.broadcast_to(self._other(ts), (n, 4)) for ts in times], dtype=float)

    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None:
        # new arrays each step: whoever kept the last state keeps it unchanged
        q, qd = self.q.copy(), self.q_dot.copy()
        u = np.ascontiguousarray(torques, dtype=float).reshape(len(self.models), 4)
        stages = None if self._other is None else self._stage_disturbances(t, dt)
        self._dynamics.step(t, dt, q, qd, u, stages, self._start)
        self.q, self.q_dot = q, qd

    def close(self) -> None:
        """Nothing to release (the Plant interface)."""


class KinematicPlant:
    """q_{k+1} = q_k + dt v_cmd (explicit Euler, as in the authors' script)."""

    kind = "kinematic"

    def __init__(self, q: np.ndarray, q_dot: np.ndarray) -> None:
        self.q = np.array(q, dtype=float)
        self.q_dot = np.array(q_dot, dtype=float)

    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None:
        self.q_dot = np.array(v_cmd, dtype=float)
        self.q = self.q + dt * self.q_dot

    def close(self) -> None:
        """Nothing to release (the Plant protocol's close)."""
