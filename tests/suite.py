"""The whole test suite in two phases: the README's test command, and CI's.

1. Every test that does not judge a run against the wall clock (``realtime``) and
   starts no fleet whose timing it claims (``e2e`` only when ``load_safe``: lockstep
   fleets, the bench's smoke run; the markers are declared by each test module and
   explained in tests/conftest.py), spread over the machine's cores
   by pytest-xdist: they are CPU-bound and independent of each other, and what they
   assert does not depend on the scheduler (on 2 cores they take about half the time
   they take one after the other, docs/layout.md).
2. The realtime tests and the other fleets (CAN bridges and their emulators judged on
   the wall clock, realtime runs, a cut link, probes that must act while a lockstep run
   of fixed length goes), one at a time: a realtime run judged beside another test would
   be judged on a scheduler that test starves (tests/realtime_clock.py), the fleets that
   no judge marks still run on the wall clock with timeouts that assume their cores, and
   a busy machine changes how fast a probe comes up against its fleet.

The two phases run **side by side** where a CPU group can be made (Linux, root or a
delegated cgroup; tests/background_cpu.py): the second in the foreground, one test at a
time as before, the first in a group whose CPU weight is a tenth of one ordinary
process's. The second phase kept about one of two cores busy (its time is its runs'
simulated seconds), and its processes get a core whenever they want one: its realtime
nodes run under SCHED_FIFO, its other processes outweigh the group ten to one. The
first phase takes what is left, and its own tests hold on a starved scheduler (that is
what puts them in it). A realtime test counts the group's CPU time apart from the other
programs' (tests/realtime_clock.py). On the 2-core CI machine the suite took ~300 s one
phase after the other and ~197 s side by side (docs/layout.md). The first phase's report
is held in a file and printed when it ends; ``SUITE_SIDE_BY_SIDE=0`` runs the phases one
after the other, and so does a host where no group can be made.

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

Exit status: 0 when both phases passed, else the first failing phase's pytest status
(with ``-x``, a phase that fails ends the other). Ctrl-C reaches pytest from the
terminal as well (one process group): this waits until pytest has ended its tests'
processes, runs no further phase, and exits 130; a SIGTERM is passed on to each pytest
and its workers as a SIGINT (the same ending), then 143.
``pytest`` alone still runs every test, one at a time; this file is only the fast path.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from typing import IO

from background_cpu import USAGE_ENV, BackgroundGroup

NOTHING_COLLECTED = 5  # pytest's exit status when the selection is empty
MAX_WORKERS = 8  # past this, worker start-up outweighs what it spreads

PARALLEL = "not realtime and (not e2e or load_safe)"
SERIAL = "realtime or (e2e and not load_safe)"
SIDE_BY_SIDE = "SUITE_SIDE_BY_SIDE"  # "0": the phases one after the other


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
    """This environment, with bytecode written (the module's docstring), without the
    suite's own switch (the fleets' nodes would inherit it)."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.pop(SIDE_BY_SIDE, None)
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


def _interrupt(procs: list[subprocess.Popen]) -> None:
    """SIGINT to each pytest and its workers (what Ctrl-C from a terminal does)."""
    for proc in procs:
        for pid in [proc.pid, *children(proc.pid)]:  # pytest ends its tests' processes
            try:
                os.kill(pid, signal.SIGINT)
            except ProcessLookupError:  # gone meanwhile
                pass


@dataclass
class Phase:
    """One pytest run of the suite: its arguments, environment, where its output goes
    (None: this terminal) and the CPU group it runs in (None: this process's)."""

    args: list[str]
    env: dict[str, str]
    log: IO[str] | None = None
    group: BackgroundGroup | None = None


