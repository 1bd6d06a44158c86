"""``omnifleet bench``: what users care about, measured side by side in one sitting.

Writes ``bench.json`` and ``bench.md`` to --out. Every figure is the median of
its repeats with the spread (min, max); targets (docs/bench.md) are stated
next to the figures and judged met or not, never asserted by a test. Fleet
figures come from real ``omnifleet run`` processes (no recording, no figures);
the costs underneath from :mod:`deploy.bench.micro` and
:mod:`deploy.bench.transport`.
"""

from __future__ import annotations

import json
import os
import platform
import signal
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from deploy.contract.scaled_scenarios import scale_scenario
from deploy.runtime.own_python import child_env, python_module

BENCH_VERSION = 4  # 4: the local data path against zenoh, CPU per step of each process
# 3: compiled kernels: in-process wall, per robot-step CPU, lab and CAN at speed
# 2: wire v2 codec figures, README command 1, realtime paper, largest N
SCALE_SIZES = (3, 10, 20, 30)


@dataclass(frozen=True)
class Settings:
    """How long and how often; --quick is a smoke run that still writes every figure."""

    repeats: int
    paper_s: float  # simulated seconds of the paper scenario (lockstep overhead)
    paper_run_s: float | None  # of README command 1 (None: the scenario's 24 s)
    realtime_s: float  # of the 500 Hz realtime loop
    realtime_paper_s: float  # of the paper scenario at 1 kHz on the realtime clock
    scale_lockstep_s: float
    scale_realtime_s: float
    agent_math_s: float
    plant_steps: int
    codec_calls: int
    hops: int
    one_core_paper_runs: int  # paper at 1 kHz pinned to one core: runs, each judged
    can_s: float  # the CAN fleet's runs pinned to one core
    floor_calls: int  # rounds of an agent step's pieces, hot and cold (the budget's floor)
    quick: bool = False  # the smoke run: fewer fleets in the budget and one-core groups

    @classmethod
    def of(cls, quick: bool, repeats: int | None) -> Settings:
        if quick:
            # a second of each realtime run: enough for every figure (the suite runs this)
            return cls(repeats or 1, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2, 200, 2000, 500, 1, 1.0,
                       200, quick=True)
        return cls(repeats or 3, 8.0, None, 20.0, 10.0, 10.0, 20.0, 2.0, 2000, 20000, 5000, 10,
                   20.0, 2000)


@dataclass
class Figure:
    name: str
    unit: str
    what: str
    samples: list[float] = field(default_factory=list)
    target: tuple[str, float] | None = None  # ("<=", 1.5) or (">=", 10)
    error: str | None = None

    def add(self, value: float | None, why: str = "not measured") -> None:
        """One sample; a run that could not measure it (None) is noted, never a crash."""
        if value is None:
            self.error = why
        else:
            self.samples.append(float(value))

    @property
    def median(self) -> float | None:
        return statistics.median(self.samples) if self.samples else None

    @property
    def met(self) -> bool | None:
        if self.target is None or self.median is None:
            return None
        op, bound = self.target
        return {"<=": self.median <= bound, "<": self.median < bound,
                ">=": self.median >= bound}[op]

    def as_json(self) -> dict[str, Any]:
        return {
            "unit": self.unit, "what": self.what, "median": self.median,
            "min": min(self.samples) if self.samples else None,
            "max": max(self.samples) if self.samples else None,
            "samples": self.samples,
            "target": None if self.target is None else f"{self.target[0]} {self.target[1]:g}",
            "met": self.met, "error": self.error,
        }


class FleetRunFailed(RuntimeError):
    pass


