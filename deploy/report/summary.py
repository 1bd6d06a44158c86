"""The run summary a person reads at the end of `omnifleet run` and `record`: each
figure of metrics.json in a line, the verdict last."""

from __future__ import annotations

from pathlib import Path

from deploy.contract.plant_registry import is_dynamic
from deploy.report.verdict import judge, verdict_line
from deploy.runtime.priority import over_realtime_limit_words


def meets_paper_criteria(m: dict) -> bool:
    """Every robot settles before sqrt(2) T_p; no contact, ever; nothing non-finite."""
    return (m["verdict"] if "verdict" in m else judge(m))["pass"]


def _fmt_list(xs) -> str:
    return "[" + ", ".join("never" if x is None else f"{x:.3f}" for x in xs) + "]"


def summary(m: dict, out: Path) -> str:
    def f(x):
        return "n/a" if x is None else f"{x:.3f}"

    return "\n".join([
        f"{m['scenario']}: {m['robots']} robots, {m['plant']} plant, {m['clock']}, "
        f"{_simulated(m)} in {m['wall_time_s']:.2f} s "
        f"(x{m['real_time_factor']:.2f} real time)",
        *([f"  INTERRUPTED ({m.get('interrupted_by')}): what follows covers the "
           f"{m['sim_time_s']:.2f} s measured before it; no figures"] if m.get("interrupted")
          else []),
        "  settling time (s)          "
        + (f"n/a ({m['plant']} plant: no dynamic level)" if not is_dynamic(m["plant"]) else
           f"{_fmt_list(m['settling_time_s'])}  bound {m['settling_bound_s']:.3f}"),
        f"  formation RMS, whole run   {_fmt_list(m['formation_rms_whole_run_m'])} m",
        "  ... after settling         " + (f"n/a ({m['plant']} plant: no settling)"
                                             if not is_dynamic(m["plant"]) else
                                             f"{_fmt_list(m['formation_rms_after_settling_m'])} m"),
        f"  min gap to an obstacle     {f(m['min_obstacle_gap_m'])} m (surface to surface)",
        f"  min gap between robots     {f(m['min_robot_gap_m'])} m (surface to surface)",
        f"  contacts                   {m['contacts']}",
        f"  peak / RMS torque (N m)    {m['peak_torque_nm']:.4g} / {m['rms_torque_nm']:.4g}",
        *_safety_lines(m),
        *_law_lines(m),
        *_transport_lines(m),
        *_hardening_lines(m),
        *_formation_lines(m),
        *[f"  note: {n}" for n in m.get("notes") or []],
        f"  written to {m.get('folder') or out}/ ({', '.join(m.get('files') or ['metrics.json'])})",
        *([verdict_line(m["verdict"])] if "verdict" in m else []),
    ])


def _formation_lines(m: dict) -> list[str]:
    """Where each robot ended against its formation position, apart from settling
    (deploy/report/formation_reach.py)."""
    end = m.get("formation_distance_end_m")
    if end is None:
        return []
    return [f"  formation position, end    {_fmt_list(end)} m away; first within "
            f"{m['formation_threshold_m']:g} m at {_fmt_list(m['formation_reached_s'])} s"]


def _simulated(m: dict) -> str:
    """"20.00 s simulated", or what fell short: "4.90 s of the 20.00 s asked simulated,
    4.88 s heard" (the steps the plant simulated, and those whose states arrived)."""
    dt = 1.0 / float(m["control_rate_hz"])
    asked, done = m.get("steps_asked"), m.get("steps_simulated", m["steps"])
    text = f"{done * dt:.2f} s"
    if asked is not None and asked != done:
        text += f" of the {asked * dt:.2f} s asked"
    text += " simulated"
    if done != m["steps"]:
        text += f" ({m['sim_time_s']:.2f} s of it heard)"
    return text


def _law_lines(m: dict) -> list[str]:
    """How often each robot's law restarted from the robot, what it computed non-finite,
    and (realtime) the longest stretch each robot ran on zero torque."""
    resets = m.get("law_resets")
    if resets is None:  # an interrupted distributed run: the agents never reported
        return ["  law restarts               n/a (the agents' reports were not collected)"]
    lines = [f"  law restarts               {_fmt_ints(resets)} (from the robot's state: a gap "
             f"or a non-finite state); non-finite commands {m.get('nonfinite_commands', 0)}"]
    slowed = m.get("overloaded_steps")
    if slowed and any(slowed):
        lines.append(f"  overloaded steps           {_fmt_ints(slowed)} (the loop slower than its "
                     "period: robot slowed, agents/pace.py)")
    longest = m.get("zero_torque_longest_s")
    if longest is not None:
        lines.append(f"  longest on zero torque     {_fmt_list(longest)} s (command timeout "
                     f"{m['command_timeout_s']:.3f} s)")
    return lines


