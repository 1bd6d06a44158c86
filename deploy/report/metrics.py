"""metrics.json: what "it works" means for a run (docs/outputs.md), from the time series.

Keys (every run, in-process or distributed): scenario, plant, clock, robots,
sim_time_s, steps, control_rate_hz, wall_time_s, real_time_factor,
settling_time_s, formation_rms_whole_run_m, formation_rms_after_settling_m,
min_obstacle_gap_m, min_robot_gap_m, contacts (+ contact_source, contact_log),
peak_torque_nm, rms_torque_nm, nonfinite_commands, safety_filter (per robot: active
steps, time and episodes, largest and mean change of the command, infeasible steps),
messages.

Formation RMS is |q_xy - (x_0 + rho_i)| per robot, over the whole run and from the
robot's own settling time on (None for a robot that never settled: a robot that
settles late would otherwise look best). The gaps are surface to surface: centre
distance minus both radii, so 0 is contact (Fig. 6 of the paper plots centre
distances; a robot-robot gap g is a centre distance g + 2 r). A wall's or polygon's gap
is the robot centre's distance to its nearest point minus the robot's radius.

``contacts`` counts physical contact events when the plant simulates bodies
(pybullet: ``contact_source`` "physics", every event in ``contact_log`` with its
time, bodies and depth); for plants without bodies (model, kinematic) it counts
geometric onsets, a pair's clearance going from > 0 to <= 0 ("geometry").
``None`` (JSON null) means "never" for a settling time and "no such pair" for a
distance; infinite limits are written as null.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from deploy.contract.plant_registry import is_dynamic
from deploy.contract.scenario import Scenario
from deploy.report.formation_reach import formation_figures
from deploy.report.timeseries import TimeSeries

# Wall-clock, process and transport figures differ between two runs of the same
# scenario (and between in-process and distributed runs); everything else in
# metrics.json is a control figure and must not.
TIMING_KEYS = ("wall_time_s", "real_time_factor", "processes", "latency_ms", "jitter_ms",
               "deadline_misses", "messages", "recording", "series_cells_filled", "early_load",
               "law_overruns",
               "odometry_drift", "liveliness", "emulator_lag_ms", "bridge_faulted_fraction",
               "bridge_latency_ms",
               # what the nodes report of themselves (a distributed run only: in process
               # there is no command to time out, no sample to arrive stale)
               "command_timeout_s", "nonfinite_commands_reported", "stale_samples",
               "overloaded_steps",
               "zero_torque_longest_s", "deadline_misses_by_node", "jitter_p99_ms_by_node",
               "longest_stall",
               "reports_missing", "unanswered_states", "restarts_not_rejoined",
               "ros2",  # what the ROS 2 gateway published and refused
               # which output files the run wrote (a recording, figures): not a figure
               "files", "folder")


def settling_time(t: np.ndarray, err_norm: np.ndarray, threshold: float) -> float | None:
    """First time after which err_norm stays below threshold; None if it never does (or
    nothing of the run was heard)."""
    if len(t) == 0:
        return None
    above = np.nonzero(err_norm >= threshold)[0]
    if len(above) == 0:
        return float(t[0])
    last = above[-1]
    return None if last + 1 >= len(t) else float(t[last + 1])


def formation_rms(t: np.ndarray, xy: np.ndarray, target: np.ndarray,
                  settling: list[float | None]) -> tuple[list[float | None], list[float | None]]:
    """Per robot, the RMS of |q_xy - target| over the whole run and from its settling
    time on (None: it never settled, or no step is left). Rows without a state (a
    realtime run before a robot's first sample: NaN) are left out."""
    err = np.linalg.norm(xy - target, axis=2)

    def rms(seg: np.ndarray) -> float | None:
        known = seg[~np.isnan(seg)]
        return float(np.sqrt(np.mean(known**2))) if len(known) else None

    whole = [rms(err[:, i]) for i in range(err.shape[1])]
    after = [None if s is None else rms(err[int(np.searchsorted(t, s)):, i])
             for i, s in enumerate(settling)]
    return whole, after


def leader_estimate_error(series: TimeSeries) -> np.ndarray:
    """Fig. 5(b), (k - 1, n): |p0_hat_i - p0| with both at the same instant. The series
    holds each agent's estimate after its step k, i.e. for t_{k+1}: it is compared with
    the leader at t_{k+1} (against the leader at t_k it would carry a spurious |v0| dt,
    up to 5 cm on ``paper`` at 1 kHz)."""
    return np.linalg.norm(series.q0_hat[:-1, :, :2] - series.leader_q[1:, None, :2], axis=2)


def pair_clearances(
    positions: np.ndarray, radii: np.ndarray, obstacles: np.ndarray, obstacle_radii: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(robot-robot clearances (k, pairs), robot-obstacle clearances (k, n*m))."""
    k, n, _ = positions.shape
    iu, ju = np.triu_indices(n, 1)
    rr = np.linalg.norm(positions[:, iu] - positions[:, ju], axis=2) - (radii[iu] + radii[ju])
    if len(obstacles) == 0:
        return rr, np.zeros((k, 0))
    diff = positions[:, :, None, :] - obstacles[None, None, :, :]
    ro = np.linalg.norm(diff, axis=3) - radii[None, :, None] - obstacle_radii[None, None, :]
    return rr, ro.reshape(k, -1)


def contact_onsets(clearance: np.ndarray) -> int:
    """Number of times a pair goes from apart (> 0) to touching (<= 0), start included."""
    if clearance.size == 0:
        return 0
    touching = clearance <= 0.0
    onsets = touching[1:] & ~touching[:-1]
    return int(touching[0].sum() + onsets.sum())


def _least(gaps: np.ndarray) -> float | None:
    """The least gap over the steps whose states exist (None: no gap, or no such step)."""
    ok = gaps[np.isfinite(gaps)]
    return float(ok.min()) if ok.size else None


def _nan_aware(fn, x: np.ndarray) -> float:
    return float(fn(x)) if np.isfinite(x).any() else float(np.abs(x).max(initial=np.nan))


def _finite_or_none(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def compute_metrics(
    sc: Scenario,
    series: TimeSeries,
    plant: str,
    clock: str,
    wall_time_s: float,
    messages: dict[str, int] | None = None,
    contact_log: list[dict[str, Any]] | None = None,
    contacts_total: int | None = None,
    steps_asked: int | None = None,
) -> dict[str, Any]:
    """``contact_log``: the plant's physical contact events (None: it has no bodies);
    ``contacts_total``: their number when the log was truncated in transit;
    ``steps_asked``: the steps the run was asked for (None: the series' own, as a run
    in process simulates exactly what it records)."""
    s = sc.spec
    t = series.t
    n = sc.n
    threshold = s.metrics.settle_threshold
    err = np.linalg.norm(series.e, axis=2)
    notes = list(sc.notes)
    if not is_dynamic(plant):
        # q follows v_d directly: no dynamic level, so no behavioral tracking error.
        settling = [None] * n
        notes.append(f"{plant} plant: no dynamic level; settling_time_s does not apply")
    else:
        settling = [settling_time(t, err[:, i], threshold) for i in range(n)]
    whole, after = formation_rms(t, series.q[:, :, :2], series.target, settling)
    rr, ro = _gaps(sc, series)
    heard = series.state_heard
    sim_time = series.steps * sc.dt
    reach = formation_figures(series, sc.robot_ids, sc.dt, s.metrics.formation_threshold_m,
                              s.metrics.expect_unreached, s.metrics.expect_unreached_why)
    notes += _expected_unreached(reach["formation_unreached"])
    return {
        "scenario": s.name,
        "law": sc.law_name,  # the agents' control law (docs/laws.md)
        "plant": plant,
        "clock": clock,
        "robots": n,
        "sim_time_s": sim_time,
        "steps": series.steps,
        # what was asked, and what the node that integrates simulated (a distributed run:
        # the plant's own count, in its report); the verdict compares the three
        "steps_asked": series.steps if steps_asked is None else steps_asked,
        "steps_simulated": series.steps,
        "control_rate_hz": s.control_rate_hz,
        "wall_time_s": wall_time_s,
        "real_time_factor": sim_time / wall_time_s if wall_time_s > 0 else None,
        "settle_threshold": threshold,
        "settling_bound_s": math.sqrt(2.0) * s.controller.T_p,
        "settling_time_s": settling,
        "formation_rms_whole_run_m": whole,
        "formation_rms_after_settling_m": after,
        **reach,
        "min_obstacle_gap_m": _least(ro),
        "min_robot_gap_m": _least(rr),
        # per robot, the steps whose state the series never received (realtime: filled
        # forward from the step before; the gaps above leave them out)
        "series_rows_missing": ([0] * n if heard is None
                                else (~heard).sum(axis=0).astype(int).tolist()),
        "contacts": (contact_onsets(rr) + contact_onsets(ro) if contact_log is None
                     else max(len(contact_log), contacts_total or 0)),
        "contact_source": "geometry" if contact_log is None else "physics",
        "contact_log": contact_log,
        # a realtime series has no torque before an agent's first telemetry (NaN)
        "peak_torque_nm": _nan_aware(np.nanmax, np.abs(series.torque)),
        "rms_torque_nm": _nan_aware(lambda x: np.sqrt(np.nanmean(x)), series.torque**2),
        "nonfinite_commands": int(series.nonfinite.sum()),
        "safety_filter": safety_figures(series, sc.dt),
        "limits": {name: _finite_or_none(getattr(s.limits, name)) for name in LIMIT_FIGURES},
        "notes": notes,
        "messages": dict(messages or {"sent": 0, "dropped": 0, "late": 0, "invalid": 0}),
    }


# the scenario's limits the metrics repeat (null where a limit is off: inf)
LIMIT_FIGURES = ("max_speed_mps", "max_yaw_rate_radps", "max_wheel_torque_nm", "max_accel_mps2",
                 "max_yaw_accel_radps2", "max_tracking_error")


def _gaps(sc: Scenario, series: TimeSeries) -> tuple[np.ndarray, np.ndarray]:
    """Surface-to-surface gaps per step: robot pairs (k, pairs) and robot-obstacle (k,
    n * bodies), NaN where a robot's state was never heard (realtime: rows filled forward
    are not gaps)."""
    n, q_xy = sc.n, series.q[:, :, :2]
    radii = np.full(n, sc.spec.robot.body_radius_m)
    rr, _ = pair_clearances(q_xy, radii, np.zeros((0, 2)), np.zeros(0))
    # discs, walls and polygons: the true geometry (plant/shapes.py, G2)
    ro = sc.obstacle_gaps(q_xy)
    steps = len(series.t)
    ro = ro.reshape(steps, ro.size // steps if steps else 0)  # (none heard: no gap at all)
    heard = series.state_heard
    if heard is not None:  # gaps only where the states were heard (not filled, never NaN)
        iu, ju = np.triu_indices(n, 1)
        rr = np.where(heard[:, iu] & heard[:, ju], rr, np.nan)
        ro = np.where(np.repeat(heard, ro.shape[1] // n if n else 0, axis=1), ro, np.nan)
    return rr, ro


def _expected_unreached(unreached: list[dict[str, Any]]) -> list[str]:
    """A note for each robot the scenario expects away from its formation position: a
    PASS beside a large formation error says why."""
    return [f"robot {u['robot']} is not at its formation position (" + (
        "no state" if u["distance_end_m"] is None else
        f"{u['distance_end_m']:.2f} m from it at the end") + f"), as the scenario "
        f"expects: {u['why']}" for u in unreached if u["expected"]]


def safety_figures(series: TimeSeries, dt: float) -> dict[str, Any]:
    """Per robot: how often, how long and by how much the safety filter changed the
    command (agents/safety_filter.py), and the steps where no command met every barrier."""
    active = series.safety_active.astype(bool)
    started = active & ~np.vstack([np.zeros((1, active.shape[1]), bool), active[:-1]])
    dv = np.where(active, series.safety_dv, np.nan)
    with np.errstate(invalid="ignore"):
        mean_dv = [float(np.nanmean(dv[:, i])) if active[:, i].any() else 0.0
                   for i in range(active.shape[1])]
    return {
        "active_steps": active.sum(axis=0).astype(int).tolist(),
        "active_time_s": (active.sum(axis=0) * dt).tolist(),
        "episodes": started.sum(axis=0).astype(int).tolist(),
        "max_dv_mps": np.where(active, series.safety_dv, 0.0).max(axis=0, initial=0.0).tolist(),
        "mean_dv_mps_when_active": mean_dv,
        "infeasible_steps": series.safety_infeasible.astype(int).sum(axis=0).tolist(),
    }


def control_figures(metrics: dict[str, Any]) -> dict[str, Any]:
    """metrics without the wall-clock keys: what two runs must agree on."""
    return {k: v for k, v in metrics.items() if k not in TIMING_KEYS}


def finite_or_null(x: Any) -> Any:
    """JSON has no NaN/Inf: a diverged run's figures are written as null."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: finite_or_null(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [finite_or_null(v) for v in x]
    return x


def write_metrics(metrics: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(finite_or_null(metrics), indent=2, allow_nan=False) + "\n")
