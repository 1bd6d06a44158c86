"""What a distributed run adds to metrics.json beside its series: messages, processes
and links, each agent's counters, zero-torque stretches, clipped torques, faults and
latency, from the nodes' reports and what the observer counted."""

from __future__ import annotations

import os
from typing import Any

import msgspec
import numpy as np

from deploy.contract.fault_plan import FaultPlan
from deploy.contract.options import DEFAULT_COMMAND_TIMEOUT_S
from deploy.contract.wire import LAUNCHER_ROLE, PLANT_ROLE, NodeReport, agent_role, bridge_role
from deploy.report.run_folder import RECORDING
from deploy.run.observer import Observer
from deploy.run.plan import Child
from deploy.runtime.fault_model import fault_metrics, merge_reports
from deploy.runtime.node_runtime import LoopClock, peak_rss_kb
from deploy.runtime.step_costs import per_step_us


def agent_figures(agents: list[NodeReport | None]) -> dict[str, Any]:
    """What each robot's agent counted (metrics.json): how often its law restarted from
    the robot (a gap longer than its inputs stay fresh, a non-finite state), the
    commands it computed non-finite (zero torques sent), the realtime samples too old
    on arrival to answer, the realtime steps of a loop slower than its period (the robot
    slowed, agents/pace.py). Reports that never came count as None."""
    def each(name: str) -> list[int | None]:
        return [None if r is None else int(getattr(r, name)) for r in agents]
    return {"law_resets": each("law_resets"),
            "nonfinite_commands_reported": each("nonfinite_commands"),
            "stale_samples": each("stale_samples"),
            "overloaded_steps": each("overloaded_steps")}


def law_fault_figures(faults: list[dict | None] | None) -> dict[str, Any]:
    """A law of the lab's own (agents/plugged.py): per robot, the steps it raised and those
    whose output was refused (braked instead), with its first error's line
    (``law_faults``), and the steps it overran its period (``law_overruns``, a timing);
    nothing for the paper's law. A robot whose report never came: None."""
    if faults is None or all(f is None for f in faults):
        return {}
    return {"law_faults": [None if f is None else {k: f[k] for k in ("errors", "refused", "error")}
                           for f in faults],
            "law_overruns": [None if f is None else f["overruns"] for f in faults]}


def agent_law_faults(agents: list[NodeReport | None], plugged: bool) -> list[dict | None] | None:
    """The agents' reports as :func:`law_fault_figures` takes them (None: the paper's law)."""
    if not plugged:
        return None
    return [None if r is None else {"errors": r.law_errors, "refused": r.law_refused,
                                    "overruns": r.law_overruns, "error": r.law_error}
            for r in agents]


def zero_torque_figures(reports: list[NodeReport], robot_ids: list[int]) -> dict[str, Any]:
    """Each stretch a robot ran on zero torque for want of a fresh command (plant or CAN
    bridge, realtime), and per robot the longest (0 when none): the verdict compares it
    with the command timeout (deploy/report/verdict.py)."""
    spans = sorted((s for r in reports for s in r.zero_torque), key=lambda s: s[1])
    longest = {rid: 0.0 for rid in robot_ids}
    for rid, _, d in spans:
        if rid in longest:
            longest[rid] = max(longest[rid], d)
    out: dict[str, Any] = {"zero_torque_longest_s": [round(longest[r], 4) for r in robot_ids],
                           "command_timeout_s": DEFAULT_COMMAND_TIMEOUT_S}
    if spans:
        out["zero_torque"] = [{"robot": r, "t_s": round(t, 4), "duration_s": round(d, 4)}
                              for r, t, d in spans]
    return out


def percentiles_ms(samples: list[int]) -> dict[str, float | None]:
    if not samples:
        return {"p50": None, "p99": None}
    a = np.asarray(samples, float) * 1e-6
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))}


def message_figures(reports: dict[str, NodeReport], obs: Observer) -> dict[str, Any]:
    """Messages sent, dropped, late and invalid over the run, and what was refused by
    node and reason (counted in ``dropped`` or ``invalid`` too)."""
    # a message for a step outside the run is never used: dropped
    messages: dict[str, Any] = {"sent": 0, "dropped": obs.collector.out_of_range, "late": 0,
                                "invalid": obs.invalid}
    refused: dict[str, int] = {}
    for r in reports.values():
        messages["sent"] += r.sent
        messages["dropped"] += r.dropped
        messages["late"] += r.late
        messages["invalid"] += r.invalid
        for why, n in r.refused.items():
            refused[f"{r.role}: {why}"] = n
    refused |= obs.refused()
    if refused:
        messages["refused"] = refused
    return messages


