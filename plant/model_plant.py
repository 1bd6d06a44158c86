"""Plants that integrate robots in-process: the model plant (eq. 4) and the
kinematic plant (q_dot = commanded velocity, what the authors' script simulates).

Both hold every robot's state and advance it by one control period with the
command held constant (zero-order hold). Pure numerics; the node that puts a
plant on the wire lives elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from plant.mecanum import MecanumModel

Disturbance = Callable[[float], np.ndarray]


class ModelPlant:
    """Integrates q_ddot = -A0 q_dot - A1 + B (u + h_d(t)) with RK4 sub-steps."""

    kind = "model"

    def __init__(
        self,
        models: Sequence[MecanumModel],
        q: np.ndarray,
        q_dot: np.ndarray,
        disturbance: Disturbance,
        substeps: int = 4,
    ) -> None:
        self.models = list(models)
        self.q = np.array(q, dtype=float)
        self.q_dot = np.array(q_dot, dtype=float)
        self.disturbance = disturbance
        self.substeps = substeps

    def _deriv(self, i: int, t: float, q: np.ndarray, qd: np.ndarray, u: np.ndarray):
        return qd, self.models[i].acceleration(q, qd, u, self.disturbance(t))

    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None:
        h = dt / self.substeps
        for i in range(len(self.models)):
            q, qd, u = self.q[i], self.q_dot[i], torques[i]
            for k in range(self.substeps):
                ts = t + k * h
                k1q, k1v = self._deriv(i, ts, q, qd, u)
                k2q, k2v = self._deriv(i, ts + h / 2, q + h / 2 * k1q, qd + h / 2 * k1v, u)
                k3q, k3v = self._deriv(i, ts + h / 2, q + h / 2 * k2q, qd + h / 2 * k2v, u)
                k4q, k4v = self._deriv(i, ts + h, q + h * k3q, qd + h * k3v, u)
                q = q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
                qd = qd + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
            self.q[i], self.q_dot[i] = q, qd


class KinematicPlant:
    """q_{k+1} = q_k + dt v_cmd (explicit Euler, as in the authors' script)."""

    kind = "kinematic"

    def __init__(self, q: np.ndarray, q_dot: np.ndarray) -> None:
        self.q = np.array(q, dtype=float)
        self.q_dot = np.array(q_dot, dtype=float)

    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None:
        self.q_dot = np.array(v_cmd, dtype=float)
        self.q = self.q + dt * self.q_dot
