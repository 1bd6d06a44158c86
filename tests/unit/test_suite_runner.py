"""The two-phase suite (tests/suite.py): every test runs in exactly one phase, and the
suite's status is a failing phase's."""

from __future__ import annotations

import itertools

import pytest
from suite import NOTHING_COLLECTED, PARALLEL, SERIAL, combined, phases, split_markers

MARKERS = ("e2e", "slow", "realtime", "root", "load_safe")  # pyproject.toml declares them


def selects(expr: str, marked: set[str]) -> bool:
    """Whether ``-m expr`` selects a test carrying ``marked``: the phases' expressions
    are marker names joined by and / or / not and brackets, Python's own grammar."""
    return bool(eval(expr, {"__builtins__": {}}, {m: m in marked for m in MARKERS}))


@pytest.mark.parametrize("marked", [set(c) for n in range(len(MARKERS) + 1)
                                    for c in itertools.combinations(MARKERS, n)])
def test_every_test_runs_in_exactly_one_phase(marked: set[str]) -> None:
    chosen = [selects(expr, marked) for expr in (PARALLEL, SERIAL)]
    assert sum(chosen) == 1
    if "realtime" in marked or ("e2e" in marked and "load_safe" not in marked):
        assert chosen == [False, True]  # never beside another test


def test_the_parallel_phase_spreads_and_the_serial_one_does_not() -> None:
    (_, parallel), (_, serial) = phases(["-x"])
    assert "-n" in parallel and int(parallel[parallel.index("-n") + 1]) >= 1
    assert "-n" not in serial
    assert parallel[-1] == serial[-1] == "-x"  # the caller's arguments go to both


def test_without_pytest_xdist_the_first_phase_runs_one_at_a_time() -> None:
    (name, parallel), (_, serial) = phases(["-x"], spread=False)
    assert "-n" not in parallel and "not installed" in name
    assert parallel[:2] == ["-m", PARALLEL] and serial[:2] == ["-m", SERIAL]


@pytest.mark.parametrize("args", [["-m", "not slow", "-x"], ["-mnot slow", "-x"],
                                  ["-m", "slow", "-m", "not slow", "-x"]])
def test_a_marker_expression_of_the_caller_narrows_each_phase(args: list[str]) -> None:
    assert split_markers(args) == ("not slow", ["-x"])
    (_, parallel), (_, serial) = phases(args)
    assert parallel.count("-m") == serial.count("-m") == 1  # not two: pytest keeps the last
    assert parallel[parallel.index("-m") + 1] == f"({PARALLEL}) and (not slow)"
    assert serial[serial.index("-m") + 1] == f"({SERIAL}) and (not slow)"
    assert parallel[-1] == serial[-1] == "-x"


@pytest.mark.parametrize(("statuses", "expected"), [
    ([0, 0], 0),
    ([0, NOTHING_COLLECTED], 0),  # a path with no fleet test in it
    ([NOTHING_COLLECTED, 0], 0),
    ([NOTHING_COLLECTED, NOTHING_COLLECTED], NOTHING_COLLECTED),
    ([1, 0], 1),
    ([0, 1], 1),
    ([2, 1], 2),  # interrupted first: that is said
    ([NOTHING_COLLECTED, 1], 1),
])
def test_the_suite_fails_when_a_phase_fails(statuses: list[int], expected: int) -> None:
    assert combined(statuses) == expected
