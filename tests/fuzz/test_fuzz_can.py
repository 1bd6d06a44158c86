"""Fuzzing CAN frame handling: the CANSimple decoder (both roles), the bridge's
frame handling (decoder -> driver monitor -> odometry) and the drive emulator.

Properties, whatever the frames (any id, standard or extended, remote, error and
FD frames, 0-64 data bytes, a DLC that disagrees with the data, valid frames with
bits flipped, float payloads that are NaN/Inf/huge):
- ``decode`` never raises, and neither does its body (the catch-all in ``decode``
  is a last resort, not a path); every frame is counted exactly once in
  :class:`FrameCounters`; what it returns passes the protocol's own checks;
- the bridge's odometry and the wheel speeds it sees stay finite;
- the emulator applies finite wheel torques within the scenario's limit (and the
  protocol's bound), its robot state stays finite, and it counts every frame.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator

import can
import numpy as np
import pytest
from fuzz_fakes import FakeNode, RecordingBus
from fuzzing import fuzz_decoder, fuzz_settings, non_finite_floats
from hypothesis import given
from hypothesis import strategies as st

from bridges.driver import DriverSettings, FrameCounters
from bridges.odrive import (
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    CMD_GET_BUS_VOLTAGE_CURRENT,
    CMD_GET_ENCODER_ESTIMATES,
    CMD_GET_ERROR,
    CMD_HEARTBEAT,
    CMD_SET_INPUT_TORQUE,
    CONTROL_MODE_TORQUE_CONTROL,
    INPUT_MODE_PASSTHROUGH,
    ClearErrors,
    DriverErrors,
    EncoderEstimate,
    Estop,
    Heartbeat,
    OdriveCanSimple,
    OdriveDriver,
    Request,
    SetAxisState,
    SetControllerMode,
    SetInputTorque,
    arbitration_id,
)
from bridges.odrive_emulator import OdriveEmulator
from deploy.contract.scenario import load_scenario
from deploy.nodes.bridge import BridgeNode
from deploy.runtime.node_runtime import StopFlag

NODE_IDS = [0, 1, 2, 3]
SCENARIOS = ["lab", "paper"]  # a 2 N m torque limit, and none (inf)

float32 = st.one_of(st.floats(width=32), st.sampled_from([math.nan, math.inf, -math.inf, 1e4, 1e3]))


def pack_floats(*xs: float) -> bytes:
    return b"".join(np.float32(x).tobytes() for x in xs)  # overflow -> inf, as a sender might


@st.composite
def any_frame(draw: st.DrawFn) -> can.Message:
    """Anything python-can can carry, ids near ours more often than not."""
    ours = st.builds(arbitration_id, st.integers(0, 7), st.integers(0, 31))
    fd = draw(st.booleans()) if draw(st.integers(0, 9)) == 0 else False
    data = draw(st.binary(max_size=64 if fd else draw(st.sampled_from([8, 8, 8, 16]))))
    dlc = len(data) if draw(st.integers(0, 3)) else draw(st.integers(0, 64))
    return can.Message(
        arbitration_id=draw(st.one_of(ours, st.integers(0, 0x7FF), st.integers(0, 0x1FFFFFFF))),
        is_extended_id=draw(st.integers(0, 4)) == 0, is_remote_frame=draw(st.integers(0, 5)) == 0,
        is_error_frame=draw(st.integers(0, 9)) == 0, is_fd=fd, data=data, dlc=dlc)


@st.composite
def float_frame(draw: st.DrawFn) -> can.Message:
    """A torque or encoder frame for one of our nodes, floats anything, length 0-8."""
    node = draw(st.sampled_from(NODE_IDS))
    cmd = draw(st.sampled_from([CMD_SET_INPUT_TORQUE, CMD_GET_ENCODER_ESTIMATES]))
    data = pack_floats(draw(float32), draw(float32))[:draw(st.sampled_from([8, 8, 8, 4, 3, 0]))]
    return can.Message(arbitration_id=arbitration_id(node, cmd), is_extended_id=False, data=data)


@st.composite
def flipped_frame(draw: st.DrawFn) -> can.Message:
    """A frame of either direction with a few bits of its id, data or DLC flipped."""
    base = draw(st.sampled_from(VALID_FRAMES))
    data = bytearray(base.data)
    for _ in range(draw(st.integers(1, 3))):
        where = draw(st.sampled_from(["data", "data", "id", "dlc"]))
        if where == "data" and data:
            bit = draw(st.integers(0, 8 * len(data) - 1))
            data[bit // 8] ^= 1 << (bit % 8)
        elif where == "id":
            arb = base.arbitration_id ^ (1 << draw(st.integers(0, 10)))
            base = can.Message(arbitration_id=arb, is_extended_id=False, data=base.data)
    dlc = len(data) if draw(st.integers(0, 3)) else draw(st.integers(0, 15))
    return can.Message(arbitration_id=base.arbitration_id, is_extended_id=False,
                       is_remote_frame=base.is_remote_frame, data=bytes(data), dlc=dlc)


def _valid_frames() -> list[can.Message]:
    host, drive = OdriveCanSimple(NODE_IDS), OdriveCanSimple(NODE_IDS, role="drive")
    out = []
    for n in NODE_IDS[:2]:
        out += [host.encode(m) for m in (SetInputTorque(n, 1.5), SetAxisState(n, 8), ClearErrors(n),
                                         SetControllerMode(n, 1, 1), Estop(n), Request(n, 9))]
        out += [drive.encode(m) for m in (Heartbeat(n, 0x800, 8), EncoderEstimate(n, 12.5, -3.0),
                                          DriverErrors(n, 1, 2))]
        out += [host.encode(Request(n, c)) for c in (CMD_HEARTBEAT, CMD_GET_ERROR,
                                                     CMD_GET_BUS_VOLTAGE_CURRENT)]
    return out


VALID_FRAMES = _valid_frames()
frames = st.one_of(any_frame(), float_frame(), flipped_frame())


# --- the decoder ------------------------------------------------------------------------------
def counted(c: FrameCounters) -> int:
    return c.decoded + c.rejected


@pytest.mark.parametrize("role", ["host", "drive"])
@fuzz_settings(400)
@given(frame=frames)
def test_decoder(role: str, frame: can.Message) -> None:
    proto = OdriveCanSimple(NODE_IDS, role=role)  # type: ignore[arg-type]
    inner = OdriveCanSimple(NODE_IDS, role=role)  # type: ignore[arg-type]
    msg = fuzz_decoder(f"CAN decode ({role})", proto.decode, frame)
    assert counted(proto.counters) == 1, proto.counters
    assert inner._decode(frame) == msg  # the body itself never raises
    assert inner.counters == proto.counters  # and the catch-all counted nothing
    if msg is not None:
        assert proto.problem(msg) is None and not non_finite_floats(list(vars(msg).values()))
        if isinstance(msg, SetInputTorque):
            assert abs(msg.torque_nm) <= proto.max_abs_torque_nm


# --- the bridge's frame handling ----------------------------------------------------------------
@pytest.fixture(scope="module", params=SCENARIOS)
def bridge(request: pytest.FixtureRequest) -> Iterator[BridgeNode]:
    sc = load_scenario(request.param)
    bus = RecordingBus()
    b = BridgeNode(sc, 1, FakeNode(sc.robot_ids, "bridge-1"), StopFlag(), bus,
                   OdriveDriver(DriverSettings(tuple(NODE_IDS))), NODE_IDS)
    yield b
    b.close()
    bus.shutdown()


@fuzz_settings(150)
@given(batch=st.lists(frames, min_size=1, max_size=12))
def test_bridge_frame_handling(bridge: BridgeNode, batch: list[can.Message]) -> None:
    before = counted(bridge.protocol.counters)
    for frame in batch:
        bridge._frames.put((0.0, frame))

    def sample(_: object) -> bool:
        bridge._sample(0.0, 0.01)
        return True

    fuzz_decoder("CAN bridge frames", sample, batch)
    assert counted(bridge.protocol.counters) - before == len(batch)
    assert np.all(np.isfinite(bridge.odometry.q)) and np.all(np.isfinite(bridge.odometry.q_dot))
    assert np.all(np.isfinite(bridge.monitor.wheel_speeds_radps()))
    bridge.monitor.fault_reasons(0.0)


# --- the drive emulator ---------------------------------------------------------------------
ARM = [OdriveCanSimple(NODE_IDS).encode(m) for n in NODE_IDS for m in (
    ClearErrors(n), SetControllerMode(n, CONTROL_MODE_TORQUE_CONTROL, INPUT_MODE_PASSTHROUGH),
    SetAxisState(n, AXIS_STATE_CLOSED_LOOP_CONTROL))]
HARD = [OdriveCanSimple(NODE_IDS).encode(SetInputTorque(n, 1000.0 * (-1) ** n)) for n in NODE_IDS]


@pytest.fixture(scope="module", params=SCENARIOS)
def emulator(request: pytest.FixtureRequest) -> Iterator[tuple[OdriveEmulator, RecordingBus]]:
    bus = RecordingBus()
    yield OdriveEmulator(load_scenario(request.param), 1, bus, watchdog_timeout_s=0.0), bus
    bus.shutdown()


@fuzz_settings(150)
@given(batch=st.lists(frames, min_size=1, max_size=12), armed=st.booleans(), hard=st.booleans())
def test_emulator_frame_handling(emulator: tuple[OdriveEmulator, RecordingBus],
                                 batch: list[can.Message], armed: bool, hard: bool) -> None:
    """Armed or not, wheels driven at the protocol's torque bound or not, then any frames."""
    emu, bus = emulator
    fed = (ARM if armed else []) + (HARD if hard else []) + batch
    received, before = emu.counters.received, counted(emu.protocol.counters)
    bus.feed(fed)

    def step(_: object) -> bool:
        emu.step(emu.t + 0.005)
        return True

    fuzz_decoder("CAN emulator frames", step, batch)
    assert emu.counters.received - received == len(fed)
    assert counted(emu.protocol.counters) - before == len(fed)
    limit = min(emu.max_torque_nm, emu.protocol.max_abs_torque_nm)
    tau = emu.wheel_torques()
    assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limit), tau
    assert np.all(np.isfinite(emu.q)) and np.all(np.isfinite(emu.q_dot))
    assert np.all(np.isfinite(emu.wheel_rev))
    host = OdriveCanSimple(NODE_IDS)
    sent = [host.decode(f) for f in bus.sent]
    bus.sent.clear()
    assert all(m is not None for m in sent), host.counters  # what it answers decodes


def test_float_frames_pack_as_sent() -> None:
    assert struct.unpack("<f", pack_floats(1.5)) == (1.5,)


# --- cases the fuzzing found, pinned ----------------------------------------------------------
def test_emulator_survives_a_bus_current_it_cannot_encode() -> None:
    """Found: with paper.toml (no torque limit) and wheels at 1000 N m, a Get_Bus_Voltage_Current
    request made ``encode`` raise (bus current ~2e5 A beyond the protocol's bound) out of
    ``step``; the frame is now dropped and counted (the encoder frames of a wheel beyond
    1e4 rev/s would have done the same from the physics tick)."""
    bus = RecordingBus()
    emu = OdriveEmulator(load_scenario("paper"), 1, bus, watchdog_timeout_s=0.0)
    bus.feed(ARM + HARD)
    emu.step(0.5)
    assert np.all(np.abs(emu.wheel_speeds_radps()) > 1000.0)  # spinning hard
    bus.sent.clear()
    bus.feed([OdriveCanSimple(NODE_IDS).encode(Request(0, CMD_GET_BUS_VOLTAGE_CURRENT))])
    emu.step(0.5)
    assert emu.counters.unencodable == 1 and bus.sent == []
    bus.shutdown()
