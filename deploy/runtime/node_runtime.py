"""What every node process shares: stop on SIGTERM/SIGINT, die with the
launcher, the realtime start barrier, a periodic timer that measures jitter,
and the end-of-run report."""

from __future__ import annotations

import heapq
import itertools
import os
import resource
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from deploy.contract.wire import MAX_REPORT_SAMPLES, WIRE_VERSION, Control, NodeReport
from deploy.runtime.fault_model import FaultModel
from deploy.runtime.step_costs import StepCosts
from deploy.runtime.transport import Mailbox, Node

START_LEAD_S = 0.3  # realtime: t = 0 this long after ``start`` is sent

CLOCKS = ("lockstep", "realtime")
MAX_SAMPLES = MAX_REPORT_SAMPLES  # timing samples kept per node (200 s at 1 kHz)


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
            node.mailbox.wake()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


@dataclass
class Timing:
    """Realtime loop figures of one node, in nanoseconds."""

    jitter_ns: list[int] = field(default_factory=list)
    latency_ns: list[int] = field(default_factory=list)
    deadline_misses: int = 0
    # the loop's longest late wake (a stall: the process off the CPU, or a wait that
    # held it) and the step it was due for; kept whole, whatever MAX_SAMPLES dropped
    longest_late_ns: int = 0
    longest_late_k: int = -1

    def add_jitter(self, ns: int) -> None:
        if len(self.jitter_ns) < MAX_SAMPLES:
            self.jitter_ns.append(ns)

    def note_late(self, ns: int, k: int) -> None:
        if ns > self.longest_late_ns:
            self.longest_late_ns, self.longest_late_k = ns, k

    def add_latency(self, ns: int) -> None:
        if len(self.latency_ns) < MAX_SAMPLES:
            self.latency_ns.append(ns)


class Periodic:
    """Wake at t0 + k * period on the monotonic clock; record |late wake|.

    ``mailbox``: the node's; the wait until step k handles what arrives meanwhile
    (a command is acted on as it comes, not at the next period)."""

    def __init__(self, t0_mono: float, period_s: float, timing: Timing,
                 mailbox: Mailbox | None = None) -> None:
        self.t0, self.period, self.timing = t0_mono, period_s, timing
        self.mailbox = mailbox
        self.k = 0

    def wait_next(self, stop: Callable[[], bool]) -> int | None:
        """Wait until step k's time; return k (or None when stopped). A wake
        more than one period late counts as a deadline miss and skips ahead."""
        target = self.t0 + self.k * self.period
        box = self.mailbox
        now = time.monotonic()
        if now < target:
            if box is not None:
                box.sleep_until(target, stop)
            else:
                while now < target and not stop():
                    time.sleep(min(target - now, 0.05))
                    now = time.monotonic()
            now = time.monotonic()
        if stop():
            return None
        if box is not None:
            # what arrived meanwhile, before the step: a plant acts on the commands that
            # came in the period (they did not wake it). At most one period of it:
            # messages that keep coming faster than their handlers run (a flood, a
            # backlog) never hold the loop. (A plant that ran late every period, the
            # paper at 1 kHz on 2 cores, never waited, so once never heard a command)
            box.drain(until=now + self.period)
        lateness = now - target
        self.timing.add_jitter(int(lateness * 1e9))
        self.timing.note_late(int(lateness * 1e9), self.k)
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

    def __init__(self, node: Node, stop: StopFlag,
                 on_genuine: Callable[[Control], None] | None = None) -> None:
        """``on_genuine``: called with every control message the node took (a CAN
        bridge e-stops its drives on ``estop``); nothing else sees ``ctl/*``. A node
        with keys takes control only from the plant or the launcher, authenticated
        by its envelope (deploy/contract/keyring.py: refused and counted in the
        transport, before it is decoded); one without keys (started by hand) takes any."""
        self.node, self.stop = node, stop
        self.start: Control | None = None
        self.tick = -1
        self.on_genuine = on_genuine
        node.subscribe(node.keys.ctl_all, Control, self._on)

    def _on(self, msg: Control) -> None:  # on the node's thread
        if self.on_genuine is not None:
            self.on_genuine(msg)
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


