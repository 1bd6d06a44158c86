"""Whether this machine keeps a realtime fleet's clock, judged in the run's first second
(docs/bench-history.md, "The realtime budget").

The launcher reads every process's CPU time from the kernel (``/proc/PID/stat``) as the
run starts and a second later: each process's CPU per step, and the fleet's share of the
cores it may use. A fleet that takes more than ``BUSY_SHARE`` of them, or one process
more than a period a step, cannot keep its clock: the launcher says so at once, naming the
heaviest process and the highest rate this machine would hold the fleet at, and
metrics.json (``early_load``) and the summary say it again. It also says when the fleet's
realtime (SCHED_FIFO) processes alone took more of the cores than the kernel lets realtime
processes have (``sched_rt_runtime_us`` of each ``sched_rt_period_us``, 95 % by default):
the kernel then holds every one of them for the rest of such a period, the plant too
(`paper` at 1 kHz on one core: stalls of 20-45 ms; docs/bench-history.md, "A late agent's
law"). The robots are still guarded
meanwhile (the safety filter, the plant's command timeout): a machine that cannot keep
up slows and stops them, it never lets them touch.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from deploy.runtime.priority import over_realtime_limit_words, under_fifo

WINDOW_S = 1.0  # judged over the run's first second
BUSY_SHARE = 0.85  # of the cores: above it, the fleet's loops wait for each other
HOLD_SHARE = 0.6  # a rate this machine holds: the fleet within this share of the cores


def cpu_seconds(pid: int) -> float | None:
    """CPU time of process ``pid`` so far (every thread, user + system), s; None once gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            stat = f.read()
        fields = stat[stat.rfind(")") + 2:].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def realtime_limit_share(root: str = "/proc/sys/kernel") -> float | None:
    """The share of each core the kernel lets SCHED_FIFO and SCHED_RR processes have
    (``sched_rt_runtime_us`` / ``sched_rt_period_us``); None without a limit (-1) or where
    it cannot be read."""
    try:
        with open(f"{root}/sched_rt_runtime_us") as f:
            runtime = int(f.read())
        with open(f"{root}/sched_rt_period_us") as f:
            period = int(f.read())
    except (OSError, ValueError):
        return None
    return None if runtime < 0 or period <= 0 else runtime / period


@dataclass(frozen=True)
class EarlyLoad:
    """The fleet's first second: CPU per step by process, against the cores."""

    cpu_us_per_step: dict[str, float]  # role -> µs of CPU a step
    period_us: float
    cores: int
    realtime: frozenset[str] = frozenset()  # the roles that ran under SCHED_FIFO
    realtime_limit: float | None = None  # realtime_limit_share() as it was read

    @property
    def realtime_share(self) -> float:
        """The realtime processes' CPU over the cores' time."""
        us = sum(v for r, v in self.cpu_us_per_step.items() if r in self.realtime)
        return us / (self.period_us * self.cores)

    @property
    def over_realtime_limit(self) -> bool:
        """The realtime processes took more than the kernel lets them have: it holds them
        all, for the rest of each period where they do."""
        return self.realtime_limit is not None and self.realtime_share > self.realtime_limit

    @property
    def busy_share(self) -> float:
        """The fleet's CPU over the cores' time (1: every core busy all the time)."""
        return sum(self.cpu_us_per_step.values()) / (self.period_us * self.cores)

    @property
    def heaviest(self) -> tuple[str, float]:
        return max(self.cpu_us_per_step.items(), key=lambda kv: kv[1])

    @property
    def behind(self) -> bool:
        """The fleet takes nearly every core, or one process more than a period a step."""
        return self.busy_share > BUSY_SHARE or self.heaviest[1] > self.period_us

    def max_rate_hz(self) -> float:
        """The highest control rate this machine would hold this fleet at: its CPU per
        step within ``HOLD_SHARE`` of the cores, and no process above that share of a
        period (a step costs about as much at any rate)."""
        total = sum(self.cpu_us_per_step.values()) * 1e-6
        rate = HOLD_SHARE * self.cores / total if total > 0 else float("inf")
        heaviest = self.heaviest[1] * 1e-6
        return min(rate, HOLD_SHARE / heaviest if heaviest > 0 else float("inf"))

    def as_json(self) -> dict:
        role, us = self.heaviest
        return {"behind": self.behind, "busy_share": round(self.busy_share, 3),
                "realtime_share": round(self.realtime_share, 3),
                "realtime_limit": self.realtime_limit,
                "over_realtime_limit": self.over_realtime_limit,
                "cores": self.cores, "heaviest": role, "heaviest_cpu_us_per_step": round(us, 1),
                "max_rate_hz": round(self.max_rate_hz(), 1),
                "cpu_us_per_step": {r: round(v, 1) for r, v in self.cpu_us_per_step.items()}}

    def message(self, rate_hz: float) -> str:
        role, us = self.heaviest
        return (f"this machine cannot keep the fleet's clock at {rate_hz:g} Hz: in the run's "
                f"first second it took {self.busy_share:.0%} of its {self.cores} core(s) "
                f"({sum(self.cpu_us_per_step.values()):.0f} µs of CPU a {self.period_us:.0f} µs "
                f"step), {role} the most ({us:.0f} µs a step); it would hold this fleet at "
                f"about {self.max_rate_hz():.0f} Hz (--control-rate). The robots stay guarded; "
                "expect deadline misses and a late settling" + self._limit_note())

    def _limit_note(self) -> str:
        if not self.over_realtime_limit:
            return ""
        words = over_realtime_limit_words(self.realtime_share, self.realtime_limit)  # type: ignore[arg-type]
        return f"; its realtime processes took {words} (stalls of tens of ms)"


class EarlyLoadProbe:
    """Reads the processes' CPU at the run's start and ``WINDOW_S`` later."""

    def __init__(self, pids: dict[str, int], period_s: float, cores: int | None = None) -> None:
        self.pids = dict(pids)
        self.period_us = period_s * 1e6
        self.cores = cores or len(os.sched_getaffinity(0))
        self._start: dict[str, float] = {}
        self.started_at: float | None = None
        self.result: EarlyLoad | None = None

    def start(self, now: float) -> None:
        self.started_at = now
        self._start = {r: c for r, p in self.pids.items() if (c := cpu_seconds(p)) is not None}

    def due(self, now: float) -> bool:
        return self.result is None and self.started_at is not None and \
            now >= self.started_at + WINDOW_S

    def finish(self, now: float) -> EarlyLoad | None:
        """The load over the window (None: nothing could be read)."""
        steps = (now - self.started_at) / (self.period_us * 1e-6)  # type: ignore[operator]
        per_step: dict[str, float] = {}
        realtime = set()
        for role, pid in self.pids.items():
            c, c0 = cpu_seconds(pid), self._start.get(role)
            if c is not None and c0 is not None and steps > 0:
                per_step[role] = (c - c0) / steps * 1e6
                if under_fifo(pid):
                    realtime.add(role)
        self.result = EarlyLoad(per_step, self.period_us, self.cores, frozenset(realtime),
                                realtime_limit_share()) if per_step else None
        return self.result
