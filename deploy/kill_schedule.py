"""The fault plan's process kills and restarts, in the order the run meets them."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from deploy.fault_plan import Kill


@dataclass(frozen=True)
class KillEvent:
    at_s: float  # run time
    process: str  # role
    restart: bool  # False: kill it; True: start it again


@dataclass
class KillSchedule:
    plan: Iterable[Kill]
    pending: list[KillEvent] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)  # what was done, for metrics.json

    def __post_init__(self) -> None:
        for k in self.plan:
            self.pending.append(KillEvent(k.at_s, k.process, False))
            if k.restart_after_s is not None:
                self.pending.append(KillEvent(k.at_s + k.restart_after_s, k.process, True))
        self.pending.sort(key=lambda e: (e.at_s, e.restart))

    def due(self, t: float) -> list[KillEvent]:
        """The events whose time has come, removed from the schedule."""
        out = [e for e in self.pending if e.at_s <= t]
        self.pending = [e for e in self.pending if e.at_s > t]
        return out

    def log(self, event: KillEvent, t: float, pid: int) -> None:
        self.events.append({"process": event.process,
                            "event": "restarted" if event.restart else "killed",
                            "planned_s": event.at_s, "t_s": round(t, 4), "pid": pid})
