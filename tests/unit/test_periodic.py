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
        time.sleep(20e-6)  # a handler's work
        if not stop.is_set():
            box.post(again)

    box.post(again)
    return box, stop


def test_a_flood_never_holds_the_loop_past_its_period():
    box, flood_stop = _flooded()
    timing = Timing()
    ticker = Periodic(time.monotonic() - 5 * PERIOD_S, PERIOD_S, timing, box)  # already late
    steps: list[int] = []

    def loop() -> None:
        for _ in range(50):
            k = ticker.wait_next(lambda: False)
            steps.append(k)

    t = threading.Thread(target=loop, daemon=True)
    started = time.monotonic()
    t.start()
    t.join(5.0)
    flood_stop.set()
    took = time.monotonic() - started
    assert not t.is_alive(), f"the loop was held by the flood ({len(steps)} of 50 steps)"
    assert len(steps) == 50 and took < 50 * PERIOD_S * 5  # a few periods at most each


def test_the_longest_late_wake_is_kept_with_its_step():
    timing = Timing()
    ticker = Periodic(time.monotonic(), PERIOD_S, timing)
    assert ticker.wait_next(lambda: False) == 0
    time.sleep(0.05)  # the process off the CPU for 25 periods
    k = ticker.wait_next(lambda: False)
    assert k >= 25  # it skips ahead to the step now due
    assert 0.045 <= timing.longest_late_ns * 1e-9 < 0.5
    assert timing.longest_late_k == 1  # the step it was due for when it stalled
