"""Fuzzing what the receivers of ``robot/i/cmd`` do with arbitrary command bytes.

The real plant node (deploy/nodes/plant.py) and CAN bridge (deploy/nodes/bridge.py) are fed
bytes through the real decoder (tests/fuzz_fakes.py stands in for zenoh and the
bus). Properties, whatever the bytes: nothing raises; the torques the plant is
stepped with, and the torque frames the bridge puts on the bus, are finite and
within the scenario's ``limits.max_wheel_torque_nm``; the kinematic plant's
velocity command is within ``max_speed_mps`` / ``max_yaw_rate_radps``.
Commands are field lists of valid shape with any float torques (huge, non-finite,
beyond float32) and look-ahead plans (agents/look_ahead.py, played for the steps
after), wrong fields, and mutated bytes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import msgspec
import numpy as np
import pytest
from fuzz_fakes import FakeNode, RecordingBus
from fuzz_wire_inputs import ROBOT_IDS, message_bytes
from fuzzing import any_float, fuzz_decoder, fuzz_settings, mutated_bytes
from hypothesis import given
from hypothesis import strategies as st

from bridges.driver import DriverSettings, DriveState, WheelReport
from bridges.odrive import OdriveCanSimple, OdriveDriver, SetInputTorque
from deploy.contract.scenario import Scenario, load_scenario
from deploy.contract.wire import WIRE_VERSION, Reply, Share, encode
from deploy.nodes.bridge import BridgeNode
from deploy.nodes.plant import PlantNode
from deploy.runtime.node_runtime import StopFlag
from plant.command import PLAUSIBLE_SPEED_MPS, PLAUSIBLE_TORQUE_NM, PLAUSIBLE_YAW_RATE_RADPS

NODE_IDS = [0, 1, 2, 3]
SCENARIOS = ["lab", "paper"]  # a 2 N m torque limit, and none (inf)
torque = st.one_of(st.floats(-5.0, 5.0), any_float, st.floats(-1e40, 1e40))


@st.composite
def command_bytes(draw: st.DrawFn) -> bytes:
    """A Reply-shaped field list with any torques, wrong fields, or mutated bytes."""
    how = draw(st.sampled_from(["torques", "torques", "wrong", "mutated"]))
    if how == "wrong":
        return draw(message_bytes(Reply, sane=False))
    fields = msgspec.msgpack.decode(draw(message_bytes(Reply, sane=True)))
    fields[0] = WIRE_VERSION
    fields[4] = ROBOT_IDS[0]
    fields[7] = draw(st.lists(torque, min_size=4, max_size=4))
    fields[8] = draw(st.lists(torque, min_size=3, max_size=3))
    # the look-ahead plan: any torques, sometimes longer than the wire allows
    fields[12:] = [draw(st.lists(st.lists(torque, min_size=4, max_size=4), max_size=20))]
    raw = msgspec.msgpack.encode(fields)
    return draw(mutated_bytes(raw)) if how == "mutated" else raw


def within(values: np.ndarray | tuple[float, ...], limit: float) -> bool:
    return all(math.isfinite(x) and abs(x) <= limit for x in np.ravel(values))


# --- the plant node ----------------------------------------------------------------------
@pytest.fixture(scope="module", params=SCENARIOS)
def plant(request: pytest.FixtureRequest) -> PlantNode:
    sc = load_scenario(request.param)
    p = PlantNode(sc, "model", FakeNode(sc.robot_ids, "plant"), StopFlag())
    # every step counts as sent and recent: the fuzzing reaches the clamps behind the
    # plant's step guard (tested on its own below)
    p.published_k, p.window_steps = 2**63, 2**64
    return p


def check_plant_inputs(p: PlantNode) -> None:
    lim = p.sc.spec.limits
    assert within(p.torques, lim.max_wheel_torque_nm), p.torques
    assert np.all(np.isfinite(p.v_cmd)), p.v_cmd
    assert np.all(np.hypot(p.v_cmd[:, 0], p.v_cmd[:, 1]) <= lim.max_speed_mps * (1 + 1e-12))
    assert np.all(np.abs(p.v_cmd[:, 2]) <= lim.max_yaw_rate_radps)


@fuzz_settings(150)
@given(raw=command_bytes())
def test_plant_applies_only_finite_torques_within_the_limit(plant: PlantNode, raw: bytes) -> None:
    rid = ROBOT_IDS[0]
    plant.newest.clear()
    plant.commands.clear()
    cmd = fuzz_decoder("plant cmd", lambda b: plant.node.deliver(plant.node.keys.cmd(rid), b), raw)
    plant._apply_newest_commands(time.monotonic())  # realtime: the newest command
    check_plant_inputs(plant)
    if cmd is not None:
        plant._take_lockstep_commands(cmd.k)  # lockstep: the command of step k
        check_plant_inputs(plant)
        for ahead in (1, 2, len(cmd.plan) + 1):  # its look-ahead for the steps after
            plant._take_lockstep_commands(cmd.k + ahead)
            check_plant_inputs(plant)
            plant._apply_newest_commands(time.monotonic())
            plant._play_plans(cmd.k + ahead)  # realtime: a later command is late
            check_plant_inputs(plant)


# --- the CAN bridge ----------------------------------------------------------------------
def enable(b: BridgeNode) -> None:
    """Every drive has said it is enabled (the bridge drives no wheel before)."""
    for n in b.node_ids:
        b.monitor.feed(WheelReport(n, state=DriveState.ENABLED, fault=0), 0.0)


@pytest.fixture(scope="module", params=SCENARIOS)
def bridge(request: pytest.FixtureRequest) -> Iterator[tuple[BridgeNode, RecordingBus]]:
    sc: Scenario = load_scenario(request.param)
    bus = RecordingBus()
    rid = sc.robot_ids[0]
    b = BridgeNode(sc, rid, FakeNode(sc.robot_ids, f"bridge-{rid}"), StopFlag(), bus,
                   OdriveDriver(DriverSettings(tuple(NODE_IDS))), NODE_IDS, command_timeout_s=1e9,
                   heartbeat_timeout_s=1e9)  # never stale, never faulted: commands reach the bus
    b.armed = True
    enable(b)
    yield b, bus
    b.close()
    bus.shutdown()


@fuzz_settings(150)
@given(raw=command_bytes())
def test_bridge_sends_only_finite_torques_within_the_limit(
        bridge: tuple[BridgeNode, RecordingBus], raw: bytes) -> None:
    b, bus = bridge
    bus.sent.clear()
    # every step counts as sent and newer than the last: the fuzzing reaches the gate
    # behind the bridge's step checks (tested on their own in tests/e2e/test_forged.py)
    b.published_k, b.command_k = 2**63, -(2**63)
    cmd = fuzz_decoder("bridge cmd", lambda x: b.node.deliver(b.node.keys.cmd(b.rid), x), raw)
    drive = OdriveCanSimple(NODE_IDS, role="drive", max_abs_torque_nm=3.4e38)
    torques = [m.torque_nm for m in map(drive.decode, bus.sent) if isinstance(m, SetInputTorque)]
    if cmd is not None:
        assert len(torques) == 4, (cmd.torques, bus.sent)
    limit = min(b.sc.spec.limits.max_wheel_torque_nm, b.protocol.max_abs_torque_nm)
    assert within(tuple(torques), limit), torques
    assert drive.counters.decoded == len(bus.sent)  # every frame sent is a valid frame
    if cmd is not None:  # periods with no command: its look-ahead, then held
        for ahead in (1, 2, len(cmd.plan) + 1):
            d = b.gate.decide(time.monotonic(), False, due_step=cmd.k + ahead)
            assert within(d.torques, limit), d


# --- cases the fuzzing found, pinned -----------------------------------------------------
def command(torques: tuple[float, ...], v_cmd: tuple[float, ...] = (0.0, 0.0, 0.0)) -> bytes:
    zero = (0.0, 0.0, 0.0)
    return encode(Reply(WIRE_VERSION, 1, 0, 0, robot=1, k=0, t=0.0, torques=torques,
                        v_cmd=v_cmd, state_seq=0, state_stamp_ns=0,
                        share=Share(zero, zero, zero, zero, zero, zero)))


@pytest.mark.parametrize("name", SCENARIOS)
def test_plant_clamps_each_wheel_and_the_velocity_command(name: str) -> None:
    """Found: the plant stepped with a command's torques as they came (1e300 N m on the
    lab robots, limit 2 N m)."""
    sc = load_scenario(name)
    p = PlantNode(sc, "model", FakeNode(sc.robot_ids, "plant"), StopFlag())
    p.published_k = 0  # the sample of step 0 went out
    p.node.deliver(p.node.keys.cmd(1), command((1e300, -3.0, 1.0, 0.0), (1e300, 0.0, -1e300)))
    p._take_lockstep_commands(0)
    lim = sc.spec.limits
    if math.isinf(lim.max_wheel_torque_nm):  # no limit: the plausibility bound still holds
        assert tuple(p.torques[0]) == (PLAUSIBLE_TORQUE_NM, -3.0, 1.0, 0.0)
        # no speed limit either: the plausibility bounds (a kinematic plant moves at it)
        assert tuple(p.v_cmd[0]) == (PLAUSIBLE_SPEED_MPS, 0.0, -PLAUSIBLE_YAW_RATE_RADPS)
    else:
        assert tuple(p.torques[0]) == (2.0, -2.0, 1.0, 0.0)
        assert tuple(p.v_cmd[0]) == pytest.approx((1.5, 0.0, -3.0), rel=1e-15)
    # beyond the bound: clipped, and counted for its robot
    assert p.node.refused == {"torque beyond the bound (clipped)": 1,
                              "velocity beyond the bound (clipped)": 1} and p.clipped == {1: 1}


def test_bridge_without_a_scenario_limit_clamps_to_what_the_protocol_encodes() -> None:
    """Found: paper.toml has no torque limit, so a 1001 N m command passed the gate and
    ``OdriveCanSimple.encode`` raised ValueError in the command callback."""
    sc = load_scenario("paper")
    bus = RecordingBus()
    b = BridgeNode(sc, 1, FakeNode(sc.robot_ids, "bridge-1"), StopFlag(), bus,
                   OdriveDriver(DriverSettings(tuple(NODE_IDS))), NODE_IDS, command_timeout_s=1e9,
                   heartbeat_timeout_s=1e9)
    try:
        b.armed = True
        enable(b)
        b.published_k = 0  # the sample of step 0 went out
        b.node.deliver(b.node.keys.cmd(1), command((1001.0, -1e30, 5.0, 0.0)))
        assert b.clipped == 1
        drive = OdriveCanSimple(NODE_IDS, role="drive")
        assert [drive.decode(f).torque_nm for f in bus.sent] == [1000.0, -1000.0, 5.0, 0.0]
    finally:
        b.close()
        bus.shutdown()


@pytest.mark.parametrize("clock", ["lockstep", "realtime"])
def test_a_command_for_a_step_not_yet_sent_is_refused_and_costs_only_itself(clock: str) -> None:
    """Found by probing (docs/hardening.md): one command for step 2^62 made a realtime plant
    order every real command after it (all dropped: robot 2 zeroed for the run), and
    future-step commands filled the lockstep table without bound. A command answers a
    sample already sent: a later step is refused, counted, and the real ones apply."""
    sc = load_scenario("lab")
    p = PlantNode(sc, "model", FakeNode(sc.robot_ids, "plant"), StopFlag(),
                  realtime=clock == "realtime")
    key = p.node.keys.cmd(1)
    for k in range(3):
        p.published_k = k
        p.node.deliver(key, reply(k, 2**62, (-2.0, -2.0, -2.0, -2.0)))  # forged: a huge seq
        p.node.deliver(key, reply(k, k + 1, (0.5, 0.5, 0.5, 0.5)))
        p.node.deliver(key, reply(k, k + 1, (-2.0, -2.0, -2.0, -2.0)))  # forged: a second
        p.node.deliver(key, reply(2**62, 0, (-2.0, -2.0, -2.0, -2.0)))  # forged
        for future in range(k + 1, k + 1000):  # a flood of future steps
            p.node.deliver(key, reply(future, 1, (-2.0, -2.0, -2.0, -2.0)))
        if clock == "lockstep":
            p._take_lockstep_commands(k)
        else:
            p._apply_newest_commands(time.monotonic())
        assert tuple(p.torques[0]) == (0.5, 0.5, 0.5, 0.5)
    assert p.node.refused == {"future step": 3 * 1000, "seq ahead of our clock": 3,
                              "second command for a step": 3}
    assert len(p.commands) <= 3 and all(k <= 2 for _r, k in p.commands)
    p.published_k = 500  # a command far older than the plant keeps: refused too
    p.node.deliver(key, reply(2, 0, (0.1, 0.1, 0.1, 0.1)))
    assert p.node.refused["stale step"] == 1


def reply(k: int, seq: int, torques: tuple[float, ...]) -> bytes:
    zero = (0.0, 0.0, 0.0)
    return encode(Reply(WIRE_VERSION, 1, seq, 0, robot=1, k=k, t=0.0, torques=torques,
                        v_cmd=zero, state_seq=0, state_stamp_ns=0,
                        share=Share(zero, zero, zero, zero, zero, zero)))
