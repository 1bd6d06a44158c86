"""``omnifleet emulate``: one robot's four motor drivers and dynamics on a CAN bus.

Runs :class:`bridges.emulator.DriverEmulator` in real time until --duration, SIGINT
or SIGTERM; then shuts the bus down, saves the ground truth (--truth-out) and
prints a one-line summary of the frame counters on stderr.

Exit codes: 0 done (duration reached), 2 bad input (arguments, scenario, a bus
that cannot be opened), 130 SIGINT, 143 SIGTERM. Also runnable alone:
``python -m bridges.emulator_cli --help``.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
from pathlib import Path

from bridges.can_options import CanBusError, add_can_options, open_bus

EXIT_BAD_INPUT = 2
_SIGNAL_EXIT = {"SIGINT": 130, "SIGTERM": 143}
PROG = "omnifleet emulate"


def _number(ok, what: str):
    """An argparse type: a finite float for which ``ok`` holds, else a clear error."""
    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            x = math.nan
        if not (math.isfinite(x) and ok(x)):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return x
    return parse


_probability = _number(lambda x: 0.0 <= x <= 1.0, "a probability in [0, 1]")
_positive = _number(lambda x: x > 0, "a positive number")
_non_negative = _number(lambda x: x >= 0, "a number >= 0")


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", required=True, metavar="S",
                   help="scenario file or bundled scenario name (the robot's physics, initial "
                   "state, torque limit and disturbance come from it)")
    p.add_argument("--robot", type=int, required=True, metavar="ID", help="the robot's id in the scenario")
    add_can_options(p)
    p.add_argument("--encoder-rate", type=_positive, default=200.0, metavar="HZ",
                   help="Get_Encoder_Estimates rate per axis (default: 200)")
    p.add_argument("--heartbeat-rate", type=_positive, default=10.0, metavar="HZ",
                   help="Heartbeat rate per axis (default: 10)")
    p.add_argument("--watchdog-timeout", type=_non_negative, default=0.2, metavar="S",
                   help="an armed axis without Set_Input_Torque for this long disarms with "
                   "WATCHDOG_TIMER_EXPIRED; 0 turns the watchdog off (default: 0.2)")
    p.add_argument("--drop-rate", type=_probability, default=0.0, metavar="P",
                   help="fault: probability that a frame (either direction) is lost (default: 0)")
    p.add_argument("--corrupt-rate", type=_probability, default=0.0, metavar="P",
                   help="fault: probability that a sent frame gets 1-3 bits flipped (default: 0)")
    p.add_argument("--silent-node", type=int, metavar="N",
                   help="fault: this node id stops sending and ignores commands ...")
    p.add_argument("--silent-after", type=_non_negative, default=None, metavar="S",
                   help="... from S seconds after start (default: 0; needs --silent-node)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="fault random seed (default: 0)")
    p.add_argument("--duration", type=_positive, metavar="S", help="stop after S seconds (default: run "
                   "until SIGINT/SIGTERM)")
    p.add_argument("--truth-out", metavar="FILE.npz",
                   help="write the robot's true pose and velocity (t, q, q_dot at the encoder "
                   "rate) here on exit")


def add_emulate_command(sub: argparse._SubParsersAction) -> None:
    """Register ``emulate`` on an ``omnifleet`` sub-command parser."""
    p = sub.add_parser(
        "emulate", help="emulate one robot's four ODrive drivers and its dynamics on a CAN bus",
        description="Play four ODrive CANSimple drives (arming, torque control, watchdog, Estop, "
        "heartbeats, encoder estimates) and the robot's dynamics (eq. 4) on a python-can bus, so "
        "a bridge runs without hardware. Runs in real time until --duration or SIGINT/SIGTERM.",
    )
    _configure(p)
    p.set_defaults(func=run_emulate)


def run_emulate(args: argparse.Namespace) -> int:
    """The ``emulate`` command; returns the exit code."""

    from bridges.emulator import DriverEmulator, EmulatorFaults
    from deploy.scenario import ScenarioError, load_scenario

    def bad(msg: str) -> int:
        print(f"{PROG}: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT

    if args.silent_after is not None and args.silent_node is None:
        return bad("--silent-after needs --silent-node")
    if args.silent_node is not None and args.silent_node not in args.node_ids:
        return bad(f"--silent-node {args.silent_node} is not one of --node-ids "
                   f"{','.join(map(str, args.node_ids))}")
    truth = Path(args.truth_out) if args.truth_out else None
    if truth is not None and not truth.parent.is_dir():
        return bad(f"--truth-out: no such directory {str(truth.parent)!r}")
    try:
        sc = load_scenario(args.scenario)
        sc.index_of(args.robot)
    except ScenarioError as exc:
        return bad(f"bad scenario: {exc}")
    faults = EmulatorFaults(args.drop_rate, args.corrupt_rate, args.silent_node,
                            args.silent_after or 0.0, args.seed)
    try:
        bus = open_bus(args)
    except CanBusError as exc:
        return bad(str(exc))
    try:
        emu = DriverEmulator(sc, args.robot, bus, args.node_ids, args.encoder_rate,
                             args.heartbeat_rate, args.watchdog_timeout, faults=faults)
    except ValueError as exc:
        bus.shutdown()
        return bad(str(exc))
    stop_reason: list[str] = []
    previous = _install_signal_handlers(stop_reason)
    print(f"{PROG}: robot {args.robot} of {sc.name!r}, drives {','.join(map(str, args.node_ids))} "
          f"on {args.can_interface}:{args.can_channel}", file=sys.stderr, flush=True)
    try:
        emu.run(lambda: bool(stop_reason), args.duration)
    finally:  # also when the bus fails: shut it down and keep what was simulated
        bus.shutdown()
        _restore_signal_handlers(previous)
        if truth is not None:
            emu.save_truth(truth)
    reason = stop_reason[0] if stop_reason else "end"
    print(f"{PROG}: t = {emu.t:.3f} s ({reason}); {emu.counters.summary()}; axes "
          + ", ".join(f"{a.node}: state {a.state} error 0x{a.axis_error:x}" for a in emu.axes),
          file=sys.stderr)
    return _SIGNAL_EXIT.get(reason, 0)


def _install_signal_handlers(reasons: list[str]) -> dict:
    def handler(signum: int, _frame: object) -> None:
        if not reasons:
            reasons.append(signal.Signals(signum).name)

    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread: the caller handles signals
            pass
    return previous


def _restore_signal_handlers(previous: dict) -> None:
    for sig, h in previous.items():
        signal.signal(sig, h)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=(__doc__ or "").split("\n\n")[0])
    _configure(p)
    return p


def main(argv: list[str] | None = None) -> int:
    return run_emulate(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
