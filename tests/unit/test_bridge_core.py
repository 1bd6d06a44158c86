"""The bridge's pure parts: wheel odometry (eq. 1 and the pose integration) and
the command gate that decides what torque may reach the bus."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridges.driver import DriverSettings, DriveState, WheelReport
from bridges.odometry import Odometry, pose_carried
from bridges.odrive import (
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    EncoderEstimate,
    Heartbeat,
    OdriveCanSimple,
    OdriveDriver,
)
from bridges.safety import ZERO, CommandGate
from deploy.contract.scenario import load_scenario

ODRIVE = OdriveDriver(DriverSettings((0, 1, 2, 3)))
DRIVES = OdriveCanSimple((0, 1, 2, 3), role="drive")


def heard(msg) -> WheelReport:
    """An ODrive frame as the bridge hears it: on the wire, then the driver's report."""
    report = ODRIVE.decode(DRIVES.encode(msg))
    assert report is not None
    return report


def encoder(node: int, position_rev: float, velocity_rev_s: float) -> WheelReport:
    return WheelReport(node, position_rev=position_rev, velocity_rev_s=velocity_rev_s)


@pytest.fixture(scope="module")
def model():
    return load_scenario("lab").model()


def wheel_speeds_of(model, body_twist) -> np.ndarray:
    """theta_dot = P v_r / R: the inverse of eq. (1) in the body frame."""
    return model.P @ np.asarray(body_twist, float) / model.params.wheel_radius_m


def test_body_twist_inverts_the_wheel_kinematics(model):
    odo = Odometry(model, np.zeros(3))
    for twist in ([1.0, 0.0, 0.0], [0.0, -0.7, 0.0], [0.0, 0.0, 2.0], [0.3, 0.4, -1.1]):
        assert np.allclose(odo.body_twist(wheel_speeds_of(model, twist)), twist, atol=1e-12)


def test_constant_twist_follows_the_exact_arc(model):
    v, w, dt, T = 1.0, 0.5, 0.005, 2.0
    odo = Odometry(model, np.zeros(3))
    speeds = wheel_speeds_of(model, [v, 0.0, w])
    for _ in range(int(round(T / dt))):
        odo.update(speeds, dt)
    exact = np.array([v / w * math.sin(w * T), v / w * (1 - math.cos(w * T)), w * T])
    assert np.abs(odo.q - exact).max() < 1e-6  # mid-heading integration: exact on arcs up to rounding
    assert np.allclose(odo.q_dot, [v * math.cos(w * T), v * math.sin(w * T), w], atol=1e-12)


def test_strafe_moves_sideways_in_the_world_frame(model):
    odo = Odometry(model, np.array([1.0, 2.0, math.pi / 2]))
    for _ in range(100):
        odo.update(wheel_speeds_of(model, [0.0, 0.5, 0.0]), 0.01)
    # heading +90 deg: body +y is world -x
    assert np.allclose(odo.q, [1.0 - 0.5, 2.0, math.pi / 2], atol=1e-12)


def test_gate_passes_fresh_commands_clamped_to_the_limit():
    gate = CommandGate(0.1, 2.0)
    gate.command((1.0, -3.0, 2.5, 0.0), now_s=10.0)
    d = gate.decide(10.05, faulted=False)
    assert d.armed and d.torques == (1.0, -2.0, 2.0, 0.0) and d.reason == "command"


@pytest.mark.parametrize("case", ["none", "stale", "faulted", "estop", "nan"])
def test_gate_gives_zero_torque_and_disarms(case):
    gate = CommandGate(0.1, 2.0)
    now = 5.0
    if case != "none":
        gate.command((math.nan, 0.0, 0.0, 0.0) if case == "nan" else (1.0, 1.0, 1.0, 1.0), now)
    if case == "stale":
        now += 0.1 + 1e-9
    if case == "estop":
        gate.estop()
        gate.command((1.0, 1.0, 1.0, 1.0), now)  # a later command does not undo an e-stop
    d = gate.decide(now, faulted=case == "faulted")
    assert d.torques == ZERO and not d.armed


