"""The safety filter: the last layer of every agent (ours, not the paper's; docs/safety.md).

A discrete-time control barrier function on the planar velocity command v (the v_d
of eq. 26 after the explicit limits), given how hard the reference may brake.

For every perceived body j (an obstacle, or another robot moving at v_j) take the unit
normal n_j = (p - p_j) / |p - p_j| and the free gap d_j = |p - p_j| - (r + r_j) - m
(m: the margin kept on top of contact). With the closing speed c_j = -n_j . (v - v_j),

    (S1)  c_j h + c_j^2 / (2 a) <= d_j,   i.e.   c_j <= c_max(d_j) = -a h + sqrt((a h)^2 + 2 a d_j)

one more period at c_j, then braking at a, ends before the gap is used up. The barrier
B_j = d_j - c_j h - c_j^2 / (2 a) is kept >= 0. It is recursively feasible for a body
that keeps its velocity: if c_j <= c_max(d_j) at step k, the gap one period later is
d' >= d_j - c_j h >= c_j^2 / (2 a), and c' = c_j - a h (one period of braking, which the
explicit acceleration limit allows) satisfies c' h + c'^2 / (2 a) <= c_j^2 / (2 a) - a h^2 / 2
<= d' (docs/safety.md). Without an acceleration limit (a = inf) (S1) becomes
c_j <= d_j / h: the gap is never crossed within one period. Inside the margin
(d_j < 0) the body must be left: c_max = d_j / ``exit_time_s`` < 0.

(S1) is linear in v: n_j . v >= n_j . v_j - c_max(d_j). Two robots that both run the
filter share each barrier (reciprocal barriers, after Wang, Ames and Egerstedt 2017):
robot i's own closing speed c_i = -n_j . v stays within half of c_max, and within what
the other's present closing speed c_j = n_j . v_j leaves of it,

    (S2)  c_i <= min(c_max(d_j) / 2, c_max(d_j) - c_j),

so that two robots that speed up at each other in the same period (each counting on the
other keeping its velocity, as (S1) alone would) cannot close at twice c_max, while a
robot that does not give way (an unpowered one is perceived as an obstacle) is met by the
second term as (S1) meets any moving body. The filter returns the command
closest to the nominal one v_nom in

    {v : every (S1),  |v - v_prev| <= a h,  |v| <= v_max}

a 2-D quadratic program solved exactly: the optimum is v_nom, the projection of v_nom on
one boundary (a line or a circle), or a point where two boundaries meet, so the feasible
candidate of least cost among those is the solution (O(m^2) candidates for m bodies; the
cost is in `omnifleet bench`). When v_nom satisfies every (S1) it is returned as it is,
the same floats: the paper's law is untouched wherever no constraint is active. When the
set is empty (the robot is already too fast for the gap it has), the command brakes as
hard as the limit allows toward the point that satisfies the barriers alone, and the step
is counted as infeasible.

Pure math on floats, no I/O; the agent passes what it perceives (plant/perception.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from math import hypot, inf, isfinite, sqrt

from agents.signals import Vec2

_TOL = 1e-9  # m/s: a candidate this close to a boundary is on it


@dataclass(frozen=True)
class Guarded:
    """A perceived body as the filter needs it: centre, velocity, radius."""

    x: float
    y: float
    vx: float
    vy: float
    radius: float
    reciprocal: bool = False  # a robot that runs the filter too: (S2) instead of (S1)


@dataclass(frozen=True)
class SafetyLimits:
    """What the filter keeps and what it may ask of the robot (from the scenario)."""

    margin_m: float  # kept on top of contact (robot radius + body radius)
    brake_mps2: float  # a: how hard the reference may brake (inf: no limit)
    max_speed_mps: float = inf
    exit_time_s: float = 0.5  # inside the margin: leave it at (gap / exit_time) m/s


@dataclass(frozen=True)
class SafetyResult:
    """The filtered planar command and what the filter did this step."""

    v: Vec2
    active: bool  # the command was changed
    binding: int  # barriers (S1) the nominal command violated
    infeasible: bool  # no command met every barrier within the limits
    dv: float  # |v - v_nom|, m/s


def closing_speed_limit(gap: float, brake: float, h: float, exit_time_s: float) -> float:
    """c_max(d) of (S1): the largest closing speed from which one more period and then
    braking at ``brake`` stop within ``gap``; negative (leave) inside the margin."""
    if gap < 0.0:
        return gap / exit_time_s
    if not isfinite(brake):
        return gap / h
    ah = brake * h
    return -ah + sqrt(ah * ah + 2.0 * brake * gap)


def stopping_distance(closing: float, brake: float, h: float) -> float:
    """The gap used up by one more period at ``closing`` m/s and braking at ``brake``
    after it: the left side of (S1), whose inverse is :func:`closing_speed_limit`."""
    if closing <= 0.0:
        return 0.0
    return closing * h + (closing * closing / (2.0 * brake) if isfinite(brake) else 0.0)


def barriers(px: float, py: float, radius: float, bodies: Sequence[Guarded],
             lim: SafetyLimits, h: float) -> list[tuple[float, float, float]]:
    """Each body's (S1) as a half-plane (n_x, n_y, b): n . v >= b."""
    out = []
    for body in bodies:
        dx, dy = px - body.x, py - body.y
        dist = hypot(dx, dy)
        nx, ny = (dx / dist, dy / dist) if dist > 1e-12 else (1.0, 0.0)
        gap = dist - radius - body.radius - lim.margin_m
        c_max = closing_speed_limit(gap, lim.brake_mps2, h, lim.exit_time_s)
        b = nx * body.vx + ny * body.vy - c_max  # (S1)
        if body.reciprocal:
            b = max(b, -0.5 * c_max)  # (S2)
        out.append((nx, ny, b))
    return out


