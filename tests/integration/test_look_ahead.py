"""Command look-ahead (agents/look_ahead.py, plant/command.py): what it predicts,
what the plant plays, and the paper-scenario failure it removes."""

from __future__ import annotations

import numpy as np
import pytest

from agents.leader import LeaderGenerator
from agents.look_ahead import LookAhead
from deploy.contract.fault_plan import uniform_drop_plan
from deploy.contract.scenario import ScenarioError, load_scenario, parse_scenario, resolve_path
from deploy.run.runner import make_agents, run_in_process
from deploy.runtime.plants import make_plant, sensor_for
from plant.command import command_for_step

pytestmark = [pytest.mark.slow]

PAPER = resolve_path("paper").read_text()


def paper_variant(*replacements: tuple[str, str], extra: str = "") -> str:
    text = PAPER
    for old, new in replacements:
        assert old in text, old
        text = text.replace(old, new)
    return text + extra


def test_command_for_step_plays_the_plan_then_gives_up() -> None:
    own, plan = (1.0, 2.0, 3.0, 4.0), [(5.0, 6.0, 7.0, 8.0), (9.0, 9.0, 9.0, 9.0)]
    assert command_for_step(10, own, plan, 10) == own
    assert command_for_step(10, own, plan, 9) == own  # never an entry for the past
    assert command_for_step(10, own, plan, 11) == plan[0]
    assert command_for_step(10, own, plan, 12) == plan[1]
    assert command_for_step(10, own, plan, 13) is None
    assert command_for_step(10, own, [], 11) is None


def test_first_predicted_torque_is_the_next_step_exactly_on_a_perfect_model() -> None:
    """With the plant the agent's model (eq. 4, no disturbance), the torque it
    predicts for k+1 is the torque it computes at k+1 (to rounding): the next
    step's reference, estimate and observer follow from step k alone. Checked
    over the paper's first 0.5 s, through its largest torques and behavior switches."""
    sc = parse_scenario(paper_variant(
        ('kind = "paper"              # d_i(t)', 'kind = "none"  #'),
        ('kind = "pybullet"', 'kind = "model"')))
    plant, agents = make_plant(sc, "model"), make_agents(sc)
    sense, leader = sensor_for(plant, sc), LeaderGenerator(sc.leader_spec(), sc.dt)
    look = [LookAhead(a, 1) for a in agents]
    shares = {rid: a.initial_share for rid, a in zip(sc.robot_ids, agents, strict=True)}
    predicted: list[np.ndarray | None] = [None] * sc.n
    rel_errors, peak = [], 0.0
    for k in range(500):
        t, torques, new_shares = k * sc.dt, np.zeros((sc.n, 4)), {}
        lead = leader.state()
        seen = sense()
        for i, a in enumerate(agents):
            robots, obstacles = seen[i]
            shs = {j: shares[j] for j, _ in a.cfg.neighbours}
            q, qd = plant.q[i].copy(), plant.q_dot[i].copy()
            ld = lead if sc.leader_weights[i] else None
            out = a.step(t, q, qd, shs, ld, obstacles, robots)
            if predicted[i] is not None:
                scale = max(float(np.abs(out.torques).max()), 1.0)
                rel_errors.append(float(np.abs(predicted[i] - out.torques).max()) / scale)
            plan = look[i].plan(a, out, t, q, qd, shs, ld, obstacles, robots)
            assert len(plan) == 1
            predicted[i] = np.array(plan[0])
            torques[i], new_shares[sc.robot_ids[i]] = out.torques, out.share
            peak = max(peak, float(np.abs(out.torques).max()))
        shares = new_shares
        plant.step(t, sc.dt, torques, np.zeros((sc.n, 3)))
        leader.advance()
    assert peak > 1e5  # the transient with its jumps was in the window
    assert np.median(rel_errors) < 1e-9
    assert max(rel_errors) < 1e-5


def test_plan_does_not_touch_the_agent() -> None:
    sc = load_scenario("lab")
    (a, *_), plant = make_agents(sc), make_plant(sc, "model")
    q, qd = plant.q[0].copy(), plant.q_dot[0].copy()
    lead = LeaderGenerator(sc.leader_spec(), sc.dt).state()
    assert not a.cfg.neighbours  # robot 1 of lab hears only the leader
    out = a.step(0.0, q, qd, {}, lead)
    before = dict(vars(a))
    plan = LookAhead(a, 3).plan(a, out, 0.0, q, qd, {}, lead)
    assert len(plan) == 3 and all(np.isfinite(plan).ravel())
    assert vars(a) == before


def paper_head(horizon: int | None, seed: int, drop: float, duration_s: float):
    extra = "" if horizon is None else f"\n[degradation]\ncommand_horizon = {horizon}\n"
    sc = parse_scenario(PAPER + extra)
    r = run_in_process(sc, duration_s=duration_s, faults=uniform_drop_plan(sc, drop, seed))
    speed = np.linalg.norm(r.series.q_dot[:, :, :2], axis=2)
    return float(speed.max()), len(r.contacts or [])


def test_look_ahead_keeps_the_paper_law_stable_under_30_percent_loss() -> None:
    """Seed 5 of the 30 % sweep: commands lost at a behavior switch (robot 3,
    t = 13-14 ms) leave it at 600 m/s into the obstacle's band, and the law
    throws it off (beyond 1e5 m/s within 25 ms; ~4e4 m/s since no torque beyond
    the plausibility bound of 1e7 N m is applied). With the default look-ahead
    the fault-free run's top speed (670 m/s) is not exceeded by more than 2x."""
    fault_free, _ = paper_head(None, 5, 0.0, 0.1)
    without, _ = paper_head(0, 5, 0.3, 0.1)
    with_plan, contacts = paper_head(None, 5, 0.3, 0.1)
    assert 600.0 < fault_free < 700.0
    assert without > 30 * fault_free  # the failure is real
    assert with_plan < 2.0 * fault_free
    assert contacts == 0


