"""``omnifleet emulate``: robots' four motor drives (of the protocol ``--driver``
names) and dynamics, each robot on a CAN bus of its own.

One process plays one or several robots (``--robot`` repeated, with one
``--can-channel`` and ``--truth-out`` per robot): :class:`bridges.fleet_emulator.FleetEmulator`
in real time until --duration, SIGINT or SIGTERM; then shuts the buses down, saves
the ground truth (--truth-out) and prints a one-line summary of each robot's frame
counters and of the lag behind the wall clock on stderr.

Exit codes: 0 done (duration reached), 2 bad input (arguments, scenario, a bus
that cannot be opened), 130 SIGINT, 143 SIGTERM. Also runnable alone:
``python -m deploy.nodes.emulator_cli --help``.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from deploy.contract.options import EXIT_BAD_INPUT, add_option
from deploy.contract.output_paths import check_file
from deploy.nodes.can_options import (
    CanBusError,
    DriverOptionError,
    add_can_options,
    driver_settings,
    open_buses,
)
from deploy.runtime.heap import freeze_startup_heap
from deploy.runtime.parent_death import die_with_parent
from deploy.runtime.priority import add_priority_argument, raise_priority

if TYPE_CHECKING:  # imported when the command runs (the emulator's start stays light)
    from bridges.fleet_emulator import FleetEmulator

_SIGNAL_EXIT = {"SIGINT": 130, "SIGTERM": 143}
PROG = "omnifleet emulate"


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", required=True, metavar="S",
                   help="scenario file or bundled scenario name (the robot's physics, initial "
                   "state, torque limit and disturbance come from it)")
    add_option(p, "--robot", required=True, action="append",
               more_help="repeat it to emulate several robots in this process (each on its own "
               "bus: one --can-channel per robot, in the same order)")
    add_can_options(p, per_robot=True)
    add_option(p, "--encoder-rate")
    add_option(p, "--heartbeat-rate")
    add_option(p, "--watchdog-timeout")
    add_option(p, "--drop-rate")
    add_option(p, "--corrupt-rate")
    add_option(p, "--silent-node")
    add_option(p, "--silent-after")
    add_option(p, "--refuse-enable")
    add_option(p, "--seed", default=0, help="fault random seed; the i-th --robot (from 0) "
               "uses K + i")
    add_option(p, "--physics-rate")
    add_option(p, "--duration", help="stop after S seconds (default: run until SIGINT/SIGTERM)")
    add_priority_argument(p, "the emulator plays the physics, which must not be starved by "
                          "the software under test")
    p.add_argument("--truth-out", metavar="FILE.npz", action="append",
                   help="write the robot's true pose and velocity (t, q, q_dot at the encoder "
                   "rate) here on exit; once per --robot, in the same order")
    p.add_argument("--exit-with-parent", action="store_true",
                   help="stop (as on SIGTERM) when the process that started this one ends, "
                   "however it ends (`omnifleet run` passes it: an emulator it can no longer "
                   "stop never outlives it)")


def add_emulate_command(sub: argparse._SubParsersAction) -> None:
    """Register ``emulate`` on an ``omnifleet`` sub-command parser."""
    p = sub.add_parser(
        "emulate", help="emulate robots' four motor drives and dynamics, each on its CAN bus",
        description="Play four drives of --driver's protocol (ODrive CANSimple: arming, torque "
        "control, watchdog, Estop, heartbeats, encoder estimates; CiA 402: NMT, SDO, PDOs on "
        "SYNC, the power state machine, quick stop, SYNC and heartbeat watchdogs) and the "
        "robot's dynamics (eq. 4) on a python-can bus, so a bridge runs without hardware; "
        "several robots in one process, each on its own bus. Runs in real time until "
        "--duration or SIGINT/SIGTERM.",
    )
    _configure(p)
    p.set_defaults(func=run_emulate)


def run_emulate(args: argparse.Namespace) -> int:
    """The ``emulate`` command; returns the exit code."""

    import functools

    from bridges.drive_emulator import EmulatorFaults
    from bridges.drivers import entry
    from bridges.fleet_emulator import FleetEmulator
    from deploy.contract.scenario import ScenarioError, load_scenario

    def bad(msg: str) -> int:
        print(f"{PROG}: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT

    # SIGTERM as the launcher dies: the handler below stops the run
    if args.exit_with_parent and not die_with_parent():
        return bad("the process that started this one has ended")
    robots: list[int] = list(args.robot)
    checked = _checked_drives(args, robots)
    if isinstance(checked, str):
        return bad(checked)
    node_ids, truths = checked
    try:
        sc = load_scenario(args.scenario)
        for r in robots:
            sc.index_of(r)
    except ScenarioError as exc:
        return bad(f"bad scenario: {exc}")
    faults = [EmulatorFaults(args.drop_rate, args.corrupt_rate, args.silent_node,
                             args.silent_after or 0.0, args.seed + i, args.refuse_enable)
              for i in range(len(robots))]
    emulator = entry(args.driver).emulator()
    if args.eds is not None:
        emulator = functools.partial(emulator, eds=args.eds)
    try:
        buses = open_buses(args, len(robots))
    except CanBusError as exc:
        return bad(str(exc))
    try:
        fleet = FleetEmulator(sc, list(zip(robots, buses, strict=True)), node_ids,
                              args.encoder_rate, args.heartbeat_rate, args.watchdog_timeout,
                              args.physics_rate, faults=faults, emulator=emulator)
    except ValueError as exc:
        for bus in buses:
            bus.shutdown()
        return bad(str(exc))
    # its start-up heap out of the collector's passes, as every realtime node's
    # (deploy/runtime/heap.py): the one full pass of a 20 s run walked it for 19 ms at
    # SCHED_FIFO 10, above the bridges, whose periods it took (3-4 steps not simulated)
    freeze_startup_heap()  # before it says it runs
    stop_reason: list[str] = []
    previous = _install_signal_handlers(stop_reason)
    if args.priority:
        print(f"{PROG}: {raise_priority(args.priority)}", file=sys.stderr, flush=True)
    for r, ch in zip(robots, args.can_channel, strict=True):
        print(f"{PROG}: robot {r} of {sc.name!r}, {args.driver} drives "
              f"{','.join(map(str, node_ids))} on {args.can_interface}:{ch}", file=sys.stderr,
              flush=True)
    try:
        fleet.run(lambda: bool(stop_reason), args.duration)
    finally:  # also when a bus fails: shut them down and keep what was simulated
        for bus in buses:
            bus.shutdown()
        _restore_signal_handlers(previous)
        if truths:
            fleet.save_truth(truths)
    reason = stop_reason[0] if stop_reason else "end"
    _print_summary(fleet, reason)
    return _SIGNAL_EXIT.get(reason, 0)


def _checked_drives(args: argparse.Namespace, robots: list[int]
                    ) -> tuple[tuple[int, ...], list[Path]] | str:
    """The drives' node ids and the ground-truth files, or what is wrong with the options
    that name robots and drives (--robot, --node-ids, --silent-*, --refuse-enable,
    --truth-out)."""
    if len(set(robots)) != len(robots):
        return f"--robot given twice for the same robot: {robots}"
    if args.silent_after is not None and args.silent_node is None:
        return "--silent-after needs --silent-node"
    try:
        node_ids = driver_settings(args).node_ids
    except DriverOptionError as exc:
        return str(exc)
    for flag, node in (("--silent-node", args.silent_node), ("--refuse-enable", args.refuse_enable)):
        if node is not None and node not in node_ids:
            return f"{flag} {node} is not one of --node-ids {','.join(map(str, node_ids))}"
    truths = [check_file(t, "--truth-out") for t in args.truth_out or []]  # exit 2 (cli.main)
    if truths and len(truths) != len(robots):
        return f"give --truth-out once per --robot ({len(robots)}), or not at all"
    for truth in truths:
        if not truth.parent.is_dir():
            return f"--truth-out: no such directory {str(truth.parent)!r}"
    return node_ids, truths


def _print_summary(fleet: FleetEmulator, reason: str) -> None:
    """Each robot's end (time, frame counters, drive states) and the physics' lag."""
    lag = fleet.lag_stats()
    for emu in fleet.emulators:
        print(f"{PROG}: robot {emu.robot_id}: t = {emu.t:.3f} s ({reason}); "
              f"{emu.counters.summary()}; drives {emu.describe_drives()}", file=sys.stderr)
    print(f"{PROG}: lag behind the wall clock p50 {lag['p50'] * 1e3:.1f} ms, p99 "
          f"{lag['p99'] * 1e3:.1f} ms, max {lag['max'] * 1e3:.1f} ms", file=sys.stderr)


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
