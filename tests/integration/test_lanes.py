"""`pytest -m EXPR` spreads over the cores by itself only for a selection with no test that
must run alone (tests/lanes.py, tests/conftest.py), and the markers it reasons from hold
on the real collection: every e2e and every realtime test is also slow."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from suite import NOTHING_COLLECTED, workers

REPO = Path(__file__).resolve().parents[2]


def pytest_run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=300)


def test_every_e2e_and_realtime_test_is_slow() -> None:
    r = pytest_run("--collect-only", "-q", "-m", "(e2e or realtime) and not slow")
    assert r.returncode == NOTHING_COLLECTED, r.stdout[-2000:]


@pytest.mark.parametrize(("args", "spread"), [
    (["-m", "not e2e and not slow"], True),
    (["-m", "not e2e and not slow", "-n", "0"], False),  # the caller's choice
    (["-m", "not e2e"], False),  # may select a realtime test
])
def test_the_quick_lane_spreads_and_a_selection_that_may_hold_a_realtime_test_does_not(
        args: list[str], spread: bool) -> None:
    r = pytest_run(*args, "tests/unit/test_mecanum.py")
    assert r.returncode == 0, r.stdout[-2000:]
    spread = spread and workers() > 1  # one core (taskset -c 0): nothing to spread over
    assert ("spread over" in r.stdout) is spread and ("workers [" in r.stdout) is spread
