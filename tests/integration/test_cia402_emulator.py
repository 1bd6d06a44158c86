"""CiA 402 drive emulator and the host driver on python-can's virtual bus.

The host's bring-up (NMT, SDO, PDO mapping) runs on canopen's SDO client, which waits
for answers: it runs on a thread while this one steps the emulator (its clock and its
answers). Everything after is driven by a virtual clock, as tests/integration/
test_can_emulator.py drives the ODrive emulator: each host period sends its frames
(torques, then SYNC), then the emulator steps 5 ms; no sleeps stand in for order.
"""

from __future__ import annotations

import math
import struct
import sys
import threading
import time
import uuid

import can
import msgspec
import numpy as np
import pytest

from bridges import cia402 as p
from bridges.cia402_driver import DEFAULT_EDS, Cia402Driver
from bridges.cia402_emulator import Cia402Emulator
from bridges.drive_emulator import EmulatorFaults
from bridges.driver import DriveError, DriverSettings, DriveState, WheelReport
from bridges.fleet_emulator import FleetEmulator
from deploy.contract.scenario import load_scenario
from deploy.nodes.emulator_cli import main as emulate_main
from plant.disturbance import make_disturbance
from plant.model_plant import ModelPlant

S = p.State
NODES = (1, 2, 3, 4)
DT = 0.005
ROBOT = 1
FORWARD = np.ones(4)


@pytest.fixture(scope="module")
def lab():
    return load_scenario("lab")


@pytest.fixture(scope="module")
def calm(lab):
    """lab without the disturbance: a torque-free robot can only slow down."""
    spec = msgspec.structs.replace(
        lab.spec, disturbance=msgspec.structs.replace(lab.spec.disturbance, kind="none"))
    return type(lab)(lab.path, spec, lab.adjacency, lab.leader_weights, lab.notes)


class Rig:
    """A host bus with the CiA 402 host driver, and the emulator, on one virtual channel."""

    def __init__(self, sc, host_ids=NODES, report_rate_hz=200.0, eds=None, **kw):
        channel = f"test-{uuid.uuid4()}"
        self.host_bus = can.Bus(interface="virtual", channel=channel)
        self.emu_bus = can.Bus(interface="virtual", channel=channel)
        self.emu = Cia402Emulator(sc, ROBOT, self.emu_bus, eds=eds, **kw)
        self.host = Cia402Driver(DriverSettings(host_ids, DT, sc.spec.limits.max_wheel_torque_nm,
                                                eds, report_rate_hz=report_rate_hz))
        self.now = 0.0
        self.raw: list[tuple[float, can.Message]] = []  # (the step that delivered it, frame)
        self.reports: list[tuple[float, WheelReport]] = []
        self.said: list[str] = []

    def bring_up(self, timeout_s: float = 20.0) -> None:
        """The host's bring-up on a thread; this one steps the emulator 1 ms at a time."""
        failed: list[BaseException] = []

        def run() -> None:
            try:
                self.host.bring_up(self.host_bus, timeout_s, self.said.append)
            except BaseException as exc:  # noqa: BLE001 - handed to the test
                failed.append(exc)

        t = threading.Thread(target=run)
        t.start()
        while t.is_alive():
            self.now = round(self.now + 0.001, 9)
            self.emu.step(self.now)
            t.join(0.0005)
        if failed:
            raise failed[0]

    def send(self, frames) -> None:
        for f in frames:
            self.host_bus.send(f)

    def period(self, torques=None, arm: bool = False, sync: bool = True, n: int = 1) -> None:
        """n host periods: arming frames (each drive not enabled), torques, SYNC and the
        host's heartbeat; then the emulator steps 5 ms and the host reads."""
        for _ in range(n):
            if arm:
                for node in self.host.node_ids:
                    if self.host.state(node) is not S.OPERATION_ENABLED:
                        self.send(self.host.clear_faults_frames(node))
                        self.send(self.host.arm_frames(node))
            if torques is not None:
                self.send([self.host.torque_frame(node, float(t))
                           for node, t in zip(self.host.node_ids, torques, strict=True)])
            frames = self.host.cycle_frames(self.now)
            self.send([f for f in frames if sync or f.arbitration_id != 0x80])
            self.now = round(self.now + DT, 9)
            self.emu.step(self.now)
            self.read()

    def read(self) -> None:
        while (f := self.host_bus.recv(timeout=0)) is not None:
            self.raw.append((self.now, f))
            r = self.host.decode(f)
            if r is not None:
                self.reports.append((self.now, r))

    def cycle_without_heartbeat(self, n: int) -> None:
        """n periods of SYNC only (the host's heartbeat stopped)."""
        for _ in range(n):
            self.send([can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)])
            self.now = round(self.now + DT, 9)
            self.emu.step(self.now)
            self.read()

    def last(self, node: int, what: str):
        vals = [getattr(r, what) for _, r in self.reports if r.node == node and getattr(r, what) is not None]
        return vals[-1]

    def enable(self, timeout_periods: int = 20) -> None:
        for _ in range(timeout_periods):
            self.period(np.zeros(4), arm=True)
            if all(self.host.state(n) is S.OPERATION_ENABLED for n in self.host.node_ids):
                return
        raise AssertionError(f"not enabled: {self.emu.states()}")

    def close(self) -> None:
        self.host_bus.shutdown()
        self.emu_bus.shutdown()


