"""The verdict fails what did not go whole or on time, naming why (deploy/report/verdict.py):
a run that simulated less than it was asked or was heard for less than it simulated, a
node whose report never came, a realtime stall of the plant longer than the command
timeout, deadline misses beyond a stated share of the steps."""

from __future__ import annotations

import pytest
from healthy_metrics import healthy_realtime

from deploy.report.summary import summary
from deploy.report.verdict import MAX_MISS_SHARE, judge, verdict_line


def test_a_healthy_realtime_run_passes_with_a_late_last_wake():
    v = judge(healthy_realtime())
    assert v["pass"] and v["whole"] and v["on_time"], v["reasons"]
    assert "on time" in verdict_line(v)


def test_the_stalled_run_of_the_report_fails_naming_each_reason():
    """``lab --plant model --clock realtime --control-rate 500 --duration 20`` that stalled:
    2,450 steps simulated of 10,000, 15 s without a wake, more misses than steps. It said
    PASS."""
    v = judge(healthy_realtime(steps_simulated=2450, steps=2450,
                        longest_stall={"node": "plant", "duration_s": 15.2, "t_s": 4.9},
                        deadline_misses_by_node={"agent-1": 5000, "agent-2": 5000,
                                                 "agent-3": 5000, "leader": 3, "plant": 7600}))
    assert not v["pass"] and not v["whole"] and not v["on_time"]
    line = verdict_line(v)
    assert "simulated 4.900 s of the 20.000 s asked (2450 of 10000 steps)" in line
    assert "the plant stalled 15.200 s from t = 4.900 s (> command timeout 0.100 s)" in line
    assert "deadline misses beyond 5% of the 10000 steps: agent-1 5000 (50%)" in line
    assert "leader" not in line.split("deadline misses")[1]  # 3 misses: within the share


def test_a_run_heard_for_less_than_it_simulated_fails():
    v = judge(healthy_realtime(steps=8000))
    assert not v["pass"] and "heard for 16.000 s of the 19.998 s simulated" in verdict_line(v)


def test_a_restart_that_never_rejoined_fails_and_is_not_a_missing_report():
    v = judge(healthy_realtime(restarts_not_rejoined=["agent-2"]))
    assert not v["pass"] and "agent-2 restarted by the fault plan but still starting" in \
        verdict_line(v)


def test_a_missing_report_fails_naming_the_node():
    v = judge(healthy_realtime(reports_missing=["agent-2"]))
    assert not v["pass"] and "no report from agent-2" in verdict_line(v)


@pytest.mark.parametrize("misses, passes", [(int(MAX_MISS_SHARE * 10000), True),
                                            (int(MAX_MISS_SHARE * 10000) + 1, False)])
def test_the_miss_share_is_the_stated_one(misses, passes):
    assert judge(healthy_realtime(deadline_misses_by_node={"plant": misses}))["pass"] is passes


def test_a_stall_of_exactly_the_timeout_passes_and_longer_fails():
    assert judge(healthy_realtime(longest_stall={"node": "plant", "duration_s": 0.1, "t_s": 1.0}))["pass"]
    assert not judge(healthy_realtime(longest_stall={"node": "bridge-2", "duration_s": 0.11,
                                              "t_s": 1.0}))["pass"]


def test_lockstep_allows_no_step_short():
    m = healthy_realtime(clock="lockstep", steps_simulated=9999, steps=9999, longest_stall=None,
                  deadline_misses_by_node=None)
    v = judge(m)
    assert not v["pass"] and "(9999 of 10000 steps)" in verdict_line(v)
    assert judge(m | {"steps_simulated": 10000, "steps": 10000})["pass"]


def test_the_summary_says_what_was_simulated_of_what_was_asked(tmp_path):
    m = healthy_realtime(steps_simulated=2450, steps=2449, sim_time_s=4.898, wall_time_s=20.31,
                  real_time_factor=0.24, formation_rms_whole_run_m=[1.0, 1.0, 1.0],
                  formation_rms_after_settling_m=[0.1, 0.1, 0.1], peak_torque_nm=2.0,
                  rms_torque_nm=0.4, law_resets=[0, 0, 0])
    m["verdict"] = judge(m)
    first = summary(m, tmp_path).splitlines()[0]
    assert "4.90 s of the 20.00 s asked simulated (4.90 s of it heard) in 20.31 s" in first
