"""`omnifleet bench --quick`: a smoke run that must write every figure.

Benchmarks are not tests: nothing here compares a time with a bound. The test
checks that the JSON is complete and coherent, and the pure parts of the bench
(generated scale scenarios) against what they promise.
"""

from __future__ import annotations

import json
import math

import pytest
from procs import finish, start

from deploy.bench.suite import markdown

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.load_safe]

# the smoke run's scale group: 3 robots only (the whole quick bench, 30 robots included,
# took 281 s of the suite's 1231 s here; the scale runs are the bench's, not the test's)
SMOKE_SIZES = (3,)
EXPECTED = {
    "lockstep.in_process_wall_s", "lockstep.distributed_wall_s", "lockstep.overhead_ratio",
    "lockstep.real_time_factor_500hz", "realtime.latency_p50_ms", "realtime.latency_p99_ms",
    "realtime.jitter_p99_ms", "realtime.deadline_misses_500hz", "memory.agent_peak_rss_mb",
    "cost.agent_step_us", "cost.agent_step_consensus_us", "cost.agent_step_consensus_pd_us",
    "cost.safety_filter_check_us", "cost.safety_filter_active_us",
    "cost.pybullet_step_us_per_robot", "cost.model_step_us_per_robot",
    "cost.zenoh_hop_runtime_us", "cost.zenoh_hop_lowlatency_us", "cost.zenoh_hop_indirect_us",
    "cost.udp_hop_us",
    "cost.defence_guard_message_us", "cost.defence_guards_per_agent_step_us",
    "cost.defence_mac_open_us", "cost.defence_mac_seal_reply_us",
    "cost.defence_mac_per_agent_step_us",
    "run.paper_wall_s", "run.paper_no_record_wall_s", "run.recording_cost_ratio",
    "realtime.paper_1khz_latency_p99_ms", "realtime.paper_1khz_latency_p50_ms",
    "realtime.paper_1khz_contacts", "realtime.paper_1khz_unsettled_robots",
    "scale.largest_n_zero_misses",
    *(f"scale.n{n}.realtime_contacts" for n in SMOKE_SIZES),
    *(f"scale.n{n}.realtime_stolen_ms" for n in SMOKE_SIZES),
    *(f"cost.codec_{m}_us" for m in ("Sample", "Reply", "LeaderState", "Telemetry",
                                     "StateLog")),
    *(f"scale.n{n}.lockstep_real_time_factor" for n in SMOKE_SIZES),
    *(f"scale.n{n}.realtime_deadline_misses" for n in SMOKE_SIZES),
    *(f"scale.n{n}.realtime_unsettled_robots" for n in SMOKE_SIZES),
    *(f"scale.n{n}.realtime_model_deadline_misses" for n in SMOKE_SIZES),
    *(f"inprocess.paper_{k}_{f}" for k in ("pybullet", "model")
      for f in ("wall_s", "us_per_robot_step")),
    "lockstep.paper_real_time_factor", "lockstep.paper_ratio_to_in_process",
    "realtime.lab_1khz_latency_p99_ms", "realtime.lab_1khz_contacts",
    "realtime.can_fleet_jitter_p99_ms", "realtime.can_fleet_settling_max_s",
    "realtime.can_fleet_1khz_pass", "realtime.can_fleet_1khz_jitter_p99_ms",
    "datapath.local_wall_s", "datapath.zenoh_wall_s", "datapath.zenoh_over_local",
    *(f"lockstep.paper_cpu_us_per_step.{w}" for w in ("plant", "agent_max", "leader",
                                                      "launcher", "all")),
    # the realtime budget (one fleet in the smoke run) and the fleets pinned to one core
    *(f"budget.paper_1khz.{w}_cpu_us" for w in ("agent_max", "plant", "leader", "launcher")),
    "budget.paper_1khz.agent_max.part.law_us",
    "budget.paper_1khz.agent_max.part.wake_and_the_rest_us",
    "budget.floor.agent_pieces_hot_us", "budget.floor.agent_pieces_cold_us", "budget.floor.wake_us",
    "budget.floor.law_kernel_hot_us", "budget.floor.law_kernel_cold_us",
    "onecore.paper_1khz_passed", "onecore.paper_1khz_unsettled_robots",
    *(f"onecore.can_odrive_cansimple{awake}_200hz_{w}" for awake in ("", "_awake") for w in (
        "pass", "steps_not_simulated", "jitter_p99_ms", "deadline_misses", "settling_max_s",
        "bridge_cpu_us")),
}
TARGETS = {"lockstep.overhead_ratio": "<= 1.5", "lockstep.real_time_factor_500hz": ">= 10",
           "realtime.latency_p99_ms": "<= 1", "realtime.jitter_p99_ms": "<= 0.5",
           "realtime.paper_1khz_latency_p99_ms": "<= 1", "realtime.paper_1khz_contacts": "<= 0",
           "realtime.paper_1khz_unsettled_robots": "<= 0",
           "memory.agent_peak_rss_mb": "<= 80",
           "inprocess.paper_pybullet_us_per_robot_step": "<= 30",
           "inprocess.paper_model_us_per_robot_step": "<= 30",
           "lockstep.paper_real_time_factor": ">= 2", "realtime.lab_1khz_latency_p99_ms": "<= 1",
           "realtime.lab_1khz_contacts": "<= 0", "realtime.can_fleet_jitter_p99_ms": "<= 1",
           "realtime.can_fleet_settling_max_s": "<= 1", "realtime.can_fleet_1khz_pass": ">= 1",
           "realtime.can_fleet_1khz_jitter_p99_ms": "<= 1"}








