"""``omnifleet run``: a scenario in process or as a fleet of processes, its outputs
written and judged."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from deploy.contract.options import EXIT_BAD_INPUT
from deploy.contract.output_paths import check_folder, usable_folder
from deploy.contract.wire import Keys
from deploy.nodes.cli import fault_plan, gui_problem, run_scenario, steps_of
from deploy.report.emulator_truth import can_fault_counts, emulator_lag_ms
from deploy.report.run_folder import RECORDING, RunFolderError
from deploy.report.run_folder import prepare as prepare_run_folder
from deploy.report.summary import summary
from deploy.report.verdict import divergence_banner, verdict_line
from deploy.runtime.fault_model import fault_metrics
from deploy.runtime.heap import frozen_heap
from deploy.runtime.plants import CAN_EMULATED, PLANTS


def _options_problem(args: argparse.Namespace, sc, plant: str) -> str | None:
    """Why these options cannot run this scenario (None: they can); sets ``args.clock``
    (realtime for a plant on the wall clock only, else lockstep unless said)."""
    if PLANTS[plant].realtime_only:  # hardware through emulated drivers runs on the wall clock
        if args.in_process or args.clock == "lockstep":
            return f"--plant {plant} runs realtime, one process per node"
        args.clock = "realtime"
    args.clock = args.clock or "lockstep"
    if args.driver is not None and plant != CAN_EMULATED:
        return f"--driver {args.driver} drives CAN bridges: it needs --plant {CAN_EMULATED}"
    problem = gui_problem(plant, args.gui)
    if problem:
        return problem
    if args.in_process and args.clock == "realtime":
        return "--in-process runs lockstep only"
    if args.keep_cores_awake and (args.clock != "realtime" or not args.priority):
        return ("--keep-cores-awake needs --clock realtime with its nodes under SCHED_FIFO "
                "(--priority 1 or more): a node of the normal policy that hands its core "
                "over would give it to the spinner (deploy/runtime/idle_poll.py)")
    if sc.leader_spec().steered is not None and (args.clock != "realtime" or args.ros2 is None):
        return ('this scenario\'s leader follows ROS 2 (leader.path = "ros2"): run it with '
                "--clock realtime --ros2 [ENDPOINT] (a ROS 2 node then drives it on "
                "/leader/cmd_vel; docs/ros2.md)")
    return None


def cmd_run(args: argparse.Namespace) -> int:
    sc = run_scenario(args)  # the ranges were checked on parse (deploy/contract/options.py)
    plant = args.plant or sc.spec.plant.kind
    problem = _options_problem(args, sc, plant)
    if problem:
        print(f"omnifleet run: {problem}", file=sys.stderr)
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
    out = check_folder(Path(args.out) if args.out else Path("runs") / sc.name, "--out")
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
    from deploy.ros2.gateway import gateway_from_args

    ros2 = gateway_from_args(args, sc, plant, "omnifleet run")
    if ros2 is False:
        if live is not None:
            live.close()
        return EXIT_BAD_INPUT
    # in process the gateway runs a thread of its own beside the live view; one process per
    # node: the launcher's loop drives it (_run_distributed)
    watchers = Watchers([w for w in (live, ros2) if w is not None]) \
        if ros2 and args.in_process else live
    metrics = None
    bag = None
    if ros2 and not args.no_record:  # the recording holds the ROS 2 topics too
        from deploy.ros2.bag import BagTopics

        bag = BagTopics(ros2.opts, realtime=args.clock == "realtime")
    drawing = None
    if not args.no_figures:  # the figure process gets ready while the run goes
        from deploy.report.figure_process import FigureProcess

        drawing = FigureProcess()
        drawing.prepare()
    try:
        if args.in_process:
            metrics = _run_in_process(sc, args, plant, plan, out, label, watchers, drawing, bag)
        else:
            with frozen_heap():  # what start-up built, out of the full passes (heap.py)
                metrics = _run_distributed(sc, args, plant, out, label, watchers, drawing,
                                           ros2 or None, bag)
            if metrics is None:
                return 1
    finally:
        _close_outputs(drawing, live, ros2, metrics)
    return _finish(args, metrics, out, bag)


def _close_outputs(drawing, live, ros2, metrics: dict | None) -> None:
    """The figure process (by pid), the live view and the ROS 2 gateway, each with its
    last word; also after a failed or interrupted run."""
    if drawing is not None:
        drawing.stop()
    if live is not None:
        live.close()
        front = live.server.front
        print(f"live view: {live.published} messages served to {sum(front.served.values())} "
              f"client(s), {live.cpu_s:.2f} s CPU"
              + (f"; {front.refused} client(s) refused (no Foxglove subprotocol offered)"
                 if front.refused else "") + "; stopped", file=sys.stderr)
    if ros2 is not None:
        ros2.close(None if metrics is None else metrics["verdict"])
        print(ros2.summary(), file=sys.stderr)


def _finish(args: argparse.Namespace, metrics: dict, out: Path, bag) -> int:
    """The bag's metadata, the summary and the exit code of a run that ended."""
    if bag is not None and bag.counts and bag.broken is None:
        _write_bag_metadata(bag, metrics)
    banner = divergence_banner(metrics["verdict"])
    if banner:
        print(banner, file=sys.stderr)
    print(summary(metrics, out))
    broken = (metrics.get("recording") or {}).get("error")
    if broken:  # never a run that looks complete with a recording that is not
        print(f"omnifleet run: FAILED: the recording failed ({broken}); "
              f"{metrics['recording']['lost']} message(s) not recorded", file=sys.stderr)
        return 1
    if args.check and not metrics["verdict"]["pass"]:
        print("omnifleet run: the run does NOT meet the criteria (the verdict above says "
              "which)", file=sys.stderr)
        return 1
    return 0


