"""``omnifleet compare``: control laws side by side on the same scenario (docs/laws.md).

Every law of ``--laws`` runs the scenario as it is and, with ``--seeds N``, N - 1 seeded
perturbations of it (obstacles and starts jittered: deploy/contract/scenario_variants.py),
each as the in-process lockstep reference on the scenario's plant or ``--plant``, as many
at once as ``--jobs``. One table (``compare.md``, and ``compare.json`` with every run):
per law, the settling time (the slowest robot, median over the runs), the formation RMS
after settling (median over robots and runs), the least gaps to an obstacle and between
robots (over every run), the contacts (every run), the wheel torques' RMS (median), the
time the safety filter changed the command (summed over the robots, median over the runs),
what the law did wrong (raised, refused) and its CPU per robot-step (median); and one
figure (``compare.png``): the unperturbed run's paths, a panel per law. Exit 1 when any
run touched.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class CompareRun:
    law: str
    seed: int  # 0: the scenario as it is
    settling_max_s: float | None  # the slowest robot (None: one never settled)
    formation_rms_m: float | None  # after settling, the mean over the robots that settled
    min_obstacle_gap_m: float | None
    min_robot_gap_m: float | None
    contacts: int
    torque_rms_nm: float
    filter_time_s: float  # the safety filter changed the command, summed over the robots
    law_errors: int  # steps the law raised, or its output was refused (braked instead)
    cpu_us_per_robot_step: float  # the run's CPU time over steps x robots
    verdict: bool


def run_one(scenario: str, law: str, seed: int, plant: str | None,
            duration: float | None) -> tuple[CompareRun, dict | None]:
    """One run; with the paths of the unperturbed one (for the figure)."""
    from deploy.contract.scenario import load_scenario
    from deploy.contract.scenario_variants import perturbed
    from deploy.report.metrics import compute_metrics
    from deploy.report.verdict import judge
    from deploy.run.run_figures import law_fault_figures
    from deploy.run.runner import run_in_process

    sc = load_scenario(scenario).with_law(law)
    if seed:
        sc = perturbed(sc, seed)
    cpu0 = time.process_time()
    res = run_in_process(sc, plant, duration)
    cpu = time.process_time() - cpu0
    m = compute_metrics(sc, res.series, res.plant, "lockstep", res.wall_time_s,
                        contact_log=res.contacts)
    m |= law_fault_figures(res.law_faults)
    faults = m.get("law_faults") or []
    settling = m["settling_time_s"]
    after = [x for x in m["formation_rms_after_settling_m"] if x is not None]
    run = CompareRun(
        law=sc.law_name, seed=seed,
        settling_max_s=None if any(x is None for x in settling) else max(settling),
        formation_rms_m=statistics.fmean(after) if after else None,
        min_obstacle_gap_m=m["min_obstacle_gap_m"], min_robot_gap_m=m["min_robot_gap_m"],
        contacts=int(m["contacts"]), torque_rms_nm=float(m["rms_torque_nm"]),
        filter_time_s=float(sum(m["safety_filter"]["active_time_s"])),
        law_errors=sum(f["errors"] + f["refused"] for f in faults if f),
        cpu_us_per_robot_step=cpu / max(1, res.series.steps * sc.n) * 1e6,
        verdict=bool(judge(m)["pass"]))
    paths = None
    if seed == 0:
        paths = {"q": res.series.q[:, :, :2].tolist()[:: max(1, res.series.steps // 2000)],
                 "leader": res.series.leader_q[:, :2].tolist()[:: max(1, res.series.steps // 2000)],
                 "obstacles": [(o.position[0], o.position[1], o.radius_m)
                               for o in sc.spec.obstacles]}
    return run, paths


def _median(xs: list[float | None]) -> float | None:
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def _least(xs: list[float | None]) -> float | None:
    xs = [x for x in xs if x is not None]
    return min(xs) if xs else None


def table(runs: list[CompareRun], scenario: str, plant: str, laws: list[str]) -> str:
    def f(x: float | None, fmt: str = ".3f") -> str:
        return "never" if x is None else format(x, fmt)

    lines = [f"# {scenario}: {len(runs)} runs, {plant} plant, in process (lockstep)", "",
             "| law | runs | settling, slowest robot (s, median) | formation RMS after settling "
             "(m, median) | least obstacle gap (m) | least robot gap (m) | contacts | torque "
             "RMS (N m, median) | safety filter (s, median) | law errors | CPU (µs a "
             "robot-step, median) | PASS |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for law in laws:
        mine = [r for r in runs if r.law == law]
        if not mine:
            continue
        lines.append(
            f"| {law} | {len(mine)} | {f(_median([r.settling_max_s for r in mine]), '.2f')}"
            + (f" ({sum(r.settling_max_s is None for r in mine)} never)"
               if any(r.settling_max_s is None for r in mine) else "")
            + f" | {f(_median([r.formation_rms_m for r in mine]))} "
            f"| {f(_least([r.min_obstacle_gap_m for r in mine]))} "
            f"| {f(_least([r.min_robot_gap_m for r in mine]))} "
            f"| {sum(r.contacts for r in mine)} "
            f"| {f(_median([r.torque_rms_nm for r in mine]), '.3g')} "
            f"| {f(_median([r.filter_time_s for r in mine]), '.2f')} "
            f"| {sum(r.law_errors for r in mine)} "
            f"| {f(_median([r.cpu_us_per_robot_step for r in mine]), '.1f')} "
            f"| {sum(r.verdict for r in mine)} of {len(mine)} |")
    touched = [f"{r.law} seed {r.seed}" for r in runs if r.contacts]
    lines += ["", f"Runs that touched: {', '.join(touched) or 'none'}.", ""]
    return "\n".join(lines)


def figure(paths: dict[str, dict], scenario: str, path: Path) -> None:
    """The unperturbed run's paths, a panel per law, on the same axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    laws = list(paths)
    fig, axes = plt.subplots(1, len(laws), figsize=(5 * len(laws), 4.5), squeeze=False,
                             sharex=True, sharey=True)
    for ax, law in zip(axes[0], laws, strict=True):
        p = paths[law]
        q = np.asarray(p["q"])
        lead = np.asarray(p["leader"])
        ax.plot(lead[:, 0], lead[:, 1], "k--", lw=1, label="leader")
        for i in range(q.shape[1]):
            ax.plot(q[:, i, 0], q[:, i, 1], lw=1.2, label=f"robot {i + 1}")
        for x, y, r in p["obstacles"]:
            ax.add_patch(plt.Circle((x, y), r, color="0.6"))
        ax.set_title(law)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x (m)")
    axes[0][0].set_ylabel("y (m)")
    axes[0][0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{scenario}: the same scenario under each law (unperturbed run)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)




