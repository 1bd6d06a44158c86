"""The whole test suite in two phases: the README's test command, and CI's.

1. Every test that does not judge a run against the wall clock (``realtime``) and
   starts no fleet whose timing it claims (``e2e`` only when ``load_safe``: lockstep
   fleets, the bench's smoke run; tests/conftest.py), spread over the machine's cores
   by pytest-xdist: they are CPU-bound and independent of each other, and what they
   assert does not depend on the scheduler (on 2 cores they take about half the time
   they take one after the other, docs/layout.md).
2. The realtime tests and the other fleets (CAN bridges and their emulators judged on
   the wall clock, realtime runs, a cut link, probes that must act while a lockstep run
   of fixed length goes), one at a time: a realtime run judged beside another test would
   be judged on a scheduler that test starves (tests/realtime_clock.py), the fleets that
   no judge marks still run on the wall clock with timeouts that assume their cores, and
   a busy machine changes how fast a probe comes up against its fleet.

Both phases let Python keep the bytecode it compiles (``__pycache__``, which git
ignores) even where ``PYTHONDONTWRITEBYTECODE`` is set, as on the CI machine: there
every process compiled what it imported anew, pytest's assertion rewriting of every
test module included, in the controller and in each worker (collecting the suite took
5.3 s instead of 1.7 s), and every fleet's nodes the project's modules (~0.8 s of CPU a
run). The first process to import a module writes it; the others read it.

Arguments go to both phases (``-x``, ``-k word``, a test path, ``-q``); a ``-m EXPR``
of the caller narrows each phase's own selection::

    python tests/suite.py                      # everything
    python tests/suite.py tests/unit -x        # a part: the phase with nothing to run
                                               # says so and counts as passed
    python tests/suite.py -m "not slow"        # both phases, without the slow tests

Exit status: 0 when both phases passed, else the first failing phase's pytest status.
Ctrl-C reaches pytest from the terminal as well (one process group): this waits until
pytest has ended its tests' processes, runs no further phase, and exits 130; a SIGTERM
is passed on to pytest and its workers as a SIGINT (the same ending), then 143.
``python -m pytest`` alone still runs every test, one at a time.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys

NOTHING_COLLECTED = 5  # pytest's exit status when the selection is empty
MAX_WORKERS = 8  # past this, worker start-up outweighs what it spreads

PARALLEL = "not realtime and (not e2e or load_safe)"
SERIAL = "realtime or (e2e and not load_safe)"


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
             ["-m", select(PARALLEL), "-n", str(workers()), "--dist", "worksteal", *rest])
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


def pytest_env() -> dict[str, str]:
    """This environment, with bytecode written (the module's docstring)."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def children(pid: int) -> list[int]:
    """The processes ``pid`` started and that still run (Linux /proc; else none)."""
    out: list[int] = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
    except OSError:
        pass
    return out


def run_phase(args: list[str]) -> tuple[int, int | None]:
    """pytest with ``args``, to its end: (its status, 130 or 143 when interrupted).

    A SIGTERM reaches pytest and its pytest-xdist workers as a SIGINT each, as Ctrl-C
    from a terminal reaches the whole foreground job: the workers end their tests at
    once. A SIGINT to the controller alone left a worker's test running until execnet
    gave up on it (the suite took 6-8 s to end after a SIGTERM, against 1-2 s after
    Ctrl-C)."""
    proc = subprocess.Popen([sys.executable, "-m", "pytest", *args], env=pytest_env())
    interrupted: int | None = None

    def on_term(_signum: int, _frame: object) -> None:
        nonlocal interrupted
        interrupted = 143
        for pid in [proc.pid, *children(proc.pid)]:  # pytest ends its tests' processes
            try:
                os.kill(pid, signal.SIGINT)
            except ProcessLookupError:  # gone meanwhile
                pass

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