def process_rows(children: list[Child], reports: dict[str, NodeReport],
                 listener_zid: str, listener_cpu: LoopClock | None = None) -> list[dict[str, Any]]:
    """One row per process started (and one for the listener itself): pid, peak memory,
    exit, and who it had a link with, from its own zenoh session (ids -> roles)."""
    role_of = {r.zid: role for role, r in reports.items() if r.zid}
    role_of[listener_zid] = LAUNCHER_ROLE
    rows = []
    for c in children:
        r = reports.get(c.role)
        c.peak_rss_mb = r.peak_rss_kb / 1024.0 if r is not None and r.peak_rss_kb else None
        rows.append({"role": c.role, "robot": c.robot, "pid": c.proc.pid,
                     "peak_rss_mb": None if c.peak_rss_mb is None else round(c.peak_rss_mb, 1),
                     "exit_code": c.exit_code, "killed": c.killed, "reported": r is not None,
                     "received": dict(r.received) if r is not None else {},
                     # a node's own figure is its run loop's; one with no report (the
                     # drive emulator), its whole life's, from the kernel
                     "cpu_s": round(r.cpu_s, 3) if r is not None else (
                         None if c.cpu_s is None else round(c.cpu_s, 3)),
                     "loop_s": round(r.loop_s, 3) if r is not None else None,
                     "step_costs_ns": dict(r.step_costs_ns) if r is not None else {},
                     **({"rejoin_s": round(r.rejoin_s, 3)}
                        if r is not None and r.rejoin_s >= 0 and c.restarted else {}),
                     "links": sorted(role_of.get(z, z) for z in r.peers) if r is not None
                     else None})
    rows.append({"role": LAUNCHER_ROLE, "robot": None, "pid": os.getpid(),
                 "peak_rss_mb": round(peak_rss_kb() / 1024.0, 1), "exit_code": None,
                 "reported": True,
                 "cpu_s": None if listener_cpu is None else round(listener_cpu.cpu_s, 3),
                 "loop_s": None if listener_cpu is None else round(listener_cpu.loop_s, 3),
                 "step_costs_ns": ({} if listener_cpu is None or listener_cpu.costs is None
                                   else listener_cpu.costs.totals())})
    return rows


def add_cost_per_step(rows: list[dict[str, Any]], steps: int) -> None:
    """Each process's CPU per step of the run (µs; ``cpu_us_per_step``) and the share of
    each part of a step in it (``parts_us_per_step``: deploy/runtime/step_costs.py)."""
    for row in rows:
        cpu, costs = row.get("cpu_s"), row.pop("step_costs_ns", {})
        if cpu is None or steps <= 0:
            continue
        row["cpu_us_per_step"] = round(cpu / steps * 1e6, 1)
        if costs:
            row["parts_us_per_step"] = {k: round(v, 1)
                                        for k, v in per_step_us(costs, cpu, steps).items()}


