"""``omnifleet safety``'s command line (the sweep: deploy/run/safety_sweep.py)."""

from __future__ import annotations

import argparse
import csv
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path

from deploy.contract.options import add_option, check_duration
from deploy.contract.output_paths import check_folder
from deploy.contract.plant_registry import add_plant_option
from deploy.nodes.cli import add_law_option
from deploy.run.safety_sweep import SweepRow, markdown, run_one

SWEEP_HELP = ("Run seeds 0..K-1 of a seeded perturbation of SCENARIO (every obstacle and "
              "start jittered, as `omnifleet scenario perturb` writes them), each in process "
              "on the scenario's plant or --plant, --jobs at once. Writes sweep.csv (a row "
              "per seed) and sweep.md (contacts, the smallest gaps, the safety filter's "
              "activity, settling) to --out, and prints a line per run. --check: exit 1 "
              "when any run touched (docs/safety.md).")


def cmd_sweep(args: argparse.Namespace) -> int:
    from deploy.contract.scenario import load_scenario

    check_folder(args.out, "--out")  # OutputPathError: exit 2 (cli.main), before anything
    sc = load_scenario(args.scenario)  # ScenarioError: exit 2 with file and key (cli.main)
    if args.law:  # a law that cannot be used: exit 2 too, before any run
        sc = sc.with_law(args.law)
    law = sc.spec.law.use if args.law else None
    check_duration(args.duration, sc.spec.control_rate_hz)  # OptionError: exit 2 (cli.main)
    plant = args.plant or sc.spec.plant.kind
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[SweepRow] = []
    started = time.monotonic()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = {pool.submit(run_one, args.scenario, seed, plant, args.duration,
                               args.obstacle_jitter, args.start_jitter, law): seed
                   for seed in range(args.seeds)}
        for fut in as_completed(futures):
            row = fut.result()
            rows.append(row)
            print(f"[{len(rows)}/{args.seeds}, {time.monotonic() - started:.0f} s] seed {row.seed}: "
                  f"{row.contacts} contact(s), least gaps {row.min_obstacle_gap_m} / "
                  f"{row.min_robot_gap_m} m, filter {row.filter_active_s:.2f} s", flush=True)
    rows.sort(key=lambda r: r.seed)
    with open(args.out / "sweep.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0])))
        w.writeheader()
        w.writerows(asdict(r) for r in rows)
    text = markdown(rows, sc.name, plant)
    (args.out / "sweep.md").write_text(text)
    print(text)
    print(f"wrote {args.out}/sweep.csv and sweep.md")
    return 1 if args.check and any(r.contacts for r in rows) else 0


def add_safety_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("safety", help="check that no robot touches: seeded perturbation sweeps")
    s = p.add_subparsers(dest="safety_cmd", required=True)
    sw = s.add_parser("sweep", help="run N seeded perturbations of a scenario in process "
                      "(obstacles and starts jittered) and count contacts",
                      description=SWEEP_HELP)
    sw.add_argument("scenario", help="bundled scenario name or TOML file")
    add_option(sw, "--seeds", default=10, help="seeds 0..K-1")
    add_plant_option(sw)
    add_option(sw, "--duration")
    add_law_option(sw)
    add_option(sw, "--obstacle-jitter")
    add_option(sw, "--start-jitter")
    add_option(sw, "--jobs", default=2, help="in-process runs at once")
    sw.add_argument("--out", type=Path, default=Path("runs/safety-sweep"),
                    help="folder for sweep.csv and sweep.md (default runs/safety-sweep)")
    sw.add_argument("--check", action="store_true", help="exit 1 when any run touched")
    sw.set_defaults(func=cmd_sweep)
