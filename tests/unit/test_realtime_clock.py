"""The judge of realtime runs (tests/realtime_clock.py): what the clock allowed decides
whether a run's claims are judged, retried once, or skipped with the measurement."""

from __future__ import annotations

import pytest
from realtime_clock import judged, starved


def _metrics(jitter_p99_ms: float | None, rate_hz: float = 200.0) -> dict:
    return {"control_rate_hz": rate_hz, "deadline_misses": 7,
            "jitter_ms": None if jitter_p99_ms is None else {"p99": jitter_p99_ms}}


def _runs(*jitters):
    calls = []

    def run():
        calls.append(1)
        return _metrics(jitters[len(calls) - 1])
    return run, calls


def test_a_run_that_kept_its_period_is_judged_at_once():
    run, calls = _runs(4.9)
    assert judged(run, lambda m: m, "x")["jitter_ms"]["p99"] == 4.9 and len(calls) == 1


def test_a_starved_run_is_retried_once_and_the_retry_judged():
    run, calls = _runs(9.0, 3.0)
    assert judged(run, lambda m: m, "x")["jitter_ms"]["p99"] == 3.0 and len(calls) == 2


def test_starved_twice_is_skipped_naming_both_measurements():
    run, calls = _runs(9.0, 8.0)
    with pytest.raises(pytest.skip.Exception, match=r"9\.0 ms.*then.*8\.0 ms"):
        judged(run, lambda m: m, "x")
    assert len(calls) == 2


def test_starved_far_beyond_the_period_is_skipped_without_a_retry():
    run, calls = _runs(63.0, 1.0)
    with pytest.raises(pytest.skip.Exception, match=r"63\.0 ms.*12\.6 periods"):
        judged(run, lambda m: m, "x")
    assert len(calls) == 1


def test_a_run_whose_jitter_never_arrived_is_retried():
    assert "did not arrive" in starved(_metrics(None))
    run, calls = _runs(None, 2.0)
    assert judged(run, lambda m: m, "x")["jitter_ms"]["p99"] == 2.0 and len(calls) == 2
