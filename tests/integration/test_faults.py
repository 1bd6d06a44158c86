"""Fault plans, the per-message fault decisions, held inputs and the agents'
degradation: pure parts, and in-process runs under faults."""

from __future__ import annotations

import math

import numpy as np
import pytest
from kernel_forms import freshest_source, next_speed_factor, reacquire, slow_down

from agents.core import AgentCore
from agents.degradation import DegradationConfig, InputAges, predict
from deploy.cli import main
from deploy.contract.fault_plan import (
    Burst,
    FaultPlanError,
    LinkFaults,
    decode_plan,
    run_edges,
    uniform_drop_plan,
)
from deploy.contract.scenario import load_scenario
from deploy.run.runner import run_in_process
from deploy.runtime.fault_model import DELIVERED, PARTITIONED, EdgeFaults, FaultModel, merge_reports
from deploy.runtime.lockstep_inputs import HeldInput

pytestmark = [pytest.mark.slow]


@pytest.fixture(scope="module")
def paper():
    return load_scenario("paper")


@pytest.fixture(scope="module")
def lab():
    return load_scenario("lab")


# -- plans ------------------------------------------------------------------------------
def test_edges_follow_the_graph(paper):
    edges = set(run_edges(paper))
    # eq. (49) with a_11 dropped: 2 hears 1, 3 hears 1 and 2, only 1 hears the leader
    assert ("leader", "agent-1") in edges and ("leader", "agent-2") not in edges
    assert {("agent-1", "agent-2"), ("agent-1", "agent-3"), ("agent-2", "agent-3")} <= edges
    assert ("agent-3", "agent-2") not in edges
    assert len(edges) == 1 + 3 + 3 + 3


def test_plan_merges_defaults_and_links_in_order(paper):
    plan = decode_plan("""
seed = 4
[defaults]
drop = 0.1
[[link]]
from = "agent-*"
to = "agent-3"
drop = 0.4
delay_s = 0.002
[[link]]
from = "agent-2"
to = "agent-3"
partitions = [[1.0, 2.0]]
""", paper)
    assert plan.link("plant", "agent-1") == LinkFaults(drop=0.1)
    assert plan.link("agent-1", "agent-3") == LinkFaults(drop=0.4, delay_s=0.002)
    assert plan.link("agent-2", "agent-3") == LinkFaults(drop=0.4, delay_s=0.002,
                                                         partitions=((1.0, 2.0),))


@pytest.mark.parametrize("text, key", [
    ("[defaults]\ndorp = 0.1\n", "dorp"),
    ("[defaults]\ndrop = 1.5\n", "defaults.drop"),
    ("[defaults]\ndrop = nan\n", "defaults.drop"),
    ("[[link]]\nfrom = 'agent-3'\nto = 'agent-2'\ndrop = 0.1\n", "link[0]"),
    ("[[link]]\nfrom = 'leader'\npartitions = [[3.0, 2.0]]\n", "link[0].partitions[0]"),
    ("[[link]]\nfrom = 'leader'\nburst = { p_enter = 0.1, p_exit = 0.0 }\n", "p_exit"),
    ("[[kill]]\nprocess = 'agent-9'\nat_s = 1.0\n", "kill[0].process"),
    ("[[kill]]\nprocess = 'agent-1'\nat_s = 99.0\n", "kill[0].at_s"),
    ("seed = -1\n", "seed"),
    ("[can]\nframe_loss = 2\n", "can.frame_loss"),
    ("drop = 0.1\n", "drop"),
    ("this is not toml", "not valid TOML"),
])
def test_bad_plans_name_the_key(paper, text, key):
    with pytest.raises(FaultPlanError, match="plan.toml") as err:
        decode_plan(text, paper, "plan.toml")
    assert key in str(err.value)


