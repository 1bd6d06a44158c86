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

The arithmetic is the compiled law's (agents/law_kernel_sections/safety.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the result type the agent reports.
"""

from __future__ import annotations

from dataclasses import dataclass

from agents.signals import Vec2


@dataclass(frozen=True)
class SafetyResult:
    """The filtered planar command and what the filter did this step."""

    v: Vec2
    active: bool  # the command was changed
    binding: int  # barriers (S1) the nominal command violated
    infeasible: bool  # no command met every barrier within the limits
    dv: float  # |v - v_nom|, m/s
