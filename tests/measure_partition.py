"""Measure recovery from a partition of leader -> agent 1 (docs/faults.md):
the scenario in-process, fault-free and with the link cut over [--cut-from,
--cut-to), side by side.

    .venv/bin/python tests/measure_partition.py paper [--cut-from 8 --cut-to 10]

Prints, after the heal, when each robot's formation error |q_xy - (x_0 + rho_i)|
is back within 1.2x the fault-free run's (plus the settling band) for at least a
second, when it stays there to the end, and the worst excess after the heal; with
the contacts and the closest approaches of the cut run.
"""

from __future__ import annotations

import argparse

import numpy as np

from deploy.contract.fault_plan import decode_plan
from deploy.contract.scenario import load_scenario
from deploy.report.metrics import compute_metrics
from deploy.run.runner import run_in_process


def within_from(ok: np.ndarray, t: np.ndarray, start: float, hold_s: float) -> float | None:
    """The first time >= start from which ``ok`` holds for ``hold_s`` (None: never)."""
    idx = np.flatnonzero(t >= start)
    dt = t[1] - t[0]
    need = max(1, int(round(hold_s / dt)))
    run = 0
    for n in idx:
        run = run + 1 if ok[n] else 0
        if run >= need:
            return float(t[n - need + 1])
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--cut-from", type=float, default=8.0)
    ap.add_argument("--cut-to", type=float, default=10.0)
    ap.add_argument("--plant", default=None)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--ratio", type=float, default=1.2)
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    plan = decode_plan(f"[[link]]\nfrom = 'leader'\nto = 'agent-1'\n"
                       f"partitions = [[{args.cut_from}, {args.cut_to}]]\n", sc)
    nominal = run_in_process(sc, args.plant, args.duration)
    cut = run_in_process(sc, args.plant, args.duration, faults=plan)
    band = sc.spec.metrics.settle_threshold
    t = cut.series.t
    heal = args.cut_to
    err = {name: np.linalg.norm(r.series.q[:, :, :2] - r.series.target, axis=2)
           for name, r in (("nominal", nominal), ("cut", cut))}
    ok = err["cut"] <= args.ratio * err["nominal"] + band
    after = t >= heal
    print(f"{sc.name}: leader -> agent-1 cut over [{args.cut_from}, {heal}) s; "
          f"back = within {args.ratio}x the fault-free formation error + {band} m")
    for i, rid in enumerate(sc.robot_ids):
        first = within_from(ok[:, i], t, heal, 1.0)
        bad = np.flatnonzero(after & ~ok[:, i])
        stays = heal if len(bad) == 0 else (float(t[bad[-1] + 1]) if bad[-1] + 1 < len(t) else None)
        line = f"  robot {rid}: back {_since(first, heal)} after the heal, stays back " \
               f"{_since(stays, heal)} after it"
        if first is not None and stays != first:
            later = t >= first  # the worst excursion once it was back
            excess = (err["cut"][later, i] - band) / np.maximum(err["nominal"][later, i], 1e-9)
            w = int(np.argmax(excess))
            line += (f"; once back, worst (error - band) / fault-free {excess[w]:.2f}x at "
                     f"t = {t[later][w]:.2f} s ({err['cut'][later, i][w]:.2f} m vs "
                     f"{err['nominal'][later, i][w]:.2f} m)")
        print(line)
    m = compute_metrics(sc, cut.series, cut.plant, "lockstep", cut.wall_time_s,
                        contact_log=cut.contacts)
    print(f"  cut run: contacts {m['contacts']}, min robot gap "
          f"{m['min_robot_gap_m']:.3f} m, min obstacle gap "
          f"{m['min_obstacle_gap_m']:.3f} m")


def _since(x: float | None, heal: float) -> str:
    return "never" if x is None else f"{x - heal:.2f} s"


if __name__ == "__main__":
    main()
