"""``omnifleet faults``'s command line: ``sweep`` (deploy/run/fault_sweep.py runs it) and
``show`` (a fault plan checked against a scenario, each edge's faults printed)."""

from __future__ import annotations

import argparse
import os
import sys
import time

from deploy.contract.options import add_option, check_duration
from deploy.contract.output_paths import check_folder
from deploy.contract.plant_registry import add_plant_option
from deploy.contract.scenario import load_scenario
from deploy.nodes.cli import add_law_option
from deploy.run.fault_sweep import SweepRow, markdown, plot, run_sweep, write_csv


def _drops(text: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not vals or any(not (0.0 <= v <= 1.0) for v in vals):
        raise argparse.ArgumentTypeError("drop rates are probabilities in [0, 1], e.g. 0,0.1,0.3")
    return sorted(set(vals))


def cmd_sweep(args: argparse.Namespace) -> int:
    sc = load_scenario(args.scenario)  # a bad scenario fails here, before any run
    if args.law:  # and a law that cannot be used (exit 2, cli.main)
        sc = sc.with_law(args.law)
    check_duration(args.duration, sc.spec.control_rate_hz)
    out = check_folder(args.out or f"runs/{sc.name}-fault-sweep", "--out")  # exit 2 (cli.main)
    out.mkdir(parents=True, exist_ok=True)
    jobs = args.jobs or os.cpu_count() or 1
    n = sum(args.seeds if d > 0.0 else 1 for d in args.drop)
    how = "distributed, one at a time" if args.distributed else f"in-process, {jobs} at a time"
    print(f"faults sweep: {sc.name}, drop {args.drop}, {args.seeds} seeds: {n} runs ({how})",
          file=sys.stderr)
    start = time.perf_counter()

    def progress(done: int, total: int, r: SweepRow) -> None:
        print(f"  [{done}/{total}] drop {r.drop:g} seed {r.seed}: formation RMS "
              f"{r.formation_rms_whole_run_m:.3f} m, contacts {r.contacts} ({r.wall_time_s:.0f} s)",
              file=sys.stderr, flush=True)

    try:
        rows = run_sweep(args.scenario, args.drop, args.seeds, out, jobs, args.distributed,
                         args.duration, args.plant, progress,
                         None if not args.law else sc.spec.law.use)
    except RuntimeError as exc:  # a distributed run failed: its log is named
        print(f"faults sweep: {exc}", file=sys.stderr)
        return 1
    write_csv(rows, out / "sweep.csv")
    table = markdown(rows, sc.name)
    (out / "sweep.md").write_text(table)
    plot(rows, out / "sweep.png", sc.name)
    print(table)
    print(f"faults sweep: {n} runs in {time.perf_counter() - start:.0f} s; written to {out}/ "
          "(sweep.csv, sweep.md, sweep.png, runs/)")
    return 0


def add_faults_command(sub: argparse._SubParsersAction) -> None:
    faults = sub.add_parser("faults", help="fault injection: sweeps, plan checks",
                            description="Fault injection tools (fault plans: docs/faults.md).")
    fsub = faults.add_subparsers(dest="faults_command", required=True, metavar="COMMAND")
    p = fsub.add_parser(
        "sweep", help="run a scenario under growing independent loss; table and plot",
        description="Run SCENARIO once per (drop rate, seed) with independent loss on every "
        "edge, and write sweep.csv, sweep.md and sweep.png (formation RMS, settling time, "
        "minimum gap between robots against drop rate).")
    p.add_argument("scenario", help="scenario file or bundled name")
    p.add_argument("--drop", type=_drops, default=_drops("0,0.1,0.3,0.5"), metavar="P,P,...",
                   help="drop rates (default: 0,0.1,0.3,0.5)")
    add_option(p, "--seeds")
    add_option(p, "--jobs")
    p.add_argument("--distributed", action="store_true",
                   help="run each through `omnifleet run` (one process per node) instead of "
                   "in-process; same results, slower")
    add_option(p, "--duration", more_help="per run")
    add_law_option(p)
    add_plant_option(p)
    p.add_argument("--out", metavar="DIR", help="default: runs/<scenario>-fault-sweep")
    p.set_defaults(func=cmd_sweep)
    show = fsub.add_parser(
        "show", help="validate a fault plan against a scenario and print every edge's faults",
        description="Validate PLAN for SCENARIO (exit 2 with the key at fault) and print the "
        "faults each edge of the run's graph gets, and the kills.")
    show.add_argument("plan", help="fault plan (TOML)")
    show.add_argument("--scenario", required=True, help="scenario file or bundled name")
    show.set_defaults(func=cmd_show)


def cmd_show(args: argparse.Namespace) -> int:
    from deploy.contract.fault_plan import edge_name, load_plan, run_edges

    sc = load_scenario(args.scenario)
    plan = load_plan(args.plan, sc)
    print(f"{plan.path}: seed {plan.seed}, scenario {sc.name}")
    for src, dst in run_edges(sc):
        f = plan.link(src, dst)
        if f is None:
            print(f"  {edge_name(src, dst):24s} perfect")
            continue
        parts = []
        if f.drop:
            parts.append(f"drop {f.drop:g}")
        if f.burst is not None:
            b = f.burst
            parts.append(f"burst (enter {b.p_enter:g}, exit {b.p_exit:g}, loss {b.loss_bad:g}/"
                         f"{b.loss_good:g})")
        if f.delay_s:
            parts.append(f"delay {f.delay_s * 1e3:g} ms")
        parts += [f"partition [{a:g}, {b:g}) s" for a, b in f.partitions]
        print(f"  {edge_name(src, dst):24s} {', '.join(parts)}")
    for k in plan.kills:
        again = "" if k.restart_after_s is None else f", restart after {k.restart_after_s:g} s"
        print(f"  kill {k.process} at {k.at_s:g} s{again}")
    if plan.can.frame_loss or plan.can.corrupt:
        print(f"  CAN: frame loss {plan.can.frame_loss:g}, corrupt {plan.can.corrupt:g}")
    return 0
