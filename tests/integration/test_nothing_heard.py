"""A distributed run whose launcher heard no robot state at all (a fleet starved from its
first step, nodes that never sent): its results are still written and its verdict says
why it failed, instead of the metrics or the figures raising on an empty series."""

from __future__ import annotations

import json

import numpy as np

from deploy.contract.scenario import load_scenario
from deploy.report.outputs import write_run
from deploy.report.recorder import McapRecorder
from deploy.report.timeseries import TimeSeries


def test_a_run_with_no_state_heard_writes_its_results_and_fails_saying_why(tmp_path, capsys):
    sc = load_scenario("lab")
    series = TimeSeries.allocate(0, sc.n)
    series.state_heard = np.zeros((0, sc.n), bool)
    out = tmp_path / "run"
    out.mkdir()
    m = write_run(sc, series, out, "can-emulated", "realtime", 1.0,
                  {"sent": 0, "dropped": 0, "late": 0, "invalid": 0}, {}, figures=True,
                  recorder=McapRecorder(out / "recording.mcap"), steps_asked=200)
    assert not m["verdict"]["pass"]
    assert "simulated 0.000 s of the 1.000 s asked (0 of 200 steps)" in m["verdict"]["reasons"]
    assert m["settling_time_s"] == [None, None, None] and m["min_robot_gap_m"] is None
    assert json.loads((out / "metrics.json").read_text())["steps"] == 0
    assert (out / "timeseries.npz").exists() and (out / "recording.mcap").exists()
    assert not list(out.glob("*.png"))  # no figure of nothing
    assert "no figures: no robot state was heard" in capsys.readouterr().err
