"""The invariant that keeps a forgery from winning a step, locking an agent out or
hanging a lockstep run (docs/hardening.md, "No lock-out, no hang"), on the real plant
and agent nodes driven with bytes (tests/fuzz_fakes.py), each with its keyring:

- the plant takes robot i's command for step k only from agent i (its tag under the
  key only agent i and the plant hold), so it steps past k only on each robot's own
  agent's command or its step deadline;
- an agent's sample, shares and leader states reach its tables and its guards only
  from their own senders, so its own clock (it answered step a at T: the plant is at
  most at a + 1 plus one step per deadline since) is never behind a plant that ran on
  forged input, and its real samples are never refused as "ahead of our clock".

Forgeries are tagged with every key a forger could hold: keys of another run, and
agent 3's own (a compromised agent)."""

from __future__ import annotations

import time

import pytest
from fuzz_fakes import FakeNode

from deploy.contract import mac
from deploy.contract.keyring import Keyring, keyring_text, new_master
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import (
    WIRE_VERSION,
    LeaderState,
    Reply,
    Sample,
    Share,
    encode,
    run_roles,
)
from deploy.nodes.agent import AgentNode
from deploy.nodes.plant import PlantNode
from deploy.runtime.node_runtime import StopFlag

Z = (0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def lab():
    return load_scenario("lab")


def _rings(sc, master=None) -> dict[str, Keyring]:
    from deploy.contract.wire import Keys

    roles = [*run_roles(sc.robot_ids), "launcher"]
    master = master or new_master()
    return {r: Keyring.from_text(keyring_text(master, "fuzz", r, roles), "test", r, sc,
                                 Keys("fuzz")) for r in roles}


def _reply(robot: int, k: int, torque: float = -2.0, q0=Z) -> bytes:
    return encode(Reply(WIRE_VERSION, robot, k + 1, 0, robot=robot, k=k, t=0.0,
                        torques=(torque,) * 4, v_cmd=Z, state_seq=k, state_stamp_ns=0,
                        share=Share(q0, Z, Z, Z, Z, Z)))


def _sample(robot: int, k: int) -> bytes:
    return encode(Sample(WIRE_VERSION, 0, k, 0, robot=robot, k=k, t=k * 0.005,
                         q=(1.0, 1.0, 0.0), q_dot=Z, robots=[], obstacles=[]))


def _forged(real: dict[str, Keyring], other: dict[str, Keyring], claimed: str, key: str,
            body: bytes) -> list[bytes]:
    """``body`` on ``key`` as ``claimed`` would send it: plain, with another run's keys,
    with agent 3's own keys as itself, and claiming ``claimed`` with each key agent 3 holds."""
    three = real["agent-3"]
    stolen = [(mac.hint(r), mac.prefixed(three._pair[held], key, claimed, r))
              for r in real[claimed].receivers.get(key, []) for held in three._pair]
    return [body, other[claimed].seal(body, key), three.seal(body, key),
            mac.seal(body, stolen, mac.trailer(mac.hint(claimed), len(stolen)))]


def test_the_plant_steps_past_k_only_on_each_robots_own_agents_command(lab):
    real, other = _rings(lab), _rings(lab)
    p = PlantNode(lab, "model", FakeNode(lab.robot_ids, "plant", real["plant"]), StopFlag())
    k = 10
    p.published_k = k
    complete = lambda: all((r, k) in p.commands for r in lab.robot_ids)  # noqa: E731 - the wait's condition
    for r in (1, 2):  # agent 3 is the rogue: its own robot is its own
        key = p.node.keys.cmd(r)
        for data in _forged(real, other, f"agent-{r}", key, _reply(r, k)):
            p.node.deliver(key, data)
        for step in (k + 1, k + 2, k + 3):  # the fling: future steps at 1e30 N m
            for data in _forged(real, other, f"agent-{r}", key, _reply(r, step, 1e30)):
                p.node.deliver(key, data)
    assert p.commands == {} and not complete() and p.clipped == {}
    assert p.node.refused == {"reply: unsigned": 8, "reply: MAC does not check": 16,
                              "reply: not signed by a sender of this key": 8}
    for r in lab.robot_ids:  # each robot's own agent: the step is complete
        p.node.deliver(p.node.keys.cmd(r), real[f"agent-{r}"].seal(_reply(r, k, 0.5),
                                                                   p.node.keys.cmd(r)))
    assert complete() and {c.torques for c in p.commands.values()} == {(0.5,) * 4}


@pytest.mark.parametrize("realtime", [False, True], ids=["lockstep", "realtime"])
def test_an_agent_is_never_behind_a_plant_that_ran_on_forged_input(lab, realtime):
    real, other = _rings(lab), _rings(lab)
    a = AgentNode(lab, 2, FakeNode(lab.robot_ids, "agent-2", real["agent-2"]), StopFlag(),
                  realtime=realtime)
    keys, inp = a.node.keys, a.inputs
    before = (a.clock.answered, a.clock.answered_at, a.guards["sample"].newest)
    for k in range(0, 5):  # samples for the steps in progress and ahead, from "the plant"
        for data in _forged(real, other, "plant", keys.sample(2), _sample(2, k)):
            a.node.deliver(keys.sample(2), data)
    for k in (-1, 0, 1):  # robot 1's shares (agent 2 listens to 1): the leader 5000 m away
        for data in _forged(real, other, "agent-1", keys.cmd(1),
                            _reply(1, k, q0=(5000.0, 5000.0, 0.0))):
            a.node.deliver(keys.cmd(1), data)
    # nothing reached a table, a guard or the clock
    assert inp.states == {} and inp.newest_state is None and inp.shares == {}
    assert inp.newest_share == {} and (a.clock.answered, a.clock.answered_at,
                                       a.guards["sample"].newest) == before
    assert set(a.node.refused) == {"sample: unsigned", "sample: MAC does not check",
                                   "sample: not signed by a sender of this key",
                                   "reply: unsigned", "reply: MAC does not check",
                                   "reply: not signed by a sender of this key"}
    # the real stream goes on: every real sample taken, none "ahead of our clock"
    for k in range(0, 5):
        a.clock.answer(k - 1, time.monotonic())  # lockstep: we answered the last step
        a.node.deliver(keys.sample(2), real["plant"].seal(_sample(2, k), keys.sample(2)))
        assert inp.newest_state.k == k
    a.node.deliver(keys.cmd(1), real["agent-1"].seal(_reply(1, 0), keys.cmd(1)))
    assert inp.newest_share[1].share.q0_hat == Z
    assert not [why for why in a.node.refused if "clock" in why or "step" in why]


def test_forged_leader_batches_are_refused_and_counted(lab):
    """They used to be dropped uncounted (a step already stored is never overwritten)."""
    real, other = _rings(lab), _rings(lab)
    a = AgentNode(lab, 1, FakeNode(lab.robot_ids, "agent-1", real["agent-1"]), StopFlag())
    key = a.node.keys.leader_state
    body = encode(LeaderState(WIRE_VERSION, 0, 0, 0, k=0, t=0.0, q=[(5000.0, 5000.0, 0.0)] * 32,
                              q_dot=[Z] * 32))
    for data in _forged(real, other, "leader", key, body):
        a.node.deliver(key, data)
    assert a.inputs.leaders == {} and a.inputs.newest_leader is None
    assert sum(a.node.refused.values()) == 4
    a.node.deliver(key, real["leader"].seal(body, key))
    assert len(a.inputs.leaders) == 32