@pytest.fixture
def rig_factory():
    rigs = []

    def make(sc, bring_up=True, **kw):
        rigs.append(Rig(sc, **kw))
        if bring_up:
            rigs[-1].bring_up()
        return rigs[-1]

    yield make
    for r in rigs:
        r.close()


def reference_plant(sc, torque_schedule, t0, t_end):
    """eq. (4) for robot ROBOT with the given wheel torques, RK4 at 1 ms as the
    emulator, the disturbance from t0 (the drives' first enabling), sampled every 5 ms
    on the host's grid."""
    q, qd = sc.initial_state()
    i = sc.index_of(ROBOT)
    d = sc.spec.disturbance
    dist = make_disturbance(d.kind, d.scale, tuple(d.constant_nm))
    plant = ModelPlant([sc.model()], q[i:i + 1], qd[i:i + 1],
                       lambda t: np.asarray(dist(t - t0)).reshape(1, 4), substeps=1)
    out = {round(t0, 9): (plant.q[0].copy(), plant.q_dot[0].copy())}
    for k in range(int(round((t_end - t0) / 1e-3))):
        t = t0 + k * 1e-3
        plant.step(t, 1e-3, torque_schedule(t)[None, :], None)
        out[round(t + 1e-3, 9)] = (plant.q[0].copy(), plant.q_dot[0].copy())
    return out


# --- boot, NMT, bring-up -------------------------------------------------------------------
def test_boot_heartbeats_and_pdos_only_when_operational(lab, rig_factory):
    r = rig_factory(lab, bring_up=False)
    r.period(n=1)
    boot = [f for _, f in r.raw if f.arbitration_id & 0x780 == 0x700]
    assert sorted((f.arbitration_id, bytes(f.data)) for f in boot) == sorted(
        [(0x700 + n, b"\x00") for n in NODES] + [(0x700 + n, b"\x7f") for n in NODES])  # pre-op
    r.period(n=60)  # 0.3 s: heartbeats at the power-up 10 Hz, no PDO before NMT start
    beats = [t for t, f in r.raw if f.arbitration_id == 0x701 and bytes(f.data) == b"\x7f"]
    assert len(beats) == 4 and np.allclose(np.diff(beats[1:]), 0.1)  # t = 0 (read at 5 ms), 0.1, ...
    assert not [f for _, f in r.raw if 0x180 <= f.arbitration_id < 0x500]
    r.send([can.Message(arbitration_id=0, data=[1, 0], is_extended_id=False)])  # start all
    r.period(n=2)
    assert {r.host.describe(n).split(", ")[0] for n in NODES} == {"SWITCH ON DISABLED"}
    assert r.last(1, "state") is DriveState.DISABLED
    r.send([can.Message(arbitration_id=0, data=[0x80, 2], is_extended_id=False)])  # node 2 pre-op
    r.raw.clear()
    r.period(n=4)
    tpdo = {f.arbitration_id & 0x7F for _, f in r.raw if 0x180 <= f.arbitration_id < 0x300}
    assert tpdo == {1, 3, 4}
    r.send([can.Message(arbitration_id=0, data=[0x81, 3], is_extended_id=False)])  # reset node 3
    r.raw.clear()
    r.period(n=1)
    assert (0x703, b"\x00") in [(f.arbitration_id, bytes(f.data)) for _, f in r.raw]