class FaultGate:
    """Realtime faults on the edges a node receives on: each message is judged
    as it arrives (by its step index, once per edge and step), and a delayed one
    is handed over later: a timer thread posts it to the node's mailbox, so its
    handler runs on the node's thread, as without faults."""

    KEEP = 256  # decisions remembered per edge

    def __init__(self, model: FaultModel, mailbox: Mailbox) -> None:
        self.model, self.mailbox = model, mailbox
        self._decided: dict[str, dict[int, bool]] = {}
        self._heap: list[tuple[float, int, Callable[[Any], None], Any]] = []
        self._order = itertools.count()
        self._wake = threading.Condition()
        self._closed = False
        self._thread: threading.Thread | None = None

    def wrap(self, src: str, dst: str, on_message: Callable[[Any], None]
             ) -> Callable[[Any], None]:
        edge = self.model.edge(src, dst)
        if edge is None:
            return on_message
        decided = self._decided.setdefault(edge.name, {})

        def gated(msg: Any) -> None:  # on the node's thread
            k = msg.k
            ok = decided.get(k)
            if ok is None:
                ok = self.model.judge(edge, k)
                decided[k] = ok
                if len(decided) > self.KEEP:  # the first kept is the oldest step
                    del decided[next(iter(decided))]
            if not ok:
                return
            if edge.spec.delay_s > 0.0:
                self._later(time.monotonic() + edge.spec.delay_s, on_message, msg)
            else:
                on_message(msg)
        return gated

    def _later(self, due: float, fn: Callable[[Any], None], msg: Any) -> None:
        with self._wake:
            heapq.heappush(self._heap, (due, next(self._order), fn, msg))
            if self._thread is None:
                self._thread = threading.Thread(target=self._deliver, daemon=True,
                                                name="fault-delay")
                self._thread.start()
            self._wake.notify()

    def _deliver(self) -> None:
        while True:
            with self._wake:
                while not self._closed and (not self._heap or self._heap[0][0] > time.monotonic()):
                    timeout = self._heap[0][0] - time.monotonic() if self._heap else None
                    self._wake.wait(timeout)
                if self._closed:
                    return
                _, _, fn, msg = heapq.heappop(self._heap)
            self.mailbox.post(fn, msg)

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify()


def process_age_s() -> float | None:
    """How long ago this process started (the kernel's start time, to its clock tick;
    a forked node's is its fork), s; None where /proc cannot say."""
    try:
        with open("/proc/self/stat") as f:
            stat = f.read()
        start_ticks = int(stat[stat.rfind(")") + 2:].split()[19])
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


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


# how long a node stays after its report for the launcher to say it holds it (within
# the launcher's wait for its nodes to exit, deploy/run/supervisor.py, 20 s, after the
# plant's linger of up to 5 s)
REPORT_FILED_TIMEOUT_S = 12.0


class LoopClock:
    """The CPU (every thread of the process) and wall time a node's run loop took."""

    def __init__(self) -> None:
        self.cpu_s = self.loop_s = 0.0
        self._cpu0 = self._wall0 = 0.0
        self.costs: StepCosts | None = None  # the node's (counted from the loop's start)

    def __enter__(self) -> LoopClock:
        self._cpu0, self._wall0 = _process_cpu_s(), time.perf_counter()
        if self.costs is not None:  # the loop's own parts, as its CPU time
            self.costs.ns[:] = [0] * len(self.costs.ns)
        return self

    def __exit__(self, *_exc: object) -> None:
        self.cpu_s = _process_cpu_s() - self._cpu0
        self.loop_s = time.perf_counter() - self._wall0


def _process_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


LOOP = LoopClock()  # this process's run loop (a node process runs one)


def publish_report(node: Node, robot: int, steps: int, timing: Timing | None = None,
                   **extra: Any) -> None:
    """The node's :class:`NodeReport`, then wait until the launcher holds it (see
    ``Node.wait_filed``); ``extra``: further NodeReport fields."""
    # every data frame out first (held for a receiver that reads behind): the report must
    # not reach the launcher before the telemetry and state rows it follows
    node.flush_data()
    if node.datagrams is not None and node.datagrams.hellos_refused:
        node.refused["connection: hello does not check"] = node.datagrams.hellos_refused
    c = node.counters
    timing = timing or Timing()
    node.publish(node.keys.report(node.role), lambda seq, stamp: NodeReport(
        WIRE_VERSION, node.sender, seq, stamp, role=node.role, robot=robot, sent=c.sent,
        dropped=c.dropped, late=c.late, invalid=c.invalid, steps=steps, nonfinite=c.nonfinite,
        latency_ns=timing.latency_ns, jitter_ns=timing.jitter_ns,
        deadline_misses=timing.deadline_misses, peak_rss_kb=peak_rss_kb(),
        longest_late_ns=timing.longest_late_ns, longest_late_k=timing.longest_late_k,
        received=dict(node.received), refused=dict(node.refused), zid=node.zid,
        peers=node.linked_peers(), cpu_s=LOOP.cpu_s, loop_s=LOOP.loop_s,
        step_costs_ns=node.costs.totals(), **extra,
    ))
    if not node.wait_filed(REPORT_FILED_TIMEOUT_S):
        print(f"{node.role}: the launcher did not say it holds this node's report within "
              f"{REPORT_FILED_TIMEOUT_S:.0f} s", file=sys.stderr, flush=True)
