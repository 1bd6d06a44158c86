"""A leader path through waypoints: a C2 cubic spline, driven along at a trapezoidal speed.

Why a spline and not straight segments. The estimator (14) tracks the leader only
while its sign-term gain exceeds the leader's acceleration (iota_4 > |a0|, erratum 16),
and the heading psi = atan2(y0', x0') (erratum 6) has rate |v0| kappa. On a polyline
both are unbounded at every corner (the velocity turns in zero time); a C2 curve
keeps the acceleration and the heading rate bounded and continuous. The spline is
scipy's ``CubicSpline`` through the waypoints (it passes through every one, so a
straight run through a gap is written as waypoints along it), parametrised by chord
length u, with "natural" ends (zero curvature at the first and last waypoint).

Why an arc-length speed profile. A spline's own parameter does not run at constant
speed; the leader instead moves its arc length s along the curve with

    s(t): accelerate at a from rest to v, cruise at v, brake at a to rest at s = L   (W1)
    (a triangle when L is too short to reach v), so the path is driven at the speed
    the scenario asks for, starting and ending at rest.

The state at t follows from s(t), s_dot, s_ddot and the curve's unit tangent T(s)
and signed curvature k(s) (exact, no finite differences):

    p0 = c(u(s)),  v0 = s_dot T,  a0 = s_ddot T + s_dot^2 k N,  psi_dot = s_dot k       (W2)

with N = T rotated by +90 degrees. u(s), the inverse of s(u) = int_0^u |c'(w)| dw,
is a cubic Hermite interpolant on a table of (s, u) with its exact slope du/ds =
1/|c'(u)|; s(u) is integrated with 8-point Gauss-Legendre on each of ``SUBDIVISIONS``
pieces per spline segment (error ~1e-12 m on the bundled paths, checked in
tests/integration/test_leader_paths.py against a finite difference of p0).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from math import atan2, hypot, sqrt
from typing import Any

import numpy as np

SUBDIVISIONS = 64  # arc-length table pieces per spline segment
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)


@dataclass(frozen=True)
class SpeedProfile:
    """(W1): arc length s(t) from 0 to ``length`` at cruise ``speed``, ramps at ``accel``."""

    length: float
    speed: float
    accel: float

    def at(self, t: float) -> tuple[float, float, float]:
        """(s, s_dot, s_ddot) at time t >= 0."""
        L, v, a = self.length, self.speed, self.accel
        t_ramp = v / a
        if a * t_ramp * t_ramp > L:  # never reaches v: a triangle
            t_ramp = sqrt(L / a)
            v = a * t_ramp
        t_cruise = (L - a * t_ramp * t_ramp) / v
        t_end = 2 * t_ramp + t_cruise
        if t <= 0.0:
            return 0.0, 0.0, 0.0
        if t < t_ramp:
            return 0.5 * a * t * t, a * t, a
        if t < t_ramp + t_cruise:
            return 0.5 * a * t_ramp * t_ramp + v * (t - t_ramp), v, 0.0
        if t < t_end:
            left = t_end - t
            return L - 0.5 * a * left * left, a * left, -a
        return L, 0.0, 0.0

    @property
    def duration(self) -> float:
        """When the leader comes to rest at the last waypoint."""
        L, v, a = self.length, self.speed, self.accel
        t_ramp = v / a
        if a * t_ramp * t_ramp > L:
            return 2 * sqrt(L / a)
        return 2 * t_ramp + (L - a * t_ramp * t_ramp) / v


@dataclass(frozen=True)
class WaypointPath:
    """The spline through ``waypoints`` driven with :class:`SpeedProfile` (W1)-(W2)."""

    waypoints: tuple[tuple[float, float], ...]
    speed: float  # cruise speed, m/s
    accel: float  # ramp acceleration, m/s^2
    _spline: Any = field(init=False, repr=False, compare=False)  # scipy CubicSpline
    _u_of_s: Any = field(init=False, repr=False, compare=False)  # scipy CubicHermiteSpline
    profile: SpeedProfile = field(init=False, compare=False)

    def __post_init__(self) -> None:
        pts = np.array(self.waypoints, dtype=float)
        u = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        # scipy.interpolate costs ~0.5 s to import: only a waypoint path loads it
        from scipy.interpolate import CubicHermiteSpline, CubicSpline

        spline = CubicSpline(u, pts, bc_type="natural")
        nodes = np.unique(np.concatenate([np.linspace(u[k], u[k + 1], SUBDIVISIONS + 1)
                                          for k in range(len(u) - 1)]))
        speed = np.hypot(*spline(nodes, 1).T)  # |c'(u)|
        pieces = []
        for a, b in zip(nodes[:-1], nodes[1:], strict=True):
            w = 0.5 * (b - a)
            x = a + w * (_GL_X + 1.0)
            pieces.append(w * float(_GL_W @ np.hypot(*spline(x, 1).T)))
        s = np.concatenate([[0.0], np.cumsum(pieces)])
        object.__setattr__(self, "_spline", spline)
        object.__setattr__(self, "_u_of_s", CubicHermiteSpline(s, nodes, 1.0 / speed))
        object.__setattr__(self, "profile", SpeedProfile(float(s[-1]), self.speed, self.accel))

    @property
    def length(self) -> float:
        return self.profile.length

    def _geometry(self, s: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(c(u(s)), unit tangent T, signed curvature k) at arc length s."""
        u = float(self._u_of_s(min(max(s, 0.0), self.length)))
        p = self._spline(u)
        d1, d2 = self._spline(u, 1), self._spline(u, 2)
        n1 = hypot(d1[0], d1[1])
        return p, d1 / n1, float(d1[0] * d2[1] - d1[1] * d2[0]) / n1**3

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """(p0, v0, a0, tangent heading, heading rate) at t, (W2)."""
        s, sd, sdd = self.profile.at(t)
        p, tangent, k = self._geometry(s)
        normal = np.array([-tangent[1], tangent[0]])
        return (np.asarray(p, float), sd * tangent, sdd * tangent + sd * sd * k * normal,
                atan2(tangent[1], tangent[0]), sd * k)


def waypoint_path(points: Sequence[Sequence[float]], speed: float, accel: float) -> WaypointPath:
    return WaypointPath(tuple((float(p[0]), float(p[1])) for p in points), float(speed), float(accel))
