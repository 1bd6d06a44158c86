"""The metrics of a healthy run, as run_figures writes them: the base a test changes one
figure of to see the verdict judge it."""

from __future__ import annotations


def healthy_realtime(**kw: object) -> dict[str, object]:
    """A healthy 20 s realtime run at 500 Hz, as run_figures writes it."""
    m = {"scenario": "lab", "robots": 3, "plant": "model", "clock": "realtime",
         "control_rate_hz": 500.0, "settling_bound_s": 5.657,
         "settling_time_s": [0.4, 0.5, 0.4], "min_obstacle_gap_m": 0.3,
         "min_robot_gap_m": 0.2, "contacts": 0, "nonfinite_commands": 0,
         "command_timeout_s": 0.1, "zero_torque_longest_s": [0.0, 0.0, 0.0],
         "steps_asked": 10000, "steps_simulated": 9999, "steps": 9999,
         "reports_missing": [],
         "longest_stall": {"node": "plant", "duration_s": 0.004, "t_s": 3.0},
         "deadline_misses_by_node": {"agent-1": 3, "leader": 0, "plant": 12}}
    return m | kw