def run_figures(obs: Observer, children: list[Child], listener_zid: str, wall: float,
                faults: FaultPlan | None = None, kill_events: list[dict] | None = None,
                listener_cpu: LoopClock | None = None,
                expected_roles: list[str] | None = None) -> dict[str, Any]:
    """Everything a run adds to metrics.json beside its series and scene.
    ``expected_roles``: the nodes that must report (default: the zenoh nodes among
    ``children``, those the fault plan killed for good left out)."""
    sc = obs.sc
    reports: dict[str, NodeReport] = dict(obs.collector.reports)
    out: dict[str, Any] = {"wall_time_s": wall, "messages": message_figures(reports, obs),
                           "processes": process_rows(children, reports, listener_zid,
                                                     listener_cpu)}
    # per robot, in the scenario's order (None: its agent's report never came); a
    # restarted agent reports for its second life too (the collector keeps the last)
    agents = [reports.get(agent_role(r)) for r in sc.robot_ids]
    out |= agent_figures(agents)
    out |= law_fault_figures(agent_law_faults(agents, sc.spec.law.use != "paper"))
    # commands that asked for more torque than the bound, clipped: per robot, a list in the
    # scenario's order like every per-robot figure (the reports key them by id, as text)
    clipped = {str(r): 0 for r in sc.robot_ids}
    for rep in reports.values():
        for rid, n in rep.torque_clipped.items():
            if rid in clipped:
                clipped[rid] += n
    out["torque_clipped"] = [clipped[str(r)] for r in sc.robot_ids]
    if obs.stopped_by is not None:
        out["stopped_by"] = obs.stopped_by
    plant = reports.get(PLANT_ROLE)
    bridges = [reports[bridge_role(r)] for r in sc.robot_ids if bridge_role(r) in reports]
    holders = [r for r in [plant, *bridges] if r is not None]  # who applies torques
    out |= zero_torque_figures(holders, sc.robot_ids)
    stops = sorted((s for r in holders for s in r.command_stops),
                   key=lambda s: s[2])  # the plant's, or on CAN each bridge's, by run time
    if stops:
        out["command_stops"] = [{"robot": r, "command_age_s": a, "t_s": t} for r, a, t in stops]
    if plant is not None and plant.contacts is not None:
        out["contact_log"] = [msgspec.structs.asdict(c) for c in plant.contacts]
        out["contacts_total"] = plant.contacts_total
    if obs.recorder is not None:
        out["recording"] = {"file": RECORDING, "messages": obs.recorder.written}
    if faults is not None:
        out["faults"] = fault_metrics(faults, merge_reports([r.faults for r in reports.values()]),
                                      kill_events or [])
    if expected_roles is None:
        # a node the fault plan killed for good, or restarted too late to rejoin, has no
        # report to send; the second is said in the verdict (restarts_not_rejoined)
        expected_roles = [c.role for c in children if c.zenoh and not (c.killed and not any(
            o.role == c.role and o.restarted for o in children)) and not c.never_rejoined]
        expected_roles = [r for r in expected_roles
                          if not any(c.role == r and c.never_rejoined for c in children)]
        late = sorted({c.role for c in children if c.never_rejoined})
        if late:
            out["restarts_not_rejoined"] = late
    out |= completeness_figures(sc.dt, expected_roles, reports, plant, bridges, obs.clock)
    add_cost_per_step(out["processes"], out.get("steps_simulated") or obs.steps)
    if obs.clock == "realtime":
        out["latency_ms"] = percentiles_ms(plant.latency_ns if plant else [])
        if bridges:  # on CAN: each command's arrival -> its torque frames on the bus
            out["bridge_latency_ms"] = percentiles_ms([x for b in bridges for x in b.latency_ns])
        out["jitter_ms"] = percentiles_ms([j for r in reports.values() for j in r.jitter_ns])
        # whose loop is late: on a loaded core the nodes differ by their priority and turn
        out["jitter_p99_ms_by_node"] = {role: percentiles_ms(r.jitter_ns)["p99"]
                                        for role, r in sorted(reports.items()) if r.jitter_ns}
        out["deadline_misses"] = sum(r.deadline_misses for r in reports.values())
        out["deadline_misses_by_node"] = {role: r.deadline_misses
                                          for role, r in sorted(reports.items())}
        if plant is not None and len(plant.unanswered) == sc.n:
            out["unanswered_states"] = list(plant.unanswered)
    return out


def completeness_figures(dt: float, expected_roles: list[str], reports: dict[str, NodeReport],
                         plant: NodeReport | None, bridges: list[NodeReport], clock: str
                         ) -> dict[str, Any]:
    """What the verdict needs to know the run went whole (deploy/report/verdict.py): the
    steps the node that integrates (the plant; on CAN each bridge) simulated, the nodes
    whose report never came, and (realtime) the longest stall of a node that applies
    torques, when it began."""
    out: dict[str, Any] = {}
    holders = [r for r in [plant, *bridges] if r is not None]
    if holders:
        out["steps_simulated"] = min(r.steps for r in holders)
    out["reports_missing"] = sorted({role for role in expected_roles if role not in reports})
    if clock == "realtime" and holders:
        worst = max(holders, key=lambda r: r.longest_late_ns)
        out["longest_stall"] = {"node": worst.role, "duration_s": worst.longest_late_ns * 1e-9,
                                "t_s": max(worst.longest_late_k, 0) * dt}
    return out
