"""The whole fleet on emulated CAN (measured end to end; docs/hardware.md):
``omnifleet run lab --plant can-emulated`` starts the leader, an agent and a CAN
bridge per robot and one driver emulator for the fleet (udp_multicast buses, no
kernel module), on the wall clock.

- Fault-free: every robot settles within sqrt(2) T_p, nothing touches, odometry
  stays within millimetres of the emulator's ground truth, no bridge faults.
- An agent killed mid-run (SIGKILL): its bridge puts zero torque on the bus within
  the command timeout plus one bridge period; restarted, the agent takes its robot
  back into the tracking band.

Realtime runs on a 2-core machine: the bounds are the acceptance's, the figures
measured on a quiet machine are in the comments (docs/hardware.md has the runs).
"""

from __future__ import annotations

import numpy as np
import pytest

from deploy.report.timeseries import TimeSeries
from tests.can_fleet_runs import (
    COMMAND_TIMEOUT_S,
    KILL_AT,
    RESTART_AFTER,
    clean_fleet_run,
    killed_fleet_run,
    run_fleet,
)

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.realtime]


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    return clean_fleet_run(tmp_path_factory, "odrive-cansimple", "lab on emulated CAN")


@pytest.fixture(scope="module")
def killed_run(tmp_path_factory):
    return killed_fleet_run(tmp_path_factory, "odrive-cansimple", "lab on emulated CAN, agent 2 killed")


def test_every_robot_settles_within_the_bound_without_contact(clean_run):
    _, stdout, m = clean_run
    print(f"\nsettling {m['settling_time_s']} s (bound {m['settling_bound_s']:.3f}), obstacle gap "
          f"{m['min_obstacle_gap_m']:.3f} m, robot gap {m['min_robot_gap_m']:.3f} m")
    assert m["plant"] == "can-emulated" and m["clock"] == "realtime"
    # measured on a quiet 2-core machine: 0.27-0.38 s (tracking error after 1 s at most 3.4 cm)
    assert all(s is not None and s < m["settling_bound_s"] for s in m["settling_time_s"])
    assert m["contacts"] == 0
    assert m["min_obstacle_gap_m"] > 0 and m["min_robot_gap_m"] > 0
    assert m["peak_torque_nm"] <= m["limits"]["max_wheel_torque_nm"]
    assert "odometry drift" in stdout and "bridge cmd->torque frame" in stdout


def test_odometry_stays_with_the_emulators_ground_truth(clean_run):
    """Median |odometry - truth| per robot, time-matched. Before the start-up fix one
    robot carried a 0.0056 rad heading error from t = 0: 3.4-3.6 cm median."""
    _, _, m = clean_run
    drift = m["odometry_drift"]
    print(f"\nodometry drift median {drift['median_m']} m, max {drift['max_m']} m")
    assert drift["robot"] == [1, 2, 3]
    assert all(x < 0.005 for x in drift["median_m"])  # measured 0.3-0.5 mm
    assert all(x < 0.05 for x in drift["max_m"])  # measured 1.3-2.7 cm (a stalled bridge)


def test_bridges_stay_healthy_and_time_their_frames(clean_run):
    _, _, m = clean_run
    assert m["bridge_faulted_fraction"] == [0.0, 0.0, 0.0]
    assert "command_stops" not in m  # no agent fell silent for 100 ms
    lat = m["bridge_latency_ms"]  # every command: arrival -> its torque frames sent
    assert 0 < lat["p50"] <= lat["p99"]
    assert m["messages"]["invalid"] == 0 and m["messages"]["dropped"] == 0


def test_a_killed_agents_robot_gets_zero_torque_on_the_bus_within_the_timeout(killed_run):
    _, m = killed_run
    killed = next(e for e in m["faults"]["kills"] if e["event"] == "killed")
    assert killed["process"] == "agent-2" and abs(killed["t_s"] - KILL_AT) < 0.1
    stops = [s for s in m["command_stops"] if s["robot"] == 2 and s["t_s"] >= KILL_AT]
    assert stops, m.get("command_stops")
    dt = 1.0 / m["control_rate_hz"]
    age = stops[0]["command_age_s"]
    print(f"\nagent-2 killed at {killed['t_s']:.3f} s; zero torque on its bus with the newest "
          f"command {age * 1e3:.1f} ms old (timeout {COMMAND_TIMEOUT_S * 1e3:.0f} ms, period "
          f"{dt * 1e3:.0f} ms)")
    # the bridge looks once per period: timeout plus one period (measured 100.8 ms),
    # plus its loop's own lateness on a loaded 2-core machine, as the plant's test allows
    assert COMMAND_TIMEOUT_S <= age <= COMMAND_TIMEOUT_S + dt + 0.025
    assert m["contacts"] == 0 and m["min_robot_gap_m"] > 0