def test_bring_up_configures_each_drive_and_reads_the_mapping_back(lab, rig_factory):
    r = rig_factory(lab, report_rate_hz=100.0)
    said = "\n".join(r.said)
    for n in NODES:
        d = r.emu.drive(n)
        assert d.operational and d.params.mode == p.MODE_CYCLIC_SYNC_TORQUE
        assert d.params.max_torque == 1000  # lab's 2 N m: 1000 per mille of 1 N m x 2
        assert d.params.consumers == ((127, 0.25),) and d.params.quick_stop_option == 2
        assert [lay.trans_type for lay in d.tpdos] == [2, 2]  # 100 Hz at a 200 Hz SYNC
        assert f"node {n}: NMT operational" in said
    assert "cyclic synchronous torque" in said and "read back" in said
    r.period(n=8)  # TPDOs on every 2nd SYNC
    assert len([f for _, f in r.raw if f.arbitration_id == 0x181]) == 4


def _two_syncs_in_one_tick(r) -> int:
    """Two SYNCs, the second due for the TPDOs (every 2nd), read in one step of the
    emulator: node 1's TPDO1 frames that came of them."""
    if r.emu.drive(1).syncs % 2 == 1:  # the next SYNC would be the due one: skip it
        r.period()
    sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
    r.send([sync, sync])
    before = len(r.raw)
    r.now = round(r.now + DT, 9)
    r.emu.step(r.now)
    r.read()
    return len([f for _, f in r.raw[before:] if f.arbitration_id == 0x181])


def test_two_syncs_within_a_tick_are_two_syncs_unless_the_emulator_reads_a_backlog(lab, rig_factory):
    """A bridge's late period, then its next on time: two SYNCs reach the emulator
    between two of its ticks. On time, the drives sample on each (the due one's TPDOs go
    out: shed, the bridge went 14-20 ms without encoder data); more than a tick behind the
    wall clock (reading what queued while it was off the CPU), the second samples nothing
    new and its TPDOs are shed and counted."""
    r = rig_factory(lab, report_rate_hz=100.0)
    r.period(n=4)
    assert _two_syncs_in_one_tick(r) == 1  # a virtual clock is never behind
    shed = r.emu.counters.shed
    r.emu.monotonic_origin_s = time.monotonic() - r.emu.t - 1.0  # 1 s behind the wall clock
    assert _two_syncs_in_one_tick(r) == 0
    assert r.emu.counters.shed > shed


def test_bring_up_names_a_drive_that_does_not_answer(lab, rig_factory, monkeypatch):
    from bridges import cia402_driver

    # what a silent drive costs is SDO_TIMEOUT_S a try: shorter here, the same refusal
    monkeypatch.setattr(cia402_driver, "SDO_TIMEOUT_S", 0.2)
    # the silent drive first: the refusal does not wait on the others' configuration,
    # which took the whole second on a machine busy with other tests
    r = rig_factory(lab, bring_up=False, host_ids=(5, 1, 2, 3))
    with pytest.raises(DriveError, match="node 5: SDO failed"):
        r.bring_up(timeout_s=1.0)


def test_bring_up_refuses_a_drive_that_is_not_cia_402(lab, rig_factory, tmp_path):
    eds = tmp_path / "io.eds"
    eds.write_text(DEFAULT_EDS.read_text().replace("DefaultValue=0x00020192", "DefaultValue=0x00000191"))
    r = rig_factory(lab, bring_up=False, eds=str(eds))
    with pytest.raises(DriveError, match=r"node 1: device type 0x00000191 is not a CiA 402 drive"):
        r.bring_up()