def test_gate_plays_the_look_ahead_for_an_overdue_step_then_holds_its_last_entry():
    gate = CommandGate(0.1, 2.0)
    gate.command((1.0, 1.0, 1.0, 1.0), 1.0, k=7, plan=[(0.5,) * 4, (3.0, -3.0, 0.0, 0.0)])
    assert gate.decide(1.004, False, due_step=7).torques == (1.0,) * 4  # on time
    d = gate.decide(1.006, False, due_step=8)
    assert d.torques == (0.5,) * 4 and d.reason == "look-ahead" and d.armed
    assert gate.decide(1.011, False, due_step=9).torques == (2.0, -2.0, 0.0, 0.0)  # clamped
    d = gate.decide(1.016, False, due_step=10)  # past the plan: its last entry held
    assert d.torques == (2.0, -2.0, 0.0, 0.0) and d.reason == "look-ahead"
    assert gate.decide(1.2, False, due_step=30).torques == ZERO  # and the timeout still acts


def test_gate_timeout_must_be_positive():
    with pytest.raises(ValueError):
        CommandGate(0.0, 1.0)


def test_monitor_faults_on_errors_and_silence_but_not_on_a_watchdog_expiry():
    from bridges.monitor import DriverMonitor

    mon = DriverMonitor([0, 1, 2, 3], heartbeat_timeout_s=0.35, started_at=0.0)
    assert not mon.faulted(0.3)
    assert mon.faulted(0.4)  # nobody heard since the start
    for n in range(4):
        mon.feed(heard(Heartbeat(n, 0, 1)), 0.5)
        mon.feed(heard(EncoderEstimate(n, 1.0, 0.5 * (n + 1))), 0.5)
    assert not mon.faulted(0.6)
    assert [a.state for a in mon.axes] == [DriveState.DISABLED] * 4
    assert np.allclose(mon.wheel_speeds_radps(), 2 * math.pi * 0.5 * np.arange(1, 5))
    # the drive stopped itself because the host fell silent: recoverable by re-arming
    mon.feed(heard(Heartbeat(2, AXIS_ERROR_WATCHDOG_TIMER_EXPIRED, 1)), 0.7)
    assert not mon.faulted(0.7) and mon.axes[2].state is DriveState.FAULT
    mon.feed(heard(Heartbeat(2, 0x1 | AXIS_ERROR_WATCHDOG_TIMER_EXPIRED, 1)), 0.8)  # another error
    assert mon.faulted(0.8) and "node 2" in mon.fault_reasons(0.8)[0]
    mon.feed(heard(Heartbeat(2, 0, 8)), 0.9)
    for n in (0, 1, 3):
        mon.feed(heard(Heartbeat(n, 0, 8)), 0.9)
    assert not mon.faulted(1.0) and all(a.state is DriveState.ENABLED for a in mon.axes)
    assert mon.faulted(1.3)  # every heartbeat 0.4 s old
    mon.feed(WheelReport(9, state=DriveState.FAULT, fault=1), 1.3)  # another node's: nothing
    assert [a.node for a in mon.axes] == [0, 1, 2, 3]
    mon.give_up(1, "not enabled")  # the bridge gave up on a drive: faulted for good
    for n in range(4):
        mon.feed(WheelReport(n, state=DriveState.ENABLED, fault=0), 1.4)
    assert mon.fault_reasons(1.4) == ["node 1: not enabled"]


def test_advance_by_wheel_rotation_equals_speed_times_dt_and_ignores_skipped_samples(model):
    """Position-based odometry: the same pose as speed x dt for the same motion, and
    an update that covers two periods (a lost encoder frame) lands where two do."""
    speeds = wheel_speeds_of(model, [0.8, -0.3, 0.0])
    by_speed, by_angle, skipping = (Odometry(model, np.array([1.0, -1.0, 0.4])) for _ in range(3))
    for k in range(200):
        by_speed.update(speeds, 0.005)
        by_angle.advance(speeds * 0.005, speeds)
        if k % 2:
            skipping.advance(speeds * 0.010, speeds)
    assert np.allclose(by_angle.q, by_speed.q, atol=1e-12)
    assert np.allclose(skipping.q, by_speed.q, atol=1e-12)  # straight line: exact
    assert np.allclose(by_angle.q_dot, by_speed.q_dot, atol=1e-12)
    turning = wheel_speeds_of(model, [1.0, 0.0, 0.5])
    a, b = Odometry(model, np.zeros(3)), Odometry(model, np.zeros(3))
    for k in range(400):
        a.update(turning, 0.005)
        if k % 2:
            b.advance(turning * 0.010, turning)
    assert np.abs(np.subtract(a.q, b.q)).max() < 1e-4  # on an arc: second order in the interval