def stolen_s() -> float | None:
    """CPU time the hypervisor has taken from this machine's processors so far
    (``steal`` in /proc/stat), s; None where it cannot be read. A virtual machine whose
    processors the host takes away stalls every loop at once, whatever their priority:
    on the 2-core development VM every deadline miss of 30 agents at 100 Hz fell in a
    burst of it (2-10 ms stalls, docs/bench-history.md)."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _ms(s: float | None) -> float | None:
    return None if s is None else s * 1e3


def cpu_per_step(m: dict[str, Any]) -> dict[str, float | None]:
    """CPU per step of a distributed run's processes (metrics.json ``processes[].cpu_s``,
    µs): the plant, the busiest agent, the leader, the launcher, all of them."""
    steps = max(1, m["steps"])
    rows = {p["role"]: p.get("cpu_s") for p in m["processes"]}
    agents = [v for r, v in rows.items() if r.startswith("agent-") and v is not None]

    def us(v: float | None) -> float | None:
        return None if v is None else v / steps * 1e6

    return {"plant": us(rows.get("plant")), "agent_max": us(max(agents, default=None)),
            "leader": us(rows.get("leader")), "launcher": us(rows.get("launcher")),
            "all": us(sum(v for v in rows.values() if v is not None) or None)}


class Bench:
    def __init__(self, out: Path, settings: Settings, log: Callable[[str], None],
                 scale_sizes: tuple[int, ...] = SCALE_SIZES) -> None:
        self.out, self.s, self.log = out, settings, log
        self.scale_sizes = scale_sizes
        self.figures: dict[str, Figure] = {}
        self.work = Path(tempfile.mkdtemp(prefix="runs-", dir=out))
        self.agent_rss_mb: list[float] = []
        self.fleet_runs = 0  # runs with a process per node: what the memory figure is of

    def figure(self, name: str, unit: str, what: str,
               target: tuple[str, float] | None = None) -> Figure:
        return self.figures.setdefault(name, Figure(name, unit, what, target=target))

    # -- fleet runs -------------------------------------------------------------------
    def run_fleet(self, scenario: str, *args: str, timeout_s: float = 900.0,
                  record: bool = False, figures: bool = False,
                  cpus: set[int] | None = None) -> dict[str, Any]:
        """One ``omnifleet run``; its metrics.json, with ``command_wall_s``: the whole
        command's wall time as a user waits for it (start-up, run, outputs). Ended by pid
        whatever happens. ``cpus``: the only processors the run and every process it
        starts may use (``taskset``; one of two: a machine half as fast)."""
        out = self.work / f"run-{len(list(self.work.iterdir()))}"
        if "--in-process" not in args:
            self.fleet_runs += 1
        cmd = [*python_module("deploy.cli"), "run", scenario, "--out", str(out),
               *([] if figures else ["--no-figures"]), *([] if record else ["--no-record"]),
               *args]
        started, stolen = time.perf_counter(), stolen_s()
        # the launcher as a user starts it (its BLAS threads too), this installation's code
        pin = None if cpus is None else (lambda: os.sched_setaffinity(0, cpus))
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                env=child_env(one_blas_thread=False), preexec_fn=pin)
        try:
            _, err = proc.communicate(timeout=timeout_s)
        finally:
            if proc.poll() is None:  # Ctrl-C or timeout: let its launcher stop its nodes
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(15.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        if proc.returncode not in (0, 1) or not (out / "metrics.json").exists():
            raise FleetRunFailed(f"`omnifleet run {scenario} {' '.join(args)}` exited "
                                 f"{proc.returncode}: {err.strip()[-600:]}")
        metrics = json.loads((out / "metrics.json").read_text())
        metrics["command_wall_s"] = time.perf_counter() - started
        now_stolen = stolen_s()
        metrics["stolen_s"] = None if stolen is None or now_stolen is None else now_stolen - stolen
        if "--in-process" not in args:
            self.agent_rss_mb += [p["peak_rss_mb"] for p in metrics["processes"]
                                  if p["role"].startswith("agent-") and p["peak_rss_mb"]]
        return metrics

    def measure(self, label: str, body: Callable[[], None], *names: str) -> None:
        """Run one benchmark; a failure is written into its figures, the others go on."""
        self.log(label)
        try:
            body()
        except FleetRunFailed as exc:
            for n in names:
                self.figures[n].error = str(exc)
            self.log(f"  FAILED: {exc}")

    # -- the benchmarks -----------------------------------------------------------------
    def lockstep_overhead(self) -> None:
        wall_in = self.figure("lockstep.in_process_wall_s", "s",
                              f"paper, model plant, {self.s.paper_s:g} s simulated, one process")
        wall_dist = self.figure("lockstep.distributed_wall_s", "s",
                                "the same, one process per node over zenoh (lockstep)")
        ratio = self.figure("lockstep.overhead_ratio", "x",
                            "distributed / in-process wall time, measured back to back",
                            ("<=", 1.5))
        dur = ("--duration", str(self.s.paper_s), "--plant", "model")

        def body() -> None:
            for _ in range(self.s.repeats):
                a = self.run_fleet("paper", "--in-process", *dur)["wall_time_s"]
                b = self.run_fleet("paper", *dur)["wall_time_s"]
                wall_in.samples.append(a)
                wall_dist.samples.append(b)
                ratio.samples.append(b / a)

        self.measure("lockstep overhead (paper, model plant)", body, wall_in.name, wall_dist.name,
                     ratio.name)

    def in_process(self) -> None:
        """``omnifleet run paper --in-process`` as a user waits for it (start-up, the 24 s
        simulated, metrics and series written; no recording or figures), and the CPU of one
        robot-step: the loop's wall time (one thread) over steps x robots."""
        targets = {"pybullet": 3.0, "model": 2.0}
        dur = () if self.s.paper_run_s is None else ("--duration", str(self.s.paper_run_s))
        for kind, bound in targets.items():
            wall = self.figure(f"inprocess.paper_{kind}_wall_s", "s",
                               f"`omnifleet run paper --in-process --plant {kind} --no-record "
                               "--no-figures`, the command's wall time",
                               ("<=", bound) if self.s.paper_run_s is None else None)
            step = self.figure(f"inprocess.paper_{kind}_us_per_robot_step", "µs",
                               f"the same: the loop's time per robot and step ({kind} plant, "
                               "agents, perception, series)", ("<=", 30.0))

            def body(kind: str = kind, wall: Figure = wall, step: Figure = step) -> None:
                for _ in range(self.s.repeats):
                    m = self.run_fleet("paper", "--in-process", "--plant", kind, *dur)
                    wall.samples.append(m["command_wall_s"])
                    step.samples.append(m["wall_time_s"] / (m["steps"] * m["robots"]) * 1e6)

            self.measure(f"in process (paper, {kind})", body, wall.name, step.name)

    def lockstep_paper(self) -> None:
        """The paper scenario distributed in lockstep (pybullet, no outputs), and the same in
        process, back to back: the real-time factor and the ratio."""
        dur = () if self.s.paper_run_s is None else ("--duration", str(self.s.paper_run_s))
        rtf = self.figure("lockstep.paper_real_time_factor", "x",
                          "paper, pybullet, one process per node (lockstep, no recording): "
                          "simulated / wall time of the run", (">=", 2.0))
        ratio = self.figure("lockstep.paper_ratio_to_in_process", "x",
                            "the same run's wall time / the in-process run's, back to back")
        cpu = {who: self.figure(f"lockstep.paper_cpu_us_per_step.{who}", "µs",
                                f"the same run: CPU of {what} (every thread) over the run "
                                "loop, per step")
               for who, what in (("plant", "the plant process"),
                                 ("agent_max", "the busiest agent process"),
                                 ("leader", "the leader process"),
                                 ("launcher", "the launcher (hearing the series)"),
                                 ("all", "every process of the run"))}

        def body() -> None:
            for _ in range(self.s.repeats):
                d = self.run_fleet("paper", *dur)
                i = self.run_fleet("paper", "--in-process", *dur)
                rtf.samples.append(d["real_time_factor"])
                ratio.samples.append(d["wall_time_s"] / i["wall_time_s"])
                for who, us in cpu_per_step(d).items():
                    cpu[who].add(us, "no CPU time reported")

        self.measure("lockstep paper (pybullet, distributed and in process)", body, rtf.name,
                     ratio.name, *(f.name for f in cpu.values()))

    def data_path(self) -> None:
        """The same lockstep run with its per-step data on the local data path (unix
        sockets, the default on one host) and on zenoh (as between hosts), back to back."""
        dur = ("--duration", str(self.s.paper_s), "--plant", "model")
        local = self.figure("datapath.local_wall_s", "s",
                            f"paper, model plant, {self.s.paper_s:g} s simulated, lockstep, "
                            "per-step data on the local data path (--data-path datagram)")
        zen = self.figure("datapath.zenoh_wall_s", "s", "the same with every message on zenoh "
                          "(--data-path zenoh)")
        ratio = self.figure("datapath.zenoh_over_local", "x", "zenoh / local, back to back")

        def body() -> None:
            for _ in range(self.s.repeats):
                a = self.run_fleet("paper", *dur, "--data-path", "datagram")["wall_time_s"]
                b = self.run_fleet("paper", *dur, "--data-path", "zenoh")["wall_time_s"]
                local.samples.append(a)
                zen.samples.append(b)
                ratio.samples.append(b / a)

        self.measure("the local data path against zenoh (paper, model plant)", body,
                     local.name, zen.name, ratio.name)

    def realtime_fast(self) -> None:
        """lab at 1 kHz on the realtime clock, and the CAN fleet (a bridge per robot, the
        drive emulator, CAN buses over udp_multicast) at lab's 200 Hz and at 1 kHz."""
        p99 = self.figure("realtime.lab_1khz_latency_p99_ms", "ms",
                          "lab at 1 kHz, realtime, model plant: state-to-command latency p99",
                          ("<=", 1.0))
        touch = self.figure("realtime.lab_1khz_contacts", "count", "the same: contacts",
                            ("<=", 0.0))
        jit = self.figure("realtime.can_fleet_jitter_p99_ms", "ms",
                          "lab --plant can-emulated (200 Hz): loop jitter p99, every node",
                          ("<=", 1.0))
        settle = self.figure("realtime.can_fleet_settling_max_s", "s",
                             "the same: the slowest robot's settling time (one that never "
                             "settled counts as the run's duration)", ("<=", 1.0))
        # at 1 kHz: as long as the scenario needs to pass where the clock is kept (lab cut at
        # 10 s ends with robot 1 held off its place by an obstacle, on any machine)
        can_1k = f"lab --plant can-emulated --control-rate 1000, {self.s.realtime_s:g} s"
        can_1k_pass = self.figure("realtime.can_fleet_1khz_pass", "bool",
                                  f"{can_1k}: verdict PASS", (">=", 1.0))
        can_1k_jit = self.figure("realtime.can_fleet_1khz_jitter_p99_ms", "ms",
                                 "the same: loop jitter p99, every node", ("<=", 1.0))

        def body() -> None:
            for _ in range(self.s.repeats):
                m = self.run_fleet("lab", "--clock", "realtime", "--control-rate", "1000",
                                   "--plant", "model", "--duration", str(self.s.realtime_s / 2))
                p99.add(m["latency_ms"]["p99"], "the plant reported no latency")
                touch.samples.append(float(m["contacts"]))
                m = self.run_fleet("lab", "--plant", "can-emulated",
                                   "--duration", str(self.s.realtime_s / 2))
                jit.add(m["jitter_ms"]["p99"], "no node reported its jitter")
                settle.samples.append(max(m["sim_time_s"] if x is None else x
                                          for x in m["settling_time_s"]))
                m = self.run_fleet("lab", "--plant", "can-emulated", "--control-rate", "1000",
                                   "--duration", str(self.s.realtime_s))
                can_1k_pass.add(float(m["verdict"]["pass"]))
                can_1k_jit.add(m["jitter_ms"]["p99"], "no node reported its jitter")

        self.measure("realtime lab at 1 kHz and the CAN fleet", body, p99.name, touch.name,
                     jit.name, settle.name, can_1k_pass.name, can_1k_jit.name)

    def paper_run(self) -> None:
        """README command 1 as a user runs it (pybullet, lockstep, recording on), and
        the same without recording, back to back: what the recording costs."""
        what = "the scenario's 24 s" if self.s.paper_run_s is None else f"{self.s.paper_run_s:g} s"
        rec = self.figure("run.paper_wall_s", "s", f"`omnifleet run paper` (README command 1: "
                          f"pybullet, lockstep, recording and figures on), {what} simulated: "
                          "the command's wall time", ("<=", 15.0) if self.s.paper_run_s is None else None)
        bare = self.figure("run.paper_no_record_wall_s", "s", "the same with --no-record")
        cost = self.figure("run.recording_cost_ratio", "x",
                           "with / without recording, measured back to back")
        dur = () if self.s.paper_run_s is None else ("--duration", str(self.s.paper_run_s))

        def body() -> None:
            for _ in range(self.s.repeats):
                a = self.run_fleet("paper", *dur, record=True, figures=True)
                b = self.run_fleet("paper", *dur)
                rec.samples.append(a["command_wall_s"])
                bare.samples.append(b["wall_time_s"])
                cost.samples.append(a["wall_time_s"] / b["wall_time_s"])

        self.measure("README command 1 (paper, pybullet, recording on and off)", body,
                     rec.name, bare.name, cost.name)

    def realtime_paper(self) -> None:
        """The paper's own rate on the wall clock: 1 kHz, pybullet."""
        p99 = self.figure("realtime.paper_1khz_latency_p99_ms", "ms",
                          "paper at 1 kHz, realtime, pybullet: state-to-command latency p99",
                          ("<=", 1.0))
        p50 = self.figure("realtime.paper_1khz_latency_p50_ms", "ms", "the same, p50")
        contacts = self.figure("realtime.paper_1khz_contacts", "count",
                               "the same: physical contacts", ("<=", 0.0))
        late = self.figure("realtime.paper_1khz_unsettled_robots", "count",
                           "the same: robots not settled before sqrt(2) T_p", ("<=", 0.0))

        def body() -> None:
            for _ in range(self.s.repeats):
                m = self.run_fleet("paper", "--clock", "realtime",
                                   "--duration", str(self.s.realtime_paper_s))
                p50.add(m["latency_ms"]["p50"], "the plant reported no latency (its report did not arrive)")
                p99.add(m["latency_ms"]["p99"], "the plant reported no latency (its report did not arrive)")
                contacts.samples.append(float(m["contacts"]))
                late.samples.append(float(sum(
                    s is None or s > m["settling_bound_s"] for s in m["settling_time_s"])))

        self.measure("realtime paper at 1 kHz (pybullet)", body, p99.name, p50.name,
                     contacts.name, late.name)

    def lockstep_rtf_500(self) -> None:
        rtf = self.figure("lockstep.real_time_factor_500hz", "x",
                          "paper at 500 Hz control, distributed lockstep, model plant: "
                          "simulated / wall time", (">=", 10.0))

        def body() -> None:
            for _ in range(self.s.repeats):
                m = self.run_fleet("paper", "--control-rate", "500", "--plant", "model",
                                   "--duration", str(self.s.paper_s))
                rtf.samples.append(m["real_time_factor"])

        self.measure("lockstep real-time factor at 500 Hz", body, rtf.name)

    def realtime_loop(self) -> None:
        p50 = self.figure("realtime.latency_p50_ms", "ms",
                          "lab scenario at 500 Hz, realtime, 3 agents: state-to-command latency")
        p99 = self.figure("realtime.latency_p99_ms", "ms", "the same, p99", ("<=", 1.0))
        jit = self.figure("realtime.jitter_p99_ms", "ms", "loop jitter p99, every node",
                          ("<=", 0.5))
        miss = self.figure("realtime.deadline_misses_500hz", "count",
                           "deadline misses, every node, over the run")

        def body() -> None:
            for _ in range(self.s.repeats):
                m = self.run_fleet("lab", "--clock", "realtime", "--control-rate", "500",
                                   "--duration", str(self.s.realtime_s))
                p50.add(m["latency_ms"]["p50"], "the plant reported no latency (its report did not arrive)")
                p99.add(m["latency_ms"]["p99"], "the plant reported no latency (its report did not arrive)")
                jit.add(m["jitter_ms"]["p99"])
                miss.samples.append(float(m["deadline_misses"]))

        self.measure("realtime loop at 500 Hz (lab)", body, p50.name, p99.name, jit.name, miss.name)

    def scale(self) -> None:
        for n in self.scale_sizes:
            path = self.work / f"scale-{n}.toml"
            path.write_text(scale_scenario(n, rate_hz=100.0))
            rtf = self.figure(f"scale.n{n}.lockstep_real_time_factor", "x",
                              f"{n} robots at 100 Hz, distributed lockstep, pybullet")
            miss = self.figure(f"scale.n{n}.realtime_deadline_misses", "count",
                               f"{n} robots at 100 Hz, realtime: deadline misses, every node",
                               ("<=", 0.0) if n == 30 else None)

            touch = self.figure(f"scale.n{n}.realtime_contacts", "count",
                                f"{n} robots at 100 Hz, realtime: physical contacts",
                                ("<=", 0.0) if n == 30 else None)
            unsettled = self.figure(f"scale.n{n}.realtime_unsettled_robots", "count",
                                    f"{n} robots at 100 Hz, realtime: robots not settled "
                                    "before the bound", ("<=", 0.0) if n == 30 else None)
            model_miss = self.figure(f"scale.n{n}.realtime_model_deadline_misses", "count",
                                     f"{n} robots at 100 Hz, realtime, model plant: deadline "
                                     "misses, every node", ("<=", 0.0) if n == 30 else None)

            stolen = self.figure(f"scale.n{n}.realtime_stolen_ms", "ms",
                                 f"{n} robots at 100 Hz, realtime, both plants: CPU time the "
                                 "hypervisor took from this machine during each run (steal), "
                                 "the cause of deadline misses no priority prevents")

            def body(path: Path = path, rtf: Figure = rtf, miss: Figure = miss,
                     touch: Figure = touch, unsettled: Figure = unsettled,
                     model_miss: Figure = model_miss, stolen: Figure = stolen) -> None:
                for _ in range(self.s.repeats):
                    m = self.run_fleet(str(path), "--duration", str(self.s.scale_lockstep_s),
                                       "--startup-timeout", "180")
                    rtf.samples.append(m["real_time_factor"])
                    m = self.run_fleet(str(path), "--clock", "realtime", "--duration",
                                       str(self.s.scale_realtime_s), "--startup-timeout", "180")
                    miss.samples.append(float(m["deadline_misses"]))
                    stolen.add(_ms(m["stolen_s"]), "/proc/stat unreadable")
                    touch.samples.append(float(m["contacts"]))
                    unsettled.samples.append(float(sum(
                        x is None or x > m["settling_bound_s"] for x in m["settling_time_s"])))
                    m = self.run_fleet(str(path), "--clock", "realtime", "--plant", "model",
                                       "--duration", str(self.s.scale_realtime_s),
                                       "--startup-timeout", "180")
                    model_miss.samples.append(float(m["deadline_misses"]))
                    stolen.add(_ms(m["stolen_s"]), "/proc/stat unreadable")

            self.measure(f"scale N={n} (lockstep, realtime)", body, rtf.name, miss.name,
                         touch.name, unsettled.name, model_miss.name)
        largest = self.figure("scale.largest_n_zero_misses", "robots",
                              "the largest N of " + ", ".join(map(str, self.scale_sizes))
                              + " whose realtime runs at 100 Hz all missed no deadline (0: none)")
        clean = [n for n in self.scale_sizes
                 if self.figures[f"scale.n{n}.realtime_deadline_misses"].samples
                 and max(self.figures[f"scale.n{n}.realtime_deadline_misses"].samples) == 0]
        largest.samples.append(float(max(clean, default=0)))

    def memory(self) -> None:
        rss = self.figure("memory.agent_peak_rss_mb", "MB",
                          "peak RSS (VmHWM) of the largest agent process of every fleet run above",
                          ("<=", 80.0))
        if self.agent_rss_mb:
            rss.samples.append(max(self.agent_rss_mb))
        else:
            rss.error = "no agent process reported its memory"

    def costs(self) -> None:
        from deploy.bench.micro import (
            agent_step_us,
            codec_us,
            defence_us,
            plant_step_us_per_robot,
            safety_filter_us,
        )
        from deploy.bench.transport import udp_hop_us, zenoh_hop_us
        from deploy.contract.scenario import load_scenario

        paper = load_scenario("paper")
        self.log("costs underneath (agent math, plant step, codec, transport floor)")
        self.figure("cost.agent_step_us", "µs", "AgentCore.step, paper, per robot per step"
                    ).samples += agent_step_us(paper, self.s.agent_math_s, self.s.repeats)
        # a law in plain Python in the paper law's place (docs/laws.md): what it costs a step
        for law in ("consensus", "consensus-pd"):
            self.figure(f"cost.agent_step_{law.replace('-', '_')}_us", "µs",
                        f"the agent's step with the bundled Python law {law} (its step, "
                        "the copies of its inputs, the checks, the compiled Law.drive), paper"
                        ).samples += agent_step_us(paper.with_law(law), self.s.agent_math_s,
                                                   self.s.repeats)
        # the safety filter inside that step (docs/safety.md): checking every perceived body on
        # paper (it never acts there), and solving its QP where it acts (gap at 1.05x)
        every, _ = safety_filter_us(paper, self.s.agent_math_s, self.s.repeats)
        self.figure("cost.safety_filter_check_us", "µs", "safety filter per agent step, paper "
                    "(5 obstacles and 2 robots guarded; it never acts)").samples += every
        from deploy.contract.scenario_variants import with_obstacle_pair

        gap = with_obstacle_pair(load_scenario("gap"), 1.05, 0.12)
        _, acting = safety_filter_us(gap, 4.0, self.s.repeats)
        self.figure("cost.safety_filter_active_us", "µs", "safety filter on a step where it "
                    "changes the command (its 2-D QP), gap at 1.05x the robot width"
                    ).add(statistics.median(acting) if acting else None,
                          "the filter never acted on the gap scenario")
        for kind in ("pybullet", "model"):
            self.figure(f"cost.{kind}_step_us_per_robot", "µs",
                        f"{kind} plant step (1 ms, 4 sub-steps), paper, per robot"
                        ).samples += plant_step_us_per_robot(paper, kind, self.s.plant_steps,
                                                             self.s.repeats)
        for name, samples in codec_us(paper, self.s.codec_calls, self.s.repeats).items():
            self.figure(f"cost.codec_{name}_us", "µs",
                        f"{name}: encode + validated decode").samples += samples
        # the defences against forged messages (docs/hardening.md): per message and per
        # agent step, the step guards and the per-node keys' MACs
        what = {"guard_message": "one received message judged against the receiver's own "
                "clock and its stream (OwnClock + StepGuard)",
                "guards_per_agent_step": "every such judgement of one agent step, paper "
                "(its sample and its neighbours' shares)",
                "mac_open": "one received message's envelope checked (its tag, keyed "
                "BLAKE2b, on the raw bytes): a Sample",
                "mac_seal_reply": "one Reply sealed for all its receivers (plant, launcher, "
                "listening agents), paper's most-listened robot",
                "mac_per_agent_step": "every MAC of one agent step, paper's most-connected "
                "robot: its sample and neighbours' shares checked, its reply sealed"}
        for name, samples in defence_us(paper, self.s.codec_calls, self.s.repeats).items():
            self.figure(f"cost.defence_{name}_us", "µs", what[name]).samples += samples
        hops = {path: self.figure(f"cost.zenoh_hop_{path}_us", "µs", what) for path, what in (
            ("runtime", "one zenoh hop between two processes as the nodes use it (ping-pong / "
             "2, 200 B, unix socket): direct callback -> SimpleQueue -> the working thread"),
            ("lowlatency", "the same on zenoh's lowlatency transport (--zenoh-transport)"),
            ("indirect", "the same through the old path: zenoh's indirect callback (a Python "
             "thread) and a Condition hand-off, default transport"))}
        udp = self.figure("cost.udp_hop_us", "µs", "one raw UDP hop between two processes "
                          "(ping-pong / 2, 200 B): this machine's floor")
        for _ in range(self.s.repeats):
            for path, fig in hops.items():
                fig.samples.append(zenoh_hop_us(self.s.hops, path))
            udp.samples.append(udp_hop_us(self.s.hops))

    def _budget_figures(self, run: str, what: str, roles: dict[str, float | None]
                        ) -> dict[str, Figure]:
        """The CPU-per-step figures of one budget run, by role (the busiest of a kind)."""
        return {role: self.figure(f"budget.{run}.{role}_cpu_us", "µs",
                                  f"{what}: run-loop CPU per step of the {role.replace('_', ' ')}"
                                  " (every thread; metrics.json processes[].cpu_us_per_step)",
                                  None if bound is None else ("<=", bound))
                for role, bound in roles.items()}

    def _add_budget(self, run: str, figs: dict[str, Figure], m: dict[str, Any]) -> None:
        """Each role's CPU per step (the busiest process of it) and the parts of its step."""
        for role, fig in figs.items():
            rows = [p for p in m["processes"] if _role_kind(p["role"]) == role.split("_")[0]
                    and p.get("cpu_us_per_step") is not None]
            if not rows:
                fig.add(None, f"no {role} reported its CPU")
                continue
            row = max(rows, key=lambda p: p["cpu_us_per_step"])
            fig.add(row["cpu_us_per_step"])
            for part, us in (row.get("parts_us_per_step") or {}).items():
                self.figure(f"budget.{run}.{role}.part.{part.replace(' ', '_')}_us", "µs",
                            f"the same process: µs a step in {part} "
                            "(deploy/runtime/step_costs.py)").add(us)

    def budget(self) -> None:
        """The realtime CPU budget per process (docs/bench-history.md, "The realtime budget"): each
        process's run-loop CPU per step at the rate its scenario asks, and the part of the
        step each piece of work takes, on this machine as it is (both cores)."""
        n = 3
        runs = {
            "paper_1khz": (("paper", "--clock", "realtime", "--plant", "model"),
                           "paper at 1 kHz, realtime, model plant",
                           {"agent_max": 60.0, "plant": 40.0 + 20.0 * n, "leader": 20.0,
                            "launcher": 30.0}),
            **{f"can_{drv.replace('-', '_')}_200hz": (
                ("lab", "--plant", "can-emulated", "--driver", drv),
                f"lab on the CAN fleet ({drv}), 200 Hz",
                {"agent_max": 60.0, "bridge_max": 150.0, "leader": 20.0, "launcher": 30.0})
               for drv in ("odrive-cansimple", "cia402")},
        }
        if self.s.quick:  # the smoke run: one fleet of each kind of figure
            runs = {k: v for k, v in runs.items() if k == "paper_1khz"}
        for run, (args, what, roles) in runs.items():
            figs = self._budget_figures(run, what, roles)

            def body(args: tuple[str, ...] = args, run: str = run,
                     figs: dict[str, Figure] = figs) -> None:
                for _ in range(self.s.repeats):
                    m = self.run_fleet(*args, "--duration", str(self.s.realtime_paper_s))
                    self._add_budget(run, figs, m)

            self.measure(f"CPU budget: {what}", body, *(f.name for f in figs.values()))
        self._budget_floor()

    def _budget_floor(self) -> None:
        """What the essential pieces of an agent step cost in this runtime's Python, hot
        and after a 1 ms sleep (deploy/bench/micro.py, cold_step_pieces_us): the floor
        under the agent's budget."""
        from deploy.bench.micro import cold_step_pieces_us
        from deploy.contract.scenario import load_scenario

        what = ("the essential pieces of one agent step of paper (its 3 inputs received "
                "and decoded, AgentCore.step, the reply encoded and sent 3 times)")
        hot = self.figure("budget.floor.agent_pieces_hot_us", "µs", f"{what}, back to back")
        cold = self.figure("budget.floor.agent_pieces_cold_us", "µs",
                           f"{what}, each after a 1 ms sleep as at 1 kHz, the wake included")
        wake = self.figure("budget.floor.wake_us", "µs", "the CPU of the wake from a 1 ms "
                           "wait alone (select)")
        kernel = "the compiled law's own step (Law.step on prepared inputs, no Python around it)"
        k_hot = self.figure("budget.floor.law_kernel_hot_us", "µs", f"{kernel}, back to back")
        k_cold = self.figure("budget.floor.law_kernel_cold_us", "µs",
                             f"{kernel}, each after a 1 ms sleep: what a step compiled whole "
                             "could not go below")

        def body() -> None:
            for _ in range(self.s.repeats):
                r = cold_step_pieces_us(load_scenario("paper"), self.s.floor_calls)
                hot.samples.append(sum(r["hot"].values()))
                cold.samples.append(sum(r["cold"].values()))
                wake.samples.append(r["cold"]["wake"])
                k_hot.samples.append(r["law kernel hot"]["kernel"])
                k_cold.samples.append(r["law kernel cold"]["kernel"])

        self.measure("CPU budget: the floor of an agent step", body, hot.name, cold.name,
                     wake.name, k_hot.name, k_cold.name)

    def one_core(self) -> None:
        """Every realtime fleet pinned to one of the two cores (what a machine half as fast
        sees): the CAN fleet at 200 Hz (both drives), lab and paper at 1 kHz."""
        cpu = {min(os.sched_getaffinity(0))}
        paper_runs = self.s.one_core_paper_runs
        passed = self.figure("onecore.paper_1khz_passed", "runs",
                             f"paper at 1 kHz, realtime, model plant, 10 s, pinned to one core: "
                             f"runs that PASS (settled, no contact) of {paper_runs}",
                             (">=", float(paper_runs)))
        unsettled = self.figure("onecore.paper_1khz_unsettled_robots", "count",
                                "the same: robots not settled before the bound, every run")

        def paper() -> None:
            count, late = 0, 0.0
            for _ in range(paper_runs):
                m = self.run_fleet("paper", "--clock", "realtime", "--plant", "model",
                                   "--duration", str(self.s.realtime_paper_s), cpus=cpu)
                count += bool(m["verdict"]["pass"])
                late += sum(x is None or x > m["settling_bound_s"] for x in m["settling_time_s"])
            passed.add(float(count))
            unsettled.add(late)

        def lab() -> None:
            p99 = self.figure("onecore.lab_1khz_latency_p99_ms", "ms",
                              "lab at 1 kHz, realtime, model plant, pinned to one core: "
                              "state-to-command latency p99", ("<=", 1.0))
            lab_pass = self.figure("onecore.lab_1khz_pass", "bool", "the same: verdict PASS",
                                   (">=", 1.0))
            for _ in range(self.s.repeats):
                m = self.run_fleet("lab", "--clock", "realtime", "--control-rate", "1000",
                                   "--plant", "model", "--duration", str(self.s.realtime_s),
                                   cpus=cpu)
                p99.add(m["latency_ms"]["p99"], "the plant reported no latency")
                lab_pass.add(float(m["verdict"]["pass"]))

        self.measure("one core: paper at 1 kHz", paper, passed.name, unsettled.name)
        if not self.s.quick:  # the smoke run: paper and the ODrive fleet
            self.measure("one core: lab at 1 kHz", lab, "onecore.lab_1khz_latency_p99_ms",
                         "onecore.lab_1khz_pass")
        drives = ("odrive-cansimple",) if self.s.quick else ("odrive-cansimple", "cia402")
        # each plain, then with the core kept from halting (deploy/runtime/idle_poll.py)
        for drv, awake in ((d, a) for d in drives for a in (False, True)):
            name = drv.replace("-", "_") + ("_awake" if awake else "")
            what = f"lab on the CAN fleet ({drv}), 200 Hz, {self.s.can_s:g} s, pinned to one " \
                   "core" + (", --keep-cores-awake" if awake else "")
            figs = {
                "pass": self.figure(f"onecore.can_{name}_200hz_pass", "bool",
                                    f"{what}: verdict PASS", (">=", 1.0)),
                "unsimulated": self.figure(f"onecore.can_{name}_200hz_steps_not_simulated",
                                           "steps", "the same: steps asked, not simulated",
                                           ("<=", 0.0)),
                "jitter": self.figure(f"onecore.can_{name}_200hz_jitter_p99_ms", "ms",
                                      "the same: loop jitter p99, every node", ("<=", 1.0)),
                "misses": self.figure(f"onecore.can_{name}_200hz_deadline_misses", "count",
                                      "the same: deadline misses, every node"),
                "settling": self.figure(f"onecore.can_{name}_200hz_settling_max_s", "s",
                                        "the same: the slowest robot's settling time (never "
                                        "settled: the run's duration)", ("<", 1.0)),
                "bridge_cpu": self.figure(f"onecore.can_{name}_200hz_bridge_cpu_us", "µs",
                                          "the same: the busiest bridge's CPU a step"),
            }

            def can(drv: str = drv, figs: dict[str, Figure] = figs, awake: bool = awake) -> None:
                for _ in range(self.s.repeats):
                    m = self.run_fleet("lab", "--plant", "can-emulated", "--driver", drv,
                                       "--duration", str(self.s.can_s),
                                       *(["--keep-cores-awake"] if awake else []), cpus=cpu)
                    figs["pass"].add(float(m["verdict"]["pass"]))
                    figs["unsimulated"].add(float(m["steps_asked"] - m["steps_simulated"]))
                    figs["jitter"].add(m["jitter_ms"]["p99"], "no node reported its jitter")
                    figs["misses"].add(float(m["deadline_misses"]))
                    figs["settling"].add(max(m["sim_time_s"] if x is None else x
                                             for x in m["settling_time_s"]))
                    figs["bridge_cpu"].add(max((p["cpu_us_per_step"] for p in m["processes"]
                                                if p["role"].startswith("bridge-")
                                                and p.get("cpu_us_per_step") is not None),
                                               default=None), "no bridge reported its CPU")

            self.measure(f"one core: the CAN fleet ({drv}) at 200 Hz"
                         + (", cores kept awake" if awake else ""), can,
                         *(f.name for f in figs.values()))

    def groups(self) -> dict[str, Callable[[], None]]:
        """The benchmarks by name, in the order a full run takes them."""
        return {"costs": self.costs, "in-process": self.in_process,
                "lockstep": self.lockstep_overhead, "lockstep-paper": self.lockstep_paper,
                "data-path": self.data_path,
                "paper-run": self.paper_run, "rtf500": self.lockstep_rtf_500,
                "realtime": self.realtime_loop, "realtime-fast": self.realtime_fast,
                "realtime-paper": self.realtime_paper, "scale": self.scale,
                "budget": self.budget, "one-core": self.one_core}

    def run_all(self, only: list[str] | None = None) -> None:
        for name, run in self.groups().items():
            if only is None or name in only:
                run()
        if self.fleet_runs:  # the groups asked for started agents (not in-process or costs)
            self.memory()

    # -- outputs --------------------------------------------------------------------------
    def report(self, quick: bool, started: float) -> dict[str, Any]:
        return {
            "version": BENCH_VERSION,
            "date": datetime.now(UTC).isoformat(timespec="seconds"),
            "quick": quick,
            "repeats": self.s.repeats,
            "bench_wall_s": round(time.monotonic() - started, 1),
            "machine": machine(),
            "figures": {name: f.as_json() for name, f in self.figures.items()},
        }


