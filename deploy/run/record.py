"""``omnifleet record``: the launcher's recorder without the launcher, for a fleet
whose nodes run on several machines.

It joins the fleet as role ``launcher`` (so nodes started with
``--wait-recorder`` wait for it and the recording misses nothing), hears the
fleet's keys, and when the plant ends the run writes the same folder as
``omnifleet run``: ``metrics.json``, ``timeseries.npz``, ``recording.mcap``,
figures. It also writes what liveliness told it: every role that disappeared
and reappeared, with wall-clock times (``liveliness`` in metrics.json).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from deploy.contract.keyring import Keyring, KeysError
from deploy.contract.options import EXIT_BAD_INPUT, add_option
from deploy.contract.output_paths import check_folder
from deploy.contract.scenario import Scenario
from deploy.contract.wire import LAUNCHER_ROLE, run_roles
from deploy.nodes.cli import add_keys_options, keyring_of, run_scenario
from deploy.run.launcher import Interrupted, LaunchOptions, make_observer, observing
from deploy.run.run_figures import run_figures
from deploy.runtime.node_runtime import StopFlag
from deploy.runtime.transport import Node, zenoh_config


class Recorder:
    """The launcher's :class:`Observer` without its plan or supervisor: the nodes run
    elsewhere, and this peer joins them through ``listen``/``connect`` endpoints or a
    zenoh configuration file (TLS and access control across hosts, deploy/fleet/)."""

    def __init__(self, sc: Scenario, opts: LaunchOptions, zenoh_file: str | None = None,
                 listen: list[str] | None = None, connect: list[str] | None = None,
                 keyring: Keyring | None = None) -> None:
        self.sc, self.opts = sc, opts
        self.zenoh_file, self.listen, self.connect = zenoh_file, listen, connect
        # the nodes run elsewhere, started by hand or by systemd: with the launcher's
        # keyring of `omnifleet deploy certs` (--keys) what they tag for it is checked;
        # without, the ACL alone says who may publish what (deploy/fleet/acl.py)
        self.keyring = keyring
        self.observer = make_observer(sc, opts, keyring)
        self.observer.on_report = self._on_report
        self.stop = StopFlag()
        self.reported_ns: dict[str, int] = {}  # role -> when its report arrived (wall, ns)

    def _on_report(self, role: str) -> None:
        # a node reports as it leaves, on the same link as its token: a token that goes
        # after the report is a departure, not a loss
        self.reported_ns.setdefault(role, time.time_ns())

    def run(self, progress=None) -> dict[str, Any]:
        o, obs = self.opts, self.observer
        o.out.mkdir(parents=True, exist_ok=True)
        node = Node(LAUNCHER_ROLE, obs.keys, obs.codec,
                    zenoh_config(self.zenoh_file, self.listen, self.connect),
                    keyring=self.keyring)
        zid = node.zid
        roles = run_roles(self.sc.robot_ids)
        with observing(obs, o, node, self.stop):
            missing = node.wait_for_roles(roles, "ready", o.startup_timeout_s, self.stop)
            if self.stop():
                raise Interrupted(self.stop.reason)
            if missing:
                raise TimeoutError(f"not ready after {o.startup_timeout_s:.0f} s: "
                                   f"{', '.join(sorted(missing))}")
            start = time.perf_counter()
            # the run ends with the plant's ``end``, or early with a genuine stop or estop
            # (no ``end`` follows one: the nodes leave, each sending its report)
            while not obs.ended and obs.stopped_by is None:
                if self.stop():
                    raise Interrupted(self.stop.reason)
                if progress is not None:
                    progress(obs.progress_k + 1, obs.steps)
                node.mailbox.wait_until(
                    lambda: obs.ended or obs.stopped_by is not None or self.stop(), 0.1)
            wall = time.perf_counter() - start
            if progress is not None:  # the steps the plant says it simulated, no more
                progress(obs.progress_k + 1, obs.steps)
            # every node reports as it ends; wait for those still alive
            node.mailbox.wait_until(
                lambda: set(obs.collector.reports) >= set(roles) or self.stop(), 10.0)
            closing_ns = time.time_ns()  # tokens seen to go after this: our own closing
        out = run_figures(obs, [], zid, wall, expected_roles=list(roles))
        out["processes"] += [  # the nodes ran elsewhere: what each reported
            {"role": r.role, "robot": None if r.robot < 0 else r.robot, "pid": None,
             "peak_rss_mb": round(r.peak_rss_kb / 1024.0, 1) if r.peak_rss_kb else None,
             "exit_code": None, "reported": True, "steps": r.steps, "sent": r.sent,
             "late": r.late, "received": dict(r.received)}
            for r in sorted(obs.collector.reports.values(), key=lambda r: r.role)]
        out["liveliness"] = liveliness_summary(
            [e for e in node.peer_events if e[0] < min(closing_ns, obs.end_unix_ns or closing_ns)
             and e[1] != LAUNCHER_ROLE],
            self.reported_ns)
        return out


def liveliness_summary(events: list[tuple[int, str, bool]],
                       reported_ns: dict[str, int]) -> dict[str, Any]:
    """Per role: how often its token went away during the run, and when it went
    and came back (wall clock, ns), from the node's liveliness events (time,
    role, alive), those after the run's end already left out. A token that goes
    after the role's report arrived is the node leaving: not counted either. (A
    node that leaves before the recorder has read ``end`` — a recorder behind on
    traffic — is still counted once, with no return.)"""
    out: dict[str, Any] = {}
    for t, role, alive in events:
        if t >= reported_ns.get(role, 1 << 62):
            continue
        r = out.setdefault(role, {"lost": 0, "lost_at_unix_ns": [], "back_at_unix_ns": []})
        if not alive:
            r["lost"] += 1
            r["lost_at_unix_ns"].append(t)
        elif r["lost"]:  # a return after a loss (the first appearance is not one)
            r["back_at_unix_ns"].append(t)
    return {role: r for role, r in out.items() if r["lost"]}


def log_progress(every_s: float = 1.0):
    """Progress as log lines (``record: step K/N``), at most one per ``every_s``:
    a recorder under systemd or in a test has no terminal."""
    last = [0.0]

    def update(done: int, total: int) -> None:
        now = time.monotonic()
        if now - last[0] >= every_s or done >= total:
            last[0] = now
            print(f"record: step {done}/{total}", file=sys.stderr, flush=True)
    return update


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
        recording = McapRecorder(Path(args.out) / "recording.mcap",
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

