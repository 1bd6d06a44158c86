"""Formation reached, apart from tracking settled (metrics.json, the verdict).

``settling_time_s`` says how well a robot tracks its *behaviour reference* q_d (the
paper's claim, |q - q_d| below ``settle_threshold``). That reference can sit far from the
robot's formation position x_0 + rho_i: avoidance holds it off an obstacle or another
robot, the safety filter blocks the way, or the robot's own leader estimate (eq. 14) puts
its formation pose (eq. 16) elsewhere. So a robot is also judged where it ends: its
distance to its formation position (true leader) at the end, the time it first came
within ``formation_threshold_m``, and, when it ends outside, the reason the run knows,
read from what acted on it over the last second.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from deploy.report.timeseries import BEHAVIOR_BITS, TimeSeries

REASON_WINDOW_S = 1.0  # what acted on a robot over the run's last second says why it is off
ACTING_SHARE = 0.2  # a behaviour or the filter active this share of that second is a reason


def formation_figures(series: TimeSeries, robot_ids: list[int], dt: float, threshold: float,
                      expected: list[int], expected_why: str) -> dict[str, Any]:
    """Per robot (lists in the scenario's order): the distance to its formation position
    at the end, the time it first came within ``threshold`` (None: never), and for each
    robot not within it at the end the reason (``formation_unreached``)."""
    n = len(robot_ids)
    if series.steps == 0:
        return {"formation_threshold_m": threshold, "formation_distance_end_m": [None] * n,
                "formation_reached_s": [None] * n, "formation_unreached": []}
    d = np.linalg.norm(series.q[:, :, :2] - series.target, axis=2)  # (k, n); NaN: no state
    end, reached, unreached = [], [], []
    for i, rid in enumerate(robot_ids):
        known = np.flatnonzero(np.isfinite(d[:, i]))
        last = float(d[known[-1], i]) if len(known) else None
        within = np.flatnonzero(d[:, i] <= threshold)
        first = float(series.t[within[0]]) if len(within) else None
        end.append(last)
        reached.append(first)
        if last is None or last > threshold:
            unreached.append({
                "robot": rid, "distance_end_m": last, "reached_s": first,
                "expected": rid in expected,
                "why": expected_why if rid in expected else why_off(series, i, dt, threshold)})
    return {"formation_threshold_m": threshold, "formation_distance_end_m": end,
            "formation_reached_s": reached, "formation_unreached": unreached}


def why_off(series: TimeSeries, i: int, dt: float, threshold: float) -> str:
    """What kept robot ``i`` off its formation position, from the run's last second."""
    k0 = max(0, series.steps - max(1, int(round(REASON_WINDOW_S / dt))))
    window = slice(k0, series.steps)
    span = (series.steps - k0) * dt
    active = series.active[window, i].astype(int)
    why = []
    filt = float(series.safety_active[window, i].mean())
    if filt >= ACTING_SHARE:
        blocked = int(series.safety_infeasible[window, i].sum())
        why.append(f"blocked by the safety filter (it changed the command {filt:.0%} of the "
                   f"last {span:.1f} s" + (f", no safe command on {blocked} step(s)" if blocked
                                           else "") + ")")
    for name, what in (("FOCB", "held off by obstacle avoidance"),
                       ("FRCB", "held off by robot avoidance")):
        share = float(((active & BEHAVIOR_BITS[name]) != 0).mean())
        if share >= ACTING_SHARE:
            why.append(f"{what} ({name} active {share:.0%} of the last {span:.1f} s)")
    ref_off = float(np.linalg.norm(series.q_fd[-1, i, :2] - series.target[-1, i]))
    if np.isfinite(ref_off) and ref_off > threshold:
        why.append(f"its own formation pose (eq. 16, from its leader estimate, eq. 14) is "
                   f"{ref_off:.2f} m from the slot")
    return "; ".join(why) or "still on its way at the end (nothing held it off in the last " \
        f"{span:.1f} s: the run may end too soon)"
