"""The pace a realtime agent's loop actually keeps, and what the law makes of it (ours,
not the paper's; docs/safety.md, "An overloaded loop").

A command acts on the robot until the next one arrives. When the loop keeps its period
that is one period; when it runs late (an overloaded machine, a 1 kHz rate the CPU cannot
hold) the plant applies each command for longer, and a safety filter that assumes one
period lets the robot close on a body for longer than it planned. So:

- the **horizon** of a step, the time its command may act before the next can brake, is
  the longest loop interval of the last ``window`` steps plus the age of the sample it
  answers (never less than the period): the avoidance engagement distance and the
  barrier of the safety filter (agents/safety_filter.py, (S1)) use it;
- a loop that cannot keep its period, its **median** interval of the window above
  ``slow_above`` periods, **slows its robot**: the planar command is scaled by
  slow_above x period / median interval (a loop at a third of its rate moves its robot at
  half speed with the default 1.5), and the agent says so and counts the steps
  (``overloaded`` in its report). One late wake is not an overload: the horizon covers
  it; slowing the robot for the whole window after each hiccup kept `lab` at 500 Hz on a
  2-core machine capped a third of its steps and its robots from settling before 15 s.

Pure arithmetic on times the caller measures; no clock is read here.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

MAX_HORIZON_S = 0.5  # beyond this a sample is stale anyway (degradation.stale_after_s)


@dataclass
class LoopPace:
    """The last ``window`` intervals of one realtime loop. Each query is O(1) while the
    loop keeps its pace (a realtime agent asks every step: sorting the window every step
    was ~3 µs of its budget): the count of intervals above ``slow_above`` periods says
    whether the median can be above it, and the longest is kept as the window moves."""

    period_s: float
    window: int = 50
    slow_above: float = 1.5
    _intervals: deque = field(init=False, repr=False)
    _slow: int = field(init=False, repr=False, default=0)  # intervals above slow_above periods
    _longest: float | None = field(init=False, repr=False, default=None)  # None: unknown

    def __post_init__(self) -> None:
        if not self.period_s > 0.0 or self.window < 1 or not self.slow_above >= 1.0:
            raise ValueError("period_s > 0, window >= 1 and slow_above >= 1 are required")
        self._intervals = deque()
        self._slow_s = self.slow_above * self.period_s

    def note(self, interval_s: float) -> None:
        """The time between this step and the one before (the loop's own clock)."""
        if not interval_s >= 0.0:
            return
        iv = self._intervals
        if len(iv) == self.window:
            old = iv.popleft()
            if old > self._slow_s:
                self._slow -= 1
            if self._longest is not None and old >= self._longest:
                self._longest = None  # found again when asked
        iv.append(interval_s)
        if interval_s > self._slow_s:
            self._slow += 1
        if self._longest is not None and interval_s > self._longest:
            self._longest = interval_s

    @property
    def longest_s(self) -> float:
        if not self._intervals:
            return self.period_s
        if self._longest is None:
            self._longest = max(self._intervals)
        return self._longest

    @property
    def typical_s(self) -> float:
        """The median interval of the window (the period while none is known)."""
        if not self._intervals:
            return self.period_s
        ordered = sorted(self._intervals)
        return ordered[len(ordered) // 2]

    def horizon(self, sample_age_s: float = 0.0) -> float:
        """How long a command made now may act before the next can brake."""
        h = max(self.period_s, self.longest_s) + max(0.0, sample_age_s)
        return min(h, MAX_HORIZON_S)

    def speed_cap(self) -> float:
        """1 while the loop keeps its pace, else slow_above x period / median interval."""
        n = len(self._intervals)
        if self._slow < n - n // 2:  # fewer above the bound than from the median up
            return 1.0
        ratio = self.typical_s / self.period_s
        return 1.0 if ratio <= self.slow_above else self.slow_above / ratio