# --- the state machine on the bus ---------------------------------------------------------
def test_every_transition_the_bridge_drives_and_no_torque_unless_enabled(lab, rig_factory):
    r = rig_factory(lab)
    seen = []
    for _ in range(6):  # arming: one transition per status
        r.period(FORWARD * 0.5, arm=True)
        seen.append(r.emu.drive(1).state)
        if seen[-1] is not S.OPERATION_ENABLED:
            assert np.all(r.emu.wheel_torques() == 0.0)  # torque frames sent, none applied
    assert seen[:3] == [S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED]  # 2, 3, 4
    r.period(FORWARD * 0.5)
    assert np.allclose(r.emu.wheel_torques(), 0.5)
    assert r.last(1, "state") is DriveState.ENABLED
    assert r.last(1, "torque_nm") == pytest.approx(0.5)  # torque actual, per mille at the wheel
    r.send(r.host.disarm_frames(1))  # shutdown: transition 8
    r.period()
    assert r.emu.drive(1).state is S.READY_TO_SWITCH_ON and r.emu.wheel_torques()[0] == 0.0
    for cw, want in ((0x07, S.SWITCHED_ON), (0x0F, S.OPERATION_ENABLED), (0x07, S.SWITCHED_ON),
                     (0x06, S.READY_TO_SWITCH_ON), (0x00, S.SWITCH_ON_DISABLED)):  # 3, 4, 5, 6, 7
        r.send([can.Message(arbitration_id=0x202, data=struct.pack("<Hh", cw, 0), is_extended_id=False)])
        r.period()
        assert r.emu.drive(2).state is want


def test_forward_torque_encoders_match_the_model_plant(lab, rig_factory):
    """All wheels +0.25 N m from the drives' enabling for 1 s: the TPDOs' wheel speeds
    are eq. (4)'s (to the increment), the emulator's truth is the reference's."""
    tau = 0.25
    r = rig_factory(lab)
    r.enable()
    t0 = r.emu.drive(1).enabled_at
    start = r.now
    r.period(FORWARD * tau, n=200)
    ref = reference_plant(lab, lambda t: FORWARD * tau * (t >= start - 1e-9), t0, r.now)
    model = lab.model()
    worst = 0.0
    for t, rep in r.reports:
        if rep.velocity_rev_s is None or t <= start:
            continue
        q, qd = ref[round(t - DT, 9)]  # sampled at the SYNC, sent at the start of the step
        w = model.wheel_speeds(float(q[2]), qd)[NODES.index(rep.node)] / (2 * math.pi)
        worst = max(worst, abs(rep.velocity_rev_s - w))
    assert worst <= 0.5 / 8192 + 1e-9  # increments per second: rounding only
    np.testing.assert_allclose(r.emu.q, ref[round(r.now, 9)][0], rtol=0, atol=1e-9)
    dx = r.emu.q[0] - lab.initial_state()[0][0][0]
    pos = [r.last(n, "position_rev") for n in NODES]
    assert dx > 0.5 and np.mean(pos) == pytest.approx(
        dx / (2 * math.pi * lab.spec.robot.wheel_radius_m), rel=0.01)


def test_torque_is_clamped_by_max_torque_and_the_scenario_limit(lab, rig_factory):
    r = rig_factory(lab)
    r.enable()
    r.period(np.array([50.0, -3.0, 1.0, 0.0]))  # 25000 per mille: the drive's max torque holds
    assert np.allclose(r.emu.wheel_torques(), [2.0, -2.0, 1.0, 0.0])  # 0x6072 = 1000: 2 N m
    with pytest.raises(ValueError):  # beyond what an int16 per mille carries: never sent
        r.host.torque_frame(1, 70.0)
    r.send([r.host.torque_frame(1, 0.5)])  # and the scenario's limit binds the emulated wheel
    r.emu.drive(1).node.sdo[p.MAX_TORQUE].raw = 2000
    r.period()
    assert r.emu.wheel_torques()[0] == 0.5
    r.send([r.host.torque_frame(1, 3.0)])
    r.period()
    assert r.emu.wheel_torques()[0] == 2.0


