"""The CAN bridges' staggered periods: each robot's bridge runs dt / n after the one
before it (deploy/contract/scenario.py ``bridge_phase_s``), and the odometry drift
matches each robot's states to the ground truth at that instant, not at t_k."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.contract.scenario import load_scenario
from deploy.report.odometry_drift import odometry_drift
from deploy.report.timeseries import TimeSeries


@pytest.mark.parametrize("name", ["lab", "paper"])
def test_the_bridges_periods_are_spread_evenly_over_one_period(name):
    sc = load_scenario(name)
    phases = [sc.bridge_phase_s(r) for r in sc.robot_ids]
    assert phases[0] == 0.0
    assert all(0.0 <= p < sc.dt for p in phases)
    assert np.allclose(np.diff(phases), sc.dt / sc.n)


def test_odometry_drift_matches_each_robot_at_its_bridges_instant(tmp_path):
    """Robots moving at 2 m/s, each state exact at its bridge's instant t_k + phase_i:
    matched there, no drift; matched at t_k, the drift is the distance covered in the
    phase (2 m/s x phase_i)."""
    sc = load_scenario("lab")
    steps, speed, t0_mono = 400, 2.0, 1000.0
    ts = TimeSeries.allocate(steps, sc.n)
    ts.t[:] = np.arange(steps) * sc.dt
    phases = [sc.bridge_phase_s(r) for r in sc.robot_ids]
    truth = {}
    for i, rid in enumerate(sc.robot_ids):
        ts.q[:, i, 0] = speed * (ts.t + phases[i])  # x at the bridge's instant
        t_truth = np.arange(0.0, steps * sc.dt + 0.1, 0.01)  # the encoder rate, 100 Hz
        q_truth = np.zeros((len(t_truth), 3))
        q_truth[:, 0] = speed * t_truth
        truth[rid] = tmp_path / f"truth-{rid}.npz"
        np.savez(truth[rid], t=t_truth, q=q_truth, monotonic_origin_s=t0_mono)
    matched = odometry_drift(ts, sc.robot_ids, truth, t0_mono, phases_s=phases)
    assert matched["robot"] == sc.robot_ids
    assert max(matched["max_m"]) < 1e-9
    at_t_k = odometry_drift(ts, sc.robot_ids, truth, t0_mono)
    assert np.allclose(at_t_k["median_m"], [speed * p for p in phases])