def _role_kind(role: str) -> str:
    """agent-3 -> agent, bridge-1 -> bridge, plant -> plant."""
    return role.split("-", 1)[0]


def machine() -> dict[str, Any]:
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "cpu": model, "python": platform.python_version(),
            "platform": platform.platform()}


def markdown(report: dict[str, Any]) -> str:
    lines = [f"# omnifleet bench — {report['date']}",
             "",
             f"{report['machine']['cpus']} CPUs ({report['machine']['cpu'] or 'unknown CPU'}), "
             f"Python {report['machine']['python']}; "
             f"{'quick (smoke) run' if report['quick'] else 'full run'}, "
             f"{report['repeats']} repeat(s), medians with (min-max).",
             "",
             "| figure | median | spread | unit | target | met | what |",
             "|---|---|---|---|---|---|---|"]
    for name, f in report["figures"].items():
        if f["median"] is None:
            lines.append(f"| {name} | — | — | {f['unit']} | {f['target'] or ''} | — | "
                         f"{f['what']}; FAILED: {(f['error'] or '')[:200]} |")
            continue
        met = {True: "yes", False: "**no**", None: ""}[f["met"]]
        lines.append(f"| {name} | {_num(f['median'])} | {_num(f['min'])}-{_num(f['max'])} | "
                     f"{f['unit']} | {f['target'] or ''} | {met} | {f['what']} |")
    return "\n".join(lines) + "\n"


def _num(x: float) -> str:
    return f"{x:.3g}" if abs(x) < 1000 else f"{x:.0f}"






