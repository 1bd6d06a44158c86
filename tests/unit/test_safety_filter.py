"""The safety filter (agents/safety_filter.py) against what it promises:

- it changes nothing while no barrier is violated (the same floats come back);
- its 2-D quadratic program gives the optimum (no point of a dense feasible cloud is
  better, and it says "empty" only where the cloud has no feasible point);
- the barrier (S1) is physical: a point robot that follows the filtered command,
  with the acceleration limit, never enters the margin of a body it drives at,
  whatever its speed; with no acceleration limit it never crosses the gap in a period;
- recursive feasibility: from a state the barrier admits, braking at the limit for
  one period keeps the barrier (the proof in docs/safety.md, checked numerically).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from kernel_forms import (
    Guarded,
    SafetyLimits,
    closest_feasible,
    closing_speed_limit,
    safety_filter,
    stopping_distance,
)

H = 0.005
LAB = SafetyLimits(margin_m=0.05, brake_mps2=8.0, max_speed_mps=1.5)


def test_nothing_changes_while_no_barrier_is_violated():
    v = (0.3141592653589793, -1.2345678901234567)
    far = [Guarded(5.0, 0.0, 0.0, 0.0, 0.15), Guarded(0.0, 4.0, -0.2, 0.1, 0.2)]
    r = safety_filter(v, (0.3, -1.2), 0.0, 0.0, 0.2, far, LAB, H)
    assert r.v is v and not r.active and r.dv == 0.0 and r.binding == 0


def test_closing_speed_limit_inverts_the_stopping_distance():
    for brake in (0.5, 8.0, 100.0, math.inf):
        for gap in (0.0, 1e-4, 0.03, 0.5, 12.0):
            c = closing_speed_limit(gap, brake, H, 0.5)
            assert stopping_distance(c, brake, H) == pytest.approx(gap, rel=1e-9, abs=1e-12)
    assert closing_speed_limit(-0.02, 8.0, H, 0.5) == pytest.approx(-0.04)  # leave the margin


_RNG = np.random.default_rng(17)
_CLOUD = np.vstack([_RNG.uniform(-4.0, 4.0, (40_000, 2)), _RNG.normal(0.0, 1.0, (20_000, 2))])


def _feasible_cloud(lines, discs):
    """Points of a dense cloud that meet every constraint (a brute-force reference)."""
    ok = np.ones(len(_CLOUD), bool)
    for nx, ny, b in lines:
        ok &= _CLOUD @ np.array([nx, ny]) >= b
    for cx, cy, r in discs:
        ok &= np.hypot(_CLOUD[:, 0] - cx, _CLOUD[:, 1] - cy) <= r
    return _CLOUD[ok]


unit = st.floats(0.0, 2 * math.pi)


@settings(max_examples=120, deadline=None)
@given(v_nom=st.tuples(st.floats(-2, 2), st.floats(-2, 2)),
       lines=st.lists(st.tuples(unit, st.floats(-1.5, 1.0)), min_size=1, max_size=4),
       disc=st.one_of(st.none(), st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.05, 2))),
       speed=st.one_of(st.none(), st.floats(0.3, 3.0)))
def test_the_quadratic_program_is_solved_exactly(v_nom, lines, disc, speed):
    lines = [(math.cos(a), math.sin(a), b) for a, b in lines]
    discs = ([] if disc is None else [disc]) + ([] if speed is None else [(0.0, 0.0, speed)])
    got = closest_feasible(v_nom, lines, discs)
    cloud = _feasible_cloud(lines, discs)
    if got is None:  # the set is empty: no point of the cloud meets every constraint
        assert len(cloud) == 0
        return
    for nx, ny, b in lines:  # feasible
        assert nx * got[0] + ny * got[1] >= b - 1e-8
    for cx, cy, r in discs:
        assert math.hypot(got[0] - cx, got[1] - cy) <= r + 1e-8
    # and optimal: no feasible point of the cloud is closer to v_nom
    got_cost = (got[0] - v_nom[0]) ** 2 + (got[1] - v_nom[1]) ** 2
    if len(cloud):
        assert got_cost <= float(np.min(np.sum((cloud - v_nom) ** 2, axis=1))) + 1e-9


@pytest.mark.parametrize("brake, speed", [(8.0, 1.5), (8.0, 3.0), (2.0, 1.0), (math.inf, 40.0)])
@pytest.mark.parametrize("angle", [0.0, 0.3, 1.2])
def test_a_robot_driven_at_a_body_stops_outside_its_margin(brake, speed, angle):
    """A point robot commanded straight at (or past) a disc at full speed, following
    the filtered command exactly with the acceleration limit: its gap never goes below
    the margin, and with the filter off it would have touched."""
    lim = SafetyLimits(margin_m=0.05, brake_mps2=brake, max_speed_mps=speed)
    obstacle = Guarded(2.0, 0.0, 0.0, 0.0, 0.3)
    radius = 0.2
    p = np.array([0.0, -2.0 * math.sin(angle) * 0.1])
    v = np.array([speed, 0.0])
    nominal = (speed * math.cos(angle * 0.1), speed * math.sin(angle * 0.1))
    least = math.inf
    for _ in range(int(4.0 / H)):
        wanted = _rate_limited(nominal, v, brake)  # the agent limits before it filters
        r = safety_filter(wanted, tuple(v), float(p[0]), float(p[1]), radius, [obstacle], lim, H)
        dv = np.array(r.v) - v
        if math.isfinite(brake):
            assert np.linalg.norm(dv) <= brake * H + 1e-9  # within the acceleration limit
        v = np.array(r.v)
        p = p + H * v
        gap = math.hypot(p[0] - obstacle.x, p[1] - obstacle.y) - radius - obstacle.radius
        least = min(least, gap)
        assert not r.infeasible
    assert least >= 0.05 - 1e-9  # the margin holds
    assert least < 0.06  # and the filter let the robot come close (it does not over-brake)


def _rate_limited(nominal, v, brake):
    d = np.array(nominal) - v
    n = float(np.linalg.norm(d))
    if math.isfinite(brake) and n > brake * H:
        d *= brake * H / n
    return tuple((v + d).tolist())


def test_two_robots_head_on_both_filtered_never_touch():
    """Two robots at the speed limit on a collision course, each filtering against the
    other (the reciprocal barrier (S2)): they keep the margin. With (S1) alone, each
    counting on the other keeping its velocity, both sped up into the gap the other
    left in the same period and went 0.1 mm into the margin."""
    lim = SafetyLimits(margin_m=0.05, brake_mps2=8.0, max_speed_mps=1.5)
    p = [np.array([-2.0, 0.0]), np.array([2.0, 0.01])]
    v = [np.array([1.5, 0.0]), np.array([-1.5, 0.0])]
    nominal = [(1.5, 0.0), (-1.5, 0.0)]
    least = math.inf
    for _ in range(int(3.0 / H)):
        new = []
        for i in (0, 1):
            j = 1 - i
            other = Guarded(*p[j], *v[j], 0.2, reciprocal=True)
            r = safety_filter(_rate_limited(nominal[i], v[i], 8.0), tuple(v[i]), *p[i], 0.2,
                              [other], lim, H)
            new.append(np.array(r.v))
        v = new
        p = [p[i] + H * v[i] for i in (0, 1)]
        least = min(least, float(np.linalg.norm(p[0] - p[1])) - 0.4)
    assert least >= 0.05 - 1e-9


@settings(max_examples=300, deadline=None)
@given(gap=st.floats(0.0, 2.0), frac=st.floats(0.0, 1.0), brake=st.floats(0.5, 50.0),
       h=st.sampled_from([0.001, 0.005, 0.01]))
def test_the_barrier_is_recursively_feasible(gap, frac, brake, h):
    """From any closing speed the barrier admits, one period at it and then braking
    at the limit for one period leaves a state the barrier admits again."""
    c = frac * closing_speed_limit(gap, brake, h, 0.5)
    gap_next = gap - c * h
    c_next = max(c - brake * h, 0.0)
    assert gap_next >= -1e-12
    assert c_next <= closing_speed_limit(gap_next, brake, h, 0.5) + 1e-9


def test_an_impossible_demand_brakes_as_hard_as_allowed_and_says_so():
    lim = SafetyLimits(margin_m=0.05, brake_mps2=8.0, max_speed_mps=1.5)
    wall = Guarded(0.3, 0.0, 0.0, 0.0, 0.0)  # 0.1 m free, closing at 1.5 m/s: too late
    r = safety_filter((1.5, 0.0), (1.5, 0.0), 0.0, 0.0, 0.2, [wall], lim, H)
    assert r.active and r.infeasible
    assert r.v[0] == pytest.approx(1.5 - 8.0 * H)  # one period of full braking
