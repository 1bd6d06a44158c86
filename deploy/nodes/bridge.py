"""One robot's CAN bridge as a process: a zenoh peer in place of the simulated
plant for that robot (docs/hardware.md). Realtime only: hardware has no lockstep.

The drives are a :class:`bridges.driver.WheelDriver` (``--driver``): the bridge sends
its frames and reads its neutral reports, whatever the protocol.

- ``robot/i/cmd`` -> torque frames, sent as the command arrives (the gate of
  :mod:`bridges.safety` clamps them to the scenario's limit, or to the driver's
  torque bound when that is lower); a period in which no command came plays the
  look-ahead torques the newest one predicted for the overdue step
  (agents/look_ahead.py), then holds the last of them; then the driver's frames of
  the period (CiA 402: SYNC and the bridge's heartbeat);
- every period: reports from the drives -> :class:`DriverMonitor`; wheel angles
  -> odometry (eq. 1) -> ``robot/i/sample`` (``faulted`` set on a drive fault, a
  missing status, or a drive that never became enabled), with the perception from
  the scenario's obstacles (the map) and the other robots' published samples; the
  states also go to observers in batches (``log/bridge-i``);
- a command older than the timeout, an e-stop or a fault -> zero torque frames
  and disarmed drives; leaving (end, Ctrl-C, a lost peer) always zeroes and disarms.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from bridges.driver import DriveState, WheelDriver
from bridges.monitor import DriverMonitor
from bridges.odometry import Odometry, pose_carried
from bridges.safety import ZERO, CommandGate, Decision
from bridges.udp_can import send_frames
from deploy.contract.options import DEFAULT_COMMAND_TIMEOUT_S
from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    WIRE_VERSION,
    Control,
    Reply,
    Sample,
    StateLog,
    StateRow,
    agent_role,
    sensed_bodies,
)
from deploy.runtime.node_runtime import ControlInbox, Periodic, StopFlag, Timing, publish_report
from deploy.runtime.step_costs import CAN, HANDLE, LAW, TELEMETRY, now_ns
from deploy.runtime.step_guard import SEQ_SLACK, OwnClock
from deploy.runtime.transport import Node
from deploy.runtime.wire_spool import SpoolWriter, spool_path
from plant.command import ZeroTorqueSpans, exceeds, torque_bound
from plant.perception import Perception

MAX_POSE_LEAD_S = 0.02  # longest the published pose is carried past the newest encoder data
LOG_ROWS = 20  # states per batch to observers (0.1 s at the lab's 200 Hz; ~1.3 kB)
# a drive not enabled for this long, having answered at least MIN_ARMING_ATTEMPTS arming
# frames with a status that says so, is given up (the robot faulted, driven no more): it
# refuses, or its state machine is stuck. A drive that does not answer at all is not
# given up: its missing status faults the robot until it answers (a host or an emulator
# off the CPU for seconds is not a drive that refuses)
ENABLE_TIMEOUT_S = 2.0
MIN_ARMING_ATTEMPTS = 5
MAX_FRAMES_PER_PERIOD = 512  # read at one period at most (a flood never holds the loop)


class BridgeNode:
    def __init__(self, sc: Scenario, robot_id: int, node: Node, stop: StopFlag, bus: Any,
                 protocol: WheelDriver, node_ids: list[int],
                 command_timeout_s: float = DEFAULT_COMMAND_TIMEOUT_S,
                 heartbeat_timeout_s: float = 0.35, spool_dir: str | None = None) -> None:
        """``spool_dir``: keep a record of every sample sent and every command heard
        there, for the recording of the launcher on this host (wire_spool.py), as the
        plant does."""
        self.sc, self.rid, self.node, self.stop = sc, robot_id, node, stop
        if spool_dir is not None:
            node.spool = SpoolWriter(spool_path(spool_dir, node.role),
                                     {node.keys.sample(robot_id), node.keys.cmd(robot_id)})
        self.index = sc.index_of(robot_id)
        # this bridge's periods start this long after the run's (staggered: the drives'
        # reports, a sample and then the torque frames of every bridge of a host no
        # longer fall due at once); step k is still the period since t = 0
        self.phase_s = sc.bridge_phase_s(robot_id)
        self.bus, self.protocol, self.node_ids = bus, protocol, list(node_ids)
        q0, _ = sc.initial_state()
        self.odometry = Odometry(sc.model(), q0[self.index])
        # the scenario's limit, and never beyond what the protocol can encode (paper.toml
        # has no limit: a 1001 N m command made the frame encoder raise in the callback)
        self.gate = CommandGate(command_timeout_s, min(torque_bound(sc.spec.limits),
                                                       protocol.max_abs_torque_nm))
        self.published_k = -1  # the newest step whose sample went out
        self.command_k = -1  # the step of the newest command taken
        self.clipped = 0  # commands that asked for more than the gate's bound (clipped)
        self.other_k = [-1] * sc.n  # the step of each other robot's newest sample taken
        self.clock = OwnClock(sc.dt)  # t = 0 set by run_realtime: nobody is past it
        self.monitor = DriverMonitor(self.node_ids, heartbeat_timeout_s, time.monotonic())
        self.timing = Timing()
        self.steps_done = 0
        self.armed = False
        self.last_reason = ""
        self.frames_sent = 0
        self.torque_sent_at = -1.0
        self.fallback_period = False  # this period's torques were a look-ahead or held
        self.zeroed_at = -1.0
        self.armed_at = -1.0
        self.arm_sent_at: dict[int, float] = {}  # each drive's newest arming frames
        self.not_enabled_since: dict[int, float] = {}  # armed, each drive not enabled since
        self.arm_attempts: dict[int, int] = {}  # arming frames answered "not enabled" since
        self.rearms = 0  # arming frames sent again to a drive not enabled yet
        # zero torque for want of a fresh command (a dead or silent agent), as
        # (robot, age of the newest command once the zero frames were sent, s; run time, s)
        self.command_stops: list[tuple[int, float, float]] = []
        self.zero_torque = ZeroTorqueSpans()  # how long each stale stop lasted
        self._send_lock = threading.Lock()
        self._frames: queue.SimpleQueue = queue.SimpleQueue()
        self._closing = False
        self._reading_in_loop = False  # the run's loop reads the bus (no reader thread)
        self._pre_run_last: float | None = None  # the odometry's newest idle period
        # the other robots, for perception: their published states (initially the scenario's)
        self.positions, self.velocities = q0[:, :2].copy(), np.zeros((sc.n, 2))
        self.radii = [sc.spec.robot.body_radius_m] * sc.n
        # what this robot perceives: the map (discs, walls, polygons) and the other robots'
        # published states, by the plant's kernel (one Perception, its arrays kept)
        self.perception = Perception(self.radii, sc.robot_ids, sc.obstacle_bodies(),
                                     sc.spec.behaviors.detection_range_m, sc.obstacle_shapes())
        self.log_rows: list[StateRow] = []
        node.subscribe(node.keys.cmd(robot_id), Reply, self._on_cmd, robot=robot_id)
        for j, rid in enumerate(sc.robot_ids):
            if rid != robot_id:
                node.subscribe(node.keys.sample(rid), Sample,
                               lambda m, j=j: self._on_other(j, m), robot=rid)
        # only control the launcher tagged for this bridge reaches _on_ctl (its keyring,
        # docs/hardening.md): a forged ctl/estop from any peer e-stopped the drives (it
        # was subscribed apart, unchecked)
        self.control = ControlInbox(node, stop, on_genuine=self._on_ctl)
        self._reader = threading.Thread(target=self._read_bus, name="can-rx", daemon=True)
        self._reader.start()
        node.declare_alive()

    # -- inputs -----------------------------------------------------------------------
    def _read_bus(self) -> None:
        """Until the run starts: the frames as they come (the bring-up and the wait for
        ``ctl/start`` read the bus for the bridge). The run's loop reads them itself."""
        wait_s = min(0.05, self.sc.dt)  # (the run's loop takes over within a period)
        while not self.stop() and not self._closing and not self._reading_in_loop:
            try:
                frame = self.bus.recv(timeout=wait_s)
            except Exception as exc:  # a bus that failed: faulted by missing heartbeats
                print(f"{self.node.role}: CAN receive failed: {exc}", file=sys.stderr)
                time.sleep(0.05)
                continue
            if frame is not None:
                self._frames.put((time.monotonic(), frame))

    def _on_other(self, j: int, m: Sample) -> None:  # on the node's thread
        # another bridge's sample: newer than the last one taken, and not past the wall
        # clock (the bridges share t = 0; step_guard.OwnClock), so one forged sample moves
        # that robot in our perception for its own step at most
        if m.k <= self.other_k[j] or self.clock.refusal(m.k, m.seq, time.monotonic()):
            self.node.refuse("other robot's sample step")
            return
        self.other_k[j] = m.k
        self.positions[j] = m.q[:2]
        self.velocities[j] = m.q_dot[:2]

    def _on_ctl(self, m: Control) -> None:  # on the node's thread
        if m.command == "estop":
            self.gate.estop()
            self._send_all(self.protocol.estop_frames)

    def _on_cmd(self, m: Reply) -> None:  # on the node's thread, as it waits
        if m.k < 0:
            return  # an initial share: no command in it
        # judged as the plant judges (deploy/nodes/plant.py): a command answers a sample already
        # sent; the newest step wins and the first command for it stays; one reply per
        # step, so the seq never runs past our step (a restarted agent counts from 0).
        # A late one for an older step is still taken when it is the newest (the gate
        # times it from its arrival, as before): the bridge keeps no table to bound
        why = ("future step" if m.k > self.published_k else
               "seq ahead of our clock" if m.seq > self.published_k + SEQ_SLACK else
               "not newer than the newest command" if m.k <= self.command_k else None)
        if why is not None:
            self.node.refuse(why)
            return
        self.command_k = m.k
        if exceeds(m.torques, m.plan, self.gate.max_torque_nm):
            self.clipped += 1
            self.node.refuse("torque beyond the bound (clipped)", dropped=False)
        arrived = time.monotonic()
        self.gate.command(m.torques, arrived, m.k, m.plan)
        if self.armed:  # torque on the bus now, not at the next period
            t0 = now_ns()
            self._apply(self.gate.decide(arrived, self.monitor.faulted(arrived)))
            self.timing.add_latency(time.monotonic_ns() - int(arrived * 1e9))
            spent = now_ns() - t0  # the frames of a command: CAN, out of its handling
            self.node.costs.ns[CAN] += spent
            self.node.costs.take_from(HANDLE, spent)

    # -- outputs ----------------------------------------------------------------------
    def _send(self, frames: list) -> None:
        """``frames`` on the bus, together where it can (bridges/udp_can.py)."""
        if not frames:
            return
        with self._send_lock:
            try:
                send_frames(self.bus, frames)
                self.frames_sent += len(frames)
            except Exception as exc:
                self.node.counters.dropped += len(frames)
                if self.node.counters.dropped <= 5:
                    print(f"{self.node.role}: CAN send failed: {exc}", file=sys.stderr)

    def _send_frame(self, frame: Any) -> None:
        self._send([frame])

    def _send_all(self, frames_of) -> None:
        for n in self.node_ids:
            self._send(frames_of(n))

    def arm(self) -> None:
        self._send_all(self.protocol.clear_faults_frames)
        self.armed_at = time.monotonic()
        self.not_enabled_since.clear()
        self.arm_attempts.clear()
        for n in self.node_ids:
            self._arm_axis(n, self.armed_at)
        self.armed = True

    def _arm_axis(self, n: int, now: float) -> None:
        self._send(self.protocol.arm_frames(n))
        self.arm_sent_at[n] = now

    def _rearm_idle_axes(self, now: float) -> None:
        """A drive whose status, heard ``rearm_after_s`` or more after its arming
        frames, still says it is not enabled: it missed them (a lost frame, a drive
        that rebooted), was stopped by its watchdog while this host was off the CPU
        (a recoverable fault: cleared first), or is one transition further on a state
        machine the driver walks one status at a time (CiA 402). Ask again. Other
        faults are not cleared here: they fault the robot. A drive not enabled for
        ENABLE_TIMEOUT_S that answered MIN_ARMING_ATTEMPTS of them so is given up: the
        bridge reports it and drives the robot no more."""
        wait = self.protocol.rearm_after_s
        for a in self.monitor.axes:
            if a.state is DriveState.ENABLED:
                self.not_enabled_since.pop(a.node, None)
                self.arm_attempts[a.node] = 0
                continue
            if a.node in self.monitor.given_up:
                continue
            since = self.not_enabled_since.setdefault(a.node, now)  # (again) not enabled
            attempts = self.arm_attempts.get(a.node, 0)
            if now - since > ENABLE_TIMEOUT_S and attempts >= MIN_ARMING_ATTEMPTS:
                self.monitor.give_up(a.node, f"not enabled {now - since:.2f} s after arming, "
                                     f"{attempts} arming frames answered (state "
                                     f"{a.state.value if a.state else 'unknown'}, "
                                     f"fault {self.protocol.describe_fault(a.fault)})")
                print(f"{self.node.role}: {self.monitor.given_up[a.node]}: node {a.node} given "
                      "up, the robot is not driven", file=sys.stderr, flush=True)
                continue
            sent = self.arm_sent_at.get(a.node, self.armed_at)
            if a.status_at is not None and a.status_at >= sent + wait and not a.fatal:
                if a.fault:
                    self._send(self.protocol.clear_faults_frames(a.node))
                self._arm_axis(a.node, now)
                self.arm_attempts[a.node] = attempts + 1
                self.rearms += 1

    def disarm(self) -> None:
        self._send_all(lambda n: [self.protocol.torque_frame(n, 0.0)])
        self.zeroed_at = time.monotonic()  # zero torque on the bus (the axes idle next)
        self._send_all(self.protocol.disarm_frames)
        self.armed = False

    def _apply(self, d: Decision) -> None:
        # no wheel is driven until every drive says it is enabled: a drive that is not
        # (still arming, stopped by its watchdog, refusing) would leave the robot pushed
        # by three wheels; one that never becomes enabled is given up (_rearm_idle_axes)
        torques = d.torques if self._all_enabled() else ZERO
        self._send([self.protocol.torque_frame(n, tau)
                    for n, tau in zip(self.node_ids, torques, strict=True)])
        self.torque_sent_at = time.monotonic()
        self.last_reason = d.reason

    def _all_enabled(self) -> bool:
        return all(a.state is DriveState.ENABLED for a in self.monitor.axes)

    def _cycle(self, now: float) -> None:
        """The driver's frames of this period, after its torques (CiA 402: SYNC)."""
        t0 = now_ns()
        with self.node.mailbox.lock:
            self._send(self.protocol.cycle_frames(now))
        self.node.costs.add(CAN, t0)

    # -- the loop ---------------------------------------------------------------------
    def _sample(self, now: float, dt: float) -> None:
        """Apply the frames heard so far, then advance the odometry by dt."""
        while True:
            try:
                at, frame = self._frames.get_nowait()
            except queue.Empty:
                break
            report = self.protocol.decode(frame)
            if report is not None:
                self.monitor.feed(report, at, frame.timestamp)
        if self._reading_in_loop:
            self._read_frames(now)
        # the wheels' rotation from the drives' angle estimates: a lost or late encoder
        # frame adds no drift (the next carries the whole rotation); see Odometry.follow
        t0 = now_ns()
        self.odometry.follow(self.monitor.wheel_positions_rev(), self.monitor.first_positions_rev(),
                             self.monitor.wheel_speeds_radps(), dt)
        self.node.costs.add(LAW, t0)

    def _read_frames(self, now: float) -> None:
        """The run's loop: the drives' frames that came since the last period, each heard
        at the time the kernel stamped it (python-can's ``timestamp``, the wall clock, on
        socketcan and udp_multicast), on this clock; ``now`` where it has none. A reader
        thread woken by every frame cost the bridge ~4 wakes a period and the GIL's
        hand-over to its loop each time (docs/bench-history.md, "The realtime budget")."""
        bus, decode, feed = self.bus, self.protocol.decode, self.monitor.feed
        offset = time.monotonic() - time.time()
        costs, t0 = self.node.costs, now_ns()
        for _ in range(MAX_FRAMES_PER_PERIOD):
            try:
                frame = bus.recv(timeout=0)
            except Exception as exc:  # a bus that failed: faulted by missing heartbeats
                print(f"{self.node.role}: CAN receive failed: {exc}", file=sys.stderr)
                break
            if frame is None:
                break
            report = decode(frame)
            if report is not None:
                stamp = frame.timestamp
                at = stamp + offset if stamp and abs(stamp + offset - now) < 1.0 else now
                feed(report, min(at, now), stamp)
        costs.add(CAN, t0)

    def idle_until_start(self, timeout_s: float) -> float | None:
        """Before the run: keep the odometry going (the robot may be pushed) and the
        axes idle until ``ctl/start``; t = 0 on this clock, or None."""
        deadline = time.monotonic() + timeout_s
        self._pre_run_last = time.monotonic()
        self._idle_until(deadline, lambda: self.control.start is not None)
        return None if self.control.start is None else self.control.wait_for_start(0.0)

    def _idle_until(self, until: float, ready: Callable[[], bool] = lambda: False) -> None:
        """Idle periods until ``until`` (time.monotonic()), ``ready()`` or a stop: the
        drives' frames the reader thread heard applied, the odometry kept going (the robot
        may be pushed), the driver's cycle frames (CiA 402: SYNC) sent, every period."""
        while not self.stop() and time.monotonic() < until:
            if self.node.mailbox.wait_until(ready, min(self.sc.dt, until - time.monotonic())):
                break
            now = time.monotonic()
            last = self._pre_run_last
            self._sample(now, self.sc.dt if last is None else now - last)
            self._cycle(now)
            self._pre_run_last = now

    def run_realtime(self, t0_mono: float, steps: int) -> None:
        dt = self.sc.dt
        self.clock.t0_s = t0_mono
        # the start's lead idles as the wait for it did, up to two periods before the
        # first: the loop reading the bus only from t = 0 found the lead's frames there
        # (0.3 s, ~120 of an ODrive robot): ~4 ms of a bridge's first period, and on one
        # core the three bridges' first periods in a row made each skip the next 1-3
        # (the run's only steps not simulated)
        self._idle_until(t0_mono + self.phase_s - 2.0 * dt)
        keys = self.node.keys
        self.node.connect_ahead([keys.sample(self.rid), keys.state_log(self.node.role)])
        # from here the loop reads the bus at each period (what the thread had queued
        # first; it hands over within a period); woken by its clock and by its agent's
        # commands only
        self._reading_in_loop = True
        self._reader.join(1.0)
        self.node.wake_on([self.node.keys.cmd(self.rid)])
        ticker = Periodic(t0_mono + self.phase_s, dt, self.timing, self.node.mailbox)
        last: float | None = self._pre_run_last
        try:
            while not self.stop():
                k = ticker.wait_next(self.stop)
                if k is None or k >= steps:
                    break
                now = time.monotonic()
                self._sample(now, dt if last is None else now - last)
                last = now
                faulted = self.monitor.faulted(now)
                with self.node.mailbox.lock:
                    d = self.gate.decide(now, faulted)
                    if d.armed and not self.armed:
                        self.zero_torque.end(self.rid, k * dt)
                        self.arm()
                        self._apply(d)
                    elif not d.armed and self.armed:
                        self.disarm()
                        if d.reason == "stale":
                            self._log_stop(k * dt)
                    if d.armed and self.armed:
                        self._rearm_idle_axes(now)
                    if d.armed and now - self.torque_sent_at >= dt:
                        # no command this period: the one answering our state of the
                        # last period is overdue; play the newest command's look-ahead
                        # torques for it, or hold them (which feeds the watchdog)
                        self._apply(self.gate.decide(now, faulted, due_step=k - 1))
                        self.fallback_period = True
                    elif not d.armed and self.last_reason != d.reason:
                        self._apply(d)  # zeros, once per reason
                self._cycle(now)
                self._publish(k, k * dt, faulted, now)
                self.steps_done += 1
        finally:
            with self.node.mailbox.lock:
                self.disarm()  # whatever ended the loop, the robot stops pushing
            self.flush_log()

    def _log_stop(self, t: float) -> None:
        age = self.gate.command_age_s(self.zeroed_at)
        self.command_stops.append((self.rid, age, t))
        self.zero_torque.begin(self.rid, t)
        print(f"{self.node.role}: t = {t:.3f} s: zero torque on the bus, the newest command "
              f"{age * 1e3:.1f} ms old", file=sys.stderr, flush=True)

    def _publish(self, k: int, t: float, faulted: bool, now: float | None = None) -> None:
        node, keys, i = self.node, self.node.keys, self.index
        q, qd = self.odometry.q, self.odometry.q_dot  # float triples (bridges/odometry.py)
        # the pose is as of the newest encoder estimates (100 Hz from an ODrive, half
        # our rate): carried to now at the velocity they gave, so the agent does not
        # see a staircase (at most two encoder periods ahead: past that it is lost)
        if now is not None:
            q = pose_carried(q, qd, self.monitor.encoder_age_s(now), MAX_POSE_LEAD_S)
        t0 = now_ns()
        with node.mailbox.lock:
            pos, vel = self.positions.copy(), self.velocities.copy()
        pos[i], vel[i] = q[:2], qd[:2]
        robots, obstacles = self.perception.rows(i, pos, vel)  # rows, as the plant's
        node.costs.add(LAW, t0)  # perception, as the plant's
        self.published_k = max(self.published_k, k)
        # the robot moved on its agent's command for our previous sample (Sample.own_torques)
        own = self.armed and self.command_k == k - 1 and not self.fallback_period
        self.fallback_period = False
        node.publish(keys.sample(self.rid), lambda seq, stamp: Sample(
            WIRE_VERSION, 0, seq, stamp, robot=self.rid, k=k, t=t, q=q, q_dot=qd,
            robots=sensed_bodies(robots),
            obstacles=sensed_bodies(obstacles), faulted=faulted, own_torques=own))
        t0, mark = now_ns(), node.costs.mark()
        self.log_rows.append(StateRow(k, t, [q], [qd], [faulted]))
        if len(self.log_rows) >= LOG_ROWS:
            self.flush_log()
        node.costs.charge(TELEMETRY, t0, mark)

    def flush_log(self) -> None:
        """This robot's states gathered so far, to observers, in one message."""
        rows, self.log_rows = self.log_rows, []
        if rows:
            self.node.publish(self.node.keys.state_log(self.node.role), lambda seq, stamp: StateLog(
                WIRE_VERSION, 0, seq, stamp, robots=[self.rid], rows=rows))

    def handshake(self, timeout_s: float) -> None:
        self.node.declare_ready()

    def close(self) -> None:
        """Stop reading the bus (before the bus is shut down)."""
        self._closing = True
        self._reader.join(1.0)

    def finish(self, linger_s: float = 5.0) -> None:
        """Report, then stay until this robot's agent has left (as the plant does),
        so it does not mistake the end of the run for a lost bridge."""
        spool = self.node.spool
        if spool is not None:  # its record of the samples and commands, whole before the report
            spool.flush()
        publish_report(self.node, self.rid, self.steps_done, self.timing,
                       command_stops=self.command_stops[:1000],
                       zero_torque=self.zero_torque.close(self.steps_done * self.sc.dt),
                       torque_clipped={str(self.rid): self.clipped} if self.clipped else {},
                       unrecorded=0 if spool is None else spool.lost)
        c = self.protocol.counters
        print(f"{self.node.role}: CAN frames sent {self.frames_sent}, arming frames sent "
              f"again {self.rearms}; received decoded {c.decoded}, rejected {c.rejected}",
              file=sys.stderr)
        agent = agent_role(self.rid)
        self.node.mailbox.wait_until(lambda: agent not in self.node.peers_alive, linger_s)
