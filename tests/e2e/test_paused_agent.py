"""A paused agent recovers, and the run says what happened (issue 21, item 1).

Found by probing: ``lab --clock realtime`` with agent 2 SIGSTOPped for 2 s, then
SIGCONT: the agent answered its backlog of samples seconds old, its law went
non-finite for good and robot 2 ran on zero torque for the rest of the run, while
the run exited 0 with ``nonfinite_commands: 0``.

- unit: a non-finite integrator or observer is restarted from the measurement
  (AgentCore.recover), the step says what it restarted, the next step is finite;
- verdict: a robot on zero torque longer than the command timeout fails the run;
- end to end (realtime, judged by the clock): the fault plan pauses agent 2; its law
  restarts once, robot 2 is back in the settling band within 2 s of SIGCONT, and
  metrics.json counts the restart and the stretch on zero torque.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from deploy.contract.fault_plan import FaultPlanError, decode_plan
from deploy.contract.scenario import load_scenario
from deploy.report.timeseries import TimeSeries
from deploy.report.verdict import judge
from deploy.run.runner import make_agents
from tests.procs import finish, pids_with, start
from tests.realtime_clock import judged

NAN3 = (math.nan, math.nan, math.nan)


@pytest.fixture(scope="module")
def lab():
    return load_scenario("lab")


def _step(agent, sc, i, t=0.0, dt=None):
    q, qd = sc.initial_state()
    leader = (np.array([0.0, 0.0, 0.0]), np.array([0.5, 0.0, 0.0]))
    shares = {j: agent.initial_share for j, _ in agent.cfg.neighbours}
    return agent.step(t, q[i], qd[i], shares, leader, dt=dt)


@pytest.mark.parametrize("field, value, restarted", [
    ("z2_hat", NAN3, ("observer",)),
    ("q_d", (math.inf, 0.0, 0.0), ("reference",)),
    ("q0_hat", NAN3, ("estimator",)),
])
def test_a_non_finite_state_is_restarted_from_the_measurement(lab, field, value, restarted):
    agent = make_agents(lab)[0]
    assert _step(agent, lab, 0).reset == ()  # a healthy step restarts nothing
    agent.law.restore(field, value)  # the compiled law's state (agents/law_kernel.pyx)
    out = _step(agent, lab, 0, lab.dt)
    assert set(restarted) <= set(out.reset)
    assert np.isfinite(out.torques).all()  # zero torques when the law diverged, never NaN
    nxt = _step(agent, lab, 0, 2 * lab.dt)
    assert nxt.reset == () and not nxt.nonfinite and np.isfinite(nxt.torques).all()
    assert all(map(math.isfinite, agent.law.state()[field]))
    if field == "q_d":  # the reference restarts at the robot: no tracking error
        q, _ = lab.initial_state()
        assert np.allclose(nxt.q_d, q[0], atol=0.05)
    if field == "q0_hat":  # robot 1 hears the leader: the estimate restarts from it
        assert abs(agent.law.state()["q0_hat"][0]) < 0.1


def test_a_diverged_step_restarts_the_dynamic_level():
    """A finite state but a non-finite command (the step itself overflowed: a
    vanishing step h puts (v_d - v_ref) / h at inf; paper has no acceleration or
    torque limit to hide it): this step's torques are zero and counted, the
    reference and observer restart, the next step is finite."""
    paper = load_scenario("paper")
    agent = make_agents(paper)[0]
    _step(agent, paper, 0)
    agent.law.restore("v_d_prev", (1.0, 0.0, 0.0))
    out = _step(agent, paper, 0, paper.dt, dt=1e-320)
    assert out.nonfinite and not out.torques.any()
    assert {"reference", "observer"} <= set(out.reset)
    nxt = _step(agent, paper, 0, 2 * paper.dt)
    assert not nxt.nonfinite and nxt.reset == ()


def _metrics(**extra):
    m = {"settling_bound_s": 5.657, "settling_time_s": [0.3, 0.3], "plant": "pybullet",
         "min_obstacle_gap_m": 0.3, "min_robot_gap_m": 0.2, "contacts": 0,
         "nonfinite_commands": 0, "command_timeout_s": 0.1,
         "zero_torque_longest_s": [0.0, 0.0]}
    return m | extra


def test_the_verdict_fails_a_robot_left_on_zero_torque_past_the_timeout():
    assert judge(_metrics())["pass"]
    assert judge(_metrics(zero_torque_longest_s=[0.0, 0.1]))["pass"]  # exactly the timeout
    v = judge(_metrics(zero_torque_longest_s=[0.0, 1.925]))
    assert not v["pass"] and not v["powered"]
    assert v["reasons"] == ["robot #2 ran on zero torque for 1.925 s (> command timeout 0.100 s)"]


def test_a_pause_and_a_restart_together_are_refused(lab):
    plan = "[[kill]]\nprocess = 'agent-2'\nat_s = 1.0\npause_s = 2.0\n"
    assert decode_plan(plan, lab).kills[0].pause_s == 2.0
    with pytest.raises(FaultPlanError, match="kill\\[0\\].pause_s"):
        decode_plan(plan + "restart_after_s = 1.0\n", lab)
    with pytest.raises(FaultPlanError, match="kill\\[0\\].pause_s"):
        decode_plan(plan.replace("2.0", "-1.0"), lab)


PAUSE_AT, PAUSE_S, DURATION_S = 2.0, 2.0, 6.5


@pytest.fixture(scope="module")
def paused_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("pause")
    plan = d / "pause.toml"
    plan.write_text(f"seed = 1\n[[kill]]\nprocess = 'agent-2'\nat_s = {PAUSE_AT}\n"
                    f"pause_s = {PAUSE_S}\n")

    def run():
        out = tmp_path_factory.mktemp("pause") / "run"
        fleet = f"t-pause-{os.getpid()}"
        code, stdout, err = finish(start(
            "run", "lab", "--clock", "realtime", "--duration", repr(DURATION_S), "--fleet", fleet,
            "--out", str(out), "--no-figures", "--no-record", "--faults", str(plan)),
            timeout=240)
        assert not (pids_with(fleet) | pids_with(str(out))), "processes of the run still alive"
        assert code == 0, err[-3000:]
        return out, stdout, json.loads((out / "metrics.json").read_text())
    return judged(run, lambda r: r[2], "lab realtime, agent 2 paused")


def test_the_paused_agents_robot_is_back_in_the_band_within_2_s(paused_run):
    out, stdout, m = paused_run
    events = {e["event"]: e["t_s"] for e in m["faults"]["kills"]}
    assert set(events) == {"paused", "resumed"}
    resumed = events["resumed"]
    ts = TimeSeries.load(out / "timeseries.npz")
    err = np.linalg.norm(ts.e[:, 1], axis=1)  # robot 2's tracking error
    band = m["settle_threshold"]
    late = np.flatnonzero((ts.t > resumed) & (err > band))
    back = ts.t[late[-1] + 1] if len(late) else resumed
    print(f"\nrobot 2 back within {band} m at t = {back:.2f} s, {back - resumed:.2f} s after SIGCONT; "
          f"law restarts {m['law_resets']}, stale samples {m['stale_samples']}, zero torque "
          f"{m['zero_torque_longest_s']} s")
    assert back - resumed < 2.0
    assert back < ts.t[-1] - 0.25  # and it stays there
    assert m["nonfinite_commands"] == 0  # the law never diverged


def test_the_run_counts_what_the_pause_did(paused_run):
    _, stdout, m = paused_run
    assert m["law_resets"][0] == 0 and m["law_resets"][2] == 0
    assert m["law_resets"][1] >= 1  # at least the restart after the gap
    zero = m["zero_torque_longest_s"]
    # zeroed one command timeout after its last command, powered again as it answers
    assert PAUSE_S - 0.5 < zero[1] < PAUSE_S + 0.5 and zero[0] == zero[2] == 0.0
    assert any(s["robot"] == 2 for s in m["zero_torque"])
    v = m["verdict"]
    assert not v["pass"] and not v["powered"]
    assert any("robot #2 ran on zero torque" in r for r in v["reasons"])
    assert "law restarts               [0, " in stdout and "longest on zero torque" in stdout
