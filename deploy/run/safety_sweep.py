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

from dataclasses import dataclass


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




