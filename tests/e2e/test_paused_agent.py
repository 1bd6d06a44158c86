"""A paused agent recovers, and the run says what happened (docs/hardening.md).

Found by probing: ``lab --clock realtime`` with agent 2 SIGSTOPped for 2 s, then
SIGCONT: the agent answered its backlog of samples seconds old, its law went
non-finite for good and robot 2 ran on zero torque for the rest of the run, while
the run exited 0 with ``nonfinite_commands: 0``.

- unit: a non-finite integrator or observer is restarted from the measurement
  (AgentCore.recover), the step says what it restarted, the next step is finite;
- verdict: a robot on zero torque longer than the command timeout fails the run;
- end to end (realtime, judged by the clock): the fault plan pauses agent 2; its law
  restarts once, robot 2 is back in the settling band within 2 s of SIGCONT, and
  metrics.json counts the restart and the stretch on zero torque.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from deploy.report.timeseries import TimeSeries
from tests.procs import finish, pids_with, start
from tests.realtime_clock import judged

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.realtime]

PAUSE_AT, PAUSE_S, DURATION_S = 2.0, 2.0, 6.5


@pytest.fixture(scope="module")
def paused_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("pause")
    plan = d / "pause.toml"
    plan.write_text(f"seed = 1\n[[kill]]\nprocess = 'agent-2'\nat_s = {PAUSE_AT}\n"
                    f"pause_s = {PAUSE_S}\n")

    def run():
        out = tmp_path_factory.mktemp("pause") / "run"
        fleet = f"t-pause-{os.getpid()}"
        code, stdout, err = finish(start(
            "run", "lab", "--clock", "realtime", "--duration", repr(DURATION_S), "--fleet", fleet,
            "--out", str(out), "--no-figures", "--no-record", "--faults", str(plan)),
            timeout=240)
        assert not (pids_with(fleet) | pids_with(str(out))), "processes of the run still alive"
        assert code == 0, err[-3000:]
        return out, stdout, json.loads((out / "metrics.json").read_text())
    return judged(run, lambda r: r[2], "lab realtime, agent 2 paused")


def test_the_paused_agents_robot_is_back_in_the_band_within_2_s(paused_run):
    out, stdout, m = paused_run
    events = {e["event"]: e["t_s"] for e in m["faults"]["kills"]}
    assert set(events) == {"paused", "resumed"}
    resumed = events["resumed"]
    ts = TimeSeries.load(out / "timeseries.npz")
    err = np.linalg.norm(ts.e[:, 1], axis=1)  # robot 2's tracking error
    band = m["settle_threshold"]
    late = np.flatnonzero((ts.t > resumed) & (err > band))
    back = ts.t[late[-1] + 1] if len(late) else resumed
    print(f"\nrobot 2 back within {band} m at t = {back:.2f} s, {back - resumed:.2f} s after SIGCONT; "
          f"law restarts {m['law_resets']}, stale samples {m['stale_samples']}, zero torque "
          f"{m['zero_torque_longest_s']} s")
    assert back - resumed < 2.0
    assert back < ts.t[-1] - 0.25  # and it stays there
    assert m["nonfinite_commands"] == 0  # the law never diverged


def test_the_run_counts_what_the_pause_did(paused_run):
    _, stdout, m = paused_run
    assert m["law_resets"][0] == 0 and m["law_resets"][2] == 0
    assert m["law_resets"][1] >= 1  # at least the restart after the gap
    zero = m["zero_torque_longest_s"]
    # zeroed one command timeout after its last command, powered again as it answers
    assert PAUSE_S - 0.5 < zero[1] < PAUSE_S + 0.5 and zero[0] == zero[2] == 0.0
    assert any(s["robot"] == 2 for s in m["zero_torque"])
    v = m["verdict"]
    assert not v["pass"] and not v["powered"]
    assert any("robot #2 ran on zero torque" in r for r in v["reasons"])
    assert "law restarts               [0, " in stdout and "longest on zero torque" in stdout
