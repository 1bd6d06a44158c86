"""docs/outputs.md read as the tests read it: the keys its tables list (metrics.json's,
the verdict's) and the columns of timeseries.npz, to hold a run's outputs against."""

from __future__ import annotations

import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "outputs.md"
_ROW = re.compile(r"^\| `([a-z_0-9]+)` \|", re.M)


def _section(text: str, start: str, end: str | None) -> str:
    i = text.index(start)
    j = text.index(end, i) if end else len(text)
    return text[i:j]


def documented() -> tuple[set[str], set[str], set[str]]:
    """(metrics.json keys, verdict keys, timeseries.npz columns) the page lists."""
    text = DOC.read_text()
    metrics = set(_ROW.findall(_section(text, "## metrics.json", "### verdict")))
    verdict = set(_ROW.findall(_section(text, "### verdict", "## timeseries.npz")))
    columns = set(_ROW.findall(_section(text, "## timeseries.npz", None)))
    return metrics, verdict, columns


def undocumented(m: dict) -> list[str]:
    """The keys of metrics.json ``m`` (and of its verdict) the page does not list."""
    keys, verdict, _ = documented()
    return sorted({k for k in m if k not in keys}
                  | {f"verdict.{k}" for k in m.get("verdict", {}) if k not in verdict})
