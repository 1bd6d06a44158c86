"""The run's verdict against the paper's criteria (docs/outputs.md says what each figure is).

PASS when every robot settles (|e| stays below ``settle_threshold``) before
sqrt(2) T_p, nothing ever touches (no contact, every surface-to-surface gap > 0) and
nothing is non-finite (no NaN/Inf in the states, and the control law never
gave one), a law of the lab's own (docs/laws.md) never raised nor had an output refused
and kept its period, no robot ran on zero torque (its agent silent) for longer than the command
timeout, the run was not interrupted, its recording did not fail, and it went to its
end: a run ended early by a genuine ``ctl/stop`` or ``ctl/estop`` (``stopped_by`` in
metrics.json) is never PASS. A run whose states become non-finite or absurd (a robot
``DIVERGED_DISTANCE_M`` from its formation target, or faster than
``DIVERGED_SPEED_MPS``) has **diverged**; the verdict says when and which robot.

A run must also have gone **whole** and **on time**; the verdict fails, naming why:

- it simulated fewer steps than it was asked (``steps_simulated`` < ``steps_asked``), or
  its states were heard for fewer steps than were simulated (``steps``): on the
  realtime clock by more than the command timeout (the last wake of a loop that runs
  late skips its last periods; a gap longer than the timeout is not a late wake);
- (realtime) a robot's states were never heard for more steps than that
  (``series_rows_missing``): the series fills them forward, and the gaps leave them out
  (a state never heard is not a gap of 0);
- a node's report never arrived (``reports_missing``): its counts, its misses and its
  zero-torque stretches are unknown, so nothing says the run was whole;
- (realtime) the node that integrates or applies the torques stalled longer than the
  command timeout (``longest_stall``): the robots ran that long on whatever they had;
- (realtime) some node missed more than ``MAX_MISS_SHARE`` of the run's steps
  (``deadline_misses_by_node``). Why 5 %: the law is a sampled-data controller whose
  gains are chosen for its period; a loop that misses more than one period in twenty
  is on average answering at under 95 % of its rate, and more than one in twenty of the
  plant's steps is then driven by a prediction (agents/look_ahead.py) or held torques
  instead of feedback. A loop that keeps its period misses almost none (``lab`` at
  100 Hz: 0-3 in 2,000 steps, docs/bench-history.md); a starved one misses more than it steps.

Written to ``metrics.json`` as ``verdict`` by every run; ``--check`` turns it
into the exit code.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from deploy.contract.plant_registry import is_dynamic
from deploy.report.timeseries import TimeSeries

DIVERGED_DISTANCE_M = 1_000.0  # from the robot's formation target (the paper's field is ~100 m)
DIVERGED_SPEED_MPS = 1_000.0  # the paper's leader peaks near 50 m/s
MAX_MISS_SHARE = 0.05  # realtime: deadline misses per step of the run a node may have (above)


def divergence(series: TimeSeries, robot_ids: list[int]) -> dict[str, Any] | None:
    """The first step where a robot's state is non-finite or absurd, or None.

    Leading rows without a state (a realtime run before a robot's first
    message, NaN in the series) do not count."""
    q, qd = series.q, series.q_dot
    if not len(series.t):
        return None
    seen = np.maximum.accumulate(np.isfinite(q).all(axis=2), axis=0)  # (k, n): state known since
    bad_value = seen & ~(np.isfinite(q).all(axis=2) & np.isfinite(qd).all(axis=2))
    with np.errstate(invalid="ignore"):
        far = np.linalg.norm(q[:, :, :2] - series.target, axis=2) > DIVERGED_DISTANCE_M
        fast = np.linalg.norm(qd[:, :, :2], axis=2) > DIVERGED_SPEED_MPS
    bad = bad_value | (seen & (far | fast))
    if not bad.any():
        return None
    k, i = np.argwhere(bad)[0]
    what = ("non-finite state" if bad_value[k, i] else
            f"{DIVERGED_DISTANCE_M:.0f} m from its formation target" if far[k, i] else
            f"faster than {DIVERGED_SPEED_MPS:.0f} m/s")
    return {"t_s": float(series.t[k]), "robot": int(robot_ids[i]), "what": what}


def judge(metrics: dict[str, Any], diverged: dict[str, Any] | None = None) -> dict[str, Any]:
    """The verdict from metrics.json's figures (and :func:`divergence`). Figures a
    run did not write (an in-process run has no reports) are not judged."""
    bound = metrics["settling_bound_s"]
    settling = metrics["settling_time_s"]
    reasons = []
    if not is_dynamic(metrics.get("plant", "")):
        settled = None  # no dynamic level: the criterion does not apply; --check still fails it
        reasons.append(f"settling does not apply to the {metrics['plant']} plant")
    else:
        late = [(i, s) for i, s in enumerate(settling) if s is None or s >= bound]
        settled = not late
        for i, s in late:
            reasons.append(f"robot #{i + 1} " + ("never settled" if s is None
                                                   else f"settled at {s:.3f} s >= {bound:.3f} s"))
    clear = [metrics["min_obstacle_gap_m"], metrics["min_robot_gap_m"]]
    no_contact = metrics["contacts"] == 0 and all(c is None or c > 0 for c in clear)
    if not no_contact:
        reasons.append(f"{metrics['contacts']} contact(s)" if metrics["contacts"]
                       else "a gap between surfaces reached 0")
    nonfinite = metrics.get("nonfinite_commands", 0)
    finite = nonfinite == 0 and diverged is None
    if nonfinite:
        reasons.append(f"{nonfinite} non-finite command(s)")
    # a robot left on zero torque (its agent silent) longer than the command timeout was
    # not under control for that long, whatever the settling figures say afterwards
    timeout = metrics.get("command_timeout_s")
    unpowered = [(i, d) for i, d in enumerate(metrics.get("zero_torque_longest_s") or [])
                 if timeout is not None and d is not None and d > timeout]
    for i, d in unpowered:
        reasons.append(f"robot #{i + 1} ran on zero torque for {d:.3f} s "
                       f"(> command timeout {timeout:.3f} s)")
    if metrics.get("interrupted"):
        reasons.append(f"interrupted ({metrics['interrupted_by']})" if metrics.get(
            "interrupted_by") else "interrupted")
    recording = metrics.get("recording") or {}
    if recording.get("error"):
        reasons.append(f"the recording failed: {recording['error']}")
    complete = not metrics.get("interrupted") and not recording.get("error")
    if diverged is not None:
        reasons.append(f"DIVERGED: robot {diverged['robot']} {diverged['what']} "
                       f"at t = {diverged['t_s']:.3f} s")
    stopped = metrics.get("stopped_by")
    if stopped:  # a genuine ctl/stop or ctl/estop ended the run early (docs/hardening.md)
        at = stopped.get("t_s")
        reasons.append(f"STOPPED by ctl/{stopped['command']}"
                       + ("" if at is None else f" at t = {at:.3f} s"))
    whole = _whole(metrics, reasons)
    on_time = _on_time(metrics, reasons)
    in_formation = _in_formation(metrics, reasons)
    law_sound = _law_sound(metrics, reasons)
    return {"pass": (bool(settled) and no_contact and finite and not unpowered and complete
                     and not stopped and whole and on_time and in_formation and law_sound),
            "law_sound": law_sound,
            "settled": settled, "in_formation": in_formation,
            "expected_unreached": [u["robot"] for u in metrics.get("formation_unreached") or []
                                   if u["expected"]],
            "no_contact": no_contact,
            "finite": finite,
            "powered": not unpowered, "complete": complete, "stopped": bool(stopped),
            "whole": whole, "on_time": on_time, "realtime": metrics.get("clock") == "realtime",
            "diverged": diverged, "settling_bound_s": bound, "reasons": reasons}


def _law_sound(metrics: dict[str, Any], reasons: list[str]) -> bool:
    """A law of the lab's (agents/plugged.py) never raised nor gave an output that was
    refused, and overran its period in at most ``MAX_MISS_SHARE`` of the steps; each
    failure names the law, the robot and the first error's line."""
    law = metrics.get("law", "paper")
    ok = True
    for i, f in enumerate(metrics.get("law_faults") or []):
        if f and (f["errors"] or f["refused"]):
            ok = False
            reasons.append(f"law {law} on robot #{i + 1}: raised in {f['errors']} step(s), "
                           f"its output refused in {f['refused']} (the robot braked instead)"
                           + (f": {f['error']}" if f["error"] else ""))
    asked = metrics.get("steps_asked") or metrics.get("steps") or 0
    for i, n in enumerate(metrics.get("law_overruns") or []):
        if n and asked and n > MAX_MISS_SHARE * asked:
            ok = False
            reasons.append(f"law {law} on robot #{i + 1} took longer than its period in {n} of "
                           f"{asked} steps")
    return ok


