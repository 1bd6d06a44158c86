"""The realtime loop's timer (deploy/runtime/node_runtime.py::Periodic): messages that keep
arriving faster than their handlers run never hold a loop past its period, and a late
wake is kept as the loop's longest stall with the step it was due for."""

from __future__ import annotations

import threading
import time

from deploy.runtime.node_runtime import Periodic, Timing
from deploy.runtime.transport import Mailbox

PERIOD_S = 0.002


def _flooded() -> tuple[Mailbox, threading.Event]:
    """A mailbox whose every handled message brings the next one (a flood, a backlog
    that never empties): before, a late loop drained it until it was empty, i.e. never."""
    box, stop = Mailbox(), threading.Event()

    def again(_item: object) -> None:
        end = time.thread_time() + 20e-6  # a handler's work: 20 us of CPU
        while time.thread_time() < end:
            pass
        if not stop.is_set():
            box.post(again)

    box.post(again)
    return box, stop


def test_a_flood_never_holds_the_loop_past_its_period():
    """Each wait handles the flood for one period of the wall clock at most. Judged on the
    CPU time the loop's own thread spent (time.thread_time), not the wall clock: this test
    runs beside others at a tenth of a process's CPU weight (tests/suite.py), where a
    starved scheduler stretched 50 such waits to 0.71 s of wall time against 0.5 s; a wait
    that drained while the flood lasted would take the thread's CPU for as long as 5 s."""
    box, flood_stop = _flooded()
    timing = Timing()
    ticker = Periodic(time.monotonic() - 5 * PERIOD_S, PERIOD_S, timing, box)  # already late
    steps: list[int] = []
    cpu: list[float] = []

    def loop() -> None:
        start = time.thread_time()
        for _ in range(50):
            k = ticker.wait_next(lambda: False)
            steps.append(k)
        cpu.append(time.thread_time() - start)

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    t.join(60.0)  # a deadlock guard only: a loop held by the flood never ends
    flood_stop.set()
    assert not t.is_alive(), f"the loop was held by the flood ({len(steps)} of 50 steps)"
    assert len(steps) == 50 and cpu[0] < 50 * PERIOD_S * 5  # a few periods at most each


def test_the_longest_late_wake_is_kept_with_its_step():
    timing = Timing()
    ticker = Periodic(time.monotonic(), PERIOD_S, timing)
    assert ticker.wait_next(lambda: False) == 0
    off = time.monotonic()
    time.sleep(0.05)  # the process off the CPU for 25 periods
    k = ticker.wait_next(lambda: False)
    off = time.monotonic() - off  # as long as this machine took (starved: longer)
    assert k >= 25  # it skips ahead to the step now due
    assert 0.045 <= timing.longest_late_ns * 1e-9 <= off
    assert timing.longest_late_k == 1  # the step it was due for when it stalled
