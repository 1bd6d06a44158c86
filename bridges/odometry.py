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

from collections.abc import Sequence
from math import cos, pi, sin

import numpy as np

from plant.mecanum import MecanumModel

REV_TO_RAD = 2.0 * pi
# a wheel turning more than this between two updates is a drive that restarted (its angle
# went back to 0) or an implausible estimate: that update falls back to speed x dt
MAX_TURNS_PER_UPDATE = 10.0

Vec3 = tuple[float, float, float]


class Odometry:
    """Dead-reckoned pose of one robot from its four wheel speeds.

    The pose ``q`` and the world velocity ``q_dot`` are float triples, and the arithmetic
    is on Python floats: numpy on vectors of three and four costs more in dispatch than
    in arithmetic, and a bridge runs this once a period after a sleep, caches cold (one
    ``follow`` cost 14 µs back to back, 76 µs after a 1 ms sleep with numpy arrays on the
    2-core development VM; docs/bench-history.md, "The bridge on floats")."""

    def __init__(self, model: MecanumModel, q0: Sequence[float]) -> None:
        x, y, phi = (float(v) for v in q0)
        self.q: Vec3 = (x, y, phi)
        self.q_dot: Vec3 = (0.0, 0.0, 0.0)
        # eq. (1): body twist from wheel speeds, constant; its rows as float quadruples
        twist = model.params.wheel_radius_m * np.linalg.pinv(model.P)
        self._rows = tuple(tuple(float(v) for v in row) for row in twist)
        self._last_rev: tuple[float, ...] | None = None  # wheel angles (turns) the pose is at

    def follow(self, positions_rev: Sequence[float] | None, first_rev: Sequence[float] | None,
               wheel_speeds_radps: Sequence[float], dt: float) -> None:
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
            self.q_dot = (0.0, 0.0, 0.0)
            return
        now = tuple(float(p) for p in positions_rev)
        last = self._last_rev if self._last_rev is not None else first_rev
        # (a NaN angle compares False: speed x dt, as for a restarted drive)
        if last is not None and all(abs(a - b) <= MAX_TURNS_PER_UPDATE
                                    for a, b in zip(now, last, strict=True)):
            self.advance([(a - b) * REV_TO_RAD for a, b in zip(now, last, strict=True)],
                         wheel_speeds_radps)
        else:
            self.update(wheel_speeds_radps, dt)
        self._last_rev = now

    def body_twist(self, wheel_speeds_radps: Sequence[float]) -> Vec3:
        """v_r = R P^+ theta_dot (eq. 1)."""
        w0, w1, w2, w3 = wheel_speeds_radps
        (a0, a1, a2, a3), (b0, b1, b2, b3), (c0, c1, c2, c3) = self._rows
        return (a0 * w0 + a1 * w1 + a2 * w2 + a3 * w3, b0 * w0 + b1 * w1 + b2 * w2 + b3 * w3,
                c0 * w0 + c1 * w1 + c2 * w2 + c3 * w3)

    def advance(self, wheel_rotation_rad: Sequence[float],
                wheel_speeds_radps: Sequence[float]) -> None:
        """Advance the pose by the wheels' rotation since the last update (body
        displacement R P^+ delta_theta, applied at the mid heading); the velocity from
        the wheel speeds measured now."""
        dx, dy, dphi = self.body_twist(wheel_rotation_rad)
        x, y, phi = self.q
        mid = phi + 0.5 * dphi
        c, s = cos(mid), sin(mid)
        phi += dphi
        self.q = (x + (c * dx - s * dy), y + (s * dx + c * dy), phi)
        vx, vy, w = self.body_twist(wheel_speeds_radps)
        c_now, s_now = cos(phi), sin(phi)
        self.q_dot = (c_now * vx - s_now * vy, s_now * vx + c_now * vy, w)

    def update(self, wheel_speeds_radps: Sequence[float], dt: float) -> None:
        """Advance the pose by dt with the wheel speeds measured now."""
        vx, vy, w = self.body_twist(wheel_speeds_radps)
        x, y, phi = self.q
        mid = phi + 0.5 * w * dt
        c, s = cos(mid), sin(mid)
        c_now, s_now = cos(phi + w * dt), sin(phi + w * dt)
        self.q = (x + dt * (c * vx - s * vy), y + dt * (s * vx + c * vy), phi + dt * w)
        self.q_dot = (c_now * vx - s_now * vy, s_now * vx + c_now * vy, w)


def pose_carried(q: Vec3, q_dot: Vec3, age_s: float | None, max_lead_s: float) -> Vec3:
    """The pose of the newest encoder data ``age_s`` old, carried to now at the velocity
    it gave, by at most ``max_lead_s`` (past that the data is lost, and the pose stays
    where the carry left it). Held at the lead, not dropped back to the uncarried pose:
    dropped back, a CiA 402 robot's published pose went 1.4-2.2 cm backwards while its
    drives' encoder data was 20-45 ms old (the pose of 25 ms before, 4 samples in a row),
    and its agent answered with torques 30x the steady ones (`lab`, 200 Hz, one core)."""
    if age_s is None or not age_s > 0.0:
        return q
    lead = age_s if age_s < max_lead_s else max_lead_s
    return q[0] + lead * q_dot[0], q[1] + lead * q_dot[1], q[2] + lead * q_dot[2]
