"""The rehearsal of the paper's law before a realtime run (agents/rehearsal.py) steps a
core of its own: the agent's law gives what it gives without it, bit for bit."""

import math

import pytest

from agents.plugged import make_core
from agents.rehearsal import REHEARSAL_LEAD_S, REHEARSAL_STEPS, rehearsal_wait, rehearse


def _agent(sc, i):
    q, qd = sc.initial_state()
    q0h, v0h = sc.initial_estimates(i)
    return sc.agent_config(i), q[i], qd[i], q0h, v0h


def _run(sc, i, steps, rehearsed):
    cfg, q, qd, q0h, v0h = _agent(sc, i)
    core = make_core(cfg, None, None, q, qd, q0h, v0h)  # built before, as the agent's is
    shares = {j: core.initial_share for j, _ in cfg.neighbours}
    lead = (core.q0_hat_vec, core.v0_hat_vec)
    if rehearsed:
        assert rehearse(cfg, q, qd, q0h, v0h, shares, lead, sc.obstacle_bodies(),
                        sc.spec.degradation.command_horizon) == REHEARSAL_STEPS
    torques = []
    for n in range(steps):
        out = core.step(n * cfg.dt, q, qd, shares, lead, sc.obstacle_bodies(), ())
        torques.append(out.torques)
    return torques


def test_the_agents_own_law_is_untouched_by_a_rehearsal(paper):
    for i in range(paper.n):
        plain = _run(paper, i, 5, rehearsed=False)
        assert _run(paper, i, 5, rehearsed=True) == plain  # bit for bit
        assert all(math.isfinite(x) and abs(x) > 1.0 for x in plain[0])  # the paper's start


def test_a_rehearsal_of_an_agent_that_does_not_hear_the_leader_without_look_ahead(paper):
    i = paper.n - 1
    cfg, q, qd, q0h, v0h = _agent(paper, i)
    assert cfg.leader_weight == 0.0
    core = make_core(cfg, None, None, q, qd, q0h, v0h)
    shares = {j: core.initial_share for j, _ in cfg.neighbours}
    assert rehearse(cfg, q, qd, q0h, v0h, shares, None, (), 0) == REHEARSAL_STEPS


def test_the_rehearsal_waits_for_its_lead_and_is_left_out_when_the_start_is_near():
    t0 = 100.0
    assert rehearsal_wait(t0, t0 - 0.3) == pytest.approx(0.3 - REHEARSAL_LEAD_S)
    assert rehearsal_wait(t0, t0 - REHEARSAL_LEAD_S) == 0.0  # at once
    assert rehearsal_wait(t0, t0 - 0.6 * REHEARSAL_LEAD_S) == 0.0
    assert rehearsal_wait(t0, t0 - 0.4 * REHEARSAL_LEAD_S) is None  # too near t = 0
    assert rehearsal_wait(t0, t0 + 1.0) is None  # the start heard late
