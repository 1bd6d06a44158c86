"""``omnifleet can-check``: what someone does first with a new robot, for any driver.

1. Listens ``--listen`` seconds and names every drive that answers (of ``--node-ids``;
   without it, of every node id the protocol can address).
2. Brings the answering drives up as the bridge does, each step printed (ODrive: nothing
   to configure; CiA 402: heartbeat, NMT, SDO reads and writes, the PDO mapping, NMT
   operational), then, sending the driver's frames of a control period (CiA 402: SYNC),
   lists each drive's state, fault, wheel angle, speed and torque.
3. Only with ``--spin`` does it move anything: each drive in turn is armed (walked to
   ENABLED, every state on the way printed), driven at ``--spin-torque`` for
   ``--spin-time`` seconds, zeroed and disarmed; its direction and peak speed are
   reported. A drive that does not become enabled within a second is reported and not
   driven.

Every drive it touched is zeroed and disarmed before it exits, also after Ctrl-C. The
drives' max torque is set to the spin limit where the protocol carries one (CiA 402).
Neutral reports only (bridges/driver.py): nothing here knows a protocol.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field, replace

from bridges.driver import DriveError, DriveState, WheelDriver
from bridges.drivers import entry
from bridges.monitor import DriverMonitor
from deploy.contract.options import EXIT_BAD_INPUT
from deploy.nodes.can_options import MAX_SPIN_TORQUE_NM, DriverOptionError

CYCLE_S = 0.01  # can-check's control period: torque and the driver's periodic frames
ENABLE_WITHIN_S = 1.0
# before its torque a wheel is held at zero torque until it turns slower than this (the
# robot on the ground still moving from the wheel spun before it), at most REST_WITHIN_S:
# a wheel carried at 1.35 rev/s by the robot slowed under +0.3 N m as the robot stopped,
# and its change read as turning against the torque (the plug-in spin test, under load)
AT_REST_REV_S = 0.05
REST_WITHIN_S = 3.0
# a spin lasts until the wheel's readings span --spin-time after its torque started, by
# when they reached this host (the kernel's stamp): can-check held off the CPU for most of
# a window timed by its own clock heard two readings of a wheel that had not sped up yet,
# and read the robot's coasting as the wheel turning against its torque (the plug-in spin
# test beside CI's realtime phase). At most this much longer when no reading comes
SPIN_GRACE_S = 2.0
STATUS_TIMEOUT_S = 10.0  # the monitor's: can-check reports silence itself


@dataclass
class Check:
    """The bus, the driver and what was heard."""

    bus: object
    driver: WheelDriver
    monitor: DriverMonitor
    heard: set[int] = field(default_factory=set)
    speeds: dict[int, list[float]] = field(default_factory=dict)
    speeds_at: dict[int, list[float]] = field(default_factory=dict)  # when each reading came
    next_cycle: float = 0.0

    def send(self, frames: list) -> None:
        for f in frames:
            self.bus.send(f)  # type: ignore[attr-defined]

    def listen(self, seconds: float, cycle: bool = False) -> None:
        """Decode what comes for ``seconds``; with ``cycle``, the driver's periodic frames
        every CYCLE_S (the drives' SYNC, the host's heartbeat)."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            now = time.monotonic()
            if cycle and now >= self.next_cycle:
                self.next_cycle = now + CYCLE_S
                self.send(self.driver.cycle_frames(now))
            frame = self.bus.recv(timeout=min(left, CYCLE_S if cycle else 0.05))  # type: ignore[attr-defined]
            report = None if frame is None else self.driver.decode(frame)
            if report is None:
                continue
            self.heard.add(report.node)
            self.monitor.feed(report, time.monotonic())
            if report.velocity_rev_s is not None:
                self.speeds.setdefault(report.node, []).append(report.velocity_rev_s)
                self.speeds_at.setdefault(report.node, []).append(arrival(frame))

    def table(self) -> str:
        rows = ["node  state      fault                         position_rev  velocity_rev/s  "
                "torque_Nm  (the drive's own words)"]
        for n in sorted(self.heard):
            a = self.monitor.axes[self.driver.node_ids.index(n)]
            state = a.state.value if a.state is not None else "?"
            seen = a.encoder_at is not None
            rows.append(
                f"{n:4d}  {state:9s}  {self.driver.describe_fault(a.fault):28s}  "
                f"{f'{a.position_rev:12.3f}' if seen else '-':>12}  "
                f"{f'{a.velocity_rev_s:14.3f}' if seen else '-':>14}  "
                f"{'-' if a.torque_nm is None else f'{a.torque_nm:9.3f}':>9}  "
                f"({self.driver.describe(n)})")
        return "\n".join(rows)


