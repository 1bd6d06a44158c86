"""Plants that integrate robots in-process: the model plant (eq. 4) and the
kinematic plant (q_dot = commanded velocity, what the authors' script simulates).

Both hold every robot's state and advance it by one control period with the
command held constant (zero-order hold). Pure numerics; the node that puts a
plant on the wire lives elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from plant.interface import DEFAULT_SUBSTEPS
from plant.mecanum import MecanumModel

Disturbance = Callable[[float], np.ndarray]


class ModelPlant:
    """Integrates q_ddot = -A0 q_dot - A1 + B (u + h_d(t)) with RK4 sub-steps.

    Every robot is integrated at once (arrays over robots): the same eq. (4)
    as :meth:`MecanumModel.acceleration`, written in the body frame so each
    stage costs a handful of numpy calls whatever the fleet size.
    """

    kind = "model"

    def __init__(
        self,
        models: Sequence[MecanumModel],
        q: np.ndarray,
        q_dot: np.ndarray,
        disturbance: Disturbance,
        substeps: int = DEFAULT_SUBSTEPS,
    ) -> None:
        self.models = list(models)
        self.q = np.array(q, dtype=float)
        self.q_dot = np.array(q_dot, dtype=float)
        self.disturbance = disturbance
        self.substeps = substeps
        # eq. (4) constants, stacked over robots; one shared matrix when every robot
        # has the same parameters (the usual case, and 2-D matmuls are faster)
        same = all(m is self.models[0] or m.params == self.models[0].params for m in self.models)
        pick = (lambda xs: xs[0]) if same else np.stack
        self._P_T = pick([m.P.T / m.params.wheel_radius_m for m in self.models])
        self._body_input_T = pick([m.body_input.T for m in self.models])
        self._A0_T = pick([m.A0.T for m in self.models])
        self._coulomb = np.array([[m.coulomb_torque_nm] for m in self.models])
        self._smooth = np.array([[m.params.coulomb_smoothing_radps] for m in self.models])
        self._body = np.empty_like(self.q)
        self._acc = np.empty_like(self.q)

    @staticmethod
    def _times(x: np.ndarray, m: np.ndarray) -> np.ndarray:
        """Row i of x times matrix m (shared 2-D, or m[i] when stacked 3-D)."""
        return x @ m if m.ndim == 2 else np.matmul(x[:, None, :], m)[:, 0, :]

    def accelerations(self, t: float, q: np.ndarray, q_dot: np.ndarray,
                      torques: np.ndarray) -> np.ndarray:
        """Eq. (4) for every robot: (n,3) accelerations."""
        c, s = np.cos(q[:, 2]), np.sin(q[:, 2])
        vx, vy = q_dot[:, 0], q_dot[:, 1]
        body = self._body  # T(phi)^T q_dot
        body[:, 0] = c * vx + s * vy
        body[:, 1] = c * vy - s * vx
        body[:, 2] = q_dot[:, 2]
        wheel = self._times(body, self._P_T)  # theta_dot = P T^T q_dot / R
        u = torques + self.disturbance(t) - self._coulomb * np.tanh(wheel / self._smooth)
        a = self._times(u, self._body_input_T)  # body frame: M_q^-1 P^T u / R
        acc = self._acc
        acc[:, 0] = c * a[:, 0] - s * a[:, 1]
        acc[:, 1] = s * a[:, 0] + c * a[:, 1]
        acc[:, 2] = a[:, 2]
        return acc - self._times(q_dot, self._A0_T)

    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None:
        h = dt / self.substeps
        q, qd, u = self.q, self.q_dot, np.asarray(torques, dtype=float)
        f = self.accelerations
        for k in range(self.substeps):
            ts = t + k * h
            k1q, k1v = qd, f(ts, q, qd, u)
            k2q, k2v = qd + h / 2 * k1v, f(ts + h / 2, q + h / 2 * k1q, qd + h / 2 * k1v, u)
            k3q, k3v = qd + h / 2 * k2v, f(ts + h / 2, q + h / 2 * k2q, qd + h / 2 * k2v, u)
            k4q, k4v = qd + h * k3v, f(ts + h, q + h * k3q, qd + h * k3v, u)
            q = q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q)
            qd = qd + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        self.q, self.q_dot = q, qd

    def close(self) -> None:
        """Nothing to release (the Plant protocol's close)."""


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
