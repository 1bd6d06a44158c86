"""``omnifleet safety sweep``: many seeded perturbations of one scenario, in process.

Seeds 0..N-1 of :func:`deploy.contract.scenario_variants.perturbed` (obstacles and starts
jittered), each run as the in-process lockstep reference on the scenario's plant (or
``--plant``), as many at once as ``--jobs``. Writes under ``--out``: ``sweep.csv``
(one row per seed) and ``sweep.md`` (contacts, the smallest gaps, the safety
filter's activity, settling); prints a line per finished run and the totals.
``--check``: exit 1 when any run touched. ``omnifleet scenario perturb NAME --seed K``
writes any one of them as a file to run alone.
"""

from __future__ import annotations

import argparse
import csv
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path

from deploy.contract.options import add_option, check_duration
from deploy.contract.output_paths import check_folder
from deploy.contract.plant_registry import add_plant_option
from deploy.nodes.cli import add_law_option

SWEEP_HELP = ("Run seeds 0..K-1 of a seeded perturbation of SCENARIO (every obstacle and "
              "start jittered, as `omnifleet scenario perturb` writes them), each in process "
              "on the scenario's plant or --plant, --jobs at once. Writes sweep.csv (a row "
              "per seed) and sweep.md (contacts, the smallest gaps, the safety filter's "
              "activity, settling) to --out, and prints a line per run. --check: exit 1 "
              "when any run touched (docs/safety.md).")


@dataclass(frozen=True)
class SweepRow:
    seed: int
    contacts: int
    min_obstacle_gap_m: float | None  # surface to surface, over the run
    min_robot_gap_m: float | None
    filter_active_s: float  # summed over the robots
    filter_infeasible_steps: int
    unsettled_robots: int  # never within the settling band, or after sqrt(2) T_p
    wall_time_s: float


def run_one(scenario: str, seed: int, plant: str | None, duration: float | None,
            obstacle_jitter: float | None, start_jitter: float | None,
            law: str | None = None) -> SweepRow:
    from deploy.contract.scenario import load_scenario
    from deploy.contract.scenario_variants import perturbed
    from deploy.report.metrics import compute_metrics
    from deploy.run.runner import run_in_process

    sc = load_scenario(scenario)
    sc = perturbed(sc.with_law(law) if law else sc, seed, obstacle_jitter, start_jitter)
    res = run_in_process(sc, plant, duration)
    m = compute_metrics(sc, res.series, res.plant, "lockstep", res.wall_time_s,
                        contact_log=res.contacts)
    f = m["safety_filter"]
    bound = m["settling_bound_s"]
    return SweepRow(seed, m["contacts"], m["min_obstacle_gap_m"], m["min_robot_gap_m"],
                    float(sum(f["active_time_s"])), int(sum(f["infeasible_steps"])),
                    sum(1 for s in m["settling_time_s"] if s is None or s >= bound),
                    res.wall_time_s)


def markdown(rows: list[SweepRow], scenario: str, plant: str) -> str:
    def least(xs):
        xs = [x for x in xs if x is not None]
        return f"{min(xs):.3f}" if xs else "n/a"

    touched = [r.seed for r in rows if r.contacts]
    acted = [r for r in rows if r.filter_active_s > 0]
    return "\n".join([
        f"# Safety sweep: {scenario}, {len(rows)} seeded perturbations, {plant} plant",
        "",
        "| seeds | runs with contact | contacts | least obstacle gap (m) | least robot gap (m) "
        "| runs where the filter acted | filter time (s, all runs) | infeasible steps "
        "| runs with an unsettled robot |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| 0-{len(rows) - 1} | {len(touched)} | {sum(r.contacts for r in rows)} "
        f"| {least(r.min_obstacle_gap_m for r in rows)} | {least(r.min_robot_gap_m for r in rows)} "
        f"| {len(acted)} | {sum(r.filter_active_s for r in rows):.2f} "
        f"| {sum(r.filter_infeasible_steps for r in rows)} "
        f"| {sum(1 for r in rows if r.unsettled_robots)} |",
        "",
        f"Seeds that touched: {', '.join(map(str, touched)) or 'none'}.",
        "",
    ])


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