def test_cli_rejects_bad_plan_with_exit_2(tmp_path, capsys):
    plan = tmp_path / "typo.toml"
    plan.write_text("[defaults]\ndrop_rate = 0.3\n")
    assert main(["run", "paper", "--in-process", "--faults", str(plan),
                 "--out", str(tmp_path / "out")]) == 2
    assert "drop_rate" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_kills_need_the_realtime_clock(tmp_path, capsys):
    plan = tmp_path / "kill.toml"
    plan.write_text("[[kill]]\nprocess = 'agent-2'\nat_s = 1.0\n")
    assert main(["run", "lab", "--faults", str(plan), "--out", str(tmp_path / "o")]) == 2
    assert "realtime" in capsys.readouterr().err


# -- decisions --------------------------------------------------------------------------
def _edge(spec: LinkFaults, seed: int = 1, dt: float = 0.001, name: str = "a->b") -> EdgeFaults:
    return EdgeFaults(name, seed, spec, dt)


def test_independent_loss_rate_and_determinism():
    n = 40_000
    e1, e2 = _edge(LinkFaults(drop=0.3)), _edge(LinkFaults(drop=0.3))
    out1 = [e1.delivered(k) for k in range(n)]
    assert out1 == [e2.delivered(k) for k in range(n)]  # same seed, same edge: same fate
    lost = n - sum(out1)
    assert abs(lost / n - 0.3) < 4 * math.sqrt(0.3 * 0.7 / n)
    other_seed = [_edge(LinkFaults(drop=0.3), seed=2).delivered(k) for k in range(n)]
    other_edge = [_edge(LinkFaults(drop=0.3), name="b->a").delivered(k) for k in range(n)]
    assert other_seed != out1 and other_edge != out1
    # any order of asking gives the same answers (messages arrive in any order)
    assert [e1.delivered(k) for k in reversed(range(1000))] == out1[:1000][::-1]


def test_gilbert_elliott_bursts():
    b = Burst(p_enter=0.02, p_exit=0.25)
    n = 200_000
    edge = _edge(LinkFaults(burst=b))
    fate = np.array([edge.delivered(k) for k in range(n)])
    lost = ~fate
    # stationary loss p_enter / (p_enter + p_exit); mean burst length 1 / p_exit
    assert abs(lost.mean() - 0.02 / 0.27) < 0.01
    starts = np.flatnonzero(lost[1:] & ~lost[:-1]) + 1
    ends = np.flatnonzero(~lost[1:] & lost[:-1]) + 1
    ends = ends[ends > starts[0]][: len(starts)]
    lengths = ends - starts[: len(ends)]
    assert abs(lengths.mean() - 1 / 0.25) < 0.3
    # a fresh edge object asked out of order agrees (the chain is recomputed)
    e = _edge(LinkFaults(burst=b))
    assert [e.delivered(k) for k in (5000, 10, 4999)] == [fate[5000], fate[10], fate[4999]]


def test_partition_window_is_exact():
    e = _edge(LinkFaults(partitions=((1.0, 1.5),)), dt=0.01)
    assert [e.outcome(k) for k in (99, 100, 149, 150)] == [DELIVERED, PARTITIONED,
                                                           PARTITIONED, DELIVERED]


def test_counts_per_edge_and_merge(paper):
    model = FaultModel(uniform_drop_plan(paper, 0.5, 3), paper.dt)
    e = model.edge("leader", "agent-1")
    got = sum(model.judge(e, k) for k in range(1000))
    c = model.report()["leader->agent-1"]
    assert c["messages"] == 1000 and c["dropped"] == 1000 - got
    merged = merge_reports([model.report(), model.report()])
    assert merged["leader->agent-1"]["dropped"] == 2 * c["dropped"]


# -- held inputs --------------------------------------------------------------------------
def test_held_input_holds_the_last_delivered_sample_and_says_how_old(paper):
    plan = decode_plan("[[link]]\nfrom='leader'\npartitions=[[0.002, 0.005]]\n", paper)
    model = FaultModel(plan, 0.001)
    held: HeldInput[str] = HeldInput(model, model.edge("leader", "agent-1"))
    got = [held.take(k, lambda i: f"s{i}") for k in range(8)]
    assert got == [("s0", 0), ("s1", 0), ("s1", 1), ("s1", 2), ("s1", 3), ("s5", 0),
                   ("s6", 0), ("s7", 0)]


