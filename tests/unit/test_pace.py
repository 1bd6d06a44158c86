"""The realtime loop's pace (agents/pace.py) and what the law makes of a late loop: the
horizon the safety filter plans over, and the speed of a loop that cannot keep its period."""

from dataclasses import replace

import numpy as np
import pytest

from agents.core import AgentCore
from agents.pace import MAX_HORIZON_S, LoopPace
from deploy.contract.scenario import load_scenario
from plant.bodies import Body


def test_a_loop_that_keeps_its_period_changes_nothing():
    pace = LoopPace(0.005)
    for _ in range(100):
        pace.note(0.005)
    assert pace.horizon() == 0.005 and pace.speed_cap() == 1.0


def test_a_late_wake_lengthens_the_horizon_but_does_not_slow_the_robot():
    pace = LoopPace(0.001, window=10)
    for interval in (0.001, 0.004, 0.001):
        pace.note(interval)
    assert pace.horizon(0.002) == pytest.approx(0.006)  # the longest interval + the age
    assert pace.speed_cap() == 1.0  # one hiccup: the loop still keeps its period
    for _ in range(10):  # the spike leaves the window
        pace.note(0.001)
    assert pace.horizon() == 0.001 and pace.speed_cap() == 1.0
    pace.note(10.0)  # a stall: the horizon stays bounded (the sample is stale anyway)
    assert pace.horizon(1.0) == MAX_HORIZON_S


def test_a_loop_that_cannot_keep_its_period_slows_its_robot():
    pace = LoopPace(0.001, window=10, swing_s=0.0)  # the scale follows its target at once
    for interval in (0.004, 0.001, 0.004, 0.004, 0.001) * 2:  # median 4 periods
        pace.note(interval)
    assert pace.speed_cap() == pytest.approx(1.5 / 4.0)  # 1.5 periods allowed, 4 taken
    assert pace.horizon() == pytest.approx(0.004)
    for _ in range(6):  # back on its period: the median returns to it
        pace.note(0.001)
    assert pace.speed_cap() == 1.0


def test_the_start_of_a_run_is_not_an_overload():
    """A run's first steps are slow in every node (`paper` at 1 kHz on one core: 3-5 ms
    apart): until the window is full the loop's pace is not known and nothing is slowed;
    the horizon covers those intervals from the first."""
    pace = LoopPace(0.001, window=50, swing_s=0.0)
    for interval in (0.003, 0.005, 0.004, 0.003):
        pace.note(interval)
        assert pace.speed_cap() == 1.0
    assert pace.horizon() == pytest.approx(0.005)
    for _ in range(46):  # still that slow when the window is full: an overload
        pace.note(0.004)
    assert pace.speed_cap() == pytest.approx(1.5 / 4.0)


def test_the_scale_moves_by_a_period_share_of_its_swing_at_a_step():
    """The law's feed-forward differentiates the command (q_d_ddot = (v_d(k) - v_d(k-1))
    / h): the scale moves toward its target by at most period / swing_s a step, down and
    back up, and settles on it exactly."""
    period, swing = 0.001, 0.02  # a step moves it by at most 0.05
    pace = LoopPace(period, window=10, swing_s=swing)
    caps = []
    for _ in range(10):
        pace.note(0.004)  # target 1.5 / 4 once the window is full
        caps.append(pace.speed_cap())
    for _ in range(30):
        pace.note(0.004)
        caps.append(pace.speed_cap())
    assert caps[-1] == pytest.approx(1.5 / 4.0)
    assert pace.target_cap() == pytest.approx(1.5 / 4.0)
    for _ in range(40):  # back on its period
        pace.note(0.001)
        caps.append(pace.speed_cap())
    assert caps[-1] == 1.0
    moves = np.abs(np.diff([1.0, *caps]))
    assert moves.max() <= period / swing + 1e-12
    assert min(caps) == pytest.approx(1.5 / 4.0)  # it got there, and no lower


def test_bad_settings_are_refused():
    with pytest.raises(ValueError):
        LoopPace(0.0)
    with pytest.raises(ValueError):
        LoopPace(0.01, slow_above=0.5)
    with pytest.raises(ValueError):
        LoopPace(0.01, swing_s=float("nan"))


def _lab_agent(**over):
    sc = load_scenario("lab")
    q, qd = sc.initial_state()
    q0, v0 = sc.initial_estimates(0)
    core = AgentCore(replace(sc.agent_config(0, sc.model()), **over), q[0], qd[0], q0, v0)
    return sc, core, np.array(q[0]), (np.array(q0), np.array(v0))


def _closing_limit(gap, brake, h):
    """c_max of (S1) (agents/safety_filter.py)."""
    return -brake * h + np.sqrt((brake * h) ** 2 + 2.0 * brake * gap)


def test_a_longer_horizon_holds_the_robot_back_where_one_period_would_not():
    """A body straight along the nominal command, at the gap where closing at the command's
    speed is allowed for one more 5 ms period but not for 100 ms: over the period the
    command is left as it is; over the longer horizon (avoidance engaging earlier, and the
    filter's barrier) it closes no faster than (S1) allows over 100 ms. Avoidance off:
    the filter alone guards the body."""
    sc, core, q, lead = _lab_agent(enabled=frozenset({"FDB"}))
    cfg = core.cfg
    qd = np.zeros(3)
    v = np.array(core.fork().step(0.0, q, qd, {}, lead).v_cmd)
    speed = float(np.hypot(*v[:2]))
    assert speed > 0.05
    brake = cfg.max_accel_mps2
    # the gap at which c_max(gap, h = 0.05) equals the speed: allowed at 5 ms, not at 100 ms
    h_mid = 0.05
    gap = (speed + brake * h_mid) ** 2 / (2 * brake) - (brake * h_mid) ** 2 / (2 * brake)
    assert _closing_limit(gap, brake, cfg.dt) > speed > _closing_limit(gap, brake, 0.1)
    radius = 0.2
    centre = q[:2] + (gap + cfg.robot_radius_m + radius + cfg.safety_margin_m) * v[:2] / speed
    body = [Body(-1, centre, np.zeros(2), radius)]
    period = core.fork().step(0.0, q, qd, {}, lead, body, [])
    late = core.fork().step(0.0, q, qd, {}, lead, body, [], horizon=0.1)
    toward = v[:2] / speed
    assert np.dot(period.v_cmd[:2], toward) == pytest.approx(speed)  # left as it is
    assert np.dot(late.v_cmd[:2], toward) < _closing_limit(gap, brake, 0.1) + 1e-9


def test_a_speed_cap_scales_the_planar_command():
    sc, core, q, lead = _lab_agent()
    free = core.fork().step(0.0, q, np.zeros(3), {}, lead).v_cmd
    capped = core.fork().step(0.0, q, np.zeros(3), {}, lead, speed_cap=0.5).v_cmd
    assert np.hypot(*capped[:2]) < np.hypot(*free[:2])


from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@given(st.lists(st.floats(0.0, 0.02), max_size=200), st.integers(1, 30))
def test_the_running_counts_answer_as_the_whole_window_does(intervals, window):
    """The speed cap's target and the horizon kept as the window moves equal those of
    the window sorted and searched whole, at every step (the target 1 until it is full)."""
    pace = LoopPace(0.001, window=window)
    for i, x in enumerate(intervals):
        pace.note(x)
        seen = intervals[max(0, i + 1 - window):i + 1]
        median = sorted(seen)[len(seen) // 2]
        ratio = median / 0.001
        full = len(seen) == window
        assert pace.target_cap() == (1.5 / ratio if full and ratio > 1.5 else 1.0)
        assert pace.longest_s == max(seen)