def test_a_parameter_written_acts_on_the_target_the_drive_holds(lab, rig_factory):
    """The drive keeps its target torque in N m between writes: a parameter written
    after it (0x6072, 0x6060) changes the torque applied without a new target."""
    r = rig_factory(lab)
    r.enable()
    r.period(np.array([1.5, -1.5, 0.5, 0.0]))
    assert np.allclose(r.emu.wheel_torques(), [1.5, -1.5, 0.5, 0.0])
    r.emu.drive(1).node.sdo[p.MAX_TORQUE].raw = 500  # 1 N m (2 N m at 1000 per mille)
    r.emu.drive(2).node.sdo[p.MODES_OF_OPERATION].raw = 0  # no mode: no torque
    r.period()
    assert np.allclose(r.emu.wheel_torques(), [1.0, 0.0, 0.5, 0.0])
    r.emu.drive(2).node.sdo[p.MODES_OF_OPERATION].raw = p.MODE_CYCLIC_SYNC_TORQUE
    r.emu.drive(1).node.sdo[p.MAX_TORQUE].raw = 1000
    r.period()
    assert np.allclose(r.emu.wheel_torques(), [1.5, -1.5, 0.5, 0.0])


def test_a_lost_sync_faults_the_enabled_drive_and_a_fault_reset_recovers_it(calm, rig_factory):
    r = rig_factory(calm, watchdog_timeout_s=0.2)
    r.enable()
    r.period(FORWARD * 0.3, n=20)
    t_last = r.now - DT  # the last SYNC was applied at the start of the last step
    r.period(FORWARD * 0.3, sync=False, n=39)  # torques and heartbeats, no SYNC: 0.195 s
    assert all(s is S.OPERATION_ENABLED for s in r.emu.states())
    r.period(FORWARD * 0.3, sync=False, n=2)
    assert all(s is S.FAULT for s in r.emu.states()) and np.all(r.emu.wheel_torques() == 0.0)
    emcy = [struct.unpack_from("<H", bytes(f.data))[0] for _, f in r.raw if f.arbitration_id == 0x81]
    assert emcy == [p.ERROR_COMMUNICATION]
    r.period(n=1)  # the status says so, with the code: recoverable (the host fell silent)
    rep = [x for _, x in r.reports if x.node == 1 and x.state is not None][-1]
    assert (rep.state, rep.fault, rep.recoverable) == (DriveState.FAULT, 0x8100, True)
    assert r.now - t_last > 0.2
    r.enable()  # fault reset (15), then 2, 3, 4
    assert [struct.unpack_from("<H", bytes(f.data))[0] for _, f in r.raw if f.arbitration_id == 0x81][-1] == 0
    r.period(FORWARD * 0.3)
    assert np.allclose(r.emu.wheel_torques(), 0.3)


def test_a_lost_host_heartbeat_faults_the_enabled_drive(calm, rig_factory):
    r = rig_factory(calm, watchdog_timeout_s=0.0)
    r.enable()
    r.period(FORWARD * 0.1, n=4)
    r.cycle_without_heartbeat(40)  # 0.2 s: within the 250 ms consumer time
    assert all(s is S.OPERATION_ENABLED for s in r.emu.states())
    r.cycle_without_heartbeat(20)
    assert all(s is S.FAULT for s in r.emu.states())
    assert {d.error_code for d in r.emu.drives} == {p.ERROR_HEARTBEAT}


def test_quick_stop_ramps_the_torque_down_then_switches_off(calm, rig_factory):
    r = rig_factory(calm)
    r.enable()
    r.period(FORWARD * 1.0, n=10)
    for n in NODES:
        r.send(r.host.estop_frames(n))
    r.period()
    assert all(s is S.QUICK_STOP_ACTIVE for s in r.emu.states())
    assert r.last(1, "state") is DriveState.STOPPING
    # torque slope 10000 per mille/s = 20 N m/s at the wheel: 1 N m to 0 in 50 ms
    torques = []
    for _ in range(12):
        r.period(FORWARD * 1.0)  # a later torque frame carries the quick stop on
        torques.append(r.emu.wheel_torques()[0])
    assert np.all(np.diff(torques[:9]) < 0) and torques[-1] == 0.0
    assert all(s is S.SWITCH_ON_DISABLED for s in r.emu.states())  # option code 2
    for n in NODES:
        r.send(r.host.disarm_frames(n))  # a disarm after an e-stop holds the quick stop
    r.period(n=2)
    assert all(s is S.SWITCH_ON_DISABLED for s in r.emu.states())


