"""``omnifleet compare``'s command line (the runs, the table and the figure:
deploy/run/compare.py)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path

from deploy.contract.options import add_option, check_duration
from deploy.contract.output_paths import check_folder
from deploy.contract.plant_registry import add_plant_option
from deploy.run.compare import CompareRun, figure, run_one, table


def cmd_compare(args: argparse.Namespace) -> int:
    from deploy.contract.scenario import load_scenario

    out = check_folder(Path(args.out) if args.out else Path("runs") / "compare", "--out")
    sc = load_scenario(args.scenario)  # ScenarioError: exit 2 (cli.main)
    check_duration(args.duration, sc.spec.control_rate_hz)
    laws = [x.strip() for x in args.laws.split(",") if x.strip()]
    if not laws or len(set(laws)) != len(laws):
        print("omnifleet compare: --laws names each law once, e.g. paper,consensus",
              file=sys.stderr)
        return 2
    names = [sc.with_law(law, "--laws").law_name for law in laws]  # exit 2 before any run
    plant = args.plant or sc.spec.plant.kind
    out.mkdir(parents=True, exist_ok=True)
    grid = [(law, seed) for law in laws for seed in range(args.seeds)]
    runs: list[CompareRun] = []
    paths: dict[str, dict] = {}
    started = time.monotonic()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = {pool.submit(run_one, args.scenario, law, seed, plant, args.duration): (law, seed)
                   for law, seed in grid}
        for fut in as_completed(futures):
            run, p = fut.result()
            runs.append(run)
            if p is not None:
                paths[run.law] = p
            print(f"[{len(runs)}/{len(grid)}, {time.monotonic() - started:.0f} s] {run.law} seed "
                  f"{run.seed}: settled {run.settling_max_s}, {run.contacts} contact(s), least "
                  f"gaps {run.min_obstacle_gap_m} / {run.min_robot_gap_m} m", flush=True)
    runs.sort(key=lambda r: (names.index(r.law), r.seed))
    text = table(runs, sc.name, plant, names)
    (out / "compare.md").write_text(text)
    (out / "compare.json").write_text(json.dumps(
        {"scenario": sc.name, "plant": plant, "laws": names,
         "runs": [asdict(r) for r in runs]}, indent=1) + "\n")
    figure({n: paths[n] for n in names if n in paths}, sc.name, out / "compare.png")
    print(text)
    print(f"wrote {out}/compare.md, compare.json and compare.png")
    return 1 if any(r.contacts for r in runs) else 0


def add_compare_command(sub: argparse._SubParsersAction) -> None:
    from agents.laws import NAMES

    p = sub.add_parser(
        "compare", help="run control laws side by side on one scenario (docs/laws.md)",
        description="Run every law of --laws on SCENARIO and on --seeds - 1 seeded "
        "perturbations of it, each in process (lockstep), and write compare.md (settling, "
        "formation RMS, least gaps, contacts, torque RMS, safety-filter time, law errors, "
        "CPU per step, per law), compare.json (every run) and compare.png (the unperturbed "
        "run's paths, a panel per law) to --out. Exit 1 when any run touched, 2 for a law "
        "that cannot be used.")
    p.add_argument("scenario", help="scenario file or bundled name")
    p.add_argument("--laws", required=True, metavar="LAW[,LAW...]",
                   help=f"the laws: {', '.join(NAMES)}, module:Class or path/to/file.py:Class")
    add_option(p, "--seeds", default=1, help="runs per law: the scenario, then seeded "
               "perturbations 1..N-1")
    add_plant_option(p)
    add_option(p, "--duration")
    add_option(p, "--jobs", default=2, help="in-process runs at once")
    p.add_argument("--out", metavar="DIR", help="default: runs/compare")
    p.set_defaults(func=cmd_compare)