def _fmt_ints(xs: list) -> str:
    return "[" + ", ".join("n/a" if x is None else str(x) for x in xs) + "]"


def _hardening_lines(m: dict) -> list[str]:
    """A run stopped early, and commands clipped to the torque bound."""
    lines = []
    s = m.get("stopped_by")
    if s:
        at = "" if s.get("t_s") is None else f" at t = {s['t_s']:.3f} s"
        lines.append(f"  STOPPED                    by ctl/{s['command']}{at} (sender {s['sender']}): "
                     "the run did not go to its end")
    refused = (m.get("messages") or {}).get("refused") or {}
    if refused:
        lines.append(f"  refused on arrival         {sum(refused.values())} message(s) by "
                     f"{len({k.split(':')[0] for k in refused})} node(s) "
                     "(metrics.json messages.refused: by node and reason)")
    clipped = m.get("torque_clipped") or []
    if any(clipped):
        lines.append(f"  torque clipped to bound    {_fmt_ints(clipped)} command(s)")
    return lines


def _safety_lines(m: dict) -> list[str]:
    f = m.get("safety_filter")
    if not f:
        return []
    if not any(f["active_steps"]):
        return ["  safety filter              never acted (the paper's law as it is)"]
    line = (f"  safety filter              acted {_fmt_list(f['active_time_s'])} s in "
            f"{f['episodes']} episode(s), command changed by up to {_fmt_list(f['max_dv_mps'])} m/s")
    if any(f["infeasible_steps"]):
        line += f"; no safe command within the limits on {f['infeasible_steps']} step(s)"
    return [line]


def _transport_lines(m: dict) -> list[str]:
    if "processes" not in m:
        return []
    msg = m["messages"]
    lines = [f"  messages                   sent {msg['sent']}, dropped {msg['dropped']}, "
             f"late {msg['late']}, invalid {msg['invalid']}"]
    rss = [p["peak_rss_mb"] for p in m["processes"] if p["peak_rss_mb"] is not None]
    lines.append(f"  processes                  {len(m['processes'])}, peak RSS up to "
                 f"{max(rss):.0f} MB" if rss else f"  processes                  {len(m['processes'])}")
    if "latency_ms" in m:
        lat, jit = m["latency_ms"], m["jitter_ms"]

        def ms(x):
            return "n/a" if x is None else f"{x:.3f}"

        if "bridge_latency_ms" in m:  # on CAN: no plant to time the agents' answers
            b = m["bridge_latency_ms"]
            lines.append(f"  bridge cmd->torque frame   p50 {ms(b['p50'])} ms, p99 {ms(b['p99'])} ms")
        else:
            lines.append(f"  state->command latency     p50 {ms(lat['p50'])} ms, p99 {ms(lat['p99'])} ms")
        lines.append(f"  loop jitter                p50 {ms(jit['p50'])} ms, p99 {ms(jit['p99'])} ms; "
                     f"deadline misses {m['deadline_misses']}")
        by_node = m.get("deadline_misses_by_node")
        if by_node and m['deadline_misses']:
            lines.append("  deadline misses by node    " + ", ".join(
                f"{role} {n}" for role, n in by_node.items() if n)
                + f" (of {m.get('steps_asked', m['steps'])} steps)")
        unanswered = m.get("unanswered_states")
        if unanswered and any(unanswered):
            lines.append(f"  states unanswered in time {_fmt_ints(unanswered)} step(s) (the "
                         "agent's command had not come by the plant's next step)")
        early = m.get("early_load")
        if early and early.get("behind"):
            lines.append(f"  machine too slow           in the first second the fleet took "
                         f"{early['busy_share']:.0%} of {early['cores']} core(s), "
                         f"{early['heaviest']} {early['heaviest_cpu_us_per_step']:.0f} µs a step; "
                         f"this machine would hold it at about {early['max_rate_hz']:.0f} Hz")
        if early and early.get("over_realtime_limit"):
            lines.append("  realtime limit             the realtime processes took "
                         + over_realtime_limit_words(early["realtime_share"],
                                                     early["realtime_limit"]))
        rows = m.get("series_rows_missing")
        if rows and any(rows):
            lines.append(f"  states never heard         {_fmt_ints(rows)} step(s) (filled forward "
                         "in the series; left out of the gaps)")
        stall = m.get("longest_stall")
        if stall:
            lines.append(f"  longest stall              {stall['node']} {stall['duration_s']:.3f} s "
                         f"from t = {stall['t_s']:.3f} s (its latest wake)")
    missing = m.get("reports_missing")
    if missing:
        lines.append(f"  reports missing            {', '.join(missing)}")
    if "odometry_drift" in m:
        d = m["odometry_drift"]

        def cm(xs):
            return ", ".join(f"{x * 100:.2f}" for x in xs)

        lines.append(f"  odometry drift (cm)        median {cm(d['median_m'])}; max {cm(d['max_m'])}")
    return lines