def test_a_drive_that_refuses_to_enable_stays_switched_on(lab, rig_factory):
    r = rig_factory(lab, faults=EmulatorFaults(refuse_enable_node=3))
    for _ in range(20):
        r.period(FORWARD * 0.5, arm=True)
    assert r.emu.states() == [S.OPERATION_ENABLED, S.OPERATION_ENABLED, S.SWITCHED_ON,
                              S.OPERATION_ENABLED]
    assert r.emu.wheel_torques()[2] == 0.0 and r.last(3, "state") is DriveState.STARTING


def test_a_synchronous_rpdo_is_applied_at_the_next_sync(lab, rig_factory, tmp_path):
    eds = tmp_path / "sync.eds"
    text = DEFAULT_EDS.read_text().replace(
        "ParameterName=Transmission type\nObjectType=0x7\nDataType=0x0005\nAccessType=rw\n"
        "DefaultValue=255", "ParameterName=Transmission type\nObjectType=0x7\nDataType=0x0005\n"
        "AccessType=rw\nDefaultValue=1")
    eds.write_text(text)
    r = rig_factory(lab, eds=str(eds))
    r.enable(timeout_periods=40)
    r.send([r.host.torque_frame(n, 0.4) for n in NODES])
    r.now = round(r.now + DT, 9)
    r.emu.step(r.now)  # received, not applied: no SYNC yet
    assert np.all(r.emu.wheel_torques() == 0.0)
    r.period()
    assert np.allclose(r.emu.wheel_torques(), 0.4)


def test_drop_rate_one_loses_everything(lab, rig_factory):
    r = rig_factory(lab, bring_up=False, faults=EmulatorFaults(drop_rate=1.0))
    r.period(FORWARD, n=50)
    assert r.raw == [] and r.emu.counters.sent == 0 and r.emu.counters.dropped_by_fault > 50


# --- several robots in one process: the same dynamics as the ODrive emulator ---------------
def test_fleet_emulator_equals_one_cia402_emulator_per_robot(lab):
    robots = lab.robot_ids
    chans = [f"t-{uuid.uuid4()}" for _ in range(2 * len(robots))]
    buses = [can.Bus(interface="virtual", channel=c) for c in chans for _ in range(2)]
    hosts, emus = buses[0::2], buses[1::2]
    try:
        fleet = FleetEmulator(lab, list(zip(robots, emus[:3], strict=True)), NODES, 200.0, 10.0,
                              0.0, 200.0, emulator=Cia402Emulator)
        singles = [Cia402Emulator(lab, rid, b, NODES, 200.0, 10.0, 0.0, 200.0)
                   for rid, b in zip(robots, emus[3:], strict=True)]
        drivers = [Cia402Driver(DriverSettings(NODES)) for _ in range(6)]
        torque = {1: 0.4, 2: -0.3, 3: 0.0}
        for k in range(1, 201):
            for i, rid in enumerate(robots):
                for h, d in ((hosts[i], drivers[i]), (hosts[3 + i], drivers[3 + i])):
                    if k == 1:  # NMT start and mode 10 by SDO (expedited download, 1 byte)
                        h.send(can.Message(arbitration_id=0, data=[1, 0], is_extended_id=False))
                        for n in NODES:
                            h.send(can.Message(arbitration_id=0x600 + n, data=[0x2F, 0x60, 0x60, 0,
                                                                               10, 0, 0, 0],
                                               is_extended_id=False))
                    while (f := h.recv(timeout=0)) is not None:
                        d.decode(f)
                    for n in NODES:
                        if k < 12:
                            for f in d.arm_frames(n):
                                h.send(f)
                        h.send(d.torque_frame(n, torque[rid]))
                    for f in d.cycle_frames(k * DT):
                        h.send(f)
            fleet.step(k * DT)
            for e in singles:
                e.step(k * DT)
        for e, one in zip(fleet.emulators, singles, strict=True):
            np.testing.assert_allclose(e.q, one.q, rtol=0, atol=1e-12)
            assert list(e.wheel_rev) == pytest.approx(list(one.wheel_rev), abs=1e-12)
            assert e.counters.sent == one.counters.sent
        assert fleet.emulators[0].q[0] > lab.initial_state()[0][0][0] + 0.1  # robot 1 went forward
    finally:
        for b in buses:
            b.shutdown()


