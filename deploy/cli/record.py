"""``omnifleet record``'s command line: a fleet started elsewhere heard, judged and written
(the recorder: deploy/run/record.py)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from deploy.contract.keyring import KeysError
from deploy.contract.options import EXIT_BAD_INPUT, add_option
from deploy.contract.output_paths import check_folder
from deploy.contract.scenario import Scenario
from deploy.contract.wire import LAUNCHER_ROLE
from deploy.nodes.cli import add_keys_options, keyring_of, run_scenario
from deploy.report.run_folder import RECORDING
from deploy.run.launcher import Interrupted, LaunchOptions
from deploy.run.record import Recorder, log_progress


def _cmd_record(args: argparse.Namespace) -> int:
    from deploy.run.runner import terminal_progress

    sc: Scenario = run_scenario(args)
    plant = args.plant or sc.spec.plant.kind
    from deploy.report.run_folder import RunFolderError, prepare

    check_folder(args.out, "--out")  # OutputPathError: exit 2 (cli.main), before anything
    try:
        removed = prepare(Path(args.out), args.overwrite)
    except RunFolderError as exc:
        print(f"omnifleet record: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if removed:
        print(f"omnifleet record: --overwrite: removed the previous run's {', '.join(removed)}",
              file=sys.stderr)
    try:
        keyring = keyring_of(args, sc, LAUNCHER_ROLE)
    except KeysError as exc:
        print(f"omnifleet record: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    opts = LaunchOptions(scenario_arg=args.scenario, plant=plant, clock=args.clock,
                         out=Path(args.out), duration_s=args.duration,
                         control_rate_hz=args.control_rate,
                         startup_timeout_s=args.startup_timeout, fleet=args.fleet or sc.name,
                         record=not args.no_record, spool=False)
    recording = None
    if not args.no_record:  # ours, so that the scene joins it at the end (docs/foxglove.md)
        from deploy.report.recorder import McapRecorder

        Path(args.out).mkdir(parents=True, exist_ok=True)
        recording = McapRecorder(Path(args.out) / RECORDING,
                                 sim_dt=sc.dt if args.clock == "lockstep" else None)
        opts.recorder = recording
    rec = Recorder(sc, opts, args.zenoh_config, args.listen, args.connect, keyring)
    from deploy.ros2.gateway import gateway_from_args

    ros2 = gateway_from_args(args, sc, plant, "omnifleet record")
    if ros2 is False:
        if recording is not None:
            recording.close()
        return EXIT_BAD_INPUT
    if ros2 is not None:
        from deploy.report.live_view import collector_rows

        ros2.bind_observer(rec.observer)
        ros2.follow(rec.observer.collector.ts,
                    collector_rows(rec.observer.collector, args.clock == "realtime"),
                    driven=True)
    progress = terminal_progress(f"{sc.name} ({plant}, {args.clock})") or log_progress()
    if ros2 is not None:
        from deploy.ros2.gateway import polling

        progress = polling(progress, ros2)
    try:
        extra = rec.run(progress)
    except BaseException as exc:
        if recording is not None:
            recording.close()  # flushed, also when the run did not end
        if ros2 is not None:
            ros2.close()
        return _ended_early(exc)
    metrics = _write_outputs(args, sc, plant, rec, opts, recording, extra)
    if ros2 is not None:
        ros2.close(metrics["verdict"])
        print(ros2.summary(), file=sys.stderr)
    print(f"omnifleet record: {metrics['steps']} steps written to {args.out} "
          f"({', '.join(metrics['files'])})", file=sys.stderr)
    broken = (metrics.get("recording") or {}).get("error")
    if broken:
        print(f"omnifleet record: FAILED: the recording failed ({broken}); "
              f"{metrics['recording']['lost']} message(s) not recorded", file=sys.stderr)
        return 1
    return 0


def _ended_early(exc: BaseException) -> int:
    """The exit code of a recording that did not reach its end (its outputs are closed):
    4 when the fleet never came, 130/143 on Ctrl-C/SIGTERM; anything else is raised."""
    if isinstance(exc, TimeoutError):
        print(f"omnifleet record: {exc}", file=sys.stderr)
        return 4
    if isinstance(exc, Interrupted):
        print(f"omnifleet record: interrupted ({exc.signal_name})", file=sys.stderr)
        return 143 if exc.signal_name == "SIGTERM" else 130
    raise exc


def _write_outputs(args: argparse.Namespace, sc: Scenario, plant: str, rec: Recorder,
                   opts: LaunchOptions, recording: Any, extra: dict[str, Any]) -> dict[str, Any]:
    """The run folder of what was heard (metrics, series, figures, the recording closed);
    its metrics."""
    from deploy.report.outputs import run_wall_clock, write_run

    end_unix_ns = time.time_ns()
    series = rec.observer.collector.series(realtime=args.clock == "realtime")
    wall, messages = extra.pop("wall_time_s"), extra.pop("messages")
    contact_log, total = extra.pop("contact_log", None), extra.pop("contacts_total", None)
    return write_run(sc, series, Path(args.out), plant, args.clock, wall, messages, extra,
                     figures=not args.no_figures, contact_log=contact_log,
                     contacts_total=total, recorder=recording, steps_asked=opts.steps(sc),
                     **run_wall_clock(end_unix_ns, wall, rec.observer.run_t0, series.steps,
                                      args.clock == "lockstep"))


def add_record_command(sub: argparse._SubParsersAction) -> None:
    from deploy.contract.plant_registry import add_plant_option
    from deploy.nodes.cli import CLOCKS

    p = sub.add_parser(
        "record", help="record a fleet whose nodes run elsewhere and write its report folder",
        description="Joins the fleet as the recorder (role launcher): start the nodes with "
        "--wait-recorder so that they wait for it. Writes metrics.json, timeseries.npz, "
        "recording.mcap and figures to --out when the plant ends the run.")
    p.add_argument("--scenario", required=True, help="scenario file or bundled name")
    p.add_argument("--fleet", help="fleet name (default: the scenario's name)")
    p.add_argument("--clock", choices=CLOCKS, default="lockstep", help="default: lockstep")
    add_plant_option(p, help_tail="the plant the fleet runs, for the report; default: the "
                     "scenario's")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--zenoh-config", metavar="FILE", help="a zenoh JSON5 config file")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    add_keys_options(p)
    add_option(p, "--duration", more_help="give the nodes the same")
    add_option(p, "--control-rate", more_help="give the nodes the same")
    add_option(p, "--startup-timeout", default=120.0)
    p.add_argument("--no-record", action="store_true", help="no recording.mcap")
    from deploy.ros2.options import add_ros2_options

    add_ros2_options(p)
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--overwrite", action="store_true",
                   help="--out already holds a run: remove its outputs first (else refused)")
    p.set_defaults(func=_cmd_record)