def test_odometry_start_up_stands_until_every_drive_reported_then_counts_queued_rotation(model):
    """The bridge's first periods. A 60 s can-emulated lab run showed a heading error
    of 0.0056 rad from t = 0 on one robot (3.5 cm drift median) and a missed 7 mm on
    another: (a) speed x dt with 0 for a drive not heard yet reads as a rotation, and
    (b) the newest angles taken as the baseline drop the rotation of frames queued
    before the first full sample. Driving straight at 0.5 m/s, measured exactly."""
    from bridges.monitor import DriverMonitor

    speeds = wheel_speeds_of(model, [0.5, 0.0, 0.0])  # rad/s; a straight line: exact
    mon = DriverMonitor([0, 1, 2, 3], heartbeat_timeout_s=0.35, started_at=0.0)
    odo = Odometry(model, np.array([1.0, 2.0, 0.0]))
    angle0 = np.array([3.0, -1.0, 0.5, 7.0])  # the drives' angles at power-up (turns)

    def report(nodes, t):
        for n in nodes:
            mon.feed(encoder(n, float(angle0[n] + speeds[n] * t / (2 * math.pi)),
                                     float(speeds[n] / (2 * math.pi))), t)

    def period(dt=0.005):
        odo.follow(mon.wheel_positions_rev(), mon.first_positions_rev(),
                   mon.wheel_speeds_radps(), dt)

    for k in range(4):  # drive 3 not heard yet: no rotation to measure, the robot stands
        report([0, 1, 2], 0.01 * k)
        period()
        assert np.array_equal(odo.q, [1.0, 2.0, 0.0]) and np.array_equal(odo.q_dot, np.zeros(3))
    report([3], 0.03)  # the first full set: every drive's angle as of t = 0.03
    for k in range(4, 9):  # five frames per drive queued before the next period
        report([0, 1, 2, 3], 0.01 * k)
    period()
    # the rotation from t = 0.03 to 0.08 is all counted (at the old baseline, the
    # newest angles, it was 0); drives first heard a burst apart would read as a turn
    assert odo.q == pytest.approx([1.0 + 0.5 * 0.05, 2.0, 0.0], abs=1e-9)
    report([0, 1, 2, 3], 0.10)
    period()
    assert odo.q_dot == pytest.approx([0.5, 0.0, 0.0], abs=1e-6)  # float32 frames in real life


def test_odometry_ignores_a_burst_of_encoder_frames_that_is_half_in():
    """A period that falls between the four drives' frames of one burst: two wheels
    at the new angle, two at the old, read as a turn the next period undid, and the
    displacement between went in at the wrong heading (a 0.2-0.9 cm random walk over
    60 s of can-emulated lab). Complete sets only: driving straight stays straight."""
    from bridges.monitor import DriverMonitor

    speeds = wheel_speeds_of(model_of_lab(), [0.0, 0.8, 0.0])  # strafing: wheels turn both ways
    mon = DriverMonitor([0, 1, 2, 3], heartbeat_timeout_s=0.35, started_at=0.0)
    odo = Odometry(model_of_lab(), np.zeros(3))

    def report(nodes, t):
        for n in nodes:
            mon.feed(encoder(n, float(speeds[n] * t / (2 * math.pi)),
                                     float(speeds[n] / (2 * math.pi))), t)

    def period():
        odo.follow(mon.wheel_positions_rev(), mon.first_positions_rev(),
                   mon.wheel_speeds_radps(), 0.005)

    report([0, 1, 2, 3], 0.0)
    period()
    for k in range(1, 41):
        report([0, 1], 0.01 * k)  # half the burst is in when the period comes
        period()
        assert odo.q == pytest.approx([0.0, 0.8 * 0.01 * (k - 1), 0.0], abs=1e-12)
        report([2, 3], 0.01 * k)
        period()
        assert odo.q == pytest.approx([0.0, 0.8 * 0.01 * k, 0.0], abs=1e-12)


def model_of_lab():
    return load_scenario("lab").model()


