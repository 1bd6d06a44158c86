"""The virtual leader (reference generator): q0 = [x0, y0, psi], v0 = d/dt q0.

Paths are parametric, x(theta), y(theta) as a*fn(f theta + p) + c with fn = sin
or cos, theta = theta0 + rate t, or a spline through waypoints driven at a
trapezoidal speed (agents/waypoint_path.py, W1-W2). Two kinds:
* ``analytic``: the leader is on the path at every t (the paper, Section 4);
* ``path_follower``: the leader starts on the path at rest and follows it with
  v = v_path + k (x_path - x), explicit Euler (the authors' public script).
The heading psi is the path tangent atan2(y', x'), unwrapped (erratum 6), or,
on request, the printed polar angle atan2(y0, x0).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import atan2, cos, pi, sin

import numpy as np

from agents.waypoint_path import WaypointPath


@dataclass(frozen=True)
class Harmonic:
    fn: str  # "sin" | "cos"
    amp: float
    freq: float
    phase: float = 0.0
    offset: float = 0.0

    def value(self, th: float) -> float:
        f = sin if self.fn == "sin" else cos
        return self.amp * f(self.freq * th + self.phase) + self.offset

    def d1(self, th: float) -> float:
        a = self.freq * th + self.phase
        return self.amp * self.freq * (cos(a) if self.fn == "sin" else -sin(a))

    def d2(self, th: float) -> float:
        a = self.freq * th + self.phase
        return -self.amp * self.freq**2 * (sin(a) if self.fn == "sin" else cos(a))


@dataclass(frozen=True)
class LeaderSpec:
    x: Harmonic | None  # the harmonic path (None with waypoints)
    y: Harmonic | None
    theta0: float = 0.0
    theta_rate: float = 1.0
    kind: str = "analytic"  # | "path_follower"
    follow_gain: float = 3.5
    heading: str = "tangent"  # | "polar"
    waypoints: WaypointPath | None = None  # instead of x, y


def _wrap(a: float) -> float:
    return (a + pi) % (2.0 * pi) - pi


class LeaderGenerator:
    """Steps the leader in fixed increments dt; ``state()`` is the state at t_k."""

    def __init__(self, spec: LeaderSpec, dt: float) -> None:
        self.spec, self.dt, self.k = spec, dt, 0
        self._wp_t: float | None = None
        self._wp: tuple = ()
        self._pos = self._path_position(0.0)
        self._vel = np.zeros(2) if spec.kind == "path_follower" else self._path_velocity(0.0)
        self._heading = self._raw_heading(0.0)

    def _theta(self, t: float) -> float:
        return self.spec.theta0 + self.spec.theta_rate * t

    def _waypoint_state(self, t: float) -> tuple:
        """The waypoint path's (W2) at t, computed once per t (~80 us with scipy)."""
        if self._wp_t != t:
            self._wp_t, self._wp = t, self.spec.waypoints.state(t)
        return self._wp

    def _path_position(self, t: float) -> np.ndarray:
        if self.spec.waypoints is not None:
            return self._waypoint_state(t)[0]
        th = self._theta(t)
        return np.array([self.spec.x.value(th), self.spec.y.value(th)])

    def _path_velocity(self, t: float) -> np.ndarray:
        if self.spec.waypoints is not None:
            return self._waypoint_state(t)[1]
        th, r = self._theta(t), self.spec.theta_rate
        return r * np.array([self.spec.x.d1(th), self.spec.y.d1(th)])

    def _path_acceleration(self, t: float) -> np.ndarray:
        if self.spec.waypoints is not None:
            return self._waypoint_state(t)[2]
        th, r = self._theta(t), self.spec.theta_rate
        return r * r * np.array([self.spec.x.d2(th), self.spec.y.d2(th)])

    def _raw_heading(self, t: float) -> float:
        if self.spec.heading == "polar":
            p = self._pos
            return atan2(p[1], p[0])
        if self.spec.waypoints is not None:  # the curve's tangent: defined at rest too
            return self._waypoint_state(t)[3]
        v = self._path_velocity(t)
        return atan2(v[1], v[0])

    def _heading_rate(self, t: float) -> float:
        if self.spec.heading == "polar":
            p, v = self._pos, self._vel
            r2 = float(p @ p)
            return 0.0 if r2 == 0.0 else float(p[0] * v[1] - p[1] * v[0]) / r2
        if self.spec.waypoints is not None:
            return self._waypoint_state(t)[4]  # s_dot k, (W2)
        v, a = self._path_velocity(t), self._path_acceleration(t)
        n2 = float(v @ v)
        return 0.0 if n2 == 0.0 else float(v[0] * a[1] - v[1] * a[0]) / n2

    @property
    def t(self) -> float:
        return self.k * self.dt

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """(q0, v0) at t_k."""
        t = self.t
        q0 = np.array([self._pos[0], self._pos[1], self._heading])
        v0 = np.array([self._vel[0], self._vel[1], self._heading_rate(t)])
        return q0, v0

    def advance(self) -> None:
        t_next = (self.k + 1) * self.dt
        if self.spec.kind == "path_follower":
            t = self.t
            v = self._path_velocity(t) + self.spec.follow_gain * (self._path_position(t) - self._pos)
            self._vel = v
            self._pos = self._pos + self.dt * v
        else:
            self._pos = self._path_position(t_next)
            self._vel = self._path_velocity(t_next)
        self.k += 1
        self._heading += _wrap(self._raw_heading(t_next) - self._heading)
