"""An agent's law restarts from the measurement when its state goes non-finite or a step
overflows, a robot left on zero torque past the command timeout fails the verdict, and a
fault plan cannot both pause and restart a process (the end-to-end pause: tests/e2e/test_paused_agent.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from deploy.contract.fault_plan import FaultPlanError, decode_plan
from deploy.contract.scenario import load_scenario
from deploy.report.verdict import judge
from deploy.run.runner import make_agents

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
    assert out.nonfinite and not any(out.torques)
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
