"""A realtime node's start-up heap kept out of the garbage collector's passes.

Every node of a fleet imports the same modules and builds the same kind of tables, so
every node reaches its first collection of generation 1 at about the same moment: in
the first steps of the run. Each pass walks what start-up left in the young
generations (~1 ms of CPU an agent), and 30 agents at 100 Hz on 2 cores ran those
passes within the same ~20 ms: a burst of ~30 ms of CPU that made samples late and
counted as deadline misses in the run's first 0.1 s (docs/bench-history.md). Collecting once
and then freezing what is left (``gc.freeze``: the objects alive now move to a
permanent generation that no later pass walks) before the loop starts takes that work
out of the run: collections of generation 1 longer than 0.5 ms in such a run went from
31 (one per agent and the plant) to 1. What start-up built stays alive for the whole
process anyway (modules, tables, the scenario); objects made during the run are
collected as before.

Only the realtime clock for a node: on the lockstep clock no deadline is missed, and the
paper's lockstep run was no faster with it (3 pairs, within their spread). The launcher
freezes its own for the distributed run, on either clock (:func:`frozen_heap`): it hears
and records the whole run on a heap of everything it imported, and the collector's full
passes over that heap took 0.32 s of CPU in README command 1 (25 passes), 0.07 s frozen
(docs/bench-history.md).
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager


def freeze_startup_heap() -> None:
    """Collect what start-up no longer holds, then keep the rest out of every later
    collection (call once, right before the node's loop)."""
    gc.collect()
    gc.freeze()


@contextmanager
def frozen_heap() -> Iterator[None]:
    """:func:`freeze_startup_heap` for the work inside, the heap given back to the
    collector after it (the launcher's run: its caller may be a longer-lived process)."""
    freeze_startup_heap()
    try:
        yield
    finally:
        gc.unfreeze()
