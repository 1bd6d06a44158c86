"""Write a run's folder: metrics.json, timeseries.npz, figures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from deploy.figures import write_figures
from deploy.metrics import compute_metrics, write_metrics
from deploy.scenario import Scenario
from deploy.timeseries import TimeSeries


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
) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics = compute_metrics(sc, series, plant, clock, wall_time_s, messages, contact_log,
                              contacts_total)
    metrics.update(extra or {})
    write_metrics(metrics, out_dir / "metrics.json")
    series.save(out_dir / "timeseries.npz")
    if figures:
        write_figures(sc, series, out_dir)
    return metrics
