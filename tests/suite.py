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

Arguments go to both phases (``-x``, ``-k word``, a test path, ``-q``); a ``-m EXPR``
of the caller narrows each phase's own selection::

    python tests/suite.py                      # everything
    python tests/suite.py tests/unit -x        # a part: the phase with nothing to run
                                               # says so and counts as passed
    python tests/suite.py -m "not slow"        # both phases, without the slow tests

Exit status: 0 when both phases passed, else the first failing phase's pytest status.
Ctrl-C reaches pytest from the terminal as well (one process group): this waits until
pytest has ended its tests' processes, runs no further phase, and exits 130; a SIGTERM
is passed on to pytest as a SIGINT (the same ending), then 143. ``python -m pytest``
alone still runs every test, one at a time.
"""

from __future__ import annotations

import importlib.util
import os
import signal
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


def split_markers(args: list[str]) -> tuple[str | None, list[str]]:
    """The caller's ``-m EXPR`` (or ``-mEXPR``; the last one, as pytest takes it) and the
    other arguments."""
    chosen, rest, i = None, [], 0
    while i < len(args):
        a = args[i]
        if a == "-m" and i + 1 < len(args):
            chosen, i = args[i + 1], i + 2
            continue
        if a.startswith("-m") and len(a) > 2 and not a.startswith("--"):
            chosen = a[2:].removeprefix("=")
        else:
            rest.append(a)
        i += 1
    return chosen, rest


def phases(args: list[str], spread: bool = True) -> list[tuple[str, list[str]]]:
    """(name, pytest arguments) of each phase, in order; ``spread``: pytest-xdist is
    there to spread the first phase (else it runs one test at a time, and says so)."""
    theirs, rest = split_markers(args)

    def select(ours: str) -> str:
        return ours if theirs is None else f"({ours}) and ({theirs})"

    first = (f"{select(PARALLEL)}, {workers()} workers",
             ["-m", select(PARALLEL), "-n", str(workers()), *rest])
    if not spread:
        first = (f"{select(PARALLEL)}, one at a time (pytest-xdist is not installed: "
                 "pip install '.[test]')", ["-m", select(PARALLEL), *rest])
    return [first, (f"{select(SERIAL)}, one at a time", ["-m", select(SERIAL), *rest])]


def combined(statuses: list[int]) -> int:
    """The suite's exit status from its phases' pytest statuses."""
    failed = [s for s in statuses if s not in (0, NOTHING_COLLECTED)]
    if failed:
        return failed[0]
    return NOTHING_COLLECTED if all(s == NOTHING_COLLECTED for s in statuses) else 0


def run_phase(args: list[str]) -> tuple[int, int | None]:
    """pytest with ``args``, to its end: (its status, 130 or 143 when interrupted)."""
    proc = subprocess.Popen([sys.executable, "-m", "pytest", *args])
    interrupted: int | None = None

    def on_term(_signum: int, _frame: object) -> None:
        nonlocal interrupted
        interrupted = 143
        proc.send_signal(signal.SIGINT)  # pytest ends its tests' processes as on Ctrl-C

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        while True:
            try:
                return proc.wait(), interrupted
            except KeyboardInterrupt:  # pytest heard it too: wait for it to end its own
                interrupted = interrupted or 130
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str]) -> int:
    statuses = []
    for name, args in phases(argv, importlib.util.find_spec("xdist") is not None):
        print(f"== tests: {name}", flush=True)
        status, interrupted = run_phase(args)
        if interrupted is not None:
            return interrupted
        statuses.append(status)
        if status not in (0, NOTHING_COLLECTED) and ("-x" in argv or "--exitfirst" in argv):
            break
    return combined(statuses)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
