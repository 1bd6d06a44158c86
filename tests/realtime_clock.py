"""Realtime tests judge what the clock allowed.

A realtime run's claims (settling, no contact, a zero torque within the command
timeout) hold for a fleet whose loops keep their periods. On a shared or slow
2-core machine the scheduler can starve them: every node wakes tens of
milliseconds late, and the run measures the machine, not the code. Such a run is
recognised from its own figures (the loop jitter every node reports: a p99 beyond
one control period means the loops did not keep their periods), run once more,
and, starved twice, the test is skipped with both measurements as the reason,
never failed. A run starved beyond ``HOPELESS`` periods is not run again: on this
machine every such run was starved again on its retry (CAN fleet 63 -> 58 ms and
29 -> 23 ms at p99 against 5 ms), and each retry cost ~30 s of the suite. A run that
the clock allowed is judged in full.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import pytest

T = TypeVar("T")
HOPELESS = 4.0  # loop jitter p99 in control periods beyond which a retry is not worth it


def _jitter_periods(metrics: dict[str, Any]) -> float | None:
    jitter = (metrics.get("jitter_ms") or {}).get("p99")
    return None if jitter is None else jitter * float(metrics["control_rate_hz"]) / 1e3


def starved(metrics: dict[str, Any]) -> str | None:
    """Why the clock did not allow this realtime run, or None when it did."""
    period_ms = 1e3 / float(metrics["control_rate_hz"])
    jitter = (metrics.get("jitter_ms") or {}).get("p99")
    if jitter is None:
        return "no loop jitter was reported (a node's report did not arrive)"
    if jitter > period_ms:
        return (f"loop jitter p99 {jitter:.1f} ms > one control period {period_ms:.1f} ms "
                f"({metrics.get('deadline_misses')} deadline misses)")
    return None


def judged(run: Callable[[], T], metrics_of: Callable[[T], dict[str, Any]], what: str) -> T:
    """``run()`` once, and once more when the clock starved it; skip when it starved
    both (the reason names both measurements), or the first beyond ``HOPELESS``."""
    first = run()
    why = starved(metrics_of(first))
    if why is None:
        return first
    periods = _jitter_periods(metrics_of(first))
    if periods is not None and periods > HOPELESS:
        pytest.skip(f"{what}: the scheduler starved the realtime run on this machine ({why}: "
                    f"{periods:.1f} periods, not retried beyond {HOPELESS:g}): its claims "
                    "cannot be judged here")
    second = run()
    why_again = starved(metrics_of(second))
    if why_again is None:
        return second
    pytest.skip(f"{what}: the scheduler starved the realtime run twice on this machine "
                f"({why}; then {why_again}): its claims cannot be judged here")
