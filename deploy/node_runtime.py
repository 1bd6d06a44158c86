"""What every node process shares: stop on SIGTERM/SIGINT, die with the
launcher, the realtime start barrier, a periodic timer that measures jitter,
and the end-of-run report."""

from __future__ import annotations

import ctypes
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from deploy.transport import Node
from deploy.wire import WIRE_VERSION, Control, NodeReport

START_LEAD_S = 0.3  # realtime: t = 0 this long after ``start`` is sent

CLOCKS = ("lockstep", "realtime")
MAX_SAMPLES = 200_000  # timing samples kept per node (enough for 200 s at 1 kHz)


class StopFlag:
    """Set by SIGTERM/SIGINT or a ``stop``/``end`` control message."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.reason = ""

    def set(self, reason: str) -> None:
        if not self._event.is_set():
            self.reason = reason
        self._event.set()

    def __call__(self) -> bool:
        return self._event.is_set()


def install_signal_handlers(stop: StopFlag, node: Node | None = None) -> None:
    def handler(signum: int, _frame: object) -> None:
        stop.set(signal.Signals(signum).name)
        if node is not None:  # wake whoever waits on the mailbox
            with node.mailbox.changed:
                node.mailbox.changed.notify_all()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def die_with_parent() -> None:
    """Linux: get SIGTERM when the launching process dies (no orphans, even
    after a SIGKILL of the launcher). Called by the child itself at start-up
    (a preexec_fn is unsafe in the launcher, which runs zenoh threads)."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@dataclass
class Timing:
    """Realtime loop figures of one node, in nanoseconds."""

    jitter_ns: list[int] = field(default_factory=list)
    latency_ns: list[int] = field(default_factory=list)
    deadline_misses: int = 0

    def add_jitter(self, ns: int) -> None:
        if len(self.jitter_ns) < MAX_SAMPLES:
            self.jitter_ns.append(ns)

    def add_latency(self, ns: int) -> None:
        if len(self.latency_ns) < MAX_SAMPLES:
            self.latency_ns.append(ns)


class Periodic:
    """Wake at t0 + k * period on the monotonic clock; record |late wake|."""

    def __init__(self, t0_mono: float, period_s: float, timing: Timing) -> None:
        self.t0, self.period, self.timing = t0_mono, period_s, timing
        self.k = 0

    def wait_next(self, stop: Callable[[], bool]) -> int | None:
        """Sleep until step k's time; return k (or None when stopped). A wake
        more than one period late counts as a deadline miss and skips ahead."""
        target = self.t0 + self.k * self.period
        while True:
            now = time.monotonic()
            if stop():
                return None
            if now >= target:
                break
            time.sleep(min(target - now, 0.05))
        lateness = now - target
        self.timing.add_jitter(int(lateness * 1e9))
        if lateness > self.period:
            skipped = int(lateness / self.period)
            self.timing.deadline_misses += skipped
            self.k += skipped
        k = self.k
        self.k += 1
        return k


class ControlInbox:
    """The ``ctl/*`` messages a node acts on: start (realtime t = 0), ticks
    (lockstep clock of the leader), end/stop/estop (leave the loop). Subscribe
    before declaring the node alive."""

    def __init__(self, node: Node, stop: StopFlag) -> None:
        self.node, self.stop = node, stop
        self.start: Control | None = None
        self.tick = -1
        node.subscribe(node.keys.ctl_all, Control, self._on)

    def _on(self, msg: Control) -> None:  # under the mailbox lock
        if msg.command == "start" and self.start is None:
            self.start = msg
        elif msg.command == "tick":
            self.tick = max(self.tick, msg.k)
        elif msg.command in ("stop", "end", "estop"):
            self.stop.set(msg.command)

    def wait_for_start(self, timeout_s: float) -> float | None:
        """Realtime: t = 0 of the run on this process's monotonic clock (None
        when stopped or timed out). Hosts must share wall time (NTP) for this."""
        self.node.mailbox.wait_until(lambda: self.start is not None or self.stop(), timeout_s)
        if self.start is None:
            return None
        return time.monotonic() + (self.start.start_unix_ns - time.time_ns()) * 1e-9


def peak_rss_kb() -> int:
    """This process's own high-water RSS (VmHWM). getrusage's ru_maxrss is not
    used: after fork+exec it still holds the parent's RSS at fork time."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def publish_report(node: Node, robot: int, steps: int, timing: Timing | None = None,
                   **extra: Any) -> None:
    """The node's :class:`NodeReport`; ``extra``: further NodeReport fields."""
    c = node.counters
    timing = timing or Timing()
    node.publish(node.keys.report(node.role), lambda seq, stamp: NodeReport(
        WIRE_VERSION, node.sender, seq, stamp, role=node.role, robot=robot, sent=c.sent,
        dropped=c.dropped, late=c.late, invalid=c.invalid, steps=steps,
        latency_ns=timing.latency_ns, jitter_ns=timing.jitter_ns,
        deadline_misses=timing.deadline_misses, peak_rss_kb=peak_rss_kb(),
        received=dict(node.received), **extra,
    ))
