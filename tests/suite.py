"""The whole test suite in two phases: the README's test command, and CI's.

1. Every test that neither starts a fleet of processes (``e2e``) nor judges a run
   against the wall clock (``realtime``), spread over the machine's cores by
   pytest-xdist: they are CPU-bound and independent of each other, and on 2 cores
   they take about half the time they take one after the other (docs/layout.md).
2. The fleets and the realtime tests, one at a time, as before: a realtime run judged
   beside another test would be judged on a scheduler that test starves
   (tests/realtime_clock.py), and many fleet tests that no judge marks still run on
   the realtime clock (CAN bridges and their emulators, fault runs, a cut link) with
   timeouts that assume their cores. Not tried in parallel: unmeasured risk of flakes.

Arguments go to both phases (``-x``, ``-k word``, a test path, ``-q``)::

    python tests/suite.py                      # everything
    python tests/suite.py tests/unit -x        # a part: the phase with nothing to run
                                               # says so and counts as passed

Exit status: 0 when both phases passed, else the first failing phase's pytest status.
``python -m pytest`` alone still runs every test, one at a time.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

NOTHING_COLLECTED = 5  # pytest's exit status when the selection is empty
MAX_WORKERS = 8  # past this, worker start-up outweighs what it spreads

PARALLEL = "not e2e and not realtime"
SERIAL = "e2e or realtime"


def workers() -> int:
    """One pytest worker per core this process may use, at most MAX_WORKERS."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_WORKERS))


def phases(args: list[str], spread: bool = True) -> list[tuple[str, list[str]]]:
    """(name, pytest arguments) of each phase, in order; ``spread``: pytest-xdist is
    there to spread the first phase (else it runs one test at a time, and says so)."""
    first = (f"{PARALLEL}, {workers()} workers", ["-m", PARALLEL, "-n", str(workers()), *args])
    if not spread:
        first = (f"{PARALLEL}, one at a time (pytest-xdist is not installed: "
                 "pip install '.[test]')", ["-m", PARALLEL, *args])
    return [first, (f"{SERIAL}, one at a time", ["-m", SERIAL, *args])]


def combined(statuses: list[int]) -> int:
    """The suite's exit status from its phases' pytest statuses."""
    failed = [s for s in statuses if s not in (0, NOTHING_COLLECTED)]
    if failed:
        return failed[0]
    return NOTHING_COLLECTED if all(s == NOTHING_COLLECTED for s in statuses) else 0


def main(argv: list[str]) -> int:
    statuses = []
    for name, args in phases(argv, importlib.util.find_spec("xdist") is not None):
        print(f"== tests: {name}", flush=True)
        try:  # Ctrl-C reaches pytest too (one process group); call() ends it by pid
            status = subprocess.call([sys.executable, "-m", "pytest", *args])
        except KeyboardInterrupt:
            return 130
        statuses.append(status)
        if status not in (0, NOTHING_COLLECTED) and ("-x" in argv or "--exitfirst" in argv):
            break
    return combined(statuses)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
