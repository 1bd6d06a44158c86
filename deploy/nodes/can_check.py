"""``omnifleet can-check``: what someone does first with a new robot.

Listens to a bus for ``--listen`` seconds and lists every driver that answers
(node id, axis state, errors, bus voltage when reported) with its encoder
reading. Only with ``--spin`` does it move anything: each answering axis in turn
is armed in torque control, driven at ``--spin-torque`` for ``--spin-time``
seconds, zeroed and idled, and its direction and peak speed are reported. Every
axis it touched is zeroed and idled before it exits, also after Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field

from bridges.protocol import (
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    AXIS_STATE_IDLE,
    CONTROL_MODE_TORQUE_CONTROL,
    INPUT_MODE_PASSTHROUGH,
    BusVoltageCurrent,
    ClearErrors,
    DriverErrors,
    EncoderEstimate,
    Heartbeat,
    OdriveCanSimple,
    SetAxisState,
    SetControllerMode,
    SetInputTorque,
)
from deploy.contract.options import EXIT_BAD_INPUT
from deploy.nodes.can_options import MAX_SPIN_TORQUE_NM


@dataclass
class DriverSeen:
    node: int
    axis_state: int | None = None
    axis_error: int = 0
    active_errors: int = 0
    bus_voltage_v: float | None = None
    position_rev: float | None = None
    velocity_rev_s: float | None = None
    speeds: list[float] = field(default_factory=list)


def listen(bus, protocol: OdriveCanSimple, seconds: float, seen: dict[int, DriverSeen]) -> None:
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        frame = bus.recv(timeout=min(left, 0.05))
        msg = None if frame is None else protocol.decode(frame)
        if msg is None:
            continue
        d = seen.setdefault(msg.node, DriverSeen(msg.node))
        if isinstance(msg, Heartbeat):
            d.axis_state, d.axis_error = msg.axis_state, msg.axis_error
        elif isinstance(msg, EncoderEstimate):
            d.position_rev, d.velocity_rev_s = msg.position_rev, msg.velocity_rev_s
            d.speeds.append(msg.velocity_rev_s)
        elif isinstance(msg, DriverErrors):
            d.active_errors = msg.active_errors
        elif isinstance(msg, BusVoltageCurrent):
            d.bus_voltage_v = msg.voltage_v


def spin(bus, protocol: OdriveCanSimple, d: DriverSeen, torque_nm: float, seconds: float,
         seen: dict[int, DriverSeen]) -> str:
    send = lambda m: bus.send(protocol.encode(m))  # noqa: E731
    d.speeds.clear()
    try:
        send(ClearErrors(d.node))
        send(SetControllerMode(d.node, CONTROL_MODE_TORQUE_CONTROL, INPUT_MODE_PASSTHROUGH))
        send(SetAxisState(d.node, AXIS_STATE_CLOSED_LOOP_CONTROL))
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            send(SetInputTorque(d.node, torque_nm))  # also feeds the driver's watchdog
            listen(bus, protocol, 0.02, seen)
    finally:
        send(SetInputTorque(d.node, 0.0))
        send(SetAxisState(d.node, AXIS_STATE_IDLE))
    if not d.speeds:
        return f"node {d.node}: no encoder estimates while spinning"
    peak = max(d.speeds, key=abs)
    direction = "positive" if peak > 0 else "negative" if peak < 0 else "did not move"
    agrees = (peak > 0) == (torque_nm > 0)
    return (f"node {d.node}: {direction}, peak {abs(peak):.3f} rev/s at {torque_nm:+.3f} N m"
            + ("" if agrees or peak == 0 else "  <- turns against the torque: check wiring/sign"))


def _cmd_can_check(args: argparse.Namespace) -> int:
    from deploy.nodes.can_options import CanBusError, open_bus

    if args.spin and not 0 < abs(args.spin_torque) <= MAX_SPIN_TORQUE_NM:
        print(f"omnifleet can-check: --spin-torque must be within (0, {MAX_SPIN_TORQUE_NM}] N m",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    protocol = OdriveCanSimple(list(range(64)))
    try:
        bus = open_bus(args)
    except CanBusError as exc:
        print(f"omnifleet can-check: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    seen: dict[int, DriverSeen] = {}
    try:
        listen(bus, protocol, args.listen, seen)
        if not seen:
            print(f"no driver answered on {args.can_interface}:{args.can_channel} "
                  f"in {args.listen:g} s")
            return 1
        print("node  state  axis_error  active_errors  bus_V  position_rev  velocity_rev/s")
        for n in sorted(seen):
            d = seen[n]
            print(f"{n:4d}  {d.axis_state if d.axis_state is not None else '?':>5}  "
                  f"0x{d.axis_error:08x}  0x{d.active_errors:08x}     "
                  f"{'-' if d.bus_voltage_v is None else f'{d.bus_voltage_v:5.1f}':>5}  "
                  f"{'-' if d.position_rev is None else f'{d.position_rev:12.3f}':>12}  "
                  f"{'-' if d.velocity_rev_s is None else f'{d.velocity_rev_s:14.3f}':>14}")
        if args.spin:
            for n in sorted(seen):
                print(spin(bus, protocol, seen[n], args.spin_torque, args.spin_time, seen))
        c = protocol.counters
        print(f"frames: decoded {c.decoded}, unknown id {c.unknown_id}, bad length "
              f"{c.bad_length}, invalid {c.invalid}")
        return 0
    except KeyboardInterrupt:
        for n in seen:  # whatever was touched stops
            bus.send(protocol.encode(SetInputTorque(n, 0.0)))
            bus.send(protocol.encode(SetAxisState(n, AXIS_STATE_IDLE)))
        return 130
    finally:
        bus.shutdown()