def test_the_restarted_agent_takes_its_robot_back_into_the_band(killed_run):
    out, m = killed_run
    ts = TimeSeries.load(out / "timeseries.npz")
    err = np.linalg.norm(ts.e[:, 1], axis=1)  # robot 2
    band = m["settle_threshold"]
    restarted = KILL_AT + RESTART_AFTER
    late = np.flatnonzero((ts.t > restarted) & (err > band))
    back = ts.t[late[-1] + 1] if len(late) else restarted
    rejoin = next(p["rejoin_s"] for p in m["processes"] if p.get("rejoin_s") is not None)
    # what this machine showed in the same run: the restarted process's start-up, and how
    # long the robots that were never stopped took to settle from rest at t = 0 (the
    # restarted agent's robot starts from rest too). Measured on the 2-core development
    # VM: start-up 0.15 s forked (0.9 s spawned, on one core), back 0.49 s after the restart
    settle = max(m["settling_time_s"][0], m["settling_time_s"][2])
    bound = max(1.0, rejoin + 1.5 * settle + 2.0 / m["control_rate_hz"])
    print(f"\nrobot 2 back within {band} m from t = {back:.2f} s (restarted at {restarted:.2f} s; "
          f"first command {rejoin:.3f} s after its process started; bound {bound:.2f} s)")
    assert rejoin <= 0.3  # imports and keys ready before they are needed: forked, not spawned
    assert back - restarted <= bound
    assert back < ts.t[-1] - 1.0  # and stayed there for the last second at least
    assert m["settling_time_s"][0] < m["settling_bound_s"]  # robots 1 and 3 carried on
    assert m["settling_time_s"][2] < m["settling_bound_s"]


def test_a_recorded_fleet_holds_every_sample_and_command_its_bridges_handled(tmp_path):
    """Each bridge keeps the samples it sends and the commands it hears for the recording
    (deploy/runtime/wire_spool.py), as the plant does; the launcher no longer hears them.
    The recording holds exactly those: per robot, one sample for each step its bridge ran,
    in order, and every command the bridge heard (its report's count). The run keeps its
    cores awake (deploy/runtime/idle_poll.py): a spinner on each, none left after it."""
    import json as json_module
    import os

    from mcap.reader import make_reader

    from tests.procs import pids_with

    out = tmp_path / "run"
    _, m = run_fleet(out, f"t-can-recorded-{os.getpid()}", "odrive-cansimple",
                     "--keep-cores-awake", duration_s=2.0, record=True)
    assert m["cores_kept_awake"] == sorted(os.sched_getaffinity(0))
    assert not pids_with("deploy.runtime.idle_poll")
    topics: dict[str, list[dict]] = {}
    with open(out / "recording.mcap", "rb") as f:
        for _s, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if channel.topic.startswith(("/robot/", "/report/bridge-")):
                topics.setdefault(channel.topic, []).append(json_module.loads(message.data))
    for r in (1, 2, 3):
        (report,) = topics[f"/report/bridge-{r}"]
        ks = [m["k"] for m in topics[f"/robot/{r}/sample"]]
        assert ks == sorted(set(ks)) and len(ks) == report["steps"] > 150, (r, len(ks))
        heard = {e["key"]: e["value"] for e in report["received"]}
        (cmds,) = [n for key, n in heard.items() if key.endswith(f"/robot/{r}/cmd")]
        assert len(topics[f"/robot/{r}/cmd"]) == cmds > 150


def test_a_launcher_killed_outright_leaves_no_emulator_nor_spinner_behind(tmp_path):
    """SIGKILL gives the launcher of a CAN fleet no chance to stop anyone: the nodes, the
    driver emulator (which runs until stopped: it was left spinning at SCHED_FIFO 10) and
    the spinners of --keep-cores-awake still end, each told by the kernel as its parent
    dies. Everything left is ended by pid on the way out, whatever happened."""
    import os
    import signal
    import time

    from tests.procs import kill_run, pids_with, start, stat_fields

    out = tmp_path / "run"
    fleet = f"t-can-sigkill-{os.getpid()}"
    proc = start("run", "lab", "--plant", "can-emulated", "--duration", "30", "--fleet", fleet,
                 "--out", str(out), "--no-record", "--no-figures", "--keep-cores-awake")

    def children_of(pid: int) -> set[int]:
        return {p for p in pids_with("deploy.") if (f := stat_fields(p)) is not None
                and int(f[1]) == pid and f[0] != "Z"}

    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and not (
                pids_with("deploy.runtime.idle_poll") & children_of(proc.pid)):
            time.sleep(0.05)  # polling for the run to start (the spinners start with it)
        ours = children_of(proc.pid)
        assert proc.poll() is None and len(ours) >= 9, ours  # 7 nodes, the emulator, spinners
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        deadline = time.monotonic() + 30  # a bound for a loaded machine, not a wait

        def left() -> set[int]:
            return {p for p in ours if (f := stat_fields(p)) is not None and f[0] != "Z"}

        while left() and time.monotonic() < deadline:
            time.sleep(0.05)  # polling for the processes to have ended
        assert not left(), "left behind by a launcher killed outright"
    finally:
        kill_run(proc, fleet)
        for p in pids_with(str(out)):  # the emulator's command line names the run's folder
            os.kill(p, signal.SIGKILL)
