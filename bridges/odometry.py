"""Wheel odometry: encoder wheel speeds -> body twist (eq. 1) -> world velocity
and pose. Pure math, no I/O; the bridge feeds it what the drivers report.

    v_r   = R P^+ theta_dot          body twist [v_x, v_y, omega], eq. (1)
    q_dot = T(phi) v_r               world frame, eq. (3)
    q    += dt * q_dot evaluated at the mid-heading phi + omega dt / 2

The mid-heading step is exact for a constant twist's heading and second order in
position, so odometry drift comes from the encoders and the wheels, not from the
integration.

:meth:`Odometry.advance` integrates the wheels' *rotation* since the last update
(the drives' position estimates) instead of speed x dt: a lost, shed or late
encoder frame then costs no drift, since the next one carries the whole rotation.
"""

from __future__ import annotations

from math import cos, pi, sin

import numpy as np

from plant.mecanum import MecanumModel

REV_TO_RAD = 2.0 * pi


class Odometry:
    """Dead-reckoned pose of one robot from its four wheel speeds."""

    def __init__(self, model: MecanumModel, q0: np.ndarray) -> None:
        self.q = np.array(q0, dtype=float)
        self.q_dot = np.zeros(3)
        # eq. (1): body twist from wheel speeds, constant
        self._twist_of_wheels = model.params.wheel_radius_m * np.linalg.pinv(model.P)

    def body_twist(self, wheel_speeds_radps: np.ndarray) -> np.ndarray:
        """v_r = R P^+ theta_dot (eq. 1)."""
        return self._twist_of_wheels @ np.asarray(wheel_speeds_radps, dtype=float)

    def advance(self, wheel_rotation_rad: np.ndarray, wheel_speeds_radps: np.ndarray) -> None:
        """Advance the pose by the wheels' rotation since the last update (body
        displacement R P^+ delta_theta, applied at the mid heading); the velocity from
        the wheel speeds measured now."""
        dx, dy, dphi = self.body_twist(wheel_rotation_rad)
        mid = float(self.q[2]) + 0.5 * dphi
        c, s = cos(mid), sin(mid)
        self.q += np.array([c * dx - s * dy, s * dx + c * dy, dphi])
        vx, vy, w = self.body_twist(wheel_speeds_radps)
        c_now, s_now = cos(float(self.q[2])), sin(float(self.q[2]))
        self.q_dot = np.array([c_now * vx - s_now * vy, s_now * vx + c_now * vy, w])

    def update(self, wheel_speeds_radps: np.ndarray, dt: float) -> None:
        """Advance the pose by dt with the wheel speeds measured now."""
        vx, vy, w = self.body_twist(wheel_speeds_radps)
        phi = float(self.q[2])
        mid = phi + 0.5 * w * dt
        c, s = cos(mid), sin(mid)
        c_now, s_now = cos(phi + w * dt), sin(phi + w * dt)
        self.q += dt * np.array([c * vx - s * vy, s * vx + c * vy, w])
        self.q_dot = np.array([c_now * vx - s_now * vy, s_now * vx + c_now * vy, w])
