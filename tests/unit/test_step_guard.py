"""StepGuard: a forged far-future step never becomes the newest and costs at most
itself; the real stream moves on, also across a real jump (pause, cut, restart)."""

from __future__ import annotations

from deploy.runtime.step_guard import JUMP_OK, StepGuard


def test_the_real_stream_moves_forward_with_small_gaps():
    g = StepGuard(newest=-1)
    assert [g.admit(k) for k in (0, 1, 2, 5, 6)] == [True, True, True, True, True]
    assert g.newest == 6 and g.held == 0
    assert not g.admit(6) and not g.admit(3)  # not newer


def test_one_forged_step_far_ahead_is_held_and_the_real_ones_go_on():
    g = StepGuard(newest=10)
    assert not g.admit(2**62)
    assert [g.admit(k) for k in range(11, 20)] == [True] * 9
    assert g.newest == 19 and g.held == 1


def test_a_real_jump_is_adopted_when_the_next_step_confirms_it():
    g = StepGuard(newest=10)
    assert not g.admit(2010)  # 2 s at 1 kHz after a pause: held once
    assert g.admit(2011) and g.newest == 2011
    assert g.admit(2012)


def test_a_forged_step_just_ahead_costs_at_most_jump_ok_steps():
    g = StepGuard(newest=10)
    assert g.admit(10 + JUMP_OK)  # believed: within the allowed gap
    lost = [k for k in range(11, 11 + 2 * JUMP_OK) if not g.admit(k)]
    assert len(lost) <= JUMP_OK


def test_two_forged_steps_far_apart_never_confirm_each_other():
    g = StepGuard(newest=0)
    assert not g.admit(10**6) and not g.admit(10**9)
    assert g.newest == 0 and g.admit(1)


def test_within_bounds_what_a_node_stores_ahead():
    g = StepGuard(newest=100)
    assert g.within(164, 64) and not g.within(165, 64)
    assert StepGuard().within(10**9, 0)


def _sample(k: int, seq: int) -> bytes:
    from deploy.contract.wire import WIRE_VERSION, Sample, encode

    return encode(Sample(WIRE_VERSION, 0, seq, 0, robot=2, k=k, t=k * 0.005, q=(0.0, 0.0, 0.0),
                         q_dot=(0.0, 0.0, 0.0), robots=[], obstacles=[]))


def test_an_agent_never_takes_a_forged_sample_as_its_newest():
    """Found by probing (docs/hardening.md): one sample for a future step hung a lockstep run
    (the agent waited for that step's other inputs every step), one with a huge seq
    silenced a realtime agent (every real sample after it looked older)."""
    import pytest

    pytest.importorskip("zenoh")
    import time

    from fuzz_fakes import FakeNode

    from deploy.contract.scenario import load_scenario
    from deploy.nodes.agent import AgentNode
    from deploy.runtime.node_runtime import StopFlag

    sc = load_scenario("lab")
    for realtime in (False, True):
        a = AgentNode(sc, 2, FakeNode(sc.robot_ids, "agent-2"), StopFlag(), realtime=realtime)
        key = a.node.keys.sample(2)
        a.node.deliver(key, _sample(0, 0))
        a.node.deliver(key, _sample(2**62, 2**62))  # forged: a far step, a huge seq
        for k in range(1, 6):
            a.clock.answer(k - 1, time.monotonic())  # lockstep: we answered the last step
            a.node.deliver(key, _sample(k, k))
            assert a.inputs.newest_state.k == k
        # a flood of far steps, each alone: 10^4 steps apart (50 s at lab's 200 Hz), so on
        # the realtime clock no stall of this process between two of them makes one look
        # like the next step of a stream that jumped (StepGuard: JUMP_OK steps of slack
        # per period elapsed; 7 apart was confirmed by a 20 ms stall of a loaded host)
        for k in range(10**6, 10**6 + 500):
            a.node.deliver(key, _sample(k * 10**4, 1))
        assert a.inputs.newest_state.k == 5
        assert max(a.inputs.states) == 5 and len(a.inputs.states) <= 6  # bounded
        if realtime:  # t = 0 not known yet (no start): the guard holds them
            assert a.node.refused == {"sample step": 501}
        else:  # lockstep: the plant cannot be past our last answer + 1 (step_guard.OwnClock)
            assert a.node.refused == {"sample: step ahead of our clock": 501}



def test_a_late_realtime_stream_that_skips_steps_is_followed():
    """Found by the quick bench (paper at 1 kHz, realtime, 2 cores) and the CAN fleet
    test: the plant ran late and stepped ~8 periods per sample, and an agent that was
    itself late saw samples close together; every such sample was a jump beyond
    JUMP_OK, held as an unconfirmed candidate, and the agents went silent."""
    g = StepGuard(period_s=0.001)
    sent = [(k * 8, 0.1 + k * 0.0085) for k in range(50)]  # 8 steps per 8.5 ms
    # the receiver handles them 0.5 ms after they leave, but every fifth after a 30 ms stall
    arrivals = [(k, at + (0.03 if n % 5 == 0 else 0.0005)) for n, (k, at) in enumerate(sent)]
    admitted = [g.admit(k, at) for k, at in arrivals]
    # the first sample, itself late, sets the clock too low: the next one is held once,
    # confirmed by the one after it; then every sample is followed
    assert admitted == [True, False] + [True] * 48
    assert g.held == 1 and g.newest == 49 * 8
    g = StepGuard(period_s=0.001)
    assert all(g.admit(k, at + 0.0005) for k, at in sent)  # a timely first: nothing held