def safety_filter(v_nom: Vec2, v_prev: Vec2 | None, px: float, py: float, radius: float,
                  bodies: Sequence[Guarded], lim: SafetyLimits, h: float) -> SafetyResult:
    """The command closest to ``v_nom`` that keeps every barrier (S1) (see the module)."""
    lines = barriers(px, py, radius, bodies, lim, h)
    binding = sum(1 for nx, ny, b in lines if nx * v_nom[0] + ny * v_nom[1] < b)
    if binding == 0:
        return SafetyResult(v_nom, False, 0, False, 0.0)
    discs = []
    if v_prev is not None and isfinite(lim.brake_mps2):
        discs.append((v_prev[0], v_prev[1], lim.brake_mps2 * h))
    if isfinite(lim.max_speed_mps):
        discs.append((0.0, 0.0, lim.max_speed_mps))
    v = closest_feasible(v_nom, lines, discs)
    infeasible = v is None
    if v is None:
        # no command meets the barriers within the limits: brake as hard as allowed
        # toward the barriers' own solution (or a standstill relative to the world)
        target = closest_feasible(v_nom, lines, []) or (0.0, 0.0)
        v = _toward(v_prev, target, lim.brake_mps2 * h) if discs and v_prev is not None \
            else target
    dv = hypot(v[0] - v_nom[0], v[1] - v_nom[1])
    return SafetyResult(v, True, binding, infeasible, dv)


def _toward(start: Vec2, target: Vec2, step: float) -> Vec2:
    dx, dy = target[0] - start[0], target[1] - start[1]
    dist = hypot(dx, dy)
    if dist <= step:
        return target
    k = step / dist
    return start[0] + k * dx, start[1] + k * dy


def closest_feasible(v_nom: Vec2, lines: Sequence[tuple[float, float, float]],
                     discs: Sequence[tuple[float, float, float]]) -> Vec2 | None:
    """argmin |v - v_nom| over {n . v >= b for every line, |v - c| <= R for every disc};
    None when the set is empty. Exact: the optimum of this convex 2-D problem is v_nom
    or lies on one boundary (the projection of v_nom on it) or on two (where they meet)."""
    def feasible(v: Vec2) -> bool:
        x, y = v
        return all(nx * x + ny * y >= b - _TOL for nx, ny, b in lines) and all(
            (x - cx) ** 2 + (y - cy) ** 2 <= (r + _TOL) ** 2 for cx, cy, r in discs)

    if feasible(v_nom):
        return v_nom
    candidates: list[Vec2] = []
    for nx, ny, b in lines:  # projection on a line (|n| = 1)
        s = b - (nx * v_nom[0] + ny * v_nom[1])
        candidates.append((v_nom[0] + s * nx, v_nom[1] + s * ny))
    for cx, cy, r in discs:  # projection on a circle
        dx, dy = v_nom[0] - cx, v_nom[1] - cy
        dist = hypot(dx, dy)
        candidates.append((cx + r * dx / dist, cy + r * dy / dist) if dist > 0 else (cx + r, cy))
    for i, (ax, ay, ab) in enumerate(lines):  # line meets line
        for bx, by, bb in lines[i + 1:]:
            det = ax * by - ay * bx
            if abs(det) > 1e-12:
                candidates.append(((ab * by - bb * ay) / det, (ax * bb - bx * ab) / det))
    for nx, ny, b in lines:  # line meets circle
        for cx, cy, r in discs:
            candidates.extend(_line_circle(nx, ny, b, cx, cy, r))
    for i, (ax, ay, ar) in enumerate(discs):  # circle meets circle
        for bx, by, br in discs[i + 1:]:
            candidates.extend(_circle_circle(ax, ay, ar, bx, by, br))
    best, best_cost = None, inf
    for v in candidates:
        cost = (v[0] - v_nom[0]) ** 2 + (v[1] - v_nom[1]) ** 2
        if cost < best_cost and feasible(v):
            best, best_cost = v, cost
    return best


def _line_circle(nx: float, ny: float, b: float, cx: float, cy: float, r: float) -> list[Vec2]:
    """Where n . v = b meets |v - c| = r."""
    s = b - (nx * cx + ny * cy)  # signed distance of the centre's foot along n
    if abs(s) > r:
        return []
    fx, fy = cx + s * nx, cy + s * ny
    half = sqrt(max(r * r - s * s, 0.0))
    return [(fx - half * ny, fy + half * nx), (fx + half * ny, fy - half * nx)]


def _circle_circle(ax: float, ay: float, ar: float, bx: float, by: float,
                   br: float) -> list[Vec2]:
    """Where |v - a| = ar meets |v - b| = br."""
    dx, dy = bx - ax, by - ay
    d = hypot(dx, dy)
    if d < 1e-12 or d > ar + br or d < abs(ar - br):
        return []
    along = (ar * ar - br * br + d * d) / (2.0 * d)
    half = sqrt(max(ar * ar - along * along, 0.0))
    mx, my = ax + along * dx / d, ay + along * dy / d
    return [(mx - half * dy / d, my + half * dx / d), (mx + half * dy / d, my - half * dx / d)]
