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

from agents.law_kernel import leader_batch_of
from agents.steered_leader import SteeredLeader, SteeredSpec, states_one_by_one
from agents.waypoint_path import WaypointPath


@dataclass(frozen=True)
class Harmonic:
    fn: str  # "sin" | "cos"
    amp: float
    freq: float
    phase: float = 0.0
    offset: float = 0.0

    def with_derivatives(self, th: float) -> tuple[float, float, float]:
        """amp fn(freq th + phase) + offset at ``th``, and its first and second
        derivatives in ``th``, the angle's sine and cosine taken once (the compiled batch,
        agents/law_kernel_sections/leader_path.pxi, does the same operations in the same
        order)."""
        a = self.freq * th + self.phase
        s, c = sin(a), cos(a)
        if self.fn == "sin":
            return (self.amp * s + self.offset, self.amp * self.freq * c,
                    -self.amp * self.freq**2 * s)
        return (self.amp * c + self.offset, self.amp * self.freq * -s,
                -self.amp * self.freq**2 * c)


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
    steered: SteeredSpec | None = None  # no path: steered from outside (agents/steered_leader.py)


def _wrap(a: float) -> float:
    return (a + pi) % (2.0 * pi) - pi


class LeaderGenerator:
    """Steps the leader in fixed increments dt; ``state()`` is the state at t_k."""

    def __init__(self, spec: LeaderSpec, dt: float) -> None:
        self.spec, self.dt, self.k = spec, dt, 0
        self._wp_t: float | None = None
        self._wp: tuple = ()
        self._h_t: float | None = None
        self._h: tuple = ()
        # the leader's position and velocity, (x, y) floats
        self._pos = self._path_position(0.0)
        self._vel = (0.0, 0.0) if spec.kind == "path_follower" else self._path_velocity(0.0)
        self._heading = self._raw_heading(0.0)

    def _theta(self, t: float) -> float:
        return self.spec.theta0 + self.spec.theta_rate * t

    def _waypoint_state(self, t: float) -> tuple:
        """The waypoint path's (W2) at t, computed once per t (~80 us with scipy)."""
        if self._wp_t != t:
            self._wp_t, self._wp = t, self.spec.waypoints.state(t)
        return self._wp

    def _harmonic(self, t: float) -> tuple[float, float, float, float, float, float]:
        """The harmonic path at t as floats, computed once per t: (x, y, dx/dt, dy/dt,
        d2x/dt2, d2y/dt2), theta = theta0 + rate t."""
        if self._h_t != t:
            th, r = self._theta(t), self.spec.theta_rate
            x, dx, ddx = self.spec.x.with_derivatives(th)
            y, dy, ddy = self.spec.y.with_derivatives(th)
            self._h_t = t
            self._h = (x, y, r * dx, r * dy, r * r * ddx, r * r * ddy)
        return self._h

    def _path_position(self, t: float) -> tuple[float, float]:
        if self.spec.waypoints is not None:
            p = self._waypoint_state(t)[0]
            return float(p[0]), float(p[1])
        return self._harmonic(t)[0:2]

    def _path_velocity(self, t: float) -> tuple[float, float]:
        if self.spec.waypoints is not None:
            v = self._waypoint_state(t)[1]
            return float(v[0]), float(v[1])
        return self._harmonic(t)[2:4]

    def _path_acceleration(self, t: float) -> tuple[float, float]:
        if self.spec.waypoints is not None:
            a = self._waypoint_state(t)[2]
            return float(a[0]), float(a[1])
        return self._harmonic(t)[4:6]

    def _raw_heading(self, t: float) -> float:
        if self.spec.heading == "polar":
            p = self._pos
            return atan2(p[1], p[0])
        if self.spec.waypoints is not None:  # the curve's tangent: defined at rest too
            return self._waypoint_state(t)[3]
        vx, vy = self._path_velocity(t)
        return atan2(vy, vx)

    def _heading_rate(self, t: float) -> float:
        if self.spec.heading == "polar":
            (px, py), (vx, vy) = self._pos, self._vel
            r2 = px * px + py * py
            return 0.0 if r2 == 0.0 else (px * vy - py * vx) / r2
        if self.spec.waypoints is not None:
            return self._waypoint_state(t)[4]  # s_dot k, (W2)
        (vx, vy), (ax, ay) = self._path_velocity(t), self._path_acceleration(t)
        n2 = vx * vx + vy * vy
        return 0.0 if n2 == 0.0 else (vx * ay - vy * ax) / n2

    @property
    def t(self) -> float:
        return self.k * self.dt

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """(q0, v0) at t_k."""
        q0, v0 = self.state_floats()
        return np.array(q0), np.array(v0)

    def state_floats(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(q0, v0) at t_k as float tuples (what the law and the wire take: no arrays built
        to be unpacked again, every step)."""
        return ((self._pos[0], self._pos[1], self._heading),
                (self._vel[0], self._vel[1], self._heading_rate(self.t)))

    def batch(self, count: int) -> tuple[list[tuple[float, float, float]],
                                         list[tuple[float, float, float]]]:
        """The states (q0, v0) of the next ``count`` steps, as ``count`` calls of
        :meth:`state_floats` then :meth:`advance` give them, bit for bit; the generator
        is left where those calls leave it. An analytic harmonic path with the tangent
        heading (the paper's, lab's) runs one loop of the same operations: the leader
        publishes its states in batches ahead of need, and at every wake the calls of
        the step-by-step path cost ~10 µs a state after a sleep here, the compiled loop
        (agents/law_kernel_sections/leader_path.pxi) well under one (bench-history.md,
        "The bridge on floats")."""
        spec = self.spec
        if spec.kind != "analytic" or spec.waypoints is not None or spec.heading == "polar" \
                or spec.x is None or spec.y is None:
            return states_one_by_one(self, count)
        k, (px, py), heading = self.k, self._pos, self._heading
        _, _, vx, vy, ax, ay = self._harmonic(k * self.dt)
        qs, vs, after = leader_batch_of(_path_args(spec.x), _path_args(spec.y), spec.theta0,
                                        spec.theta_rate, self.dt, k,
                                        (px, py, heading, vx, vy, ax, ay), count)
        px, py, heading, vx, vy, ax, ay = after
        self.k = k = k + count
        self._pos, self._vel, self._heading = (px, py), (vx, vy), heading
        self._h_t, self._h = k * self.dt, (px, py, vx, vy, ax, ay)
        return qs, vs

    def advance(self) -> None:
        t_next = (self.k + 1) * self.dt
        if self.spec.kind == "path_follower":  # v = v_path + k (x_path - x), explicit Euler
            t, k, dt = self.t, self.spec.follow_gain, self.dt
            (vx, vy), (px, py) = self._path_velocity(t), self._path_position(t)
            x, y = self._pos
            self._vel = v = (vx + k * (px - x), vy + k * (py - y))
            self._pos = (x + dt * v[0], y + dt * v[1])
        else:
            self._pos = self._path_position(t_next)
            self._vel = self._path_velocity(t_next)
        self.k += 1
        self._heading += _wrap(self._raw_heading(t_next) - self._heading)


def _path_args(h: Harmonic) -> tuple[bool, float, float, float, float]:
    """A harmonic as the compiled batch takes it."""
    return (h.fn == "sin", h.amp, h.freq, h.phase, h.offset)


def leader_generator(spec: LeaderSpec, dt: float) -> LeaderGenerator | SteeredLeader:
    """The leader of ``spec``: on its path, or steered from outside."""
    if spec.steered is not None:
        return SteeredLeader(spec.steered, dt)
    return LeaderGenerator(spec, dt)