def test_held_input_with_delay_uses_the_sample_lag_steps_back(paper):
    plan = decode_plan("[[link]]\nfrom='leader'\ndelay_s = 0.003\n", paper)
    model = FaultModel(plan, 0.001)
    held: HeldInput[int] = HeldInput(model, model.edge("leader", "agent-1"))
    got = [held.take(k, lambda i: i) for k in range(6)]
    assert got == [(0, 0), (0, 1), (0, 2), (0, 3), (1, 3), (2, 3)]
    assert model.report()["leader->agent-1"]["delayed"] == 2


def test_take_present_is_take_on_a_sound_link_and_declines_a_faulty_one(paper):
    """The plant's shortcut for a command in hand leaves the link as ``take`` would."""
    plan = decode_plan("[[link]]\nfrom='leader'\npartitions=[[0.002, 0.005]]\n", paper)
    model = FaultModel(plan, 0.001)
    sound: HeldInput[str] = HeldInput(model, None, exempt_first=False)
    by_take: HeldInput[str] = HeldInput(model, None, exempt_first=False)
    for k in range(4):
        assert sound.take_present(k, f"s{k}")
        assert by_take.take(k, lambda i: f"s{i}") == (f"s{k}", 0)
        assert (sound.value, sound.k_value) == (by_take.value, by_take.k_value)
    faulty: HeldInput[str] = HeldInput(model, model.edge("leader", "agent-1"))
    assert not faulty.take_present(0, "s0")
    assert (faulty.value, faulty.k_value) == (None, None)


