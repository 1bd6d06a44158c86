"""A law of the lab's in a fleet of processes (docs/laws.md): one process per agent, in
lockstep equal to the in-process reference bit for bit, and on the wall clock a law that
raises is contained, named by the verdict and by its agent's log."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from procs import assert_same_series, finish, pids_with, start
from realtime_clock import judged

from deploy.report.metrics import control_figures
from deploy.report.timeseries import TimeSeries

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

BAD = str(Path(__file__).resolve().parents[1] / "laws" / "misbehaving.py")


@pytest.mark.load_safe
def test_a_python_law_in_lockstep_equals_the_in_process_reference(tmp_path):
    fleet = f"t-law-{os.getpid()}"
    args = ("run", "lab", "--law", "consensus", "--plant", "model", "--duration", "3",
            "--no-figures", "--no-record")
    rc, _, err = finish(start(*args, "--out", str(tmp_path / "d"), "--fleet", fleet))
    assert rc == 0, err
    assert not pids_with(fleet), "a node of the run outlived it"
    rc, _, err = finish(start(*args, "--in-process", "--out", str(tmp_path / "i")))
    assert rc == 0, err
    a = TimeSeries.load(tmp_path / "d" / "timeseries.npz")
    b = TimeSeries.load(tmp_path / "i" / "timeseries.npz")
    assert a.steps == b.steps == 600
    assert_same_series(a, b)
    ma = json.loads((tmp_path / "d" / "metrics.json").read_text())
    mb = json.loads((tmp_path / "i" / "metrics.json").read_text())
    assert control_figures(ma) == control_figures(mb)
    assert ma["law"] == "consensus" and ma["law_faults"] == mb["law_faults"]


@pytest.mark.realtime
def test_a_law_that_raises_on_the_wall_clock_is_contained_and_named(tmp_path):
    """Every agent's law divides by zero from 1 s on: each robot brakes every step from
    then (its controller given v_d = 0), nothing touches, the run ends, the verdict fails
    naming the law and the error's line, and each agent's log says it."""
    def run():
        out = tmp_path / f"run-{len(list(tmp_path.iterdir()))}"
        rc, _, err = finish(start("run", "lab", "--law", f"{BAD}:Raises", "--clock",
                                  "realtime", "--plant", "model", "--duration", "2.5",
                                  "--out", str(out), "--no-figures", "--no-record"))
        assert rc == 0, err
        return out, json.loads((out / "metrics.json").read_text())
    out, m = judged(run, lambda r: r[1], "lab realtime, a law that raises")
    assert m["law"] == "raises" and m["contacts"] == 0 and m["nonfinite_commands"] == 0
    assert all(f["errors"] > 0 and "ZeroDivisionError" in f["error"] for f in m["law_faults"])
    reasons = " ".join(m["verdict"]["reasons"])
    assert not m["verdict"]["pass"] and "law raises on robot #1: raised in" in reasons
    assert "ZeroDivisionError: division by zero" in reasons
    for i in (1, 2, 3):
        log = (out / "logs" / f"agent-{i}.log").read_text()
        assert "law raises: raised" in log and "ZeroDivisionError" in log
