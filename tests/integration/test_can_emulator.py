"""Driver emulator on python-can's virtual bus, driven by a virtual clock (no sleeps).

A host Bus and the emulator's Bus share one virtual channel. Each test steps the
emulator in 5 ms increments (a 200 Hz host), sending the host's frames before
each step: they are applied at the start of that step's interval.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import cantools
import msgspec
import numpy as np
import pytest

from bridges.drive_emulator import EmulatorFaults, flip_bits
from bridges.fleet_emulator import FleetEmulator
from bridges.odrive import (
    AXIS_ERROR_ESTOP_REQUESTED,
    AXIS_ERROR_INVALID_STATE,
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    AXIS_STATE_IDLE,
    CMD_GET_BUS_VOLTAGE_CURRENT,
    CMD_GET_ERROR,
    DBC_PATH,
    BusVoltageCurrent,
    ClearErrors,
    DriverErrors,
    EncoderEstimate,
    Estop,
    Heartbeat,
    OdriveCanSimple,
    Request,
    SetAxisState,
)
from bridges.odrive_emulator import OdriveEmulator
from deploy.contract.scenario import load_scenario
from deploy.nodes.emulator_cli import main as emulate_main
from plant.disturbance import make_disturbance
from plant.model_plant import ModelPlant

DB = cantools.database.load_file(str(DBC_PATH))
SIGNAL_BITS = {m.frame_id: sum(((1 << s.length) - 1) << s.start for s in m.signals) for m in DB.messages}
ROOT = Path(__file__).resolve().parents[2]
NODES = (0, 1, 2, 3)
DT = 0.005  # host period
ROBOT = 1
FORWARD = np.ones(4)
STRAFE_LEFT = np.array([-1.0, 1.0, 1.0, -1.0])  # the y column of P


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
    """Host bus + emulator on one virtual channel, with a virtual clock."""

    def __init__(self, sc, **kw):
        channel = f"test-{uuid.uuid4()}"
        self.host_bus = can.Bus(interface="virtual", channel=channel)
        self.emu_bus = can.Bus(interface="virtual", channel=channel)
        self.emu = OdriveEmulator(sc, ROBOT, self.emu_bus, **kw)
        self.host = OdriveCanSimple(self.emu.node_ids)
        self.now = 0.0
        self.log: list[tuple[float, object]] = []  # (time of the step that delivered it, frame)
        self.raw: list[can.Message] = []  # the frames as received

    def send(self, *msgs) -> None:
        for m in msgs:
            self.host_bus.send(m if isinstance(m, can.Message) else self.host.encode(m))

    def arm(self) -> None:
        for n in self.emu.node_ids:
            self.send(*self.host.arm_frames(n))

    def step(self, torques=None, n: int = 1) -> None:
        """n host periods; before each, one Set_Input_Torque per axis (if torques)."""
        for _ in range(n):
            if torques is not None:
                for node, tq in zip(self.emu.node_ids, torques, strict=True):
                    self.send(self.host.torque_frame(node, float(tq)))
            self.now = round(self.now + DT, 9)
            self.emu.step(self.now)
            while (f := self.host_bus.recv(timeout=0)) is not None:
                self.log.append((self.now, self.host.decode(f)))
                self.raw.append(f)

    def frames(self, kind, node=None, after=-1.0):
        return [(t, m) for t, m in self.log
                if isinstance(m, kind) and (node is None or m.node == node) and t > after]

    def last(self, kind, node):
        return self.frames(kind, node)[-1][1]

    def close(self) -> None:
        self.host_bus.shutdown()
        self.emu_bus.shutdown()


@pytest.fixture
def rig_factory():
    rigs = []

    def make(sc, **kw):
        rigs.append(Rig(sc, **kw))
        return rigs[-1]

    yield make
    for r in rigs:
        r.close()


def reference_plant(sc, torque_schedule, t_end):
    """eq. (4) for robot ROBOT with the given wheel torques, RK4 at 1 ms, sampled every 5 ms."""
    q, qd = sc.initial_state()
    i = sc.index_of(ROBOT)
    d = sc.spec.disturbance
    plant = ModelPlant([sc.model()], q[i:i + 1], qd[i:i + 1],
                       make_disturbance(d.kind, d.scale, tuple(d.constant_nm)), substeps=1)
    out = {}
    for k in range(int(round(t_end / 1e-3))):
        t = k * 1e-3
        plant.step(t, 1e-3, torque_schedule(t)[None, :], None)
        if (k + 1) % 5 == 0:
            out[round((k + 1) * 1e-3, 9)] = (plant.q[0].copy(), plant.q_dot[0].copy())
    return out


def test_arming_needs_torque_mode_and_cleared_errors(lab, rig_factory):
    r = rig_factory(lab)
    r.step(n=2)
    assert all(r.last(Heartbeat, n) == Heartbeat(n, 0, AXIS_STATE_IDLE, 0, True) for n in NODES)
    # closed loop in ODrive's default position-control mode: refused, error latched
    r.send(SetAxisState(0, AXIS_STATE_CLOSED_LOOP_CONTROL))
    r.step(n=20)
    hb = r.last(Heartbeat, 0)
    assert hb.axis_state == AXIS_STATE_IDLE and hb.axis_error == AXIS_ERROR_INVALID_STATE
    r.arm()  # torque mode now set, but the error is still latched: refused again
    r.step(n=20)
    assert r.last(Heartbeat, 0).axis_state == AXIS_STATE_IDLE
    assert all(r.last(Heartbeat, n).axis_state == AXIS_STATE_CLOSED_LOOP_CONTROL for n in (1, 2, 3))
    r.send(ClearErrors(0), *r.host.arm_frames(0))
    r.step(FORWARD * 0.0, n=20)
    assert all(r.last(Heartbeat, n) == Heartbeat(n, 0, AXIS_STATE_CLOSED_LOOP_CONTROL, 0, True)
               for n in NODES)


def test_forward_torque_encoders_match_the_model_plant(lab, rig_factory):
    """All wheels +0.25 N m from t = 0 for 1 s: the encoder speeds are the eq. (4) wheel
    speeds (float32 on the wire) and the robot drives forward (heading 0: +x)."""
    tau = 0.25
    r = rig_factory(lab)
    r.arm()
    r.step(FORWARD * tau, n=200)
    ref = reference_plant(lab, lambda t: FORWARD * tau, 1.0)
    model = lab.model()
    worst = 0.0
    for n in NODES:
        est = [m for _, m in r.frames(EncoderEstimate, n)]
        assert len(est) == 201  # t = 0, 0.005, ..., 1.0: the k-th is at k * 5 ms
        for k, m in enumerate(est[1:], start=1):
            q, qd = ref[round(k * DT, 9)]
            w_ref = model.wheel_speeds(float(q[2]), qd)[n] / (2 * math.pi)
            worst = max(worst, abs(m.velocity_rev_s - w_ref))
    assert worst < 1e-6  # measured 2.4e-7 rev/s (relative 5.6e-8): float32 rounding, up to 6.3 rev/s
    truth_q = np.array([s[1] for s in r.emu.truth])
    dx, dy = truth_q[-1, :2] - truth_q[0, :2]
    assert np.allclose(truth_q[-1], ref[1.0][0], atol=1e-9)  # measured: identical
    assert dx > 0.5 and abs(dy) < 0.1 * dx  # measured dx 0.957 m, dy 0.041 m (the disturbance turns it)
    pos = [r.last(EncoderEstimate, n).position_rev for n in NODES]
    # encoder positions integrate the speeds; their mean is the body-x distance / (2 pi R) (eq. 1):
    # dx up to the small turn (measured 3.0477 vs 3.0452 rev)
    assert all(p > 0 for p in pos)
    assert np.mean(pos) == pytest.approx(dx / (2 * math.pi * lab.spec.robot.wheel_radius_m), rel=0.01)


def test_disturbance_acts_from_the_first_arming_on_the_run_clock(lab, rig_factory):
    """An unpowered robot is not pushed (lab's disturbance outweighs its friction: it
    crept 1.1 cm and 0.008 rad before a can-emulated run started); armed at t_a, it
    moves as eq. (4) from rest with d(t - t_a), and stays disturbed when disarmed."""
    r = rig_factory(lab)
    r.step(n=100)  # 0.5 s idle
    q0, _ = lab.initial_state()
    assert np.array_equal(r.emu.q, q0[lab.index_of(ROBOT)])
    r.arm()  # applied at the next step's start: t_a = 0.5 s
    r.step(np.zeros(4), n=100)
    ref = reference_plant(lab, lambda t: np.zeros(4), 0.5)
    np.testing.assert_allclose(r.emu.q, ref[0.5][0], rtol=0, atol=1e-12)
    assert np.hypot(*(r.emu.q[:2] - q0[lab.index_of(ROBOT)][:2])) > 1e-3  # it is pushed
    for n in NODES:
        r.send(SetAxisState(n, AXIS_STATE_IDLE))
    before = r.emu.q.copy()
    r.step(n=40)
    assert np.hypot(*(r.emu.q[:2] - before[:2])) > 1e-4


def test_strafe_pattern_moves_sideways(lab, rig_factory):
    r = rig_factory(lab)
    r.arm()
    r.step(STRAFE_LEFT * 0.25, n=200)
    q0, q1 = r.emu.truth[0][1], r.emu.truth[-1][1]
    dx, dy = q1[:2] - q0[:2]
    assert dy > 0.5 and abs(dx) < 0.2 * dy  # measured dy 0.860 m, dx 0.110 m (the disturbance)
    v = np.array([r.last(EncoderEstimate, n).velocity_rev_s for n in NODES])
    assert np.all(np.sign(v) == STRAFE_LEFT)


def test_torque_is_clamped_to_the_scenario_limit(lab, rig_factory):
    r = rig_factory(lab)
    r.arm()
    r.step(FORWARD * 50.0, n=2)  # lab: max_wheel_torque_nm = 2
    assert np.all(r.emu.wheel_torques() == 2.0)


def test_watchdog_trips_to_idle_and_wheels_slow_down(calm, rig_factory):
    r = rig_factory(calm, watchdog_timeout_s=0.2)
    r.arm()
    r.step(FORWARD * 0.25, n=100)  # last torque frame applied at t = 0.495
    t_last = r.now - DT
    r.step(n=38)  # t = 0.690: 0.195 s since the last torque
    assert all(a.state == AXIS_STATE_CLOSED_LOOP_CONTROL for a in r.emu.axes)
    r.step(n=2)  # t = 0.700: the timeout (0.2 s after t_last = 0.495 is 0.695) has passed
    assert all(a.state == AXIS_STATE_IDLE for a in r.emu.axes)
    assert np.all(r.emu.wheel_torques() == 0.0)
    r.step(n=200)
    for n in NODES:
        late = r.frames(Heartbeat, n, after=t_last + 0.2 + 0.1 + 1e-3)  # one heartbeat period later
        assert late and all(hb.axis_state == AXIS_STATE_IDLE
                            and hb.axis_error & AXIS_ERROR_WATCHDOG_TIMER_EXPIRED for _, hb in late)
        v = np.array([m.velocity_rev_s for _, m in r.frames(EncoderEstimate, n, after=t_last + 0.2)])
        assert np.all(np.diff(v) < 0) and v[-1] < 0.8 * v[0]  # friction only: slowing down
    # re-arming needs Clear_Errors first
    r.arm()
    r.step(FORWARD * 0.1, n=5)
    assert all(a.state == AXIS_STATE_IDLE for a in r.emu.axes)
    for n in NODES:
        r.send(ClearErrors(n), *r.host.arm_frames(n))
    r.step(FORWARD * 0.1, n=5)
    assert all(a.state == AXIS_STATE_CLOSED_LOOP_CONTROL for a in r.emu.axes)


def test_estop_disarms_the_addressed_axis(lab, rig_factory):
    r = rig_factory(lab)
    r.arm()
    r.step(FORWARD * 0.2, n=10)
    r.send(Estop(1))
    r.step(FORWARD * 0.2, n=30)
    assert r.last(Heartbeat, 1).axis_state == AXIS_STATE_IDLE
    assert r.last(Heartbeat, 1).axis_error == AXIS_ERROR_ESTOP_REQUESTED
    assert all(r.last(Heartbeat, n).axis_state == AXIS_STATE_CLOSED_LOOP_CONTROL for n in (0, 2, 3))
    assert r.emu.wheel_torques()[1] == 0.0
    r.send(Request(1, CMD_GET_ERROR), Request(1, CMD_GET_BUS_VOLTAGE_CURRENT))
    r.step()
    assert r.last(DriverErrors, 1) == DriverErrors(1, AXIS_ERROR_ESTOP_REQUESTED, AXIS_ERROR_ESTOP_REQUESTED)
    assert r.last(BusVoltageCurrent, 1) == BusVoltageCurrent(1, 24.0, 0.0)  # no torque, no power


def test_silent_node_stops_answering(lab, rig_factory):
    r = rig_factory(lab, faults=EmulatorFaults(silent_node=2, silent_after_s=0.3))
    r.arm()
    r.step(FORWARD * 0.1, n=200)
    hb2 = r.frames(Heartbeat, 2)
    assert hb2 and max(t for t, _ in hb2) <= 0.3
    assert max(t for t, _ in r.frames(EncoderEstimate, 2)) <= 0.3
    assert not r.frames(Heartbeat, 2, after=0.3) and len(r.frames(Heartbeat, 0, after=0.3)) >= 6
    # it hears no torque frames either: its own watchdog disarms it
    assert r.emu.axes[2].state == AXIS_STATE_IDLE
    assert r.emu.axes[2].axis_error & AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
    assert r.emu.counters.silenced > 0


def test_drop_rate_one_loses_everything(lab, rig_factory):
    r = rig_factory(lab, faults=EmulatorFaults(drop_rate=1.0))
    r.arm()
    r.step(FORWARD * 0.2, n=100)
    assert r.log == []
    c = r.emu.counters
    assert c.sent == 0 and c.dropped_by_fault > 4 * 100 and c.protocol.decoded == 0
    assert all(a.state == AXIS_STATE_IDLE for a in r.emu.axes)  # the commands were lost too


def test_corruption_is_rejected_or_changes_values_never_raises(lab, rig_factory):
    clean = rig_factory(lab)
    bad = rig_factory(lab, faults=EmulatorFaults(corrupt_rate=1.0, seed=3))
    for rig in (clean, bad):
        rig.arm()
        rig.step(FORWARD * 0.2, n=100)
    assert bad.emu.counters.corrupted_by_fault == bad.emu.counters.sent > 0
    assert len(bad.log) == len(clean.log)
    k = bad.host.counters
    assert k.decoded + k.invalid == len(bad.log) and k.invalid > 0
    unchanged = 0
    for (_, good), (_, got), f_good, f_bad in zip(clean.log, bad.log, clean.raw, bad.raw, strict=True):
        assert f_good.arbitration_id == f_bad.arbitration_id and f_good.data != f_bad.data
        if got is not None and got == good:
            # only bits no signal uses were flipped (the heartbeat's reserved bits 49-63)
            flipped = int.from_bytes(bytes(a ^ b for a, b in zip(f_good.data, f_bad.data, strict=True)),
                                     "little")
            assert flipped & SIGNAL_BITS[f_good.arbitration_id & 0x1F] == 0
            unchanged += 1
    assert unchanged < 0.2 * len(bad.log)
    # the commands were not corrupted: the dynamics are the same
    assert np.array_equal(clean.emu.q, bad.emu.q)


def test_flip_bits_flips_one_to_three():
    rng = np.random.default_rng(0)
    for _ in range(200):
        data = bytes(rng.integers(0, 256, 8, dtype=np.uint8))
        flipped = sum(bin(a ^ b).count("1") for a, b in zip(data, flip_bits(data, rng), strict=True))
        assert 1 <= flipped <= 3


def test_other_node_ids_and_truth_file(lab, rig_factory, tmp_path):
    r = rig_factory(lab, node_ids=(8, 9, 10, 11))
    r.send(OdriveCanSimple([0]).encode(SetAxisState(0, AXIS_STATE_CLOSED_LOOP_CONTROL)))
    r.arm()
    r.step(FORWARD * 0.1, n=40)
    assert r.emu.counters.protocol.unknown_id == 1
    assert {m.node for _, m in r.log} == {8, 9, 10, 11}
    path = tmp_path / "truth.npz"
    r.emu.save_truth(path)
    d = np.load(path)
    assert d["q"].shape == d["q_dot"].shape == (len(d["t"]), 3)
    assert np.allclose(np.diff(d["t"]), 1 / 200) and d["t"][0] == 0.0
    assert d["t"][-1] == pytest.approx(0.2)


def test_constructor_rejects_bad_arguments(lab):
    bus = can.Bus(interface="virtual", channel=f"test-{uuid.uuid4()}")
    try:
        for kw in ({"node_ids": (0, 1, 2)}, {"encoder_rate_hz": 0.0}, {"encoder_rate_hz": 5e3},
                   {"watchdog_timeout_s": -1.0}, {"faults": EmulatorFaults(silent_node=7)}):
            with pytest.raises(ValueError):
                OdriveEmulator(lab, ROBOT, bus, **kw)
        with pytest.raises(ValueError):
            EmulatorFaults(drop_rate=1.5)
    finally:
        bus.shutdown()


# --- several robots in one process ----------------------------------------------------
def _fleet_rigs(sc, robots):
    """A host bus and an emulator bus per robot, each pair on a virtual channel of its own."""
    chans = [f"test-{uuid.uuid4()}" for _ in robots]
    hosts = [can.Bus(interface="virtual", channel=c) for c in chans]
    emus = [can.Bus(interface="virtual", channel=c) for c in chans]
    return hosts, emus


@pytest.mark.parametrize("physics_rate_hz", [1000.0, 200.0])
def test_fleet_emulator_equals_one_emulator_per_robot_each_on_its_bus(lab, calm, physics_rate_hz):
    """One process for the fleet: each robot's frames stay on its own bus, and every
    robot moves exactly as a one-robot emulator driven with the same frames."""
    robots = lab.robot_ids
    patterns = {1: FORWARD * 0.4, 2: STRAFE_LEFT * 0.3, 3: None}  # robot 3: never armed
    for sc in (lab, calm):
        hosts, emus = _fleet_rigs(sc, robots)
        s_hosts, s_emus = _fleet_rigs(sc, robots)
        fleet = FleetEmulator(sc, list(zip(robots, emus, strict=True)),
                              physics_rate_hz=physics_rate_hz)
        singles = [OdriveEmulator(sc, r, b, physics_rate_hz=physics_rate_hz)
                   for r, b in zip(robots, s_emus, strict=True)]
        codec = OdriveCanSimple(NODES)
        try:
            for r, h, sh in zip(robots, hosts, s_hosts, strict=True):
                if patterns[r] is not None:
                    for bus in (h, sh):
                        for n in NODES:
                            for f in codec.arm_frames(n):
                                bus.send(f)
            heard: dict[int, list] = {r: [] for r in robots}
            for k in range(1, 201):  # 1 s at 200 Hz
                for r, h, sh in zip(robots, hosts, s_hosts, strict=True):
                    if patterns[r] is not None:
                        for bus in (h, sh):
                            for n, tq in zip(NODES, patterns[r], strict=True):
                                bus.send(codec.torque_frame(n, float(tq)))
                now = round(k * DT, 9)
                fleet.step(now)
                for e in singles:
                    e.step(now)
                for r, h in zip(robots, hosts, strict=True):
                    while (f := h.recv(timeout=0)) is not None:
                        heard[r].append(codec.decode(f))
            for r, e, one in zip(robots, fleet.emulators, singles, strict=True):
                assert e.robot_id == r and e.t == one.t == pytest.approx(1.0)
                np.testing.assert_allclose(e.q, one.q, rtol=0, atol=1e-12)
                np.testing.assert_allclose(e.q_dot, one.q_dot, rtol=0, atol=1e-12)
                assert list(e.wheel_rev) == pytest.approx(list(one.wheel_rev), abs=1e-12)
                assert e.counters.sent == one.counters.sent
                # what robot r's bus carried is robot r's: its encoder angles, its states
                last = {m.node: m for m in heard[r] if isinstance(m, EncoderEstimate)}
                assert [last[n].position_rev for n in NODES] == pytest.approx(
                    list(e.wheel_rev), abs=1e-6)
                armed = patterns[r] is not None
                assert all(a.armed == armed for a in e.axes)
            # never armed: robot 3 has not moved at all, disturbance or none (it acts
            # from a robot's first arming on: ArmedDisturbance)
            q0, _ = sc.initial_state()
            assert np.array_equal(fleet.emulators[2].q, q0[2])
        finally:
            for b in (*hosts, *emus, *s_hosts, *s_emus):
                b.shutdown()


def test_fleet_emulator_catching_up_sheds_stale_encoder_frames(lab):
    """Realtime catch-up (behind_s): the physics advances in 20 ms RK4 steps, only the
    newest encoder estimates go out, heartbeats all do, and the result stays close to
    the tick-by-tick physics."""
    hosts, emus = _fleet_rigs(lab, [1])
    ref_hosts, ref_emus = _fleet_rigs(lab, [1])
    fleet = FleetEmulator(lab, [(1, emus[0])], physics_rate_hz=200.0, watchdog_timeout_s=0.0)
    ref = FleetEmulator(lab, [(1, ref_emus[0])], physics_rate_hz=200.0, watchdog_timeout_s=0.0)
    codec = OdriveCanSimple(NODES)
    try:
        for h in (hosts[0], ref_hosts[0]):
            for n in NODES:
                for f in [*codec.arm_frames(n), codec.torque_frame(n, 0.5)]:
                    h.send(f)
        fleet.step(1.0, behind_s=0.02)  # 1 s late at once
        ref.step(1.0)
        e, r = fleet.emulators[0], ref.emulators[0]
        assert e.t == r.t == pytest.approx(1.0)
        assert e.counters.shed > 0 and e.counters.sent < r.counters.sent
        sent = []
        while (f := hosts[0].recv(timeout=0)) is not None:
            sent.append(codec.decode(f))
        beats = [m for m in sent if isinstance(m, Heartbeat)]
        assert len(beats) == 11 * 4  # 10 Hz from t = 0 to 1 s, every one of them
        assert np.linalg.norm(e.q[:2] - r.q[:2]) < 1e-3, (e.q, r.q)
    finally:
        for b in (*hosts, *emus, *ref_hosts, *ref_emus):
            b.shutdown()


# --- the command line --------------------------------------------------------------
@pytest.mark.parametrize("argv", [
    ["--drop-rate", "2"],
    ["--node-ids", "0,1,2"],
    ["--node-ids", "0,1,1,2"],
    ["--encoder-rate", "-5"],
    ["--silent-after", "1"],
    ["--silent-node", "9"],
    ["--can-interface", "nonsense"],
    ["--robot", "99"],
    ["--scenario", "no-such-scenario"],
    ["--truth-out", "/no/such/dir/t.npz"],
])
def test_cli_bad_input_exits_2(argv, capsys):
    base = {"--scenario": "lab", "--robot": "1", "--can-interface": "virtual",
            "--can-channel": f"test-{uuid.uuid4()}", "--duration": "0.01"}
    base.update(dict(zip(argv[::2], argv[1::2], strict=True)))
    with pytest.raises(SystemExit) as exc:
        sys.exit(emulate_main([x for kv in base.items() for x in kv]))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "omnifleet emulate" in err and "Traceback" not in err


def test_cli_runs_for_a_duration_in_process(tmp_path, capsys):
    out = tmp_path / "truth.npz"
    code = emulate_main(["--scenario", "lab", "--robot", "2", "--can-interface", "virtual",
                         "--can-channel", f"test-{uuid.uuid4()}", "--duration", "0.1",
                         "--truth-out", str(out)])
    assert code == 0
    err = capsys.readouterr().err
    assert "(end); sent " in err
    assert_sampled_to_the_end(np.load(out)["t"])


def assert_sampled_to_the_end(t: np.ndarray, duration_s: float = 0.1) -> None:
    """A truth sample every encoder period (5 ms: 21 over 0.1 s, the last at the end). A
    starved emulator, more than ``behind_s`` (20 ms) behind the wall clock, steps over up
    to that much at once and samples after such a step (FleetEmulator.step): then the
    samples are fewer, still from 0 to within one period of the end."""
    gaps = np.diff(t)
    assert t[0] == 0.0 and np.all(gaps > 0) and gaps.max() <= 0.02 + 0.005 + 1e-9, t
    assert t[-1] > duration_s - 0.005 - 1e-9, t
    if not np.any(gaps > 0.005 + 1e-9):  # it kept pace with the wall clock
        assert len(t) == 21 and t[-1] == pytest.approx(duration_s), t


def test_cli_several_robots_in_one_process(tmp_path, capsys):
    outs = [tmp_path / f"truth-{r}.npz" for r in (1, 3)]
    base = ["--scenario", "lab", "--can-interface", "virtual", "--duration", "0.1"]
    code = emulate_main([*base, "--robot", "1", "--can-channel", f"a-{uuid.uuid4()}",
                         "--truth-out", str(outs[0]), "--robot", "3",
                         "--can-channel", f"b-{uuid.uuid4()}", "--truth-out", str(outs[1])])
    assert code == 0
    err = capsys.readouterr().err
    assert "robot 1: t = 0.100 s (end); sent " in err and "robot 3: t = 0.100 s" in err
    assert "lag behind the wall clock" in err
    for r, out in zip((1, 3), outs, strict=True):
        d = np.load(out)
        assert int(d["robot_id"]) == r
        assert_sampled_to_the_end(d["t"])
    q0, _ = load_scenario("lab").initial_state()
    assert np.allclose(np.load(outs[1])["q"][0], q0[2])  # robot 3's own initial pose
    # one channel per robot, and a per-robot --can-arg once or once per robot
    for extra in (["--robot", "1", "--robot", "2", "--can-channel", "x"],
                  ["--robot", "1", "--robot", "1", "--can-channel", "x", "--can-channel", "y"],
                  ["--robot", "1", "--robot", "2", "--can-channel", "x", "--can-channel", "y",
                   "--truth-out", str(outs[0])]):
        assert emulate_main([*base, *extra]) == 2
    assert "once per --robot" in capsys.readouterr().err


def test_cli_sigterm_exits_cleanly_and_saves_truth(tmp_path):
    out = tmp_path / "truth.npz"
    proc = subprocess.Popen(
        [sys.executable, "-m", "deploy.nodes.emulator_cli", "--scenario", "lab", "--robot", "1",
         "--can-interface", "virtual", "--can-channel", "x", "--truth-out", str(out)],
        cwd=ROOT, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert "on virtual:x" in proc.stderr.readline()  # running
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err
    assert "(SIGTERM); sent " in err and "Traceback" not in err
    assert len(np.load(out)["t"]) > 10
