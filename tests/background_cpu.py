"""A CPU group of low weight for the suite's first phase, run beside its second
(tests/suite.py), and what the group used (tests/realtime_clock.py).

The second phase (realtime runs, fleets on the wall clock, one test at a time) kept
about one of the two cores busy: most of its time is its runs' simulated seconds, not
CPU. The first phase (CPU-bound, spread over the cores) now runs at the same time in a
cgroup whose weight is a tenth of one ordinary process's: wherever the second phase's
processes want a core they get it (its realtime nodes run under SCHED_FIFO, which no
ordinary process preempts; where the kernel schedules realtime tasks by group, as here,
a new group has no realtime time at all, and the first phase's own realtime runs stay
ordinary processes), and the first phase takes what they leave. The group's CPU time
is read from the group itself, so a realtime test can tell it apart from programs the
suite does not control.

Linux only, as root (or with the cgroup delegated): cgroup v1 ``cpu`` and ``cpuacct``
hierarchies (``cpu.shares``, ``cpuacct.usage``), or v2 with the ``cpu`` controller
(``cpu.weight``, ``cpu.stat``). Where neither can be made the phases run one after the
other, as before.
"""

from __future__ import annotations

import os
from pathlib import Path

SHARES_V1 = 102  # of 1024, an ordinary (nice 0) process's
WEIGHT_V2 = 10  # of 100, the same
USAGE_ENV = "SUITE_BACKGROUND_CPU"  # where a realtime test reads the group's time (no
# OMNIFLEET_ in its name: the nodes inherit it, and a test checks that they carry none)


def _mounts() -> list[tuple[str, str, set[str]]]:
    """(mount point, file system type, options) of every cgroup mount."""
    out = []
    try:
        with open("/proc/self/mounts") as f:
            for line in f:
                _dev, point, fstype, opts, *_ = line.split()
                if fstype in ("cgroup", "cgroup2"):
                    out.append((point, fstype, set(opts.split(","))))
    except OSError:
        pass
    return out


def _own_paths() -> dict[str, str]:
    """This process's cgroup path in each hierarchy: controller name (``""`` for v2)."""
    out: dict[str, str] = {}
    try:
        with open("/proc/self/cgroup") as f:
            for line in f:
                _n, controllers, path = line.rstrip("\n").split(":", 2)
                for c in controllers.split(",") if controllers else [""]:
                    out[c] = path
    except OSError:
        pass
    return out


class BackgroundGroup:
    """A cgroup (one directory per hierarchy) a process and its descendants are moved to."""

    def __init__(self, dirs: list[Path], usage: Path) -> None:
        self.dirs = dirs  # every hierarchy's directory of the group (procs written to each)
        self.usage = usage  # cpuacct.usage (ns) or cpu.stat (usage_usec)

    @classmethod
    def make(cls, name: str) -> BackgroundGroup | None:
        """The group, made under this process's own; None where the host does not let us."""
        own = _own_paths()
        mounts = _mounts()
        v1 = {c: point for point, fstype, opts in mounts if fstype == "cgroup"
              for c in ("cpu", "cpuacct") if c in opts}
        made: list[Path] = []
        try:
            if {"cpu", "cpuacct"} <= v1.keys() and {"cpu", "cpuacct"} <= own.keys():
                cpu = Path(v1["cpu"] + own["cpu"]) / name
                acct = Path(v1["cpuacct"] + own["cpuacct"]) / name
                for d in dict.fromkeys([cpu, acct]):
                    d.mkdir()
                    made.append(d)
                (cpu / "cpu.shares").write_text(str(SHARES_V1))
                return cls(made, acct / "cpuacct.usage")
            v2 = [point for point, fstype, _ in mounts if fstype == "cgroup2"]
            if v2 and "" in own:
                parent = Path(v2[0] + own[""])
                if "cpu" not in (parent / "cgroup.controllers").read_text().split():
                    return None
                if "cpu" not in (parent / "cgroup.subtree_control").read_text().split():
                    (parent / "cgroup.subtree_control").write_text("+cpu")
                d = parent / name
                d.mkdir()
                made.append(d)
                (d / "cpu.weight").write_text(str(WEIGHT_V2))
                return cls(made, d / "cpu.stat")
        except OSError:
            for d in made:
                _remove(d)
        return None

    def add(self, pid: int) -> None:
        """Move ``pid`` into the group (its children to come follow it)."""
        for d in self.dirs:
            (d / "cgroup.procs").write_text(str(pid))

    def remove(self) -> None:
        """Remove the group (once its processes are gone; else it stays, harmless)."""
        for d in self.dirs:
            _remove(d)


def _remove(d: Path) -> None:
    try:
        d.rmdir()
    except OSError:
        pass


def usage_s(path: str | os.PathLike[str]) -> float | None:
    """A group's CPU time so far, s, from ``cpuacct.usage`` or ``cpu.stat``; None when
    unreadable."""
    try:
        text = Path(path).read_text()
    except OSError:
        return None
    if Path(path).name == "cpu.stat":
        for line in text.splitlines():
            key, _, value = line.partition(" ")
            if key == "usage_usec":
                return int(value) / 1e6
        return None
    try:
        return int(text) / 1e9
    except ValueError:
        return None


def background_usage_s() -> float | None:
    """CPU time so far of the suite's background phase, when this process runs beside it
    (``$SUITE_BACKGROUND_CPU``); else None."""
    path = os.environ.get(USAGE_ENV)
    return usage_s(path) if path else None
