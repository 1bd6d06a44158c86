"""A realtime agent that was a period late (the newest sample came while it worked) steps
its law on each sample it missed before the newest, as lockstep does, and not once over
the periods between (deploy/nodes/agent.py, ``AgentNode._catch_up``): one step over two
periods integrates the reference (eq. 11) and the observer (39) over two periods ahead of
one (tests/integration/test_late_agent_steps.py measures what that does to a robot)."""

from __future__ import annotations

import time

from fuzz_fakes import FakeNode

from agents.pace import LoopPace
from agents.share import Share
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import WIRE_VERSION, Reply, Sample, encode
from deploy.nodes.agent import MAX_CATCH_UP, AgentNode
from deploy.runtime.node_runtime import StopFlag

ZERO = (0.0, 0.0, 0.0)


def _agent():
    sc = load_scenario("lab")
    rid = sc.robot_ids[1]
    a = AgentNode(sc, rid, FakeNode(sc.robot_ids, f"agent-{rid}"), StopFlag(), realtime=True)
    a.clock.t0_s = time.monotonic() - 10.0  # the run began 10 s ago: these steps are past
    return sc, rid, a


def _sample(a: AgentNode, sc, rid: int, k: int) -> None:
    a.node.deliver(a.node.keys.sample(rid), encode(Sample(
        WIRE_VERSION, 0, k, 0, robot=rid, k=k, t=k * sc.dt, q=(0.1 * k, 0.0, 0.0),
        q_dot=ZERO, robots=[], obstacles=[], own_torques=k != 2)))


def _share(a: AgentNode, sc, j: int, k: int) -> None:
    share = Share((float(k), 0.0, 0.0), ZERO, ZERO, ZERO, ZERO, ZERO, 0.0)
    a.node.deliver(a.node.keys.cmd(j), encode(Reply(
        WIRE_VERSION, j, k + 1, 0, robot=j, k=k, t=k * sc.dt, torques=(0.0,) * 4, v_cmd=ZERO,
        state_seq=k, state_stamp_ns=0, share=share)))


def _recorded(a: AgentNode) -> list[tuple]:
    calls = []
    step = a.core.step

    def recording(t, q, q_dot, shares, *rest):
        calls.append((t, q[0], rest[-5], rest[-1], {j: s.q0_hat[0] for j, s in shares.items()}))
        return step(t, q, q_dot, shares, *rest)

    a.core.step = recording
    return calls


def test_each_missed_sample_is_stepped_on_in_order_one_period_each():
    sc, rid, a = _agent()
    for k in range(-1, 4):
        for j in a.neighbours:
            _share(a, sc, j, k)
    for k in range(5):
        _sample(a, sc, rid, k)
    calls = _recorded(a)
    # sample 1 was answered; 2, 3 came while the loop worked, 4 is the newest
    missed = a._missed_inputs(last_k=1)
    assert [m.state.k for m in missed] == [2, 3]
    stepped_to = a._catch_up(missed, 1 * sc.dt, LoopPace(sc.dt), 4 * sc.dt)
    assert stepped_to == 3 * sc.dt  # the newest's own step is then one period
    assert [c[0] for c in calls] == [2 * sc.dt, 3 * sc.dt]  # each sample's time, in order
    assert [c[1] for c in calls] == [0.2, 0.30000000000000004]  # each its own robot state
    assert all(abs(c[2] - sc.dt) < 1e-12 for c in calls)  # h: one period each
    assert [c[3] for c in calls] == [False, True]  # own_torques as each sample said
    # each step with the neighbours' shares of the step before its own, as in lockstep
    assert [set(c[4].values()) for c in calls] == [{1.0}, {2.0}]
    assert a.caught_up == 2 and a.steps_done == 0  # no command: none sent
    assert not a.node.published


def test_only_the_newest_few_are_caught_up_and_none_without_the_neighbours():
    sc, rid, a = _agent()
    for k in range(MAX_CATCH_UP + 6):
        _sample(a, sc, rid, k)
    newest = MAX_CATCH_UP + 5
    missed = a._missed_inputs(last_k=0)
    assert [m.state.k for m in missed] == list(range(newest - MAX_CATCH_UP, newest))
    calls = _recorded(a)
    # no neighbour's share heard yet: nothing to step on (the newest steps over them all)
    assert a._catch_up(missed, 0.0, LoopPace(sc.dt), newest * sc.dt) == 0.0
    assert calls == [] and a.caught_up == 0
    assert a._missed_inputs(last_k=newest) == []  # nothing between the last answer and it


def test_a_sample_before_any_share_is_taken_without_the_neighbours():
    """A rejoining agent whose neighbour is gone hears samples and never that neighbour:
    its step's inputs are taken without it (the loop waits for it), never a KeyError."""
    sc, rid, a = _agent()
    _sample(a, sc, rid, 0)
    shares: dict = {}
    state, _, _ = a._step_inputs(shares)
    assert state.k == 0 and shares == {}


def test_a_missed_sample_before_a_neighbour_was_heard_is_stepped_over():
    """Not stepped on before every neighbour was heard (as the newest is not): the next
    one stepped on spans its period too, and the newest's step starts from it."""
    sc, rid, a = _agent()
    for j in a.neighbours:
        _share(a, sc, j, 2)  # first heard with its share of step 2
    for k in range(5):
        _sample(a, sc, rid, k)
    calls = _recorded(a)
    missed = a._missed_inputs(last_k=1)
    assert [m.state.k for m in missed] == [2, 3]
    assert a._catch_up(missed, 1 * sc.dt, LoopPace(sc.dt), 4 * sc.dt) == 3 * sc.dt
    assert [c[0] for c in calls] == [3 * sc.dt]  # sample 2 wanted the shares of step 1
    assert abs(calls[0][2] - 2 * sc.dt) < 1e-12 and a.caught_up == 1