def test_quick_bench_writes_every_figure(tmp_path):
    rc, _, err = finish(start("bench", "--quick", "--scale-sizes", "3", "--out", str(tmp_path)),
                        timeout=600)
    assert rc == 0, err
    report = json.loads((tmp_path / "bench.json").read_text())
    assert report["quick"] is True and report["machine"]["cpus"] >= 1
    figures = report["figures"]
    assert EXPECTED <= figures.keys()
    for name, f in figures.items():
        assert f["error"] is None, (name, f["error"])
        assert f["samples"] and all(math.isfinite(x) and x >= 0 for x in f["samples"]), name
        assert f["min"] <= f["median"] <= f["max"], name
        assert (f["met"] is None) == (f["target"] is None), name
    for name, target in TARGETS.items():
        assert figures[name]["target"] == target
    # what the figures mean, checked where it is a physical fact
    assert figures["cost.udp_hop_us"]["median"] > 0
    assert figures["lockstep.overhead_ratio"]["median"] == pytest.approx(
        figures["lockstep.distributed_wall_s"]["median"]
        / figures["lockstep.in_process_wall_s"]["median"])
    assert figures["datapath.zenoh_over_local"]["median"] == pytest.approx(
        figures["datapath.zenoh_wall_s"]["median"] / figures["datapath.local_wall_s"]["median"])
    cpu = {w: figures[f"lockstep.paper_cpu_us_per_step.{w}"]["median"]
           for w in ("plant", "agent_max", "leader", "launcher", "all")}
    assert all(v > 0 for v in cpu.values()), cpu  # every process reported its CPU
    assert cpu["all"] >= cpu["plant"] + cpu["agent_max"] + cpu["leader"] + cpu["launcher"]
    # the floor's cold round is the hot one plus a wake: never cheaper
    floor = {w: figures[f"budget.floor.{w}"]["median"] for w in
             ("agent_pieces_hot_us", "agent_pieces_cold_us", "wake_us")}
    assert floor["agent_pieces_cold_us"] > floor["agent_pieces_hot_us"] > 0 < floor["wake_us"]
    # the compiled law alone is a part of AgentCore.step, itself one of the pieces
    kernel = {w: figures[f"budget.floor.law_kernel_{w}_us"]["median"] for w in ("hot", "cold")}
    assert 0 < kernel["hot"] < floor["agent_pieces_hot_us"]
    assert 0 < kernel["cold"] < floor["agent_pieces_cold_us"]
    table = (tmp_path / "bench.md").read_text()
    assert table == markdown(report)
    assert all(name in table for name in EXPECTED)
    assert not any(p.name.startswith("runs-") for p in tmp_path.iterdir())  # cleaned up