def _in_formation(metrics: dict[str, Any], reasons: list[str]) -> bool:
    """Every robot within the formation threshold of its formation position at the end,
    but those the scenario expects never to get there (deploy/report/formation_reach.py)."""
    off = [u for u in metrics.get("formation_unreached") or [] if not u["expected"]]
    threshold = metrics.get("formation_threshold_m")
    for u in off:
        where = ("no state" if u["distance_end_m"] is None
                 else f"{u['distance_end_m']:.2f} m from it at the end")
        came = (f"never within {threshold:g} m" if u["reached_s"] is None
                else f"within {threshold:g} m from t = {u['reached_s']:.2f} s, then left")
        reasons.append(f"robot {u['robot']} not at its formation position ({where}; {came}): "
                       f"{u['why']}")
    return not off


def _slack_steps(metrics: dict[str, Any]) -> int:
    """Steps a run may fall short by: none in lockstep; on the realtime clock, the
    command timeout's worth (a late last wake)."""
    if metrics.get("clock") != "realtime":
        return 0
    timeout = metrics.get("command_timeout_s") or 0.0
    return int(timeout * float(metrics.get("control_rate_hz") or 0.0))


def _whole(metrics: dict[str, Any], reasons: list[str]) -> bool:
    """Whether the run simulated what it was asked, was heard for all of it, and every
    node reported (appends why not to ``reasons``)."""
    ok = True
    dt = 1.0 / float(metrics.get("control_rate_hz") or 1.0)
    slack = _slack_steps(metrics)
    asked, simulated = metrics.get("steps_asked"), metrics.get("steps_simulated")
    heard = metrics.get("steps")
    if asked is not None and simulated is not None and asked - simulated > slack:
        ok = False
        reasons.append(f"simulated {simulated * dt:.3f} s of the {asked * dt:.3f} s asked "
                       f"({simulated} of {asked} steps)")
    if simulated is not None and heard is not None and simulated - heard > slack:
        ok = False
        reasons.append(f"the robots' states were heard for {heard * dt:.3f} s of the "
                       f"{simulated * dt:.3f} s simulated: the rest cannot be judged")
    rows = metrics.get("series_rows_missing") or []
    unheard = [(i, r) for i, r in enumerate(rows) if r > slack]
    if unheard:  # named, never read as a gap (metrics: the gaps leave these rows out)
        ok = False
        reasons.append("states never heard: " + ", ".join(
            f"robot #{i + 1} {r} step(s) ({r * dt:.3f} s)" for i, r in unheard)
            + " (filled forward in the series: those steps cannot be judged)")
    late = metrics.get("restarts_not_rejoined") or []
    if late:
        ok = False
        reasons.append(f"{', '.join(late)} restarted by the fault plan but still starting when "
                       "the run ended (stopped; no report)")
    missing = metrics.get("reports_missing") or []
    if missing:
        ok = False
        reasons.append(f"no report from {', '.join(missing)}: its counts, deadline misses "
                       "and zero-torque stretches are unknown")
    return ok


