"""The pybullet plant in whole runs: real contacts counted and logged, the same
numbers in-process and distributed (lockstep), a run with contacts fails --check.

The collision scenario is the lab scenario with obstacle and robot avoidance
disabled (only FDB) and no safety filter (the last layer, docs/safety.md, would stop them):
without them robots 1 and 2 touch at t ~ 1.08 s and robot 3
drives into obstacle 1 at t ~ 5.4 s (the model plant, which has no bodies, sees
the same encounters as overlapping circles).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest
from procs import assert_same_series, finish, pids_with, start

from deploy.report.metrics import control_figures
from deploy.report.timeseries import TimeSeries

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.load_safe]

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def no_avoidance(tmp_path_factory) -> Path:
    text = (REPO / "deploy" / "scenarios" / "lab.toml").read_text()
    text, n = re.subn(r'(?m)^enabled = .*$', 'enabled = ["FDB"]', text)
    assert n == 1
    text = re.sub(r'(?m)^name = "lab"', 'name = "lab-no-avoidance"', text)
    text += "\n[safety]\nfilter = false\n"
    path = tmp_path_factory.mktemp("scenario") / "lab-no-avoidance.toml"
    path.write_text(text)
    return path


def metrics_of(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def test_driving_into_bodies_is_counted_logged_and_fails_the_check(no_avoidance, tmp_path):
    rc, _, err = finish(start("run", str(no_avoidance), "--in-process", "--duration", "6",
                              "--out", str(tmp_path), "--no-figures", "--check"))
    assert rc == 1, err
    assert "does NOT meet" in err
    m = metrics_of(tmp_path)
    assert m["plant"] == "pybullet" and m["contact_source"] == "physics"
    log = m["contact_log"]
    assert m["contacts"] == len(log) >= 2
    pairs = {(e["body_a"], e["body_b"]) for e in log}
    assert (1, 2) in pairs, "robots 1 and 2 touch"
    assert any(b < 0 for _, b in pairs), "a robot touches an obstacle"
    for e in log:
        assert 0 < e["t_start"] < 6
        assert e["t_end"] is None or e["t_start"] < e["t_end"] <= 6  # released after it began
        # bodies stop at each other's surface: they never pass through
        assert e["max_depth_m"] < 1e-3
    first = min(log, key=lambda e: e["t_start"])
    assert (first["body_a"], first["body_b"]) == (1, 2) and 1.0 < first["t_start"] < 1.2


def test_distributed_pybullet_run_equals_in_process_contacts_included(no_avoidance, tmp_path):
    fleet = f"t-pb-{os.getpid()}"
    dist, ref = tmp_path / "dist", tmp_path / "ref"
    common = ("--duration", "1.5", "--no-figures", "--no-record")
    rc, _, err = finish(start("run", str(no_avoidance), "--out", str(dist), "--fleet", fleet,
                              *common))
    assert rc == 0, err
    assert not pids_with(fleet), "a node of the run outlived it"
    rc, _, err = finish(start("run", str(no_avoidance), "--in-process", "--out", str(ref),
                              *common))
    assert rc == 0, err
    a, b = TimeSeries.load(dist / "timeseries.npz"), TimeSeries.load(ref / "timeseries.npz")
    assert a.steps == b.steps == 300
    assert_same_series(a, b)
    ma, mb = metrics_of(dist), metrics_of(ref)
    assert ma["contacts"] >= 1 and ma["contact_log"][0]["body_a"] == 1
    assert control_figures(ma) == control_figures(mb)


def test_gui_without_a_display_is_a_clear_error(tmp_path):
    env_display = os.environ.pop("DISPLAY", None)
    try:
        rc, _, err = finish(start("run", "lab", "--gui", "--out", str(tmp_path)))
        assert rc == 2 and "DISPLAY" in err
        rc, _, err = finish(start("plant", "--scenario", "lab", "--gui"))
        assert rc == 2 and "DISPLAY" in err
        rc, _, err = finish(start("run", "lab", "--plant", "model", "--gui", "--in-process",
                                  "--out", str(tmp_path)))
        assert rc == 2 and "pybullet" in err
    finally:
        if env_display is not None:
            os.environ["DISPLAY"] = env_display