def _run_in_process(sc, args: argparse.Namespace, plant: str, plan, out: Path, label: str, live,
                    drawing=None, bag=None):
    from deploy.report.outputs import write_run
    from deploy.run.run_figures import law_fault_figures
    from deploy.run.runner import run_in_process, run_progress

    progress = _with_live(run_progress(label), live)
    result = run_in_process(sc, plant, args.duration, progress, gui=args.gui, faults=plan,
                            on_series=None if live is None else live.follow)
    extra = {} if plan is None else {"faults": fault_metrics(plan, result.faults or {})}
    extra["law_resets"] = result.law_resets
    extra |= law_fault_figures(result.law_faults)
    clipped = result.torque_clipped or {}
    extra["torque_clipped"] = [clipped.get(r, 0) for r in sc.robot_ids]  # per robot, a list
    recorder = None
    if not args.no_record:
        # the folder may have gone while the run went: the recording goes where the
        # results will (write_run names a rescue folder then)
        usable, why = usable_folder(out, sc.name)
        if why is not None:
            print(f"omnifleet run: cannot write to {out} any more ({why}); the run's results "
                  f"go to {usable}/", file=sys.stderr)
        out = usable
        from deploy.report.recorder import McapRecorder  # mcap: only for a recording

        recorder = McapRecorder(out / RECORDING, sim_dt=sc.dt)
        if bag is not None:
            recorder.with_scene.append(bag)
    if result.interrupted:
        from deploy.report.outputs import write_interrupted

        metrics = write_interrupted(sc, result.series, out, plant, "lockstep",
                                    result.wall_time_s, result.interrupted, extra, recorder,
                                    contact_log=result.contacts, step_unix_ns=result.step_unix_ns)
        _interrupted(metrics, out)
    return write_run(sc, result.series, out, plant, "lockstep", result.wall_time_s,
                     extra=extra, figures=not args.no_figures, contact_log=result.contacts,
                     recorder=recorder, step_unix_ns=result.step_unix_ns,
                     steps_asked=steps_of(sc, args), drawing=drawing)


