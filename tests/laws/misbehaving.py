"""Laws that misbehave on purpose (tests/integration/test_laws.py): each must be contained
by the runtime (agents/plugged.py) and named by the verdict."""

from __future__ import annotations

import time
from dataclasses import dataclass

from agents.law_api import BehaviorLaw, BehaviorOutput, LawInputs
from agents.laws.consensus import ConsensusLaw, ConsensusParams


@dataclass(frozen=True)
class After(ConsensusParams):
    after_s: float = 1.0  # misbehaves from this time on


class Raises(ConsensusLaw):
    """The consensus law, until it divides by zero."""

    name = "raises"
    Params = After

    def step(self, x: LawInputs) -> BehaviorOutput:
        if x.t >= self.params.after_s:
            return 1 / 0  # type: ignore[return-value]
        return super().step(x)


class Nan(ConsensusLaw):
    name = "nan"
    Params = After

    def step(self, x: LawInputs) -> BehaviorOutput:
        out = super().step(x)
        if x.t >= self.params.after_s:
            return BehaviorOutput((float("nan"), 0.0, 0.0), out.share)
        return out


class Absurd(ConsensusLaw):
    """Asks for 1e9 m/s."""

    name = "absurd"
    Params = After

    def step(self, x: LawInputs) -> BehaviorOutput:
        out = super().step(x)
        if x.t >= self.params.after_s:
            return BehaviorOutput((1e9, 0.0, 0.0), out.share)
        return out


class Slow(ConsensusLaw):
    """Computes for 3 ms of CPU a step from after_s on (a period is 5 ms at lab's 200 Hz,
    2 ms at 500 Hz): the thread's CPU time, so a starved host makes it no longer."""

    name = "slow"
    Params = After

    def step(self, x: LawInputs) -> BehaviorOutput:
        if x.t >= self.params.after_s:
            end = time.thread_time() + 0.003
            while time.thread_time() < end:
                pass
        return super().step(x)


class Meddles(ConsensusLaw):
    """Tries to change what it is given: its inputs are copies (tuples, a fresh dict)."""

    name = "meddles"

    def step(self, x: LawInputs) -> BehaviorOutput:
        x.shares.clear()  # type: ignore[attr-defined]  a copy: the runtime's stays whole
        return super().step(x)


class NotALaw:
    """Not a subclass of BehaviorLaw or TorqueLaw."""


class NoStep(BehaviorLaw):
    """A law that forgot its step."""
