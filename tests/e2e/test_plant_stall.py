"""A realtime run whose plant stops stepping says so (deploy/report/verdict.py).

Seen: ``lab --plant model --clock realtime --control-rate 500 --duration 20`` sat at one
step for 15 s, then printed 100 %, "4.90 s simulated", more deadline misses than steps,
and PASS. Here the fault plan holds the plant (SIGSTOP) for longer than the command
timeout, within the run and past its end: the verdict fails naming the stall and when it
began (and, past the end, what was simulated of what was asked); the progress lines
never claim a step whose state was not heard."""

from __future__ import annotations

import json
import os

import pytest

from tests.procs import finish, pids_with, start

# a run on the wall clock (its claims hold however loaded)
pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.realtime]


@pytest.mark.parametrize("hold_at, hold_s, duration_s", [(1.5, 1.0, 4.0), (1.0, 3.0, 3.0)],
                         ids=["within the run", "past its end"])
def test_a_plant_held_longer_than_the_command_timeout_fails_the_verdict(
        tmp_path, hold_at, hold_s, duration_s):
    plan = tmp_path / "hold.toml"
    plan.write_text(f"seed = 1\n[[kill]]\nprocess = 'plant'\nat_s = {hold_at}\n"
                    f"pause_s = {hold_s}\n")
    out, fleet = tmp_path / "run", f"t-hold-{os.getpid()}"
    code, stdout, err = finish(start(
        "run", "lab", "--clock", "realtime", "--plant", "model", "--duration", repr(duration_s),
        "--fleet", fleet, "--out", str(out), "--no-figures", "--no-record", "--faults",
        str(plan), "--check"), timeout=240)
    assert not pids_with(fleet), "processes of the run still alive"
    m = json.loads((out / "metrics.json").read_text())
    stall = m["longest_stall"]
    print(f"\nstall {stall}, simulated {m['steps_simulated']} of {m['steps_asked']}, heard "
          f"{m['steps']}, misses {m['deadline_misses_by_node']}")
    assert code == 1, err[-2000:]  # --check: the run does not meet the criteria
    assert stall["node"] == "plant"
    # held hold_s or up to the end (a starved host can only add to it), from when it was held
    assert stall["duration_s"] >= min(hold_s, duration_s - hold_at) - 0.05
    assert abs(stall["t_s"] - hold_at) < 0.3
    v = m["verdict"]
    assert not v["pass"] and not v["on_time"]
    assert any(r.startswith(f"the plant stalled {stall['duration_s']:.3f} s") for r in v["reasons"])
    assert "the plant stalled" in stdout.splitlines()[-1]  # the summary's verdict line
    assert m["reports_missing"] == []
    if hold_at + hold_s >= duration_s:  # it woke after the end: the rest was never simulated
        assert m["steps_simulated"] <= (hold_at + 0.3) * m["control_rate_hz"]
        assert not v["whole"] and any(r.startswith("simulated ") for r in v["reasons"])
    # progress lines (not a terminal) never claim a step whose state was not heard
    claimed = [int(line.split("step ")[1].split("/")[0]) for line in err.splitlines()
               if ": step " in line]
    assert claimed and max(claimed) <= m["steps"] <= m["steps_asked"]