# -- degradation math -----------------------------------------------------------------------
def test_predict_and_freshest_source_ages_add_along_the_graph():
    assert predict((1.0, 2.0, 0.5), (2.0, -1.0, 0.1), 0.5) == (2.0, 1.5, 0.55)
    leader = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    # a neighbour heard 0.1 s ago whose own information is 0.3 s old: 0.4 s, older
    # than the leader sample 0.25 s old
    f = freshest_source(leader, 0.25, [((5.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.1, 0.3)])
    assert f.age_s == 0.25 and f.q0 == (0.25, 0.0, 0.0)
    f = freshest_source(None, 0.0, [((5.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.1, 0.0)])
    assert f.age_s == 0.1 and f.q0 == (5.1, 0.0, 0.0)


def test_speed_factor_falls_with_age_and_rises_no_faster_than_the_ramp():
    cfg = DegradationConfig(slow_after_s=0.5, slow_ramp_s=1.0)
    h = 0.01
    assert next_speed_factor(1.0, 0.4, cfg, h) == 1.0
    assert next_speed_factor(1.0, 1.0, cfg, h) == pytest.approx(0.5)
    assert next_speed_factor(0.5, 3.0, cfg, h) == 0.0
    f, steps = 0.0, 0
    while f < 1.0:  # fresh again: back to full speed over slow_ramp_s, not at once
        f = next_speed_factor(f, 0.0, cfg, h)
        steps += 1
    assert steps == pytest.approx(cfg.slow_ramp_s / h, abs=1)


def test_slow_down_caps_planar_speed_and_never_raises_it():
    v = (3.0, 4.0, 1.0)
    assert slow_down(v, 1.0, 0.3) == v
    vx, vy, w = slow_down(v, 0.0, 0.3)
    assert math.hypot(vx, vy) == pytest.approx(0.3) and w == pytest.approx(0.06)
    assert slow_down((0.1, 0.0, 0.2), 0.0, 0.3) == (0.1, 0.0, 0.2)


def test_reacquire_converges_without_a_jump():
    cfg = DegradationConfig(reacquire_tau_s=0.25, reacquire_tol_m=0.05)
    q, v, on = (50.0, 0.0, 0.0), (0.0, 0.0, 0.0), True
    steps, biggest = 0, 0.0
    while on:
        q_new, v, on = reacquire(q, v, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), cfg, 0.001)
        biggest = max(biggest, abs(q_new[0] - q[0]))
        q, steps = q_new, steps + 1
    assert abs(q[0]) <= 0.05
    assert biggest <= 50.0 * 0.001 / 0.25 + 1e-9  # first-order: no step bigger than h / tau
    assert steps * 0.001 == pytest.approx(0.25 * math.log(50 / 0.05), rel=0.01)


def _core(sc, i=0):
    q, qd = sc.initial_state()
    q0, v0 = sc.initial_estimates(i)
    return AgentCore(sc.agent_config(i), q[i], qd[i], q0, v0), q[i], qd[i]


def test_fresh_ages_change_nothing(paper):
    """A fault plan that leaves an agent's links alone must not change its law."""
    a, q, qd = _core(paper)
    b, _, _ = _core(paper)
    lead = (np.array([1.0, 2.0, 0.3]), np.array([0.5, -0.2, 0.1]))
    for k in range(50):
        t = k * paper.dt
        oa = a.step(t, q, qd, {}, lead)
        ob = b.step(t, q, qd, {}, lead, ages=InputAges())
        assert np.array_equal(oa.torques, ob.torques) and np.array_equal(oa.share.q0_hat,
                                                                         ob.share.q0_hat)


def test_without_any_input_the_estimator_integrates_its_own_velocity(paper):
    core, q, qd = _core(paper)
    lead = (np.array([1.0, 2.0, 0.3]), np.array([0.5, -0.2, 0.1]))
    q0, v0 = core.q0_hat, core.v0_hat
    out = core.step(0.0, q, qd, {}, lead, ages=InputAges(leader_s=1.0))  # > stale_after
    assert out.left_out == 1 and out.input_age_s == 1.0
    assert np.allclose(core.q0_hat, q0 + paper.dt * v0, atol=1e-15)
    assert np.array_equal(core.v0_hat, v0)


# -- runs --------------------------------------------------------------------------------------
def test_in_process_fault_runs_are_reproducible_and_seeded(lab):
    plan = uniform_drop_plan(lab, 0.3, 5)
    a = run_in_process(lab, "model", 1.5, faults=plan)
    b = run_in_process(lab, "model", 1.5, faults=plan)
    c = run_in_process(lab, "model", 1.5, faults=uniform_drop_plan(lab, 0.3, 6))
    assert np.array_equal(a.series.q, b.series.q) and a.faults == b.faults
    assert not np.array_equal(a.series.q, c.series.q)
    total = sum(e["messages"] for e in a.faults.values())
    lost = sum(e["dropped"] for e in a.faults.values())
    # every message once: 3 command edges x 300 steps; the plant's and leader's first
    # samples are exempt (4 edges x 299), and the shares of steps 0..298 are used (3 x 299)
    assert total == 3 * 300 + 4 * 299 + 3 * 299
    assert abs(lost / total - 0.3) < 0.03


def test_partition_of_the_leader_degrades_then_recovers(lab):
    """lab, leader -> agent 1 cut for 2 s from t = 8 s. During the cut agent 1
    says its information is old, and every agent slows down (ages travel along
    the graph); no contact; the torque never steps by more than the limit.
    After the heal the estimates are back at the fault-free level within 1.5 s
    (re-acquisition) and the formation error within 1.2x the fault-free run's
    (plus the settling band) within 4 s: the robots were slowed to 0.3 m/s while
    the leader went on, and catch up at the 1.5 m/s speed limit (3.4 s measured;
    the paper scenario's figures are in docs/faults.md).

    Torque: the fault-free law itself swings full scale (-2 -> +2 N m) between
    steps when its sliding variable saturates (124 times in these 16 s), so the
    check is that the heal adds no such step: after it, no more steps larger
    than the limit than the fault-free run has over the same window."""
    duration, heal = 16.0, 10.0
    plan = decode_plan("[[link]]\nfrom = 'leader'\nto = 'agent-1'\npartitions = [[8.0, 10.0]]\n",
                       lab)
    nominal = run_in_process(lab, "model", duration).series
    cut = run_in_process(lab, "model", duration, faults=plan).series
    t = cut.t
    assert cut.input_age[(t >= 9.0) & (t < heal), 0].min() >= 1.0 - 1e-9
    assert cut.speed_factor[(t >= 9.6) & (t < heal)].max() == 0.0  # all three slowed
    assert cut.speed_factor[t < 8.0].min() == 1.0
    limit = lab.spec.limits.max_wheel_torque_nm
    after = (t[1:] >= heal) & (t[1:] < heal + 3.0)
    big_cut = (np.abs(np.diff(cut.torque, axis=0)).max(axis=2) > limit)[after].sum()
    big_nom = (np.abs(np.diff(nominal.torque, axis=0)).max(axis=2) > limit)[after].sum()
    assert big_cut <= big_nom

    def settled_after(err_cut, err_nom, band):
        ok = np.all(err_cut <= 1.2 * err_nom + band, axis=1)
        bad = np.flatnonzero((t >= heal) & ~ok)
        assert len(bad) == 0 or bad[-1] + 1 < len(t), "never recovered"
        return (t[bad[-1] + 1] if len(bad) else heal) - heal

    est_cut = np.linalg.norm(cut.q0_hat[:, :, :2] - cut.leader_q[:, None, :2], axis=2)
    est_nom = np.linalg.norm(nominal.q0_hat[:, :, :2] - nominal.leader_q[:, None, :2], axis=2)
    assert est_cut[(t >= 9.5) & (t < heal)].min() > 10 * est_nom.max()  # it did drift
    assert settled_after(est_cut, est_nom, 0.01) <= 1.5
    form_cut = np.linalg.norm(cut.q[:, :, :2] - cut.target, axis=2)
    form_nom = np.linalg.norm(nominal.q[:, :, :2] - nominal.target, axis=2)
    assert settled_after(form_cut, form_nom, lab.spec.metrics.settle_threshold) <= 4.0
    radii = 2 * lab.spec.robot.body_radius_m
    for i in range(3):
        for j in range(i + 1, 3):
            gap = np.linalg.norm(cut.q[:, i, :2] - cut.q[:, j, :2], axis=1) - radii
            assert gap.min() > 0.0


# -- the sweep and show commands ------------------------------------------------------------
def test_sweep_writes_table_csv_and_plot(tmp_path, capsys):
    import csv

    out = tmp_path / "sweep"
    assert main(["faults", "sweep", "lab", "--drop", "0,0.5", "--seeds", "2", "--duration",
                 "0.5", "--plant", "model", "--jobs", "2", "--out", str(out)]) == 0
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert [(r["drop"], r["seed"]) for r in rows] == [("0.0", "1"), ("0.5", "1"), ("0.5", "2")]
    assert int(rows[0]["messages_judged"]) == 0  # no loss: nothing judged, nothing lost
    for r in rows[1:]:
        judged, lost = int(r["messages_judged"]), int(r["messages_lost"])
        assert abs(lost / judged - 0.5) < 0.05
    assert rows[1]["formation_rms_whole_run_m"] != rows[2]["formation_rms_whole_run_m"]  # the seeds differ
    table = (out / "sweep.md").read_text()
    assert "| 0.5 | 2 |" in table and "| 0 | 1 |" in table
    assert (out / "sweep.png").stat().st_size > 10_000
    assert (out / "runs" / "drop-0.5-seed-2" / "metrics.json").exists()


@pytest.mark.parametrize("args", [["--drop", "0,1.5"], ["--drop", "a,b"], ["--seeds", "0"]])
def test_sweep_rejects_bad_arguments(args, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["faults", "sweep", "lab", *args])
    assert exc.value.code == 2


def test_show_lists_every_edge_of_the_run(tmp_path, capsys):
    plan = tmp_path / "p.toml"
    plan.write_text("seed = 2\n[[link]]\nfrom = 'agent-1'\ndrop = 0.25\n"
                    "[[kill]]\nprocess = 'agent-3'\nat_s = 5.0\n")
    assert main(["faults", "show", str(plan), "--scenario", "paper"]) == 0
    lines = {ln.split()[0]: " ".join(ln.split()[1:]) for ln in
             capsys.readouterr().out.splitlines()[1:]}
    assert lines["agent-1->agent-2"] == lines["agent-1->plant"] == "drop 0.25"
    assert sum(v == "perfect" for v in lines.values()) == 10 - 3
    assert lines["kill"] == "agent-3 at 5 s"
