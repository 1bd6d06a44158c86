"""A machine that cannot keep a realtime fleet's clock says so in the run's first second
(deploy/run/early_load.py): which process, its CPU per step, the rate it would hold."""

from __future__ import annotations

import os
import time

import pytest

from deploy.run.early_load import EarlyLoad, EarlyLoadProbe, cpu_seconds, realtime_limit_share


def test_paper_at_1khz_on_one_core_is_behind_and_says_what_it_would_hold():
    """The figures of paper at 1 kHz pinned to one core (metrics.json, 2026-11-29)."""
    load = EarlyLoad({"plant": 285.8, "agent-1": 201.4, "agent-2": 216.9, "agent-3": 225.1,
                      "leader": 20.8, "launcher": 55.4}, period_us=1000.0, cores=1)
    assert load.behind and load.heaviest == ("plant", 285.8)
    assert load.busy_share == pytest.approx(1.0054, abs=1e-3)
    assert load.max_rate_hz() == pytest.approx(0.6 / 1005.4e-6, rel=1e-3)  # ~597 Hz
    text = load.message(1000.0)
    assert "plant the most (286 µs a step)" in text and "about 597 Hz" in text


def test_a_fleet_well_within_its_cores_is_not_behind():
    load = EarlyLoad({"plant": 50.0, "agent-1": 60.0}, period_us=1000.0, cores=2)
    assert not load.behind and load.max_rate_hz() > 1000.0


def test_one_process_above_a_period_is_behind_however_many_cores():
    load = EarlyLoad({"bridge-1": 6000.0, "agent-1": 100.0}, period_us=5000.0, cores=8)
    assert load.behind and load.max_rate_hz() == pytest.approx(100.0)  # 0.6 / 6 ms


def test_the_probe_reads_a_busy_process_from_the_kernel():
    probe = EarlyLoadProbe({"me": os.getpid()}, period_s=0.001, cores=1)
    t0 = time.monotonic()
    probe.start(t0)
    end = time.thread_time() + 0.3
    while time.thread_time() < end:  # 0.3 s of CPU
        pass
    load = probe.finish(time.monotonic())
    assert load is not None and load.cpu_us_per_step["me"] > 0
    assert cpu_seconds(2 ** 22 + 12345) is None  # a process that is not there


def test_realtime_processes_above_the_kernels_limit_are_named(tmp_path):
    """paper at 1 kHz on one core in a slow hour (2026-11-29, 21:13): the SCHED_FIFO nodes
    took ~97 % of the core, above the 95 % the kernel lets them have, and the plant stalled
    20-45 ms; the launcher, not realtime, does not count."""
    (tmp_path / "sched_rt_runtime_us").write_text("950000\n")
    (tmp_path / "sched_rt_period_us").write_text("1000000\n")
    limit = realtime_limit_share(str(tmp_path))
    assert limit == pytest.approx(0.95)
    cpu = {"plant": 290.0, "agent-1": 205.0, "agent-2": 215.0, "agent-3": 245.0,
           "leader": 16.0, "launcher": 32.0}
    load = EarlyLoad(cpu, 1000.0, 1, frozenset(set(cpu) - {"launcher"}), limit)
    assert load.realtime_share == pytest.approx(0.971) and load.over_realtime_limit
    assert "above the 95% the kernel lets them have" in load.message(1000.0)
    assert load.as_json()["over_realtime_limit"] is True
    within = EarlyLoad(cpu, 1000.0, 1, frozenset({"plant", "agent-1"}), limit)
    assert not within.over_realtime_limit and "kernel" not in within.message(1000.0)
    (tmp_path / "sched_rt_runtime_us").write_text("-1\n")  # no limit
    assert realtime_limit_share(str(tmp_path)) is None
    assert realtime_limit_share(str(tmp_path / "absent")) is None
