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
:meth:`Odometry.follow` is what a bridge calls each period with what the drives last
reported; it owns the wheel angles the next rotation is measured from.
"""

from __future__ import annotations

from math import cos, pi, sin

import numpy as np

from plant.mecanum import MecanumModel

REV_TO_RAD = 2.0 * pi
# a wheel turning more than this between two updates is a drive that restarted (its angle
# went back to 0) or an implausible estimate: that update falls back to speed x dt
MAX_TURNS_PER_UPDATE = 10.0


class Odometry:
    """Dead-reckoned pose of one robot from its four wheel speeds."""

    def __init__(self, model: MecanumModel, q0: np.ndarray) -> None:
        self.q = np.array(q0, dtype=float)
        self.q_dot = np.zeros(3)
        # eq. (1): body twist from wheel speeds, constant
        self._twist_of_wheels = model.params.wheel_radius_m * np.linalg.pinv(model.P)
        self._last_rev: np.ndarray | None = None  # wheel angles (turns) the pose is at

    def follow(self, positions_rev: np.ndarray | None, first_rev: np.ndarray | None,
               wheel_speeds_radps: np.ndarray, dt: float) -> None:
        """One bridge period: the drives' newest angle estimates (None until every
        drive has sent one), their angles when every drive had first reported
        (``DriverMonitor.first_positions_rev``), their speeds.

        - Until every drive has reported, the pose stays where it is: there is nothing
          to measure a rotation from. (Integrating the speeds of the drives heard so far
          with 0 for the others read as a rotation that never happened: a 0.0056 rad
          heading error, 3.5 cm of drift over a 60 s lab run.)
        - The first time, the rotation is measured from the angles when the last drive
          was first heard, so motion in frames queued before this period counts too.
        - A wheel that turned more than MAX_TURNS_PER_UPDATE (a drive that restarted
          from angle 0) makes this one period speed x dt.
        """
        if positions_rev is None:
            self.q_dot = np.zeros(3)
            return
        last = self._last_rev if self._last_rev is not None else first_rev
        if last is not None and np.all(np.abs(positions_rev - last) <= MAX_TURNS_PER_UPDATE):
            self.advance((positions_rev - last) * REV_TO_RAD, wheel_speeds_radps)
        else:
            self.update(wheel_speeds_radps, dt)
        self._last_rev = np.array(positions_rev, dtype=float)

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