def run_phases(runs: list[Phase], on_end: Callable[[int, int], bool] = lambda _i, _s: False,
               ) -> tuple[list[int], int | None]:
    """pytest for each phase at once, each to its end: (their statuses, 130 or 143 when
    interrupted). ``on_end(i, status)`` as phase ``i`` ends: True ends the others (``-x``).

    A SIGTERM reaches each pytest and its pytest-xdist workers as a SIGINT each, as
    Ctrl-C from a terminal reaches the whole foreground job: the workers end their tests
    at once. A SIGINT to the controller alone left a worker's test running until execnet
    gave up on it (the suite took 6-8 s to end after a SIGTERM, against 1-2 s after
    Ctrl-C)."""
    interrupted: int | None = None
    procs: list[subprocess.Popen] = []

    def on_term(_signum: int, _frame: object) -> None:
        nonlocal interrupted
        interrupted = 143
        _interrupt(procs)

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        for run in runs:
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "pytest", *run.args], env=run.env, stdout=run.log,
                stderr=None if run.log is None else subprocess.STDOUT))
            if run.group is not None:  # before its workers start: they follow it there
                try:
                    run.group.add(procs[-1].pid)
                except OSError as exc:  # it runs, at the weight of any other process
                    print(f"== tests: could not move pytest {procs[-1].pid} into its CPU "
                          f"group ({exc}): that phase runs at ordinary weight", flush=True)
        statuses: list[int | None] = [None] * len(procs)
        while None in statuses:
            try:
                for i, proc in enumerate(procs):
                    if statuses[i] is None and proc.poll() is not None:
                        statuses[i] = proc.returncode
                        if on_end(i, proc.returncode):
                            _interrupt([p for p in procs if p.poll() is None])
                if None in statuses:
                    wait_any()
            except KeyboardInterrupt:  # pytest heard it too: wait for it to end its own
                interrupted = interrupted or 130
        return [int(s) for s in statuses], interrupted
    finally:
        signal.signal(signal.SIGTERM, previous)


def wait_any() -> None:
    """Until a child of this process has ended, left for its ``Popen`` to reap (the
    suite's children are its phases' pytest processes)."""
    try:
        os.waitid(os.P_ALL, 0, os.WEXITED | os.WNOWAIT)
    except ChildProcessError:
        pass


def run_one_after_the_other(named: list[tuple[str, list[str]]], argv: list[str]) -> int:
    statuses = []
    for name, args in named:
        print(f"== tests: {name}", flush=True)
        (status,), interrupted = run_phases([Phase(args, pytest_env())])
        if interrupted is not None:
            return interrupted
        statuses.append(status)
        if status not in (0, NOTHING_COLLECTED) and ("-x" in argv or "--exitfirst" in argv):
            break
    return combined(statuses)


def run_side_by_side(named: list[tuple[str, list[str]]], argv: list[str],
                     group: BackgroundGroup) -> int:
    """The first phase in ``group`` (its output printed as it ends), the second in the
    foreground, at the same time (tests/background_cpu.py)."""
    (first, first_args), (second, second_args) = named
    print(f"== tests: {first}, beside the next phase at a tenth of a process's CPU weight "
          "(its report follows when it ends)", flush=True)
    print(f"== tests: {second}", flush=True)
    stop_early = "-x" in argv or "--exitfirst" in argv

    with tempfile.TemporaryFile("w+") as log:
        def on_end(i: int, status: int) -> bool:
            if i == 0:
                log.seek(0)
                print(f"\n== tests: {first}: ended\n{log.read()}", end="", flush=True)
            return stop_early and status not in (0, NOTHING_COLLECTED)

        try:
            statuses, interrupted = run_phases(
                [Phase(first_args, pytest_env(), log, group),
                 Phase(second_args, {**pytest_env(), USAGE_ENV: str(group.usage)})], on_end)
        finally:
            group.remove()
    return interrupted if interrupted is not None else combined(statuses)


def main(argv: list[str]) -> int:
    named = phases(argv, importlib.util.find_spec("xdist") is not None)
    group = None
    if os.environ.get(SIDE_BY_SIDE, "1") != "0":
        group = BackgroundGroup.make(f"omnifleet-suite-{os.getpid()}")
    if group is None:
        return run_one_after_the_other(named, argv)
    return run_side_by_side(named, argv, group)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
