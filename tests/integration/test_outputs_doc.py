"""docs/outputs.md lists every key of metrics.json and every column of timeseries.npz with
its unit, and lists nothing the code does not write: checked here against an in-process
run, and against the fleet's lockstep and realtime runs in tests/e2e/test_distributed.py.

Seen: no page listed them; ``torque_clipped`` was a dict keyed "1".."3" where every other
per-robot figure is a list; ``files`` said "figures" instead of the file names."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from outputs_doc import documented, undocumented

from deploy.cli import main
from deploy.report.run_folder import FIGURE_FILES
from deploy.report.timeseries import COLUMNS

REPO = Path(__file__).resolve().parents[2]


def test_an_in_process_runs_outputs_are_all_documented_and_per_robot_figures_are_lists(
        tmp_path, capsys):
    plan = tmp_path / "drop.toml"
    plan.write_text("seed = 1\n[defaults]\ndrop = 0.1\n")
    out = tmp_path / "run"
    assert main(["run", "lab", "--in-process", "--plant", "model", "--duration", "0.3",
                 "--faults", str(plan), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert undocumented(m) == []
    # per robot: a list in the scenario's order, never a dict keyed by id
    for key in ("settling_time_s", "formation_rms_whole_run_m", "formation_distance_end_m",
                "formation_reached_s", "torque_clipped", "law_resets"):
        assert isinstance(m[key], list) and len(m[key]) == m["robots"], key
    assert m["files"] == ["metrics.json", "timeseries.npz", "recording.mcap", *FIGURE_FILES]
    assert sorted(p.name for p in out.iterdir()) == sorted(m["files"])  # exactly those
    with np.load(out / "timeseries.npz") as z:
        _, _, columns = documented()
        assert set(z.files) == columns == set(COLUMNS)


def test_every_documented_key_is_one_the_code_writes():
    """A key on the page that no module of deploy/ names is stale."""
    source = "\n".join(p.read_text() for p in (REPO / "deploy").rglob("*.py"))
    keys, verdict, columns = documented()
    stale = sorted(k for k in keys | verdict | columns
                   if not re.search(rf"[\"']{re.escape(k)}[\"']|\b{re.escape(k)}:", source))
    assert stale == [], stale
