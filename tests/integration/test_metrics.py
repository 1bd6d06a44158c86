"""metrics.json says what its numbers are: formation RMS over the whole run and after
settling, both named; the smallest distances are gaps between surfaces."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from deploy.contract.scenario import load_scenario
from deploy.report.metrics import compute_metrics, formation_rms
from tests.conftest import cached_run


def test_formation_rms_whole_run_and_after_settling():
    """Robot A is 2 m off for the first half and on target after; B is 1 m off all
    along and never settles; C is on target all along."""
    t = np.arange(10) * 0.1
    target = np.zeros((10, 3, 2))
    xy = np.zeros((10, 3, 2))
    xy[:5, 0, 0] = 2.0
    xy[:, 1, 1] = 1.0
    whole, after = formation_rms(t, xy, target, [0.5, None, 0.0])
    assert whole == pytest.approx([math.sqrt(0.5 * 4.0), 1.0, 0.0])
    assert after == [0.0, None, 0.0]  # a robot that never settled has no after-settling RMS


def test_a_realtime_row_without_a_state_is_left_out():
    t = np.arange(4) * 0.1
    xy = np.ones((4, 1, 2))
    xy[0] = np.nan  # before the robot's first sample
    whole, after = formation_rms(t, xy, np.zeros((4, 1, 2)), [None])
    assert whole == pytest.approx([math.sqrt(2.0)]) and after == [None]


def test_paper_metrics_name_both_rms_and_the_gaps_are_surface_to_surface():
    sc = load_scenario("paper")
    run = cached_run("paper", 7.0)
    m = compute_metrics(sc, run.series, "model", "lockstep", run.wall_time_s)
    assert "formation_rms_m" not in m and "min_robot_separation_m" not in m
    for whole, after in zip(m["formation_rms_whole_run_m"], m["formation_rms_after_settling_m"],
                            strict=True):
        assert after is not None and after <= whole  # the transient is in the whole run only
    q = run.series.q[:, :, :2]
    r = sc.spec.robot.body_radius_m
    centres = min(np.linalg.norm(q[:, i] - q[:, j], axis=1).min()
                  for i in range(sc.n) for j in range(i + 1, sc.n))
    assert m["min_robot_gap_m"] == pytest.approx(centres - 2 * r)  # Fig. 6 plots centres
    obstacles = np.array([o.position for o in sc.spec.obstacles])
    to_obstacles = np.linalg.norm(q[:, :, None] - obstacles[None, None], axis=3).min()
    assert m["min_obstacle_gap_m"] == pytest.approx(to_obstacles - r)  # point obstacles


def test_a_state_never_heard_is_no_gap_and_is_counted():
    """A realtime series whose robot 3 was first heard at step 20 (its first rows NaN, as a
    late bridge leaves them) and missed step 60 (filled forward): the gaps are taken over
    the states heard, never NaN, and the rows are counted per robot. The CAN fleet at
    200 Hz on a slow host said "a gap between surfaces reached 0" for such a run."""
    sc = load_scenario("lab")
    run = cached_run("lab", 0.5)
    series = copy.deepcopy(run.series)  # the cached run is shared with other tests
    heard = np.ones((series.steps, sc.n), dtype=bool)
    heard[:20, 2] = False
    heard[60, 2] = False
    series.q[:20, 2] = np.nan
    series.q[60, 2] = series.q[59, 2]
    series.state_heard = heard
    m = compute_metrics(sc, series, "model", "realtime", run.wall_time_s)
    assert m["series_rows_missing"] == [0, 0, 21]
    assert math.isfinite(m["min_robot_gap_m"]) and m["min_robot_gap_m"] > 0
    assert math.isfinite(m["min_obstacle_gap_m"]) and m["min_obstacle_gap_m"] > 0
    assert m["contacts"] == 0
    from deploy.report.verdict import judge, verdict_line

    m.update(clock="realtime", command_timeout_s=0.05, steps_asked=series.steps)
    line = verdict_line(judge(m))
    assert "gap between surfaces" not in line
    assert "states never heard: robot #3 21 step(s)" in line  # beyond 0.05 s at 200 Hz