def _interrupted(metrics: dict, out: Path) -> None:
    """Say what an interrupted run wrote, then end as interrupted (exit 130/143)."""
    print(summary(metrics, out) if metrics.get("steps") else
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
    print(f"live view: {url(host, live.port)} (Foxglove or Lichtblick: Open connection -> "
          "Foxglove WebSocket; layout docs/foxglove-layout.json)", file=sys.stderr, flush=True)
    return live


def process_state(child) -> str:
    """A child of the run as /fleet/status says it (read on the launcher's thread)."""
    if child.killed:
        return "killed by the fault plan"
    return "running" if child.exit_code is None else f"exited {child.exit_code}"


def _write_bag_metadata(bag, metrics: dict) -> None:
    """The run folder as a rosbag2 bag: its metadata.yaml, named among the run's files."""
    from deploy.report.metrics import write_metrics

    folder = Path(metrics["folder"])
    bag.write_metadata(folder)
    metrics["files"] += ["ros2.mcap", "metadata.yaml"]
    write_metrics(metrics, folder / "metrics.json")


class Watchers:
    """Several observers of the series (the live view, the ROS 2 gateway) as one."""

    def __init__(self, members: list) -> None:
        self.members = members

    def follow(self, series, ready=None):
        for w in self.members:
            w.follow(series, ready)
        return self

    def publish(self, k: int) -> None:
        for w in self.members:
            w.publish(k)


def _with_live(progress, live):
    """A progress callback that also tells the live view how far the series is."""
    if live is None:
        return progress

    def both(done: int, total: int) -> None:
        live.publish(done - 1)
        if progress is not None:
            progress(done, total)

    return both


def _run_distributed(sc, args: argparse.Namespace, plant: str, out: Path, label: str, live=None,
                     drawing=None, ros2=None, bag=None):
    import time

    from deploy.report.outputs import run_wall_clock, write_run
    from deploy.run.launcher import Interrupted, Launcher, LaunchOptions, RunFailed
    from deploy.run.runner import run_progress

    recorder = None if args.no_record else _recorder(sc, args.clock, out, bag)
    opts = LaunchOptions(
        scenario_arg=args.scenario, plant=plant, clock=args.clock, out=out,
        duration_s=args.duration, control_rate_hz=args.control_rate,
        step_deadline_s=args.step_deadline, startup_timeout_s=args.startup_timeout,
        record=not args.no_record, fleet=args.fleet, endpoint=args.endpoint, gui=args.gui,
        keep_cores_awake=args.keep_cores_awake,
        faults=fault_plan(args, sc), realtime_priority=args.priority, recorder=recorder,
        lowlatency=args.zenoh_transport == "lowlatency", datagrams=args.data_path == "datagram",
        # --law: the agents read the scenario's file, and are told (a file's path made absolute)
        extra_agent_args=["--law", sc.spec.law.use] if args.law else [],
        steering=None if ros2 is None else ros2.steering,
        **({} if args.driver is None else {"driver": args.driver}),
    )
    launcher = Launcher(sc, opts)
    if drawing is not None and not args.no_figures:
        # the figures start drawing while the nodes are still leaving (write_run finds
        # them started)
        launcher.on_heard = lambda series: drawing.start(sc, series, out)
    if live is not None:
        from deploy.report.live_view import collector_rows

        heard = launcher.observer.collector
        live.follow(heard.ts, collector_rows(heard, args.clock == "realtime"))
    progress = run_progress(label)
    if ros2 is not None:
        progress = _driven_gateway(ros2, launcher, args.clock == "realtime", progress)
    started = time.perf_counter()
    try:
        extra = launcher.run(progress)
    except RunFailed as exc:
        print(f"omnifleet run: FAILED: {exc}", file=sys.stderr)
        if recorder is not None:
            recorder.close()
        return None
    except Interrupted as exc:  # every child stopped: write what was measured, marked
        from deploy.report.outputs import write_interrupted

        series = launcher.observer.collector.series(realtime=args.clock == "realtime")
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
    if ros2 is not None:
        extra["ros2"] = ros2.counts_json()
    series = launcher.final_series()
    if args.clock == "realtime":
        extra["series_cells_filled"] = launcher.observer.collector.filled
    if launcher.truth_files and launcher.observer.t0_mono is not None:
        extra.update(_emulated_can_figures(sc, series, launcher, extra.get("faults")))
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
                     steps_asked=opts.steps(sc), drawing=drawing,
                     **run_wall_clock(end_unix_ns, wall, launcher.observer.run_t0, series.steps,
                                      args.clock == "lockstep"))


def _recorder(sc, clock: str, out: Path, bag=None):
    """recording.mcap, ours, so that the scene joins it at the end (LaunchOptions.recorder),
    and a ROS 2 bag's channels with the scene when ``bag`` is given."""
    from deploy.report.recorder import McapRecorder

    out.mkdir(parents=True, exist_ok=True)
    recorder = McapRecorder(out / RECORDING, sim_dt=sc.dt if clock == "lockstep" else None)
    if bag is not None:
        recorder.with_scene.append(bag)
    return recorder


