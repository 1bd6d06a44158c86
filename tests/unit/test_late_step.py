"""A realtime agent's first step after a stall (agents/law_kernel_sections/law.pxi,
``_to_sample_time``): the leader estimate (14) and the reference (11) are carried to the
sample's time before the step, so its command is of now and the next step's feed-forward
q_d_ddot = (v_d(k) - v_d(k-1)) / h has nothing to undo."""

import copy

import numpy as np

from agents.core import AgentCore
from agents.leader import LeaderGenerator
from deploy.contract.scenario import load_scenario

STALL_STEPS = 20  # 20 ms at paper's 1 kHz: the stalls of an agent on a loaded core


def _follow(core, lead, x, v, k0, n, dt):
    """``n`` lockstep steps of robot 1 of ``paper`` on a kinematic robot (q_dot = v_cmd)."""
    peak = 0.0
    out = None
    for k in range(k0, k0 + n):
        out = core.step(k * dt, x, v, {}, lead.state())
        v = np.array(out.v_cmd)
        x = x + v * dt
        lead.advance()
        peak = max(peak, float(np.abs(out.torques).max()))
    return x, v, out, peak


def test_the_step_after_a_stall_commands_what_lockstep_would_and_no_spike_follows():
    """Robot 1 of ``paper`` (it hears the leader only) 3 s in, following the leader at
    ~28 m/s: lockstep takes the next 20 steps, the late agent one step 20 ms later (its
    robot moved on at its last command meanwhile). The late step's command is within 1.5
    m/s of lockstep's at that time (computed from the estimate and the reference of 19 ms
    before: 6.2 m/s off, FDB's gain times the leader's way), and the step after it, one
    period later, stays within twice the steady torques (before: 47x)."""
    sc = load_scenario("paper")
    cfg = sc.agent_config(0)
    assert cfg.neighbours == () and cfg.leader_weight != 0.0
    dt = cfg.dt
    q, qd = sc.initial_state()
    q0, v0 = sc.initial_estimates(0)
    core = AgentCore(cfg, q[0], qd[0], q0, v0)
    lead = LeaderGenerator(sc.leader_spec(), dt)
    x, v, _, _ = _follow(core, lead, np.array(q[0], float), np.zeros(3), 0, 2900, dt)
    x, v, _, steady = _follow(core, lead, x, v, 2900, 100, dt)
    k = 3000

    lockstep = core.fork()
    _, _, at_stall_end, _ = _follow(lockstep, copy.deepcopy(lead), x.copy(), v.copy(), k,
                                    STALL_STEPS, dt)

    late, late_lead = core.fork(), copy.deepcopy(lead)
    for _ in range(STALL_STEPS - 1):
        late_lead.advance()
    x_late = x + v * (STALL_STEPS - 1) * dt
    t_late = (k + STALL_STEPS - 1) * dt
    first = late.step(t_late, x_late, v, {}, late_lead.state(), dt=STALL_STEPS * dt)
    off = np.hypot(*np.subtract(first.v_cmd, at_stall_end.v_cmd)[:2])
    assert off < 1.5, f"the late step commanded {off:.2f} m/s away from lockstep"

    late_lead.advance()
    v_late = np.array(first.v_cmd)
    after = late.step(t_late + dt, x_late + v_late * dt, v_late, {}, late_lead.state(), dt=dt)
    assert np.abs(first.torques).max() < 2.0 * steady
    assert np.abs(after.torques).max() < 2.0 * steady, (
        f"{np.abs(after.torques).max():.0f} N m after the late step, {steady:.0f} steady")
