"""Which selections of tests may run spread over the cores (pytest-xdist) by default.

A selection (``pytest -m EXPR``) spreads when no test it can select is one the suite runs
one at a time (tests/suite.py: ``realtime``, or ``e2e`` without ``load_safe``), judged
from the markers alone, before collection: every ``e2e`` and every ``realtime`` test is
also ``slow`` (tests/conftest.py marks them so), so ``-m "not slow"`` and the quick lane
``-m "not e2e and not slow"`` spread, and ``-m "not e2e"`` (a realtime integration test
is neither) does not. ``-n N`` (``-n 0``: one at a time) is the caller's choice and
always kept.
"""

from __future__ import annotations

import itertools

from _pytest.mark.expression import Expression  # how pytest evaluates -m

MARKERS = ("e2e", "slow", "realtime", "root", "load_safe")


def possible(marked: set[str]) -> bool:
    """Whether a test can carry exactly these markers (tests/conftest.py)."""
    return not ({"e2e", "realtime"} & marked) or "slow" in marked


def one_at_a_time(marked: set[str]) -> bool:
    """Whether the suite runs a test with these markers alone (tests/suite.py, SERIAL)."""
    return "realtime" in marked or ("e2e" in marked and "load_safe" not in marked)


def spreads(markexpr: str) -> bool:
    """Whether ``-m markexpr`` selects no test that must run alone ("": every test)."""
    if not markexpr.strip():
        return False
    expr = Expression.compile(markexpr)
    for n in range(len(MARKERS) + 1):
        for combo in itertools.combinations(MARKERS, n):
            marked = set(combo)
            if possible(marked) and one_at_a_time(marked) and expr.evaluate(
                    lambda name, marked=marked, **_: name in marked):
                return False
    return True
