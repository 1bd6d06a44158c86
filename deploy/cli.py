"""The ``omnifleet`` command line.

Exit codes: 0 success, 1 the run failed (a node died) or did not meet the
scenario's criteria (with ``--check``), 2 bad input (scenario, arguments,
zenoh configuration, an output path that cannot be written), 3 a node lost a peer it cannot run without, 130
interrupted (SIGINT), 143 terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import sys

from deploy.contract.plant_registry import find_plant
from deploy.run.node_forks import close_early, start_early

# What the parser needs is imported when it is built, not with this module: a run that
# starts a fleet starts the nodes' fork server first, and its imports then run beside
# these (~0.2 s of CPU each; deploy/nodes/forks.py).


def package_version() -> str:
    """The installed package's version (its metadata, from pyproject.toml)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("omnifleet")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


class _Version(argparse.Action):
    """``--version``: the package's metadata read only when asked (importlib.metadata
    costs ~11 ms, on every command otherwise)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(f"omnifleet {package_version()}")  # on stdout, as argparse's own
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    from deploy.contract.options import add_option
    from deploy.contract.plant_registry import CAN_EMULATED, add_plant_option
    from deploy.contract.scenario import bundled_names
    from deploy.nodes.can_options import add_driver_option
    from deploy.nodes.cli import CLOCKS, add_law_option
    from deploy.nodes.entry import add_every_node_command
    from deploy.run.run_cli import cmd_run
    from deploy.runtime.priority import EMULATOR_PRIORITY, REALTIME_PRIORITY, WORLD_ABOVE_AGENTS

    p = argparse.ArgumentParser(
        prog="omnifleet",
        description="Collision-free formation control for mecanum-wheel robot fleets. "
        "Start with `omnifleet scenario list` and `omnifleet run lab --in-process` (a report "
        "folder in runs/lab/, ending with a verdict); COMMAND --help says more, README.md "
        "and docs/ the rest.",
    )
    p.add_argument("--version", action=_Version, nargs=0,
                   help="show the installed version and exit")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = sub.add_parser(
        "run", help="run a scenario and write its report folder",
        description="Run a scenario (a TOML file, or the name of a bundled one: "
        f"{', '.join(bundled_names())}; `omnifleet scenario list` says what each is) and "
        "write metrics.json, timeseries.npz, recording.mcap and the figures to --out, "
        "ending with the verdict (docs/outputs.md).",
    )
    run.add_argument("scenario", help="scenario file or bundled scenario name")
    run.add_argument("--in-process", action="store_true",
                     help="run leader, plant and all agents in this process (the reference "
                     "loop) instead of one process per node")
    add_plant_option(run, in_process=False)
    add_driver_option(run, None, f"--plant {CAN_EMULATED}: the drives' CAN protocol, for the "
                      "bridges and the emulator")
    run.add_argument("--gui", action="store_true",
                     help="pybullet: open the simulator's window (needs a display)")
    run.add_argument("--clock", choices=CLOCKS, default=None,
                     help="lockstep: deterministic, equals --in-process; realtime: every "
                     "process on its own clock at the scenario's rates (default: lockstep)")
    add_option(run, "--step-deadline")
    add_option(run, "--startup-timeout")
    run.add_argument("--fleet", help="fleet name: keys are omr/<fleet>/... (default: the "
                     "scenario's name; two runs on one machine never link: each has its own "
                     "private endpoints)")
    run.add_argument("--endpoint", metavar="ENDPOINT",
                     help="zenoh endpoint the launcher listens on and the nodes connect to "
                     "(default: a unix socket in the run's private directory)")
    run.add_argument("--zenoh-transport", choices=("default", "lowlatency"),
                     default="default",
                     help="zenoh's unicast transport between the run's nodes: zenoh's default, "
                     "or lowlatency (a put is written by the publishing thread: a hop ~20 %% "
                     "faster here, but zenoh 1.10.2 lost 1 in 24 messages over 64 kB on it, "
                     "e.g. a node's final report; docs/distributed.md) (default: default)")
    run.add_argument("--data-path", choices=("datagram", "zenoh"), default="datagram",
                     help="how the per-step data (samples, replies, leader, telemetry, state "
                     "logs) travels between the run's processes: unix datagrams in the run's "
                     "private directory, ~5x cheaper than a zenoh hop on one host, with "
                     "control, liveliness and reports on zenoh; or all of it on zenoh, as "
                     "across hosts (docs/distributed.md) (default: datagram)")
    run.add_argument("--no-record", action="store_true",
                     help="do not write recording.mcap (the scene, plot signals and, for one "
                     "process per node, every wire message, in Foxglove's schemas; docs/foxglove.md)")
    run.add_argument("--live", metavar="[HOST:]PORT", nargs="?", const=str(8765),
                     help="serve the scene and plots over Foxglove's WebSocket protocol while the "
                     "run goes (default 127.0.0.1:8765; loopback unless HOST is given, e.g. "
                     "0.0.0.0:8765; port 0: any free one)")
    from deploy.ros2.options import add_ros2_options

    add_ros2_options(run)
    run.add_argument("--out", metavar="DIR", help="output folder (default: runs/<scenario>)")
    add_option(run, "--duration")
    add_option(run, "--control-rate")
    add_law_option(run)
    run.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    run.add_argument("--overwrite", action="store_true",
                     help="--out already holds a run: remove its outputs first (without it "
                     "such a folder is refused: a run never mixes its outputs with another's)")
    add_option(run, "--priority", default=REALTIME_PRIORITY,
               help="realtime: run every node's loop under SCHED_FIFO at priority N and "
               "at nice -N (its session's autogroup too; needs CAP_SYS_NICE, else each "
               "node says so), so other work on the host does not stall the control "
               "loops, and the "
               f"simulated plant's by N + {WORLD_ABOVE_AGENTS} (it is the fleet's clock); 0 "
               "leaves them at normal priority; the driver emulator always asks for "
               f"{EMULATOR_PRIORITY}")
    run.add_argument("--faults", metavar="PLAN",
                     help="inject the faults of a fault plan (TOML; docs/faults.md): lossy, "
                     "delayed or partitioned links, killed and restarted processes, CAN frame "
                     "loss; counted per link in metrics.json")
    run.add_argument("--check", action="store_true",
                     help="exit 1 unless the verdict is PASS: every robot settles before "
                     "sqrt(2) T_p and ends at its formation position, no contact, nothing "
                     "non-finite, the whole run simulated and heard (docs/outputs.md)")
    run.set_defaults(func=cmd_run)
    add_every_node_command(sub)
    from deploy.bench.suite import add_bench_command
    from deploy.nodes.can_check_cli import add_can_check_command
    from deploy.run.fault_sweep import add_faults_command

    add_can_check_command(sub)
    add_bench_command(sub)
    add_faults_command(sub)
    from deploy.run.compare import add_compare_command
    from deploy.run.safety_sweep import add_safety_command

    add_safety_command(sub)
    add_compare_command(sub)
    from deploy.fleet.cli import add_deploy_commands
    from deploy.scenario_cli import add_scenario_commands

    add_scenario_commands(sub)
    from deploy.fleet.router import add_router_command
    from deploy.report.view import add_view_command
    from deploy.run.record import add_record_command

    add_record_command(sub)
    add_view_command(sub)
    add_router_command(sub)
    add_deploy_commands(sub)
    return p


def fleet_clock(argv: list[str]) -> str | None:
    """The clock of the fleet ``omnifleet run ...`` will start (``--clock``, lockstep by
    default, realtime for a ``--plant`` that runs on the wall clock only), or None: not a
    run, ``--in-process``, or help. A scenario's own plant is not read here."""
    if argv[:1] != ["run"] or "--in-process" in argv or {"-h", "--help"} & set(argv):
        return None
    options: dict[str, str] = {}
    for i, a in enumerate(argv):
        for name in ("--clock", "--plant"):
            if a == name and i + 1 < len(argv):
                options[name] = argv[i + 1]
            elif a.startswith(f"{name}="):
                options[name] = a.removeprefix(f"{name}=")
    plant = find_plant(options["--plant"]) if "--plant" in options else None
    if plant is not None and plant.realtime_only:
        return "realtime"
    return options.get("--clock", "lockstep")


def main(argv: list[str] | None = None) -> int:
    clock = fleet_clock(sys.argv[1:] if argv is None else argv)
    if clock is not None:
        start_early(clock)  # its nodes' fork server, when they are forked
    try:
        from deploy.nodes.entry import dispatch

        return dispatch(build_parser().parse_args(argv))
    finally:
        close_early()  # started, and no run took it (bad input, an early error)


if __name__ == "__main__":
    sys.exit(main())