# --- the command line -------------------------------------------------------------------------
@pytest.mark.parametrize(("argv", "names"), [
    (["--node-ids", "0,1,2,3"], "--node-ids 0,1,2,3"),
    (["--node-ids", "1,2,3,128"], "--node-ids"),
    (["--refuse-enable", "9"], "--refuse-enable 9"),
    (["--eds", "/no/such/file.eds"], "/no/such/file.eds"),
])
def test_cli_bad_input_exits_2_naming_it(argv, names, capsys):
    base = ["--scenario", "lab", "--robot", "1", "--driver", "cia402", "--can-interface", "virtual",
            "--can-channel", f"test-{uuid.uuid4()}", "--duration", "0.01"]
    with pytest.raises(SystemExit) as exc:
        sys.exit(emulate_main([*base, *argv]))
    err = capsys.readouterr().err
    assert exc.value.code == 2 and names in err and "Traceback" not in err


def test_cli_a_bad_eds_exits_2_naming_it(tmp_path, capsys):
    eds = tmp_path / "broken.eds"
    eds.write_text(DEFAULT_EDS.read_text().replace("[6040]", "[6999]"))
    code = emulate_main(["--scenario", "lab", "--robot", "1", "--driver", "cia402",
                         "--can-interface", "virtual", "--can-channel", f"t-{uuid.uuid4()}",
                         "--duration", "0.01", "--eds", str(eds)])
    err = capsys.readouterr().err
    assert code == 2 and str(eds) in err and "0x6040" in err


def test_cli_runs_cia402_drives_for_a_duration(tmp_path, capsys):
    out = tmp_path / "truth.npz"
    t = time.monotonic()
    code = emulate_main(["--scenario", "lab", "--robot", "2", "--driver", "cia402",
                         "--can-interface", "virtual", "--can-channel", f"t-{uuid.uuid4()}",
                         "--duration", "0.1", "--truth-out", str(out)])
    assert code == 0 and time.monotonic() - t < 30
    err = capsys.readouterr().err
    assert "cia402 drives 1,2,3,4" in err
    assert "1: SWITCH ON DISABLED, error 0x0000, NMT PRE-OPERATIONAL" in err
    # the truth at the encoder rate (200 Hz) over 0.1 s: 21 samples when the emulator kept
    # the clock; a host that took the CPU away for more than behind_s (20 ms) sheds the stale
    # samples of its catch-up (FleetEmulator.step), so judge the samples by that rule
    t = np.load(out)["t"]
    assert t[0] == 0.0 and np.all(np.diff(t) > 0) and 0.095 - 1e-9 <= t[-1] <= 0.1 + 1e-9
    assert np.diff(t).max() <= 0.005 + 0.02 + 1e-9, np.diff(t)
    assert len(t) <= 21


# --- the bridge's e-stop is the drives' own quick stop, held ----------------------------------
def test_the_bridges_e_stop_is_each_drives_quick_stop_and_a_disarm_keeps_it(lab):
    from fuzz_fakes import FakeNode, RecordingBus

    from deploy.contract.wire import WIRE_VERSION, Control
    from deploy.nodes.bridge import BridgeNode
    from deploy.runtime.node_runtime import StopFlag

    bus = RecordingBus()
    b = BridgeNode(lab, 1, FakeNode(lab.robot_ids, "bridge-1"), StopFlag(), bus,
                   Cia402Driver(DriverSettings(NODES)), list(NODES))
    try:
        b._on_ctl(Control(WIRE_VERSION, 0, 0, 0, command="estop"))
        b.disarm()  # what the loop does next, on the gate's "estop"

        def controlwords(frames):
            return {(f.arbitration_id - 0x200, struct.unpack("<Hh", bytes(f.data))) for f in frames}

        first, rest = bus.sent[:4], bus.sent[4:]
        assert controlwords(first) == {(n, (0x02, 0)) for n in NODES}  # quick stop (11)
        assert controlwords(rest) == {(n, (0x02, 0)) for n in NODES}  # held, zero target
        assert b.gate.estopped
    finally:
        b.close()
        bus.shutdown()


