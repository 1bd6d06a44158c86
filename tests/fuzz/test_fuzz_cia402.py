"""Fuzzing the CiA 402 frame handling as tests/fuzz/test_fuzz_can.py fuzzes ODrive's:
the host driver's decoding, the bridge's frame handling through it (decoder -> monitor
-> odometry) and the CiA 402 drive emulator (canopen's SDO server and NMT slave behind
it).

Properties, whatever the frames (any id, standard or extended, remote, error and FD
frames, 0-64 data bytes, a DLC that disagrees with the data, valid frames with bits
flipped, statuswords of no state, positions at the int32 edges):
- ``decode`` never raises, and neither does its body; every frame is counted exactly
  once; what it returns is a wheel report with finite numbers and a known state;
- the bridge's odometry and wheel speeds stay finite;
- the emulator applies finite wheel torques within the scenario's limit, its robot
  state stays finite, it counts every frame, and what it sends the host decodes.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator

import can
import numpy as np
import pytest
from fuzz_fakes import FakeNode, RecordingBus
from fuzzing import fuzz_decoder, fuzz_settings
from hypothesis import given
from hypothesis import strategies as st

from bridges.cia402_driver import Cia402Driver
from bridges.cia402_emulator import Cia402Emulator
from bridges.driver import DriverSettings, FrameCounters, WheelReport
from deploy.contract.scenario import load_scenario
from deploy.nodes.bridge import BridgeNode
from deploy.runtime.node_runtime import StopFlag

NODE_IDS = (1, 2, 3, 4)
SCENARIOS = ["lab", "paper"]  # a 2 N m torque limit, and none (inf)
# the COB-IDs of this bus: NMT, SYNC, EMCY, TPDO1-2, RPDO1, SDO, heartbeats, for our nodes
OURS = [0x000, 0x080, *(base + n for n in (*NODE_IDS, 5, 127)
                        for base in (0x080, 0x180, 0x200, 0x280, 0x580, 0x600, 0x700))]
INT32_EDGES = [0, 1, -1, 2**31 - 1, -(2**31), 8192, -8192]


def _counted(c: FrameCounters) -> int:
    return c.decoded + c.rejected


@st.composite
def any_frame(draw: st.DrawFn) -> can.Message:
    """Anything python-can can carry, ids of this bus more often than not."""
    fd = draw(st.booleans()) if draw(st.integers(0, 9)) == 0 else False
    data = draw(st.binary(max_size=64 if fd else draw(st.sampled_from([8, 8, 8, 16]))))
    dlc = len(data) if draw(st.integers(0, 3)) else draw(st.integers(0, 64))
    return can.Message(
        arbitration_id=draw(st.one_of(st.sampled_from(OURS), st.integers(0, 0x7FF),
                                      st.integers(0, 0x1FFFFFFF))),
        is_extended_id=draw(st.integers(0, 4)) == 0, is_remote_frame=draw(st.integers(0, 5)) == 0,
        is_error_frame=draw(st.integers(0, 9)) == 0, is_fd=fd, data=data, dlc=dlc)


@st.composite
def pdo_frame(draw: st.DrawFn) -> can.Message:
    """A TPDO or RPDO of ours with any values, at the int32 edges often, length 0-8."""
    node = draw(st.sampled_from(NODE_IDS))
    kind = draw(st.sampled_from(["status", "motion", "rpdo"]))
    if kind == "status":
        data = struct.pack("<HhH", draw(st.integers(0, 0xFFFF)), draw(st.integers(-32768, 32767)),
                           draw(st.integers(0, 0xFFFF)))
        cob = 0x180 + node
    elif kind == "motion":
        i32 = st.one_of(st.sampled_from(INT32_EDGES), st.integers(-(2**31), 2**31 - 1))
        data, cob = struct.pack("<ii", draw(i32), draw(i32)), 0x280 + node
    else:
        data = struct.pack("<Hh", draw(st.integers(0, 0xFFFF)), draw(st.integers(-32768, 32767)))
        cob = 0x200 + node
    data = data[:draw(st.sampled_from([8, 8, 8, 6, 4, 3, 0]))]
    return can.Message(arbitration_id=cob, is_extended_id=False, data=data)


@st.composite
def flipped_frame(draw: st.DrawFn) -> can.Message:
    """A valid frame of either direction with a few bits of its id, data or DLC flipped."""
    base = draw(st.sampled_from(VALID_FRAMES))
    data = bytearray(base.data)
    arb = base.arbitration_id
    for _ in range(draw(st.integers(1, 3))):
        where = draw(st.sampled_from(["data", "data", "id", "dlc"]))
        if where == "data" and data:
            bit = draw(st.integers(0, 8 * len(data) - 1))
            data[bit // 8] ^= 1 << (bit % 8)
        elif where == "id":
            arb ^= 1 << draw(st.integers(0, 10))
    dlc = len(data) if draw(st.integers(0, 3)) else draw(st.integers(0, 15))
    return can.Message(arbitration_id=arb, is_extended_id=False, data=bytes(data), dlc=dlc)


def _valid_frames() -> list[can.Message]:
    host = Cia402Driver(DriverSettings(NODE_IDS))
    out = []
    for n in NODE_IDS[:2]:
        out += [host.torque_frame(n, 1.5), *host.arm_frames(n), *host.estop_frames(n),
                *host.disarm_frames(n),
                can.Message(arbitration_id=0x180 + n, data=struct.pack("<HhH", 0x237, 250, 0),
                            is_extended_id=False),
                can.Message(arbitration_id=0x280 + n, data=struct.pack("<ii", 81920, -4096),
                            is_extended_id=False),
                can.Message(arbitration_id=0x600 + n, data=bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]),
                            is_extended_id=False),  # SDO upload of the statusword
                can.Message(arbitration_id=0x600 + n, data=bytes([0x2F, 0x60, 0x60, 0, 10, 0, 0, 0]),
                            is_extended_id=False),  # SDO download: mode 10
                can.Message(arbitration_id=0x700 + n, data=b"\x05", is_extended_id=False)]
    out += [*host.cycle_frames(0.0), can.Message(arbitration_id=0, data=[1, 0], is_extended_id=False),
            can.Message(arbitration_id=0, data=[0x81, 1], is_extended_id=False)]
    return out


VALID_FRAMES = _valid_frames()
frames = st.one_of(any_frame(), pdo_frame(), flipped_frame())


def _check_report(r: WheelReport) -> None:
    assert isinstance(r, WheelReport) and r.node in NODE_IDS
    for x in (r.position_rev, r.velocity_rev_s, r.torque_nm):
        assert x is None or math.isfinite(x)
    assert r.fault is None or 0 <= r.fault <= 0xFFFF


# --- the decoder ------------------------------------------------------------------------------
@fuzz_settings(400)
@given(frame=frames)
def test_decoder(frame: can.Message) -> None:
    d = Cia402Driver(DriverSettings(NODE_IDS))
    inner = Cia402Driver(DriverSettings(NODE_IDS))
    r = fuzz_decoder("CiA 402 decode (host)", d.decode, frame, check=_check_report)
    assert _counted(d.counters) == 1, d.counters
    assert inner._decode(frame) == r  # the body itself never raises
    assert inner.counters == d.counters  # and the catch-all counted nothing


# --- the bridge's frame handling ---------------------------------------------------------------
@pytest.fixture(scope="module", params=SCENARIOS)
def bridge(request: pytest.FixtureRequest) -> Iterator[BridgeNode]:
    sc = load_scenario(request.param)
    bus = RecordingBus()
    b = BridgeNode(sc, 1, FakeNode(sc.robot_ids, "bridge-1"), StopFlag(), bus,
                   Cia402Driver(DriverSettings(NODE_IDS)), list(NODE_IDS))
    yield b
    b.close()
    bus.shutdown()


@fuzz_settings(150)
@given(batch=st.lists(frames, min_size=1, max_size=12))
def test_bridge_frame_handling(bridge: BridgeNode, batch: list[can.Message]) -> None:
    before = _counted(bridge.protocol.counters)
    for frame in batch:
        bridge._frames.put((0.0, frame))

    def sample(_: object) -> bool:
        bridge._sample(0.0, 0.01)
        return True

    fuzz_decoder("CiA 402 bridge frames", sample, batch)
    assert _counted(bridge.protocol.counters) - before == len(batch)
    assert np.all(np.isfinite(bridge.odometry.q)) and np.all(np.isfinite(bridge.odometry.q_dot))
    assert np.all(np.isfinite(bridge.monitor.wheel_speeds_radps()))
    bridge.monitor.fault_reasons(0.0)


# --- the drive emulator -------------------------------------------------------------------
def _enable_frames() -> list[can.Message]:
    """NMT start, mode 10 by SDO, shutdown / switch on / enable operation, a hard torque."""
    out = [can.Message(arbitration_id=0, data=[1, 0], is_extended_id=False)]
    for n in NODE_IDS:
        out.append(can.Message(arbitration_id=0x600 + n, data=bytes([0x2F, 0x60, 0x60, 0, 10, 0, 0, 0]),
                               is_extended_id=False))
    return out


def _rpdo(n: int, cw: int, torque_pm: int) -> can.Message:
    return can.Message(arbitration_id=0x200 + n, data=struct.pack("<Hh", cw, torque_pm),
                       is_extended_id=False)


@pytest.fixture(scope="module", params=SCENARIOS)
def emulator(request: pytest.FixtureRequest) -> Iterator[tuple[Cia402Emulator, RecordingBus]]:
    bus = RecordingBus()
    emu = Cia402Emulator(load_scenario(request.param), 1, bus, watchdog_timeout_s=0.0)
    yield emu, bus
    bus.shutdown()


@fuzz_settings(150)
@given(batch=st.lists(frames, min_size=1, max_size=12), armed=st.booleans(), hard=st.booleans())
def test_emulator_frame_handling(emulator: tuple[Cia402Emulator, RecordingBus],
                                 batch: list[can.Message], armed: bool, hard: bool) -> None:
    """Enabled or not, wheels driven at the per-mille bound or not, then any frames."""
    emu, bus = emulator
    fed = []
    if armed:
        fed += _enable_frames() + [_rpdo(n, cw, 0) for cw in (0x80, 0x06, 0x07, 0x0F) for n in NODE_IDS]
    if hard:
        fed += [_rpdo(n, 0x0F, 32767 * (-1) ** n) for n in NODE_IDS]
    received, before = emu.counters.received, _counted(emu.counters.protocol)
    bus.feed(fed + batch)

    def step(_: object) -> bool:
        emu.step(emu.t + 0.005)
        return True

    fuzz_decoder("CiA 402 emulator frames", step, batch)
    assert emu.counters.received - received == len(fed) + len(batch)
    assert _counted(emu.counters.protocol) - before == len(fed) + len(batch)
    tau = emu.wheel_torques()
    assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= min(emu.max_torque_nm, 32767 * 0.002))
    assert np.all(np.isfinite(emu.q)) and np.all(np.isfinite(emu.q_dot))
    assert np.all(np.isfinite(emu.wheel_rev))
    host = Cia402Driver(DriverSettings(NODE_IDS))
    sent = [host.decode(f) for f in bus.sent]
    bus.sent.clear()
    assert all(r is not None for r in sent), host.counters  # what it answers decodes