@pytest.mark.parametrize("value", ["-1", "17", "2.5"])
def test_bad_horizon_is_a_clear_error(value: str) -> None:
    with pytest.raises(ScenarioError, match="command_horizon"):
        parse_scenario(PAPER + f"\n[degradation]\ncommand_horizon = {value}\n")


@pytest.mark.parametrize("clock", ["lockstep", "realtime"])
def test_plant_node_plays_the_newest_plan_for_missing_steps(clock: str) -> None:
    """Only the command of step 5 arrives: the plant applies it at step 5, its
    look-ahead at steps 6 and 7, then holds (lab: missed_command = "hold"); the samples
    after steps 6-8 tell the agent its own torques did not act (Sample.own_torques)."""
    import time

    from fuzz_fakes import FakeNode

    from deploy.contract.wire import WIRE_VERSION, Reply, Share, encode
    from deploy.nodes.plant import PlantNode
    from deploy.runtime.node_runtime import StopFlag

    sc = load_scenario("lab")
    p = PlantNode(sc, "model", FakeNode(sc.robot_ids, "plant"), StopFlag())
    own, plan = (0.1, 0.2, 0.3, 0.4), [(1.0, 1.0, -1.0, -1.0), (0.5, 0.0, 0.0, 9.0)]
    p.published_k = 5  # the sample of step 5 went out
    zero = (0.0, 0.0, 0.0)
    p.node.deliver(p.node.keys.cmd(1), encode(Reply(
        WIRE_VERSION, 1, 0, 0, robot=1, k=5, t=0.025, torques=own, v_cmd=zero,
        state_seq=0, state_stamp_ns=0, share=Share(zero, zero, zero, zero, zero, zero),
        plan=plan)))
    applied, own_flags = [], []
    for k in range(5, 9):
        p.own_torques = [True] * sc.n  # as each sample's publication leaves them
        if clock == "lockstep":
            p._take_lockstep_commands(k)
        else:
            p._apply_newest_commands(time.monotonic())
            p._play_plans(k)
        applied.append(tuple(p.torques[0]))
        own_flags.append(list(p.own_torques))
    limit = sc.spec.limits.max_wheel_torque_nm  # 2 N m: the last entry is clamped
    assert applied == [own, plan[0], (0.5, 0.0, 0.0, limit), (0.5, 0.0, 0.0, limit)]
    assert [f[0] for f in own_flags] == [True, False, False, False]
    assert not any(f[i] for f in own_flags for i in range(1, sc.n))  # never commanded


@pytest.mark.parametrize("horizon", [0, 2])
def test_a_command_delay_longer_than_the_plan_still_drives_the_robots(horizon: int) -> None:
    """agent -> plant delayed by 10 periods (50 ms), more than the look-ahead: the
    plant applies each command as it arrives (held past its plan), so the lab fleet
    still reaches its formation; stuck on the first command it would not."""
    from deploy.contract.fault_plan import decode_plan

    sc = parse_scenario(resolve_path("lab").read_text()
                        + f"\n[degradation]\ncommand_horizon = {horizon}\n")
    plan = decode_plan("[[link]]\nfrom = 'agent-*'\nto = 'plant'\ndelay_s = 0.05\n", sc)
    r = run_in_process(sc, "model", 8.0, faults=plan)
    err = np.linalg.norm(r.series.q[:, :, :2] - r.series.target, axis=2)
    assert err[-1].max() < 0.3, err[-1]


def test_a_bridge_says_whether_the_robot_moved_on_its_agents_command() -> None:
    """The CAN bridge's sample after a period: own torques when the command answering its
    previous sample came and drove the drives; not when none came (the look-ahead or held
    torques played) or the drives were not armed (Sample.own_torques)."""
    from fuzz_fakes import FakeNode, RecordingBus

    from bridges.driver import DriverSettings
    from bridges.odrive import OdriveDriver
    from deploy.nodes.bridge import BridgeNode
    from deploy.runtime.node_runtime import StopFlag

    sc = load_scenario("lab")
    ids, bus = [0, 1, 2, 3], RecordingBus()
    b = BridgeNode(sc, 2, FakeNode(sc.robot_ids, "bridge-2"), StopFlag(), bus,
                   OdriveDriver(DriverSettings(tuple(ids))), ids, command_timeout_s=1e9,
                   heartbeat_timeout_s=1e9)
    try:
        _bridge_flags(b, sc)
    finally:
        b.close()
        bus.shutdown()


def _bridge_flags(b, sc) -> None:
    from deploy.contract.wire import WIRE_VERSION, Reply, Sample, Share, encode

    z = (0.0, 0.0, 0.0)

    def sample_after(k: int) -> Sample:
        b._publish(k, k * sc.dt, False)
        return next(m for _, m in reversed(b.node.published) if isinstance(m, Sample))

    assert not sample_after(0).own_torques  # not armed: nothing drove the wheels
    b.armed = True
    b.published_k = 4
    b.node.deliver(b.node.keys.cmd(2), encode(Reply(
        WIRE_VERSION, 2, 0, 0, robot=2, k=4, t=4 * sc.dt, torques=(0.1,) * 4, v_cmd=z,
        state_seq=0, state_stamp_ns=0, share=Share(z, z, z, z, z, z))))
    assert sample_after(5).own_torques  # the answer to sample 4 drove period 4 -> 5
    b.fallback_period = True  # no command in period 5 -> 6: its look-ahead played
    assert not sample_after(6).own_torques
    assert not sample_after(7).own_torques  # still the answer to sample 4