def test_on_the_realtime_clock_a_forged_far_step_is_still_held():
    g = StepGuard(period_s=0.001)
    assert g.admit(100, 0.1005)  # lead -0.5 ms
    assert not g.admit(2**62, 0.1006)  # far beyond what the clock allows
    assert g.admit(108, 0.1085)  # the real stream, 8 ms later, goes on
    assert g.newest == 108 and g.held == 1
    assert not g.admit(150, 0.109)  # 42 steps in 0.5 ms: held, not adopted
    assert g.newest == 108 and g.admit(109, 0.1095)


# --- OwnClock: the newest step a sender can be at, on the receiver's own clock ------------
def test_lockstep_the_plant_is_at_most_one_step_past_our_answer_plus_one_per_deadline():
    from deploy.runtime.step_guard import DEADLINE_MARGIN, OwnClock

    c = OwnClock(dt=0.005, deadline_s=2.0, answered_at=100.0)  # the initial share at t = 100
    assert c.latest(100.0) == 0 and c.refusal(0, 0, 100.0) is None
    assert c.refusal(1, 0, 100.5) == "step ahead of our clock"  # before we answered step 0
    c.answer(41, 101.0)
    assert c.refusal(42, 42, 101.0) is None and c.refusal(43, 0, 101.0) is not None
    assert c.refusal(42, 45, 101.0) == "seq ahead of our clock"  # seq <= step + SEQ_SLACK
    # stalled: the plant moves on one step per deadline, and is believed to
    later = 101.0 + 3 * 2.0 * DEADLINE_MARGIN + 1e-6
    assert c.latest(later) == 45 and c.refusal(45, 45, later) is None
    # a restarted sender numbers from 0: heard
    assert c.refusal(42, 0, 101.0) is None
    # the leader's batches run ahead of the plant by design
    assert c.refusal(42 + 100, 3, 101.0, ahead=100) is None


def test_lockstep_an_answer_to_an_old_sample_does_not_pull_the_bound_back():
    """A link down 3 s: the plant went on one step per deadline; the first sample heard
    when the link is back is an old one the link held. Answering it leaves the bound
    where the plant may be, so its newer samples are heard."""
    from deploy.runtime.step_guard import DEADLINE_MARGIN, OwnClock

    c = OwnClock(dt=0.001, deadline_s=0.05, answered_at=0.0)
    c.answer(150, 10.0)  # the last answer before the cut
    back = 10.0 + 3.3
    may_be = c.latest(back)
    assert may_be == 151 + int(3.3 / (0.05 * DEADLINE_MARGIN))
    c.answer(151, back)  # the held sample of step 151, answered late
    assert c.latest(back) == may_be and c.refusal(may_be, may_be, back) is None
    assert c.refusal(may_be + 1, 0, back) == "step ahead of our clock"  # still a bound
    c.answer(may_be, back + 0.001)  # answered promptly again: as tight as before
    assert c.latest(back + 0.001) == may_be + 1


def test_realtime_no_sender_is_past_the_wall_clock():
    from deploy.runtime.step_guard import CLOCK_SKEW_S, OwnClock

    c = OwnClock(dt=0.001)
    assert c.latest(5.0) is None and c.refusal(2**62, 2**62, 5.0) is None  # t = 0 unknown
    c.t0_s = 5.0
    assert c.refusal(1000, 1000, 6.0) is None  # 1 s after t = 0
    assert c.refusal(1000 + int(CLOCK_SKEW_S / 0.001), 0, 6.0) is None  # within the skew
    assert c.refusal(1200, 0, 6.0) == "step ahead of our clock"
    assert c.refusal(900, 2**62, 6.0) == "seq ahead of our clock"


def test_realtime_an_initial_share_is_heard_before_the_run_starts():
    """A neighbour's initial share (k = -1) goes out at the handshake, before t = 0: one
    handled after ``ctl/start`` told us t = 0 but before that instant is real (refused
    as "step ahead", 0.3 s before t = 0 at 100 Hz: most likely the realtime forgery test's
    flake), while a sample of step 0 that early is not."""
    from deploy.runtime.step_guard import CLOCK_SKEW_S, OwnClock

    c = OwnClock(dt=0.01)
    c.t0_s = 10.0
    for before in (0.3, 1.0, 60.0):
        assert c.latest(10.0 - before) == -1
        assert c.refusal(-1, 0, 10.0 - before) is None
        assert c.refusal(0, 0, 10.0 - before) == "step ahead of our clock"
    assert c.refusal(0, 0, 10.0 - CLOCK_SKEW_S + 1e-6) is None  # within the skew of t = 0
