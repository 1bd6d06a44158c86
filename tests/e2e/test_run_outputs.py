"""A run's folder says what the run did (docs/hardening.md): an interrupted fleet leaves
metrics.json marked interrupted with what was measured and a readable recording (the
folder's other checks, in process: tests/integration/test_run_folder.py)."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest

from deploy.report.recorder import messages_in
from tests.procs import finish, kill_run, pids_with, start

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.load_safe]


def test_sigint_leaves_a_readable_recording_and_metrics_marked_interrupted(tmp_path):
    """Found by probing: SIGINT left a readable MCAP but no metrics.json."""
    out = tmp_path / "run"
    fleet = f"t-sigint-{os.getpid()}"
    proc = start("run", "lab", "--plant", "model", "--duration", "60", "--fleet", fleet,
                 "--out", str(out), "--no-figures")
    try:
        deadline = time.monotonic() + 120
        rec = out / "recording.mcap"
        while time.monotonic() < deadline and proc.poll() is None:
            if rec.exists() and rec.stat().st_size > 100_000:  # the run is measuring
                break
            time.sleep(0.1)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        os.kill(proc.pid, signal.SIGINT)
        code, stdout, err = finish(proc, timeout=120)
    finally:
        kill_run(proc)
    assert code == 130, err[-2000:]
    assert not pids_with(fleet), "processes of the run still alive"
    m = json.loads((out / "metrics.json").read_text())
    assert m["interrupted"] is True and m["interrupted_by"] == "SIGINT"
    assert 0 < m["steps"] < 60 * m["control_rate_hz"]
    assert m["sim_time_s"] == pytest.approx(m["steps"] / m["control_rate_hz"])
    assert not m["verdict"]["pass"] and "interrupted (SIGINT)" in m["verdict"]["reasons"]
    assert m["recording"]["messages"] == messages_in(out / "recording.mcap") > 0
    assert "INTERRUPTED (SIGINT)" in stdout and "verdict: FAIL" in stdout
    assert not list(out.glob("fig*.png"))










