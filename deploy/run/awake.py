"""The launcher's side of ``--keep-cores-awake``: a spinning process at the lowest
priority on each core the fleet may run on, for as long as the fleet's run lasts
(deploy/runtime/idle_poll.py says why and what it costs)."""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from deploy.runtime.own_python import child_env, python_module
from deploy.runtime.priority import under_fifo

STOP_WAIT_S = 5.0
# how long a child with no readiness of its own (the driver emulator) is given to be under
# SCHED_FIFO once every ready node is: on a loaded core it was under a second after them;
# a host that grants the nodes' priority and refuses the emulator's higher one (an
# RLIMIT_RTPRIO between the two) delays the run's start by this much, not by the start-up
# timeout
STARTING_GRACE_S = 5.0


def not_realtime(pids: dict[str, int]) -> list[str]:
    """The roles among ``pids`` whose process does not run under SCHED_FIFO (the host
    refused it: no CAP_SYS_NICE, or a CPU group without realtime time), or is gone. A
    spinner beside such a node takes the core each time the node hands it over
    (deploy/runtime/idle_poll.py): a CAN fleet in the suite's CPU group of low weight,
    its nodes refused SCHED_FIFO there, had no state heard in a 1 s run."""
    return [role for role, pid in sorted(pids.items()) if not under_fifo(pid)]


def refused_realtime(ready: dict[str, int], starting: dict[str, int], within_s: float,
                     stop: Callable[[], bool]) -> list[str]:
    """The roles not under SCHED_FIFO (``not_realtime``). ``ready``: nodes that raised
    their priority before saying they were ready, so their policy is final. ``starting``:
    children with no readiness of their own (the driver emulator), which raise theirs as
    their loop begins, and on a loaded core after the nodes are ready: once every ready
    node is under SCHED_FIFO (the host grants it), each is given ``within_s`` to be."""
    refused = not_realtime(ready)
    if refused:
        return refused
    deadline = time.monotonic() + within_s
    while (refused := not_realtime(starting)) and time.monotonic() < deadline and not stop():
        time.sleep(0.01)  # polling: a process's policy changes without telling anyone
    return refused


@contextmanager
def cores_kept_awake(cores: set[int] | None) -> Iterator[list[int]]:
    """While inside: one spinner per core of ``cores`` (None or empty: none), pinned and
    at the lowest priority; yields their pids. On the way out, however left, each is
    killed by pid and reaped."""
    procs: list[subprocess.Popen] = []
    try:
        for core in sorted(cores or ()):
            procs.append(subprocess.Popen(
                [*python_module("deploy.runtime.idle_poll"), str(core), str(os.getpid())],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=child_env(),
                # a session, so an autogroup, of its own: it lowers that one, not ours
                start_new_session=True))
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        for p in procs:
            try:
                p.wait(STOP_WAIT_S)
            except subprocess.TimeoutExpired:  # cannot happen after SIGKILL; never hang on it
                pass