def test_odometry_from_sets_that_straddle_two_bursts_stays_straight():
    """A bridge that first hears the drives mid-burst (drives 2 and 3 of one burst,
    then 0 and 1 of the next) completed every later set across two bursts too: two
    wheels one encoder period behind the others, for the whole run. Idle, that is
    nothing; accelerating, the lag read as a turn (a can-emulated lab run: robot 1's
    heading 0.03 rad off in its first 0.2 s, 9.6 cm median drift). Each angle is now
    carried to the set's newest frame by its own speed: strafing from rest at 12 m/s^2,
    the odometry stays on the straight line the wheels drive."""
    from bridges.monitor import DriverMonitor

    model = model_of_lab()
    mon = DriverMonitor([0, 1, 2, 3], heartbeat_timeout_s=0.35, started_at=0.0)
    odo = Odometry(model, np.zeros(3))
    unit = wheel_speeds_of(model, [0.0, 1.0, 0.0])  # rad/s per m/s of strafing
    accel, start, period_s = 12.0, 0.05, 0.01

    def speed(t):  # m/s: standing, then 12 m/s^2 for 0.15 s, then steady
        return accel * min(max(t - start, 0.0), 0.15)

    def distance(t):
        u = min(max(t - start, 0.0), 0.15)
        return 0.5 * accel * u * u + speed(t) * max(t - start - 0.15, 0.0)

    def report(nodes, t):
        for n in nodes:
            mon.feed(encoder(n, float(unit[n] * distance(t) / (2 * math.pi)),
                             float(unit[n] * speed(t) / (2 * math.pi))), t)

    report([2, 3], 0.0)  # the bridge's first frames: the end of a burst
    for k in range(1, 51):
        report([0, 1, 2, 3], k * period_s)  # every later burst whole
        odo.follow(mon.wheel_positions_rev(), mon.first_positions_rev(),
                   mon.wheel_speeds_radps(), period_s)
    t = 50 * period_s
    assert odo.q[1] == pytest.approx(distance(t), abs=1e-4)  # 0.675 m along y
    assert abs(odo.q[2]) < 1e-9 and abs(odo.q[0]) < 1e-3  # no turn; aside: 2nd order only


def test_odometry_carries_angles_by_the_bus_times_not_the_readers():
    """The angles are carried by the times the bus took the frames (python-can's
    ``timestamp``), not the times a reader thread, waiting for the GIL, got to them: one
    burst's frames heard up to 5 ms apart are still one instant. The burst-straddling
    start above, with every frame heard 0-5 ms late at random: no turn."""
    from bridges.monitor import DriverMonitor

    model = model_of_lab()
    rng = np.random.default_rng(4)
    mon = DriverMonitor([0, 1, 2, 3], heartbeat_timeout_s=0.35, started_at=0.0)
    odo = Odometry(model, np.zeros(3))
    unit = wheel_speeds_of(model, [0.0, 1.0, 0.0])

    def report(nodes, t):  # at rest, then strafing at 2 m/s from t = 0.05; the bus's
        moving = t >= 0.05  # time t, heard later
        for n in nodes:
            mon.feed(encoder(n, float(unit[n] * 2.0 * max(t - 0.05, 0.0) / (2 * math.pi)),
                             float(unit[n] * 2.0 * moving / (2 * math.pi))),
                     t + rng.uniform(0.0, 0.005), t)

    report([2, 3], 0.0)
    for k in range(1, 51):
        report([0, 1, 2, 3], k * 0.01)
        odo.follow(mon.wheel_positions_rev(), mon.first_positions_rev(),
                   mon.wheel_speeds_radps(), 0.01)
    assert odo.q == pytest.approx([0.0, 0.9, 0.0], abs=1e-9)


def test_the_published_pose_is_carried_to_now_and_never_back_when_the_encoders_go_quiet():
    """The bridge's pose of encoder data ``age`` old, carried at its velocity by at most
    the lead: as the data ages past the lead the pose holds where the carry left it; it
    never steps back to the pose of the data (a robot moving at 0.7 m/s read 1.4-2.2 cm
    behind for 4 samples, and its agent answered with torques 30x the steady ones)."""
    q, qd, lead = (1.0, 2.0, 0.1), (0.7, -0.5, 0.2), 0.02
    assert pose_carried(q, qd, None, lead) == q
    assert pose_carried(q, qd, 0.0, lead) == q
    ages = np.arange(0.0, 0.06, 0.005)
    xs = [pose_carried(q, qd, a, lead)[0] for a in ages]
    assert np.all(np.diff(xs) >= 0.0)  # along the velocity, never back
    assert xs[-1] == pytest.approx(1.0 + 0.7 * lead)
    assert pose_carried(q, qd, 0.01, lead) == pytest.approx((1.007, 1.995, 0.102))
