"""The fault plan's process kills, restarts, pauses and resumes, in the order the run
meets them."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from deploy.contract.fault_plan import Kill

# what the launcher does at an event, and the word metrics.json logs it under
KILL, RESTART, PAUSE, RESUME = "killed", "restarted", "paused", "resumed"
_ORDER = {KILL: 0, PAUSE: 0, RESTART: 1, RESUME: 1}  # at one instant: stop before start


@dataclass(frozen=True)
class KillEvent:
    at_s: float  # run time
    process: str  # role
    action: str  # KILL (SIGKILL), RESTART (start it again), PAUSE (SIGSTOP), RESUME (SIGCONT)

    @property
    def restart(self) -> bool:
        return self.action == RESTART


@dataclass
class KillSchedule:
    plan: Iterable[Kill]
    pending: list[KillEvent] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)  # what was done, for metrics.json

    def __post_init__(self) -> None:
        for k in self.plan:
            if k.pause_s is not None:  # SIGSTOP, then SIGCONT: a process off the CPU
                self.pending.append(KillEvent(k.at_s, k.process, PAUSE))
                self.pending.append(KillEvent(k.at_s + k.pause_s, k.process, RESUME))
                continue
            self.pending.append(KillEvent(k.at_s, k.process, KILL))
            if k.restart_after_s is not None:
                self.pending.append(KillEvent(k.at_s + k.restart_after_s, k.process, RESTART))
        self.pending.sort(key=lambda e: (e.at_s, _ORDER[e.action]))

    def due(self, t: float) -> list[KillEvent]:
        """The events whose time has come, removed from the schedule."""
        out = [e for e in self.pending if e.at_s <= t]
        self.pending = [e for e in self.pending if e.at_s > t]
        return out

    def log(self, event: KillEvent, t: float, pid: int) -> None:
        self.events.append({"process": event.process, "event": event.action,
                            "planned_s": event.at_s, "t_s": round(t, 4), "pid": pid})