def _driven_gateway(ros2, launcher, realtime: bool, progress):
    """The ROS 2 gateway fed by the launcher's observer and driven by its loop (no wake
    of its own: docs/ros2.md); the progress callback that also drives it."""
    from deploy.report.live_view import collector_rows
    from deploy.ros2.gateway import polling

    heard = launcher.observer.collector
    ros2.bind_observer(launcher.observer)
    ros2.processes = lambda: {c.role: process_state(c) for c in launcher.supervisor.children
                              if c.proc is not None}
    ros2.follow(heard.ts, collector_rows(heard, realtime), driven=True)
    return polling(progress, ros2)


def _emulated_can_figures(sc, series, launcher, faults: dict | None) -> dict:
    """A run on emulated CAN: the bridges' odometry against the emulators' ground truth,
    the emulators' lag, the drives' protocol, the share of states a bridge reported
    faulted, and (with a fault plan) the CAN frames the emulators dropped or corrupted
    (into ``faults``)."""
    from deploy.report.odometry_drift import odometry_drift

    c, truth = launcher.observer.collector, launcher.truth_files
    got = c.have_state.sum(axis=0)
    if faults is not None:
        faults["can"] = can_fault_counts(truth)
    return {
        "odometry_drift": odometry_drift(
            series, sc.robot_ids, truth, launcher.observer.t0_mono, c.have_state,
            [sc.bridge_phase_s(r) for r in sc.robot_ids]),
        "emulator_lag_ms": emulator_lag_ms(truth),
        "driver": launcher.opts.driver,  # the drives' protocol on every robot's bus
        "bridge_faulted_fraction": [float(f) / g if g else None
                                    for f, g in zip(c.faulted.sum(axis=0), got, strict=True)],
    }


def add_run_command(sub: argparse._SubParsersAction) -> None:
    """``omnifleet run``: its options, each with its help."""
    from deploy.contract.options import add_option
    from deploy.contract.plant_registry import add_plant_option
    from deploy.contract.scenario import bundled_names
    from deploy.nodes.can_options import add_driver_option
    from deploy.nodes.cli import CLOCKS, add_law_option
    from deploy.ros2.options import add_ros2_options
    from deploy.runtime.priority import EMULATOR_PRIORITY, REALTIME_PRIORITY, WORLD_ABOVE_AGENTS

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
    _add_transport_options(run)
    run.add_argument("--no-record", action="store_true",
                     help="do not write recording.mcap (the scene, plot signals and, for one "
                     "process per node, every wire message, in Foxglove's schemas; docs/foxglove.md)")
    run.add_argument("--live", metavar="[HOST:]PORT", nargs="?", const=str(8765),
                     help="serve the scene and plots over Foxglove's WebSocket protocol while the "
                     "run goes (default 127.0.0.1:8765; loopback unless HOST is given, e.g. "
                     "0.0.0.0:8765; port 0: any free one)")
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
    run.add_argument("--keep-cores-awake", action="store_true",
                     help="realtime: keep every core this run may use from halting while the "
                     "fleet runs (a spinning process below everything else on each): on a "
                     "virtual machine a halted CPU wakes slow and cold; the CAN fleet pinned "
                     "to one core kept its period with it where it did not without. The cores "
                     "show busy meanwhile; on a guest using all of its CPUs the host may then "
                     "preempt it (docs/distributed.md)")
    run.add_argument("--faults", metavar="PLAN",
                     help="inject the faults of a fault plan (TOML; docs/faults.md): lossy, "
                     "delayed or partitioned links, killed and restarted processes, CAN frame "
                     "loss; counted per link in metrics.json")
    run.add_argument("--check", action="store_true",
                     help="exit 1 unless the verdict is PASS: every robot settles before "
                     "sqrt(2) T_p and ends at its formation position, no contact, nothing "
                     "non-finite, the whole run simulated and heard (docs/outputs.md)")
    run.set_defaults(func=cmd_run)


def _add_transport_options(run: argparse.ArgumentParser) -> None:
    """How the run's processes find and talk to each other: the fleet's name, the
    launcher's endpoint, zenoh's transport and the per-step data's path."""
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
