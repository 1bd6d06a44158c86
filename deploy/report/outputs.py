"""Write a run's folder: metrics.json (with the verdict), timeseries.npz, figures."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from deploy.contract.output_paths import rescue_folder, usable_folder
from deploy.contract.scenario import Scenario
from deploy.report.figure_process import FigureProcess
from deploy.report.metrics import compute_metrics, write_metrics
from deploy.report.run_folder import FIGURE_FILES
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
    steps_asked: int | None = None,
    drawing: FigureProcess | None = None,
) -> dict[str, Any]:
    """``drawing``: the figure process the caller prepared when the run started (one is
    spawned now when not); ended here whatever happens. ``recorder``: the run's open
    recording; the scene and plots of ``series`` are added to it (``step_unix_ns``: each
    step's wall clock, when known; ``t0_unix_ns``: the wall clock at t = 0) and it is
    closed. ``steps_asked``: the steps the run was asked for (metrics.json
    ``steps_asked``). A folder that cannot be written any more (it vanished, or became a
    file, while the run went) is not the end of the results: they go to a folder under
    the temporary directory, said on stderr and in ``folder``."""
    out_dir = _usable(out_dir, sc.name)
    # the figures draw in a process of their own while the rest is written here
    if not figures and drawing is not None:
        drawing.stop()
    drawing = (drawing or FigureProcess()) if figures else None
    try:
        if drawing is not None:
            drawing.start(sc, series, out_dir)
        return _write_run(sc, series, out_dir, plant, clock, wall_time_s, messages, extra,
                          drawing, contact_log, contacts_total, recorder, step_unix_ns,
                          t0_unix_ns, steps_asked)
    finally:
        if drawing is not None:
            drawing.stop()


def _write_run(sc: Scenario, series: TimeSeries, out_dir: Path, plant: str, clock: str,
               wall_time_s: float, messages: dict[str, int] | None,
               extra: dict[str, Any] | None, drawing: FigureProcess | None,
               contact_log: list[dict[str, Any]] | None, contacts_total: int | None,
               recorder: McapRecorder | None, step_unix_ns: np.ndarray | None,
               t0_unix_ns: int | None, steps_asked: int | None) -> dict[str, Any]:
    figures = drawing is not None
    metrics = compute_metrics(sc, series, plant, clock, wall_time_s, messages, contact_log,
                              contacts_total, steps_asked)
    metrics.update(extra or {})
    if recorder is not None:
        try:
            recorder.write_scene(sc, series, t0_unix_ns, step_unix_ns)
        finally:
            recorder.close({"scenario": sc.name, "plant": plant, "clock": clock})
        metrics["recording"] = recorder.summary()
    metrics["verdict"] = judge(metrics, divergence(series, sc.robot_ids))
    # what this run writes, file by file, and nothing else (the summary names exactly these;
    # logs/ is the launcher's, each node's output)
    metrics["files"] = ["metrics.json", "timeseries.npz", *(
        [recorder.path.name] if recorder is not None else []),
        *(FIGURE_FILES if figures else ()), *(["logs/"] if (out_dir / "logs").is_dir() else [])]
    metrics["folder"] = str(out_dir)
    try:
        _write_files(sc, series, metrics, out_dir, drawing)
    except OSError as exc:  # the folder went away between the check and the writing
        rescue = _usable(rescue_folder(sc.name), sc.name, f"{out_dir}: {exc.strerror or exc}")
        metrics["folder"] = str(rescue)
        if drawing is not None:
            drawing.stop()
        _write_files(sc, series, metrics, rescue, None, figures)
    return metrics


def _write_files(sc: Scenario, series: TimeSeries, metrics: dict[str, Any], out_dir: Path,
                 drawing: FigureProcess | None, figures: bool = False) -> None:
    """metrics.json and timeseries.npz; the figures from ``drawing`` (the process that
    draws them into ``out_dir``), or drawn here when it failed or ``figures`` without one."""
    write_metrics(metrics, out_dir / "metrics.json")
    series.save(out_dir / "timeseries.npz")
    if series.steps == 0 and (drawing is not None or figures):  # a run nobody heard a state of
        if drawing is not None:
            drawing.stop()
        print("omnifleet: no figures: no robot state was heard (metrics.json says why the "
              "run failed)", file=sys.stderr, flush=True)
        return
    if (drawing is not None and not drawing.finish()) or (drawing is None and figures):
        # matplotlib costs ~0.4 s to import: only a run that draws loads it
        from deploy.report.figures import write_figures

        write_figures(sc, series, out_dir)


def _usable(out_dir: Path, name: str, failed: str | None = None) -> Path:
    """``out_dir`` if it can be written now, else a rescue folder, said on stderr."""
    folder, why = usable_folder(out_dir, name)
    why = failed or (None if why is None else f"{out_dir}: {why}")
    if why is not None:
        print(f"omnifleet: cannot write the run's results to {why}; they are in {folder}/",
              file=sys.stderr, flush=True)
    return folder


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
