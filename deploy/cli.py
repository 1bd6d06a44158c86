"""The ``omnifleet`` command line.

Exit codes: 0 success, 1 the run failed (a node died) or did not meet the
scenario's criteria (with ``--check``), 2 bad input (scenario, arguments,
zenoh configuration), 3 a node lost a peer it cannot run without, 130
interrupted (SIGINT), 143 terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from deploy.contract.fault_plan import FaultPlanError
from deploy.contract.options import EXIT_BAD_INPUT, OptionError, add_option
from deploy.contract.scenario import PLANT_KINDS, ScenarioError
from deploy.contract.wire import FleetNameError, Keys
from deploy.nodes.cli import CLOCKS, add_node_commands, fault_plan, gui_problem, run_scenario
from deploy.report.run_folder import RunFolderError
from deploy.report.run_folder import prepare as prepare_run_folder
from deploy.report.verdict import divergence_banner, judge, verdict_line
from deploy.runtime.fault_model import fault_metrics
from deploy.runtime.priority import EMULATOR_PRIORITY, REALTIME_PRIORITY
from deploy.runtime.transport import TransportError

RECORDING = "recording.mcap"


def _cmd_run(args: argparse.Namespace) -> int:
    sc = run_scenario(args)  # the ranges were checked on parse (deploy/contract/options.py)
    plant = args.plant or sc.spec.plant.kind
    if plant == "can-emulated":  # hardware through emulated drivers runs on the wall clock
        if args.in_process or args.clock == "lockstep":
            print("omnifleet run: --plant can-emulated runs realtime, one process per node",
                  file=sys.stderr)
            return EXIT_BAD_INPUT
        args.clock = "realtime"
    args.clock = args.clock or "lockstep"
    problem = gui_problem(plant, args.gui)
    if problem:
        print(f"omnifleet run: {problem}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.in_process and args.clock == "realtime":
        print("omnifleet run: --in-process runs lockstep only", file=sys.stderr)
        return EXIT_BAD_INPUT
    plan = fault_plan(args, sc)
    if plan is not None and plan.kills and args.clock != "realtime":
        print("omnifleet run: a fault plan that kills processes needs --clock realtime (in "
              "lockstep the plant would wait for the dead agent's commands)", file=sys.stderr)
        return EXIT_BAD_INPUT
    for note in sc.notes:
        print(f"note: {note}", file=sys.stderr)
    if not args.in_process:
        Keys(args.fleet or sc.name)  # FleetNameError: exit 2 (main), before --out is touched
    out = Path(args.out) if args.out else Path("runs") / sc.name
    try:
        removed = prepare_run_folder(out, args.overwrite)
    except RunFolderError as exc:
        print(f"omnifleet run: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if removed:
        print(f"omnifleet run: --overwrite: removed the previous run's {', '.join(removed)} "
              f"from {out}/", file=sys.stderr)
    label = f"{sc.name} ({plant}, {'in-process' if args.in_process else args.clock})"
    live = _start_live(args, sc)
    if live is False:
        return EXIT_BAD_INPUT
    try:
        if args.in_process:
            metrics = _run_in_process(sc, args, plant, plan, out, label, live)
        else:
            metrics = _run_distributed(sc, args, plant, out, label, live)
            if metrics is None:
                return 1
    finally:
        if live is not None:
            live.close()
            print(f"live view: {live.published} messages served, {live.cpu_s:.2f} s CPU; stopped",
                  file=sys.stderr)
    banner = divergence_banner(metrics["verdict"])
    if banner:
        print(banner, file=sys.stderr)
    print(_summary(metrics, out))
    broken = (metrics.get("recording") or {}).get("error")
    if broken:  # never a run that looks complete with a recording that is not
        print(f"omnifleet run: FAILED: the recording failed ({broken}); "
              f"{metrics['recording']['lost']} message(s) not recorded", file=sys.stderr)
        return 1
    if args.check and not metrics["verdict"]["pass"]:
        print("omnifleet run: the run does NOT meet the criteria (settling, no contact, "
              "nothing non-finite)", file=sys.stderr)
        return 1
    return 0


def _run_in_process(sc, args: argparse.Namespace, plant: str, plan, out: Path, label: str, live):
    from deploy.report.outputs import write_run
    from deploy.report.recorder import McapRecorder
    from deploy.run.runner import run_in_process, run_progress

    progress = _with_live(run_progress(label), live)
    result = run_in_process(sc, plant, args.duration, progress, gui=args.gui, faults=plan,
                            on_series=None if live is None else live.follow)
    extra = {} if plan is None else {"faults": fault_metrics(plan, result.faults or {})}
    extra["law_resets"] = result.law_resets
    extra["torque_clipped"] = {str(r): n for r, n in (result.torque_clipped or {}).items()}
    recorder = None
    if not args.no_record:
        out.mkdir(parents=True, exist_ok=True)
        recorder = McapRecorder(out / RECORDING, sim_dt=sc.dt)
    if result.interrupted:
        from deploy.report.outputs import write_interrupted

        metrics = write_interrupted(sc, result.series, out, plant, "lockstep",
                                    result.wall_time_s, result.interrupted, extra, recorder,
                                    contact_log=result.contacts, step_unix_ns=result.step_unix_ns)
        _interrupted(metrics, out)
    return write_run(sc, result.series, out, plant, "lockstep", result.wall_time_s,
                     extra=extra, figures=not args.no_figures, contact_log=result.contacts,
                     recorder=recorder, step_unix_ns=result.step_unix_ns)


def _interrupted(metrics: dict, out: Path) -> None:
    """Say what an interrupted run wrote, then end as interrupted (exit 130/143)."""
    print(_summary(metrics, out) if metrics.get("steps") else
          f"{metrics['scenario']}: interrupted before any step; written to {out}/ "
          f"({', '.join(metrics['files'])})\n{verdict_line(metrics['verdict'])}")
    exc = KeyboardInterrupt(metrics["interrupted_by"])
    exc.signal_name = metrics["interrupted_by"]  # type: ignore[attr-defined]
    raise exc


def _start_live(args: argparse.Namespace, sc):
    """The --live view (None without it; False: a bad address, already said)."""
    if args.live is None:
        return None
    from deploy.report.live_view import LiveView
    from deploy.report.ws_address import LiveAddressError, parse_address, url

    try:
        host, port = parse_address(args.live)
        live = LiveView(sc, host, port, realtime=args.clock == "realtime")
    except (LiveAddressError, RuntimeError, OSError) as exc:
        print(f"omnifleet run: --live {args.live}: {exc}", file=sys.stderr)
        return False
    print(f"live view: {url(host, live.port)} (Foxglove: Open connection -> "
          "Foxglove WebSocket; layout docs/foxglove-layout.json)", file=sys.stderr, flush=True)
    return live


def _with_live(progress, live):
    """A progress callback that also tells the live view how far the series is."""
    if live is None:
        return progress

    def both(done: int, total: int) -> None:
        live.publish(done - 1)
        if progress is not None:
            progress(done, total)

    return both


def _run_distributed(sc, args: argparse.Namespace, plant: str, out: Path, label: str, live=None):
    import time

    from deploy.report.outputs import run_wall_clock, write_run
    from deploy.report.recorder import McapRecorder
    from deploy.run.launcher import Interrupted, Launcher, LaunchOptions, RunFailed
    from deploy.run.runner import run_progress

    recorder = None
    if not args.no_record:  # ours, so that the scene joins it at the end (LaunchOptions.recorder)
        out.mkdir(parents=True, exist_ok=True)
        recorder = McapRecorder(out / RECORDING,
                                sim_dt=sc.dt if args.clock == "lockstep" else None)
    opts = LaunchOptions(
        scenario_arg=args.scenario, plant=plant, clock=args.clock, out=out,
        duration_s=args.duration, control_rate_hz=args.control_rate,
        step_deadline_s=args.step_deadline, startup_timeout_s=args.startup_timeout,
        record=not args.no_record, fleet=args.fleet, endpoint=args.endpoint, gui=args.gui,
        faults=fault_plan(args, sc), realtime_priority=args.priority, recorder=recorder,
        lowlatency=args.zenoh_transport == "lowlatency",
    )
    launcher = Launcher(sc, opts)
    if live is not None:
        from deploy.report.live_view import collector_rows

        live.follow(launcher.collector.ts, collector_rows(launcher.collector, args.clock == "realtime"))
    started = time.perf_counter()
    try:
        extra = launcher.run(run_progress(label))
    except RunFailed as exc:
        print(f"omnifleet run: FAILED: {exc}", file=sys.stderr)
        if recorder is not None:
            recorder.close()
        return None
    except Interrupted as exc:  # every child stopped: write what was measured, marked
        from deploy.report.outputs import write_interrupted

        series = launcher.collector.series(realtime=args.clock == "realtime")
        metrics = write_interrupted(
            sc, series, out, plant, args.clock, time.perf_counter() - started, exc.signal_name,
            {"messages": None, "reports": "not collected (interrupted)",
             "law_resets": None}, recorder)
        _interrupted(metrics, out)
    except BaseException:
        if recorder is not None:
            recorder.close()  # flushed, also after Ctrl-C
        raise
    end_unix_ns = time.time_ns()
    series = launcher.collector.series(realtime=args.clock == "realtime")
    if args.clock == "realtime":
        extra["series_cells_filled"] = launcher.collector.filled
    if launcher.truth_files and launcher.t0_mono is not None:
        from deploy.report.odometry_drift import odometry_drift

        extra["odometry_drift"] = odometry_drift(series, sc.robot_ids, launcher.truth_files,
                                                 launcher.t0_mono, launcher.collector.have_state)
        extra["emulator_lag_ms"] = emulator_lag_ms(launcher.truth_files)
        c = launcher.collector
        got = c.have_state.sum(axis=0)
        extra["bridge_faulted_fraction"] = [
            float(f) / g if g else None for f, g in zip(c.faulted.sum(axis=0), got, strict=True)]
        if "faults" in extra:
            extra["faults"]["can"] = can_fault_counts(launcher.truth_files)
    # an agent counts every non-finite command it computed; the series only the rows its
    # telemetry carried (realtime decimates them): the larger of the two
    reported = [x for x in extra.get("nonfinite_commands_reported", []) if x is not None]
    extra["nonfinite_commands"] = max(int(series.nonfinite.sum()), sum(reported))
    wall = extra.pop("wall_time_s")
    messages = extra.pop("messages")
    contact_log, contacts_total = extra.pop("contact_log", None), extra.pop("contacts_total", None)
    # the wall clock of each step for the scene (the wire messages carry their own)
    return write_run(sc, series, out, plant, args.clock, wall, messages, extra,
                     figures=not args.no_figures, contact_log=contact_log,
                     contacts_total=contacts_total, recorder=recorder,
                     **run_wall_clock(end_unix_ns, wall, launcher.run_t0, series.steps,
                                      args.clock == "lockstep"))


def emulator_lag_ms(truth_files: dict[int, Path]) -> dict[str, float | None]:
    """How far the driver emulator's physics was behind the wall clock during the
    run (sampled every 10 ms; every robot's truth file carries the same log)."""
    import numpy as np

    for path in truth_files.values():
        try:
            with np.load(path) as d:
                lag = np.asarray(d["lag_s"], float) * 1e3
        except (OSError, KeyError, ValueError):
            continue
        if len(lag):
            return {"p50": float(np.median(lag)), "p99": float(np.percentile(lag, 99)),
                    "max": float(lag.max())}
    return {"p50": None, "p99": None, "max": None}


def can_fault_counts(truth_files: dict[int, Path]) -> dict[str, dict[str, int]]:
    """Frames each robot's driver emulator lost or corrupted (the plan's [can])."""
    import numpy as np

    out = {}
    for robot, path in truth_files.items():
        try:
            with np.load(path) as d:
                out[f"robot-{robot}"] = {"dropped": int(d["dropped_by_fault"]),
                                         "corrupted": int(d["corrupted_by_fault"])}
        except (OSError, KeyError, ValueError):
            out[f"robot-{robot}"] = {"dropped": -1, "corrupted": -1}  # no truth file: unknown
    return out


def meets_paper_criteria(m: dict) -> bool:
    """Every robot settles before sqrt(2) T_p; no contact, ever; nothing non-finite."""
    return (m["verdict"] if "verdict" in m else judge(m))["pass"]


def _fmt_list(xs) -> str:
    return "[" + ", ".join("never" if x is None else f"{x:.3f}" for x in xs) + "]"


def _summary(m: dict, out: Path) -> str:
    def f(x):
        return "n/a" if x is None else f"{x:.3f}"

    return "\n".join([
        f"{m['scenario']}: {m['robots']} robots, {m['plant']} plant, {m['clock']}, "
        f"{m['sim_time_s']:.2f} s simulated in {m['wall_time_s']:.2f} s "
        f"(x{m['real_time_factor']:.2f} real time)",
        *([f"  INTERRUPTED ({m.get('interrupted_by')}): what follows covers the "
           f"{m['sim_time_s']:.2f} s measured before it; no figures"] if m.get("interrupted")
          else []),
        "  settling time (s)          "
        + ("n/a (kinematic plant: no dynamic level)" if m["plant"] == "kinematic" else
           f"{_fmt_list(m['settling_time_s'])}  bound {m['settling_bound_s']:.3f}"),
        f"  formation RMS, whole run   {_fmt_list(m['formation_rms_whole_run_m'])} m",
        "  ... after settling         " + ("n/a (kinematic plant: no settling)"
                                             if m["plant"] == "kinematic" else
                                             f"{_fmt_list(m['formation_rms_after_settling_m'])} m"),
        f"  min gap to an obstacle     {f(m['min_obstacle_gap_m'])} m (surface to surface)",
        f"  min gap between robots     {f(m['min_robot_gap_m'])} m (surface to surface)",
        f"  contacts                   {m['contacts']}",
        f"  peak / RMS torque (N m)    {m['peak_torque_nm']:.4g} / {m['rms_torque_nm']:.4g}",
        *_safety_lines(m),
        *_law_lines(m),
        *_transport_lines(m),
        *_hardening_lines(m),
        f"  written to {out}/ ({', '.join(m.get('files') or ['metrics.json'])})",
        *([verdict_line(m["verdict"])] if "verdict" in m else []),
    ])


def _law_lines(m: dict) -> list[str]:
    """How often each robot's law restarted from the robot, what it computed non-finite,
    and (realtime) the longest stretch each robot ran on zero torque."""
    resets = m.get("law_resets")
    if resets is None:  # an interrupted distributed run: the agents never reported
        return ["  law restarts               n/a (the agents' reports were not collected)"]
    lines = [f"  law restarts               {_fmt_ints(resets)} (from the robot's state: a gap "
             f"or a non-finite state); non-finite commands {m.get('nonfinite_commands', 0)}"]
    longest = m.get("zero_torque_longest_s")
    if longest is not None:
        lines.append(f"  longest on zero torque     {_fmt_list(longest)} s (command timeout "
                     f"{m['command_timeout_s']:.3f} s)")
    return lines


def _fmt_ints(xs: list) -> str:
    return "[" + ", ".join("n/a" if x is None else str(x) for x in xs) + "]"


def _hardening_lines(m: dict) -> list[str]:
    """A run stopped early, and commands clipped to the torque bound."""
    lines = []
    s = m.get("stopped_by")
    if s:
        at = "" if s.get("t_s") is None else f" at t = {s['t_s']:.3f} s"
        lines.append(f"  STOPPED                    by ctl/{s['command']}{at} (sender {s['sender']}): "
                     "the run did not go to its end")
    refused = (m.get("messages") or {}).get("refused") or {}
    if refused:
        lines.append(f"  refused on arrival         {sum(refused.values())} message(s) by "
                     f"{len({k.split(':')[0] for k in refused})} node(s) "
                     "(metrics.json messages.refused: by node and reason)")
    clipped = m.get("torque_clipped") or {}
    if any(clipped.values()):
        lines.append("  torque clipped to bound    "
                     + ", ".join(f"robot {r}: {n}" for r, n in clipped.items() if n)
                     + " command(s)")
    return lines


def _safety_lines(m: dict) -> list[str]:
    f = m.get("safety_filter")
    if not f:
        return []
    if not any(f["active_steps"]):
        return ["  safety filter              never acted (the paper's law as it is)"]
    line = (f"  safety filter              acted {_fmt_list(f['active_time_s'])} s in "
            f"{f['episodes']} episode(s), command changed by up to {_fmt_list(f['max_dv_mps'])} m/s")
    if any(f["infeasible_steps"]):
        line += f"; no safe command within the limits on {f['infeasible_steps']} step(s)"
    return [line]


def _transport_lines(m: dict) -> list[str]:
    if "processes" not in m:
        return []
    msg = m["messages"]
    lines = [f"  messages                   sent {msg['sent']}, dropped {msg['dropped']}, "
             f"late {msg['late']}, invalid {msg['invalid']}"]
    rss = [p["peak_rss_mb"] for p in m["processes"] if p["peak_rss_mb"] is not None]
    lines.append(f"  processes                  {len(m['processes'])}, peak RSS up to "
                 f"{max(rss):.0f} MB" if rss else f"  processes                  {len(m['processes'])}")
    if "latency_ms" in m:
        lat, jit = m["latency_ms"], m["jitter_ms"]

        def ms(x):
            return "n/a" if x is None else f"{x:.3f}"

        if "bridge_latency_ms" in m:  # on CAN: no plant to time the agents' answers
            b = m["bridge_latency_ms"]
            lines.append(f"  bridge cmd->torque frame   p50 {ms(b['p50'])} ms, p99 {ms(b['p99'])} ms")
        else:
            lines.append(f"  state->command latency     p50 {ms(lat['p50'])} ms, p99 {ms(lat['p99'])} ms")
        lines.append(f"  loop jitter                p50 {ms(jit['p50'])} ms, p99 {ms(jit['p99'])} ms; "
                     f"deadline misses {m['deadline_misses']}")
    if "odometry_drift" in m:
        d = m["odometry_drift"]

        def cm(xs):
            return ", ".join(f"{x * 100:.2f}" for x in xs)

        lines.append(f"  odometry drift (cm)        median {cm(d['median_m'])}; max {cm(d['max_m'])}")
    return lines


def package_version() -> str:
    """The installed package's version (its metadata, from pyproject.toml)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("omnifleet")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="omnifleet",
        description="Collision-free formation control for mecanum-wheel robot fleets.",
    )
    p.add_argument("--version", action="version", version=f"omnifleet {package_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = sub.add_parser(
        "run", help="run a scenario and write its report folder",
        description="Run a scenario (a TOML file, or the name of a bundled one: paper, lab, "
        "reference-code) and write metrics.json, timeseries.npz and figures to --out.",
    )
    run.add_argument("scenario", help="scenario file or bundled scenario name")
    run.add_argument("--in-process", action="store_true",
                     help="run leader, plant and all agents in this process (the reference "
                     "loop) instead of one process per node")
    run.add_argument("--plant", choices=[*PLANT_KINDS, "can-emulated"], default=None,
                     help="pybullet (rigid bodies, real contacts), model (eq. 4, RK4), "
                     "kinematic, or can-emulated (every robot through a CAN bridge and a driver "
                     "emulator; realtime) (default: the scenario's plant.kind)")
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
    run.add_argument("--no-record", action="store_true",
                     help="do not write recording.mcap (the scene, plot signals and, for one "
                     "process per node, every wire message, in Foxglove's schemas; docs/foxglove.md)")
    run.add_argument("--live", metavar="[HOST:]PORT", nargs="?", const=str(8765),
                     help="serve the scene and plots over Foxglove's WebSocket protocol while the "
                     "run goes (default 127.0.0.1:8765; loopback unless HOST is given, e.g. "
                     "0.0.0.0:8765; port 0: any free one)")
    run.add_argument("--out", metavar="DIR", help="output folder (default: runs/<scenario>)")
    add_option(run, "--duration")
    add_option(run, "--control-rate")
    run.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    run.add_argument("--overwrite", action="store_true",
                     help="--out already holds a run: remove its outputs first (without it "
                     "such a folder is refused: a run never mixes its outputs with another's)")
    add_option(run, "--priority", default=REALTIME_PRIORITY,
               help="realtime: raise every node's CPU priority by N (nice -N and its "
               "session's autogroup; needs CAP_SYS_NICE, else each node says so), so "
               "other work on the host does not stall the control loops; 0 leaves them "
               f"at normal priority; the driver emulator always asks for {EMULATOR_PRIORITY}")
    run.add_argument("--faults", metavar="PLAN",
                     help="inject the faults of a fault plan (TOML; docs/faults.md): lossy, "
                     "delayed or partitioned links, killed and restarted processes, CAN frame "
                     "loss; counted per link in metrics.json")
    run.add_argument("--check", action="store_true",
                     help="exit 1 unless the verdict is PASS: every robot settles before "
                     "sqrt(2) T_p, no contact, nothing non-finite")
    run.set_defaults(func=_cmd_run)
    add_node_commands(sub)
    from deploy.bench.suite import add_bench_command
    from deploy.nodes.bridge_cli import add_bridge_commands
    from deploy.nodes.can_check_cli import add_can_check_command
    from deploy.nodes.emulator_cli import add_emulate_command
    from deploy.run.fault_sweep import add_faults_command

    add_bridge_commands(sub)
    add_emulate_command(sub)
    add_can_check_command(sub)
    add_bench_command(sub)
    add_faults_command(sub)
    from deploy.run.safety_sweep import add_safety_command

    add_safety_command(sub)
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


def _prog(args: argparse.Namespace) -> str:
    """``omnifleet COMMAND [SUBCOMMAND]`` as the user typed it."""
    words = [args.command] + [v for k, v in vars(args).items()
                              if k.endswith("_command") and isinstance(v, str)]
    return " ".join(["omnifleet", *words])


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ScenarioError as exc:
        print(f"omnifleet: bad scenario: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except FaultPlanError as exc:
        print(f"omnifleet: bad fault plan: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (TransportError, FleetNameError) as exc:
        print(f"omnifleet: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OptionError as exc:
        print(f"{_prog(args)}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as exc:
        print("omnifleet: interrupted; every process of the run was stopped", file=sys.stderr)
        return 143 if getattr(exc, "signal_name", "") == "SIGTERM" else 130


if __name__ == "__main__":
    sys.exit(main())