def _on_time(metrics: dict[str, Any], reasons: list[str]) -> bool:
    """Realtime: no stall of the node that applies torques longer than the command
    timeout, and no node missing more than MAX_MISS_SHARE of the steps."""
    if metrics.get("clock") != "realtime":
        return True
    ok = True
    timeout = metrics.get("command_timeout_s")
    stall = metrics.get("longest_stall")
    if stall and timeout is not None and stall["duration_s"] > timeout:
        ok = False
        reasons.append(f"the {stall['node']} stalled {stall['duration_s']:.3f} s from "
                       f"t = {stall['t_s']:.3f} s (> command timeout {timeout:.3f} s): "
                       "the robots ran that long without it")
    asked = metrics.get("steps_asked") or metrics.get("steps") or 0
    by_node = metrics.get("deadline_misses_by_node") or {}
    over = {role: n for role, n in by_node.items() if asked and n > MAX_MISS_SHARE * asked}
    if over:
        ok = False
        reasons.append("deadline misses beyond " + f"{MAX_MISS_SHARE:.0%} of the {asked} steps: "
                       + ", ".join(f"{role} {n} ({n / asked:.0%})" for role, n in over.items()))
    return ok


def verdict_line(v: dict[str, Any]) -> str:
    """The summary's last line."""
    if v["pass"]:
        expected = v.get("expected_unreached") or []
        where = ("ended at its formation position" if not expected else
                 "ended at its formation position but robot(s) "
                 f"{', '.join(map(str, expected))}, as the scenario expects (notes)")
        return (f"verdict: PASS (every robot settled before {v['settling_bound_s']:.3f} s and "
                f"{where}, no contact, nothing non-finite, never unpowered, the whole run "
                "simulated and heard" + (", on time" if v.get("realtime") else "") + ")")
    return "verdict: FAIL (" + "; ".join(v["reasons"]) + ")"


def divergence_banner(v: dict[str, Any]) -> str | None:
    d = v.get("diverged")
    if not d:
        return None
    line = (f"!!! THE RUN DIVERGED: robot {d['robot']} {d['what']} at t = {d['t_s']:.3f} s; "
            "figures and metrics after that are meaningless !!!")
    bar = "!" * min(len(line), 100)
    return f"{bar}\n{line}\n{bar}"
