"""Write a run's folder: metrics.json (with the verdict), timeseries.npz, figures."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from deploy.contract.scenario import Scenario
from deploy.report.metrics import compute_metrics, write_metrics
from deploy.report.timeseries import TimeSeries
from deploy.report.verdict import divergence, judge

if TYPE_CHECKING:
    from deploy.report.recorder import McapRecorder


def write_run(
    sc: Scenario,
    series: TimeSeries,
    out_dir: Path,
    plant: str,
    clock: str,
    wall_time_s: float,
    messages: dict[str, int] | None = None,
    extra: dict[str, Any] | None = None,
    figures: bool = True,
    contact_log: list[dict[str, Any]] | None = None,
    contacts_total: int | None = None,
    recorder: McapRecorder | None = None,
    step_unix_ns: np.ndarray | None = None,
    t0_unix_ns: int | None = None,
) -> dict[str, Any]:
    """``recorder``: the run's open recording; the scene and plots of ``series``
    are added to it (``step_unix_ns``: each step's wall clock, when known;
    ``t0_unix_ns``: the wall clock at t = 0) and it is closed."""
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics = compute_metrics(sc, series, plant, clock, wall_time_s, messages, contact_log,
                              contacts_total)
    metrics.update(extra or {})
    if recorder is not None:
        try:
            recorder.write_scene(sc, series, t0_unix_ns, step_unix_ns)
        finally:
            recorder.close({"scenario": sc.name, "plant": plant, "clock": clock})
        metrics["recording"] = recorder.summary()
    metrics["verdict"] = judge(metrics, divergence(series, sc.robot_ids))
    # what this run writes, and nothing else (the summary names exactly these)
    metrics["files"] = ["metrics.json", "timeseries.npz", *(
        [recorder.path.name] if recorder is not None else []), *(["figures"] if figures else [])]
    write_metrics(metrics, out_dir / "metrics.json")
    series.save(out_dir / "timeseries.npz")
    if figures:
        # matplotlib costs ~0.4 s to import: only a run that draws loads it
        from deploy.report.figures import write_figures

        write_figures(sc, series, out_dir)
    return metrics


def run_wall_clock(end_unix_ns: int, wall_s: float, run_t0_monotonic: float | None, steps: int,
                   lockstep: bool) -> dict[str, Any]:
    """``t0_unix_ns`` and ``step_unix_ns`` for :func:`write_run` after a distributed
    run that ended at ``end_unix_ns``: t = 0 from the run's start (realtime:
    ``ctl/start``, a monotonic time), each lockstep step spread over the run."""
    import time

    t0 = end_unix_ns - int(wall_s * 1e9)
    if run_t0_monotonic is not None:
        t0 = time.time_ns() - int((time.monotonic() - run_t0_monotonic) * 1e9)
    return {"t0_unix_ns": t0, "step_unix_ns": np.linspace(t0, end_unix_ns, steps).astype(np.int64)
            if lockstep else None}


def write_interrupted(sc: Scenario, series: TimeSeries, out_dir: Path, plant: str, clock: str,
                      wall_time_s: float, signal_name: str, extra: dict[str, Any] | None = None,
                      recorder: McapRecorder | None = None, **kw: Any) -> dict[str, Any]:
    """An interrupted run's folder: metrics.json marked ``"interrupted": true`` with what
    was measured up to then (no figures; the recording closed readable, with the scene
    of the steps measured). Its verdict is never PASS (deploy/report/verdict.py). With no step
    measured at all, metrics.json says only that."""
    extra = {**(extra or {}), "interrupted": True, "interrupted_by": signal_name}
    if series.steps > 0:
        return write_run(sc, series, out_dir, plant, clock, wall_time_s, extra=extra,
                         figures=False, recorder=recorder, **kw)
    if recorder is not None:
        recorder.close({"scenario": sc.name, "plant": plant, "clock": clock})
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics = {"scenario": sc.name, "plant": plant, "clock": clock, "robots": sc.n, "steps": 0,
               "sim_time_s": 0.0, "wall_time_s": wall_time_s, **extra,
               "verdict": {"pass": False, "complete": False, "diverged": None,
                           "reasons": [f"interrupted ({signal_name}) before any step"]},
               "files": ["metrics.json", *([recorder.path.name] if recorder else [])]}
    if recorder is not None:
        metrics["recording"] = recorder.summary()
    write_metrics(metrics, out_dir / "metrics.json")
    return metrics
