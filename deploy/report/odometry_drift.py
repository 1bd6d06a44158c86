"""Odometry drift of a run on CAN: the bridges' states (the run's series, built
from the bridges' state logs) against each emulator's ground truth, matched in time on the
host's monotonic clock (every process of one host shares it)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from deploy.report.timeseries import TimeSeries


def odometry_drift(series: TimeSeries, robot_ids: list[int], truth_files: dict[int, Path],
                   t0_mono: float, received: np.ndarray | None = None,
                   phases_s: Sequence[float] | None = None) -> dict[str, Any]:
    """Per robot: median, max and final |xy_odometry - xy_truth| (m) over the run.
    ``received`` (steps, robots): the states that reached the launcher; only those are
    judged (a realtime series fills a missing one forward: a pose held still while
    the robot moved on read as up to 9 cm of drift on a busy host). ``phases_s``: when
    each robot's bridge measures step k, after t_k (``Scenario.bridge_phase_s``)."""
    out: dict[str, Any] = {"robot": [], "median_m": [], "max_m": [], "final_m": []}
    for i, rid in enumerate(robot_ids):
        path = truth_files.get(rid)
        if path is None or not path.exists():
            continue
        with np.load(path) as g:
            t_truth = g["t"] + float(g["monotonic_origin_s"])
            q_truth = g["q"]
        # when the bridge sampled step k
        t_run = t0_mono + series.t + (0.0 if phases_s is None else phases_s[i])
        # the truth is sampled with the encoder estimates (100 Hz): interpolated to the
        # bridge's instant (the next sample instead was up to 1 cm off at 1 m/s)
        truth_xy = np.stack([np.interp(t_run, t_truth, q_truth[:, c]) for c in (0, 1)], axis=1)
        err = np.linalg.norm(series.q[:, i, :2] - truth_xy, axis=1)
        if received is not None:
            err = err[received[: len(err), i]]
        if not len(err):
            continue
        out["robot"].append(rid)
        out["median_m"].append(float(np.median(err)))
        out["max_m"].append(float(err.max()))
        out["final_m"].append(float(err[-1]))
    return out
