"""The command line: outputs written, bad input refused with exit code 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.load_safe]

REPO = Path(__file__).resolve().parents[2]
REQUIRED_KEYS = {
    "scenario", "plant", "clock", "robots", "sim_time_s", "steps", "control_rate_hz",
    "wall_time_s", "real_time_factor", "settling_time_s", "formation_rms_whole_run_m",
    "formation_rms_after_settling_m",
    "min_obstacle_gap_m", "min_robot_gap_m", "contacts", "peak_torque_nm",
    "rms_torque_nm", "messages",
}


def omnifleet(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", *args], cwd=REPO, capture_output=True, text=True,
        timeout=timeout,
    )


def test_run_writes_metrics_series_and_figures(tmp_path):
    out = tmp_path / "paper"
    r = omnifleet("run", "paper", "--in-process", "--duration", "0.2", "--out", str(out))
    assert r.returncode == 0, r.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert REQUIRED_KEYS <= m.keys()
    # pybullet is the default plant: contacts come from its physics, with their log
    assert m["steps"] == 200 and m["robots"] == 3 and m["plant"] == "pybullet"
    assert m["contact_source"] == "physics" and m["contact_log"] == [] and m["contacts"] == 0
    assert "pybullet build time" not in r.stderr + r.stdout  # its import banner is silenced
    assert m["messages"] == {"sent": 0, "dropped": 0, "late": 0, "invalid": 0}
    with np.load(out / "timeseries.npz") as ts:
        assert ts["q"].shape == (200, 3, 3) and ts["torque"].shape == (200, 3, 4)
        assert np.isfinite(ts["torque"]).all()
    for name in ("fig4_trajectories.png", "fig5_errors.png", "fig6_distances_torques.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_kinematic_plant_option(tmp_path):
    r = omnifleet("run", "paper", "--in-process", "--plant", "kinematic", "--duration", "0.05",
                  "--out", str(tmp_path), "--no-figures")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "metrics.json").read_text())["plant"] == "kinematic"


def test_unknown_scenario_name_fails_fast():
    r = omnifleet("run", "no-such-scenario", "--in-process")
    assert r.returncode == 2
    assert "no-such-scenario" in r.stderr and "paper" in r.stderr


def test_help_describes_the_run_command():
    r = omnifleet("run", "--help")
    assert r.returncode == 0
    assert "--in-process" in r.stdout and "--out" in r.stdout
