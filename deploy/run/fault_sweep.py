"""``omnifleet faults sweep``: the same scenario under growing independent loss.

One run per (drop rate, seed): every edge of the run's graph loses each
message with probability ``drop`` (deploy/fault_plan.uniform_drop_plan). By
default the runs are the in-process lockstep reference, as many at once as the
machine has cores (a lockstep run with a fault plan equals its distributed run
bit for bit; tests/integration/test_faults.py checks it); ``--distributed`` runs each
through ``omnifleet run`` instead, one at a time.

Writes, under --out: ``sweep.csv`` (one row per run), ``sweep.md`` (per drop
rate: median and range over the seeds), ``sweep.png`` (formation RMS, settling
time and minimum gap between robots against drop rate) and each run's folder.
"""

from __future__ import annotations

import csv
import statistics
import subprocess
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from deploy.contract.fault_plan import uniform_drop_plan
from deploy.contract.scenario import load_scenario
from deploy.runtime.own_python import child_env, python_module


@dataclass(frozen=True)
class SweepRow:
    drop: float
    seed: int
    formation_rms_whole_run_m: float  # over every robot and the whole run: |q_xy - (x_0 + rho_i)|
    settling_s: float | None  # the slowest robot's settling time; None: some robot never
    unsettled_robots: int
    min_robot_gap_m: float | None  # surface to surface
    min_obstacle_gap_m: float | None
    contacts: int
    messages_judged: int
    messages_lost: int
    wall_time_s: float


def plan_text(drop: float, seed: int) -> str:
    return f"# omnifleet faults sweep\nseed = {seed}\n[defaults]\ndrop = {drop!r}\n"


def row_from_run(drop: float, seed: int, run_dir: Path) -> SweepRow:
    import json

    m = json.loads((run_dir / "metrics.json").read_text())
    with np.load(run_dir / "timeseries.npz") as ts:
        err = np.linalg.norm(ts["q"][:, :, :2] - ts["target"], axis=2)
    settling = m["settling_time_s"]
    totals = m.get("faults", {}).get("totals", {})
    lost = sum(totals.get(k, 0) for k in ("dropped", "burst", "partitioned"))
    return SweepRow(
        drop, seed, float(np.sqrt(np.nanmean(err**2))),
        None if any(s is None for s in settling) else max(settling),
        sum(s is None for s in settling), m["min_robot_gap_m"],
        m["min_obstacle_gap_m"], m["contacts"], totals.get("messages", 0), lost,
        m["wall_time_s"])


def _run_in_process(scenario: str, drop: float, seed: int, run_dir: Path,
                    duration: float | None, plant: str | None, law: str | None = None
                    ) -> SweepRow:
    from deploy.report.outputs import write_run
    from deploy.run.runner import run_in_process
    from deploy.runtime.fault_model import fault_metrics

    sc = load_scenario(scenario)
    if law:
        sc = sc.with_law(law)
    plan = uniform_drop_plan(sc, drop, seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "faults.toml").write_text(plan_text(drop, seed))
    result = run_in_process(sc, plant, duration, faults=plan)
    write_run(sc, result.series, run_dir, result.plant, "lockstep", result.wall_time_s,
              extra={"faults": fault_metrics(plan, result.faults or {})}, figures=False,
              contact_log=result.contacts)
    return row_from_run(drop, seed, run_dir)