def test_the_bridge_drives_no_wheel_until_every_drive_is_enabled_and_gives_up_on_one(lab):
    """The gate behind every protocol (deploy/nodes/bridge.py), fed neutral reports."""
    from fuzz_fakes import FakeNode, RecordingBus

    from bridges.safety import Decision
    from deploy.nodes.bridge import ENABLE_TIMEOUT_S, MIN_ARMING_ATTEMPTS, BridgeNode
    from deploy.runtime.node_runtime import StopFlag

    bus = RecordingBus()
    b = BridgeNode(lab, 1, FakeNode(lab.robot_ids, "bridge-1"), StopFlag(), bus,
                   Cia402Driver(DriverSettings(NODES)), list(NODES), heartbeat_timeout_s=1e9)
    try:
        b.arm()
        t0 = b.armed_at
        for n in NODES:  # three drives enabled, drive 3 stuck in SWITCHED ON
            state = DriveState.STARTING if n == 3 else DriveState.ENABLED
            b.monitor.feed(WheelReport(n, state=state, fault=0), t0 + 0.01)

        def torques_sent():
            frames, bus.sent[:] = list(bus.sent), []
            return [struct.unpack("<Hh", bytes(f.data))[1] for f in frames if f.arbitration_id >= 0x200]

        bus.sent.clear()
        b._apply(Decision((0.5,) * 4, True, "command"))
        assert torques_sent() == [0, 0, 0, 0]  # refused: one drive is not enabled
        b._rearm_idle_axes(t0 + 0.02)  # drive 3 asked again (its status came after arming)
        assert b.rearms == 1 and not b.monitor.faulted(t0 + 0.02)
        for k in range(2, 8):  # many answered attempts within 2 s of being seen not enabled:
            b.monitor.feed(WheelReport(3, state=DriveState.STARTING, fault=0), t0 + 0.02 * k)
            b._rearm_idle_axes(t0 + 0.02 * k)  # (a recoverable fault's reset and re-arm)
        assert b.arm_attempts[3] == 7 and not b.monitor.given_up
        late = t0 + ENABLE_TIMEOUT_S + 0.5  # 2 s on, still not enabled, 7 attempts answered
        assert b.arm_attempts[3] >= MIN_ARMING_ATTEMPTS
        b.monitor.feed(WheelReport(3, state=DriveState.STARTING, fault=0), late + 0.05)
        b._rearm_idle_axes(late + 0.1)
        assert b.monitor.faulted(late + 0.1)  # given up: faulted for good
        assert "node 3: not enabled" in b.monitor.fault_reasons(late + 0.1)[0]
        assert not [n for n in (1, 2, 4) if n in b.monitor.given_up]
        b.monitor.feed(WheelReport(3, state=DriveState.ENABLED, fault=0), t0 + 3.0)
        bus.sent.clear()
        b._apply(Decision((0.5,) * 4, True, "command"))
        assert torques_sent() == [250] * 4  # every drive enabled: torques go out
        assert b.monitor.faulted(t0 + 3.0)  # and the robot stays faulted: the gate zeroes it
    finally:
        b.close()
        bus.shutdown()


def test_the_bridge_does_not_give_up_on_drives_that_do_not_answer(lab):
    """No status at all (a starved emulator, a cable): the robot is faulted for the
    missing status, until the drives answer; nothing is latched."""
    from fuzz_fakes import FakeNode, RecordingBus

    from deploy.nodes.bridge import ENABLE_TIMEOUT_S, BridgeNode
    from deploy.runtime.node_runtime import StopFlag

    bus = RecordingBus()
    b = BridgeNode(lab, 1, FakeNode(lab.robot_ids, "bridge-1"), StopFlag(), bus,
                   Cia402Driver(DriverSettings(NODES)), list(NODES), heartbeat_timeout_s=0.35)
    try:
        b.arm()
        for k in range(1, 11):
            b._rearm_idle_axes(b.armed_at + k * ENABLE_TIMEOUT_S / 2)
        later = b.armed_at + 5 * ENABLE_TIMEOUT_S
        assert not b.monitor.given_up and b.rearms == 0
        assert b.monitor.faulted(later) and "no status" in b.monitor.fault_reasons(later)[0]
        for n in NODES:
            b.monitor.feed(WheelReport(n, state=DriveState.ENABLED, fault=0), later)
        assert not b.monitor.faulted(later + 0.01)
    finally:
        b.close()
        bus.shutdown()
