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
- a loop that cannot keep its period, its **median** interval of a full window above
  ``slow_above`` periods, **slows its robot**: the planar command is scaled by
  slow_above x period / median interval (a loop at a third of its rate moves its robot at
  half speed with the default 1.5), and the agent says so and counts the steps
  (``overloaded`` in its report). One late wake is not an overload: the horizon covers
  it; slowing the robot for the whole window after each hiccup kept `lab` at 500 Hz on a
  2-core machine capped a third of its steps and its robots from settling before 15 s;
- the scale **moves gradually**, by at most one period's share of ``swing_s`` a step
  (``swing_s`` for the whole way from 1 to 0), and not before the window is full. The
  law's feed-forward q_d_ddot = (v_d(k) - v_d(k-1)) / h differentiates the command, scale
  included: `paper` at 1 kHz on one core, its start's few late intervals capped the
  robots at 0.2-0.4 and the median then jumped between 0.6 and 1.0 from step to step;
  each jump of the command (~100 m/s in a period at the start's speeds) became a torque
  spike of 1-6e5 N m and runs diverged (a robot past 1000 m/s at 13-23 ms). A start's
  intervals are the start's (every node's first steps cost several times the later
  ones), not the loop's pace.

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
    swing_s: float = 0.2
    _intervals: deque = field(init=False, repr=False)
    _slow: int = field(init=False, repr=False, default=0)  # intervals above slow_above periods
    _longest: float | None = field(init=False, repr=False, default=None)  # None: unknown
    _cap: float = field(init=False, repr=False, default=1.0)  # the scale the law is given

    def __post_init__(self) -> None:
        if (not self.period_s > 0.0 or self.window < 1 or not self.slow_above >= 1.0
                or not self.swing_s >= 0.0):
            raise ValueError("period_s > 0, window >= 1, slow_above >= 1 and swing_s >= 0 "
                             "are required")
        self._intervals = deque()
        self._slow_s = self.slow_above * self.period_s
        # how far the scale may move at a step (all the way at once with swing_s = 0)
        self._cap_step = 1.0 if self.swing_s == 0.0 else min(1.0, self.period_s / self.swing_s)

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
        target, cap = self.target_cap(), self._cap
        if target != cap:
            step = self._cap_step
            self._cap = target if abs(target - cap) <= step else (
                cap + step if target > cap else cap - step)

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
        """The planar speed scale for this step: 1 while the loop keeps its pace, else
        moving toward :meth:`target_cap` by at most a period's share of ``swing_s``."""
        return self._cap

    def target_cap(self) -> float:
        """1 until the window is full and while the loop keeps its pace, else slow_above x
        period / median interval."""
        n = len(self._intervals)
        if n < self.window or self._slow < n - n // 2:  # fewer above it than from the median up
            return 1.0
        ratio = self.typical_s / self.period_s
        return 1.0 if ratio <= self.slow_above else self.slow_above / ratio