def _run_distributed(scenario: str, drop: float, seed: int, run_dir: Path,
                     duration: float | None, plant: str | None, law: str | None = None
                     ) -> SweepRow:
    run_dir.mkdir(parents=True, exist_ok=True)
    plan = run_dir / "faults.toml"
    plan.write_text(plan_text(drop, seed))
    cmd = [*python_module("deploy.cli"), "run", scenario, "--faults", str(plan),
           "--out", str(run_dir), "--overwrite", "--no-figures", "--no-record"]
    if duration is not None:
        cmd += ["--duration", repr(duration)]
    if plant is not None:
        cmd += ["--plant", plant]
    if law:
        cmd += ["--law", law]
    with open(run_dir / "run.log", "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                env=child_env(one_blas_thread=False))
        try:
            code = proc.wait()
        finally:
            if proc.poll() is None:  # interrupted: the launcher stops its own children
                proc.terminate()
                proc.wait()
    if code != 0:
        raise RuntimeError(f"run drop={drop} seed={seed} failed (exit {code}); "
                           f"see {run_dir / 'run.log'}")
    return row_from_run(drop, seed, run_dir)


def run_sweep(scenario: str, drops: list[float], seeds: int, out: Path, jobs: int,
              distributed: bool = False, duration: float | None = None,
              plant: str | None = None,
              progress: Callable[[int, int, SweepRow], None] | None = None,
              law: str | None = None) -> list[SweepRow]:
    """``law``: every agent on another law (--law; docs/laws.md)."""
    # without loss the seed decides nothing: one run stands for all
    grid = [(d, s) for d in drops for s in (range(1, seeds + 1) if d > 0.0 else (1,))]
    fn = _run_distributed if distributed else _run_in_process
    rows: list[SweepRow] = []

    def folder(d: float, s: int) -> Path:
        return out / "runs" / f"drop-{d:g}-seed-{s}"

    if jobs <= 1 or distributed:
        for d, s in grid:
            rows.append(fn(scenario, d, s, folder(d, s), duration, plant, law))
            if progress:
                progress(len(rows), len(grid), rows[-1])
    else:
        # here, not at the top: the command line builds this command's parser on every run
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(fn, scenario, d, s, folder(d, s), duration, plant, law)
                       for d, s in grid]
            for f in as_completed(futures):
                rows.append(f.result())
                if progress:
                    progress(len(rows), len(grid), rows[-1])
    rows.sort(key=lambda r: (r.drop, r.seed))
    return rows


def write_csv(rows: list[SweepRow], path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0])))
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))


def _median_range(xs: list[float | None], fmt: str = "{:.3f}") -> str:
    vals = [x for x in xs if x is not None]
    never = len(xs) - len(vals)
    if not vals:
        return "never"
    text = fmt.format(statistics.median(vals)) + f" ({fmt.format(min(vals))}-{fmt.format(max(vals))})"
    return text + (f", never in {never}" if never else "")


def markdown(rows: list[SweepRow], scenario: str) -> str:
    drops = sorted({r.drop for r in rows})
    lines = [f"# Fault sweep: {scenario}", "",
             "Independent loss on every edge; median (min-max) over the seeds. Formation RMS: "
             "|q_xy - (x_0 + rho_i)| over every robot and the whole run. Settling: the slowest "
             "robot's.", "",
             "| drop | runs | formation RMS, whole run (m) | ratio to 0 % | settling (s) | min robot gap (m) "
             "| min obstacle gap (m) | contacts | lost / judged |",
             "|---|---|---|---|---|---|---|---|---|"]
    base = [r.formation_rms_whole_run_m for r in rows if r.drop == 0.0]
    base_med = statistics.median(base) if base else None
    for d in drops:
        rs = [r for r in rows if r.drop == d]
        med = statistics.median(r.formation_rms_whole_run_m for r in rs)
        ratio = f"{med / base_med:.2f}" if base_med else "n/a"
        lines.append(
            f"| {d:g} | {len(rs)} | {_median_range([r.formation_rms_whole_run_m for r in rs])} | {ratio} | "
            f"{_median_range([r.settling_s for r in rs])} | "
            f"{_median_range([r.min_robot_gap_m for r in rs])} | "
            f"{_median_range([r.min_obstacle_gap_m for r in rs])} | "
            f"{sum(r.contacts for r in rs)} | "
            f"{sum(r.messages_lost for r in rs)} / {sum(r.messages_judged for r in rs)} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[SweepRow], path: Path, scenario: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drops = sorted({r.drop for r in rows})
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    series = [("formation RMS, whole run (m)", lambda r: r.formation_rms_whole_run_m),
              ("settling time, slowest robot (s)", lambda r: r.settling_s),
              ("min gap between robots (m)", lambda r: r.min_robot_gap_m)]
    for ax, (label, get) in zip(axes, series, strict=True):
        for r in rows:
            v = get(r)
            if v is not None:
                ax.plot(r.drop * 100, v, "o", color="tab:blue", alpha=0.35, ms=4)
        med = [statistics.median([v for r in rows if r.drop == d and (v := get(r)) is not None]
                                 or [np.nan]) for d in drops]
        ax.plot([d * 100 for d in drops], med, "-", color="tab:blue", label="median")
        ax.set_xlabel("drop rate on every edge (%)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"{scenario}: fault sweep ({len(rows)} runs)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)








