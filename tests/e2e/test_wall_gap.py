"""A scenario a user writes (docs/scenarios.md): ``omnifleet scenario new --from wall-gap`` (a
waypoint leader through the gap between a wall and a polygon) run distributed, one
process per node in lockstep, and in process: the same series and control figures,
through the gap with no contact; and one robot sent at a wall stops short of it."""

from __future__ import annotations

import json
import os

import pytest
from procs import assert_same_series, finish, pids_with, start

from deploy.cli import main
from deploy.contract.scenario import load_scenario
from deploy.report.metrics import control_figures
from deploy.report.timeseries import TimeSeries

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.load_safe]

zenoh = pytest.importorskip("zenoh")

# robot 3 (the last) is past the polygon's east corner (x = 2.9 + its radius) at 3.75 s,
# and the safety filter acts on it from 3.08 s to 3.87 s (measured on the full 6 s run)
DURATION = "4.0"


def test_a_new_waypoint_scenario_runs_distributed_as_in_process_through_the_gap(tmp_path, capsys):
    mine = tmp_path / "mine.toml"
    assert main(["scenario", "new", str(mine), "--from", "wall-gap"]) == 0
    capsys.readouterr()
    sc = load_scenario(mine)
    assert sc.name == "mine" and sc.spec.leader.path == "waypoints"
    assert len(sc.spec.walls) == len(sc.spec.polygons) == 1
    dist, local = tmp_path / "dist", tmp_path / "local"
    fleet = f"t-wallgap-{os.getpid()}"
    rc, _, err = finish(start("run", str(mine), "--duration", DURATION, "--out", str(dist),
                              "--no-figures", "--fleet", fleet))
    assert rc == 0, err
    assert not pids_with(fleet), "a node of the run outlived it"
    # the in-process reference in this process (its imports are paid already)
    assert main(["run", str(mine), "--in-process", "--duration", DURATION, "--out", str(local),
                 "--no-figures"]) == 0
    capsys.readouterr()
    a, b = TimeSeries.load(dist / "timeseries.npz"), TimeSeries.load(local / "timeseries.npz")
    assert a.steps == b.steps == 400
    assert_same_series(a, b)
    ma = json.loads((dist / "metrics.json").read_text())
    mb = json.loads((local / "metrics.json").read_text())
    assert control_figures(ma) == control_figures(mb)
    assert ma["stale_samples"] == [0, 0, 0]  # nothing went stale in lockstep
    # through the gap, nothing touched: pybullet's contacts, and the true geometry's gaps
    assert ma["contact_source"] == "physics" and ma["contacts"] == 0
    gaps = sc.obstacle_gaps(a.q[:, :, :2])
    assert gaps.min() == pytest.approx(ma["min_obstacle_gap_m"]) and gaps.min() > 0.0
    assert a.q[-1, :, 0].min() > 2.9 + sc.spec.robot.body_radius_m  # all three past it
    # the wall and the polygon were guarded: robot 3 (whose place in the rigid column
    # cuts the polygon's corner in the turn) was held off it by the filter
    assert a.safety_active[:, 2].any()