def spin(c: Check, n: int, torque_nm: float, seconds: float) -> str:
    """Arm drive ``n`` step by step, drive it, zero and disarm it: what it did."""
    d, axis = c.driver, c.monitor.axes[c.driver.node_ids.index(n)]
    c.speeds[n] = []
    try:
        c.send(d.clear_faults_frames(n))
        start, sent_at, last = time.monotonic(), -1.0, None
        while axis.state is not DriveState.ENABLED:
            if time.monotonic() - start > ENABLE_WITHIN_S:
                return (f"node {n}: NOT enabled within {ENABLE_WITHIN_S:g} s ({d.describe(n)}, "
                        f"fault {d.describe_fault(axis.fault)}): not driven; check its enable "
                        "input (safe torque off), its errors, its mode")
            if axis.status_at is not None and axis.status_at > sent_at + d.rearm_after_s:
                if d.describe(n) != last:
                    last = d.describe(n)
                    print(f"node {n}: {last}")
                c.send(d.arm_frames(n))
                sent_at = time.monotonic()
            c.send([d.torque_frame(n, 0.0)])
            c.listen(CYCLE_S, cycle=True)
        print(f"node {n}: {d.describe(n)}")
        rest_by = time.monotonic() + REST_WITHIN_S
        while c.speeds[n] and abs(c.speeds[n][-1]) > AT_REST_REV_S \
                and time.monotonic() < rest_by:
            c.send([d.torque_frame(n, 0.0)])  # (feeds an ODrive's watchdog)
            c.listen(CYCLE_S, cycle=True)
        before = c.speeds[n][-1] if c.speeds[n] else 0.0  # its speed as the torque starts
        c.speeds[n], c.speeds_at[n] = [], []
        started, give_up = time.time(), time.monotonic() + seconds + SPIN_GRACE_S
        while not spun_long_enough(c.speeds_at[n], started, seconds) \
                and time.monotonic() < give_up:
            c.send([d.torque_frame(n, torque_nm)])  # also feeds an ODrive's watchdog
            c.listen(CYCLE_S, cycle=True)
    finally:
        c.send([d.torque_frame(n, 0.0), *d.disarm_frames(n)])
        c.listen(3 * CYCLE_S, cycle=True)
    speeds = c.speeds.get(n, [])
    if not speeds:
        return f"node {n}: no encoder readings while spinning"
    return spin_verdict(n, torque_nm, before, speeds)


def arrival(frame: object) -> float:
    """When ``frame`` reached this host (time.time()): the bus's stamp (the kernel's, on
    socketcan and the UDP buses), or now where it has none or another clock's."""
    now = time.time()
    stamp = getattr(frame, "timestamp", None) or 0.0
    return stamp if abs(stamp - now) < 1.0 else now


def spun_long_enough(readings_at: list[float], started: float, seconds: float) -> bool:
    """Whether the readings of a wheel driven since ``started`` (time.time()) span
    ``seconds`` of it: the newest came that long after the torque started."""
    return bool(readings_at) and readings_at[-1] >= started + seconds


def spin_verdict(n: int, torque_nm: float, before: float, speeds: list[float]) -> str:
    """Which way drive ``n`` turned under ``torque_nm``, judged by how its speed changed from
    ``before`` (its last reading as the torque started): a wheel that already turned (a
    robot on the ground, moved by the wheels spun before it; a wheel still coasting) is
    not taken for one that turns against its torque."""
    peak = max((v - before for v in speeds), key=abs)
    direction = "positive" if peak > 0 else "negative" if peak < 0 else "did not move"
    agrees = (peak > 0) == (torque_nm > 0)
    return (f"node {n}: {direction}, peak {abs(peak):.3f} rev/s at {torque_nm:+.3f} N m "
            f"(the change from {before:+.3f} rev/s as the torque started)"
            + ("" if agrees or peak == 0 else "  <- turns against the torque: check wiring/sign"))


def _cmd_can_check(args: argparse.Namespace) -> int:
    from deploy.nodes.can_options import CanBusError, driver_settings, open_bus

    if args.spin and not 0 < abs(args.spin_torque) <= MAX_SPIN_TORQUE_NM:
        print(f"omnifleet can-check: --spin-torque must be within (0, {MAX_SPIN_TORQUE_NM}] N m",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    e = entry(args.driver)
    lo, hi = e.node_id_range
    try:
        settings = driver_settings(args, CYCLE_S, MAX_SPIN_TORQUE_NM)
        # without --node-ids: every node the protocol can address
        scan = settings.node_ids if args.node_ids is not None else tuple(range(lo, hi + 1))
        make = e.make
        scanner = make(replace(settings, node_ids=scan))
        bus = open_bus(args)
    except (CanBusError, DriverOptionError, ValueError) as exc:
        print(f"omnifleet can-check: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    touched: list[int] = []
    c = Check(bus, scanner, DriverMonitor(list(scan), STATUS_TIMEOUT_S, time.monotonic()))
    try:
        c.listen(args.listen)
        if not c.heard:
            print(f"no driver answered on {args.can_interface}:{args.can_channel} "
                  f"in {args.listen:g} s")
            return 1
        found = sorted(c.heard)
        print(f"{args.driver}: node(s) {', '.join(map(str, found))} answered in {args.listen:g} s")
        c = Check(bus, make(replace(settings, node_ids=tuple(found))),
                  DriverMonitor(found, STATUS_TIMEOUT_S, time.monotonic()), set(found))
        try:
            c.driver.bring_up(bus, args.bring_up_timeout, print)
        except DriveError as exc:
            print(f"bring-up failed: {exc}")
            return 1
        c.listen(0.3, cycle=True)
        print(c.table())
        if args.spin:
            for n in found:
                touched.append(n)
                print(spin(c, n, args.spin_torque, args.spin_time))
        k = [scanner.counters, c.driver.counters]
        print(f"frames: decoded {sum(x.decoded for x in k)}, unknown id "
              f"{sum(x.unknown_id for x in k)}, bad length {sum(x.bad_length for x in k)}, "
              f"invalid {sum(x.invalid for x in k)}")
        return 0
    except KeyboardInterrupt:
        for n in touched:  # whatever was touched stops
            c.send([c.driver.torque_frame(n, 0.0), *c.driver.disarm_frames(n)])
        return 130
    finally:
        bus.shutdown()  # type: ignore[attr-defined]

