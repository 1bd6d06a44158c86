"""Which received step may become a node's newest (docs/hardening.md: one forged message must
cost at most itself).

A plant's samples, a neighbour's replies and the leader's states arrive step after
step: the newest moves forward by one step, a few when messages are lost. A message
stamped far ahead of the newest is not believed at once: it is held as a candidate,
and adopted only when a second one confirms it (a step within ``jump_ok`` after the
candidate), as the real stream does after a pause, a cut link or a restart. A single
forged step (2^62, or a huge seq) therefore never becomes the newest, and the real
messages after it keep flowing; a forged step within ``jump_ok`` costs at most
``jump_ok`` steps. Pure logic: the nodes call it, the tests drive it directly.

On the realtime clock (``period_s`` set) steps are stamps of the sender's clock, and
a sender cannot run ahead of the wall clock: the guard keeps the stream's *lead*,
k * period - now on the receiver's clock, at its largest over the accepted steps
(the sample that came fastest), and believes at once any step whose lead is at
most ``jump_ok`` periods beyond it, however many steps it skips. A realtime plant or
bridge that runs late steps several periods per sample (the paper at 1 kHz on 2
cores: ~8), and a receiver that was itself late sees its next samples close
together; with a fixed step allowance every such sample was held as a far jump,
and the agents went silent (found by the quick bench and the CAN fleet test).
A forged far step is still held; one within the allowance costs at most
``jump_ok`` steps, as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

JUMP_OK = 3  # steps the newest may move at once without a confirmation


@dataclass
class StepGuard:
    """The newest accepted step of one stream, and a candidate for a far jump."""

    newest: int | None = None  # None: nothing accepted yet (the first step is taken)
    jump_ok: int = JUMP_OK
    candidate: int | None = None
    held: int = 0  # steps held back as unconfirmed jumps (counted as refused)
    period_s: float | None = None  # realtime: the stream's step period (None: lockstep)
    lead_s: float = -math.inf  # realtime: the largest k * period - now accepted
    candidate_lead_s: float = -math.inf

    def _follows(self, k: int, now: float, last: int, lead_s: float) -> bool:
        """Whether ``k`` (newer than ``last``) continues the stream whose newest step
        is ``last`` (lockstep) or whose lead is ``lead_s`` (realtime)."""
        if self.period_s is None:
            return k <= last + self.jump_ok
        return k * self.period_s - now <= lead_s + self.jump_ok * self.period_s

    def _take(self, k: int, now: float, new_clock: bool = False) -> bool:
        self.newest, self.candidate = k, None
        if self.period_s is not None:
            lead = k * self.period_s - now
            self.lead_s = lead if new_clock else max(self.lead_s, lead)
        return True

    def admit(self, k: int, now: float = 0.0) -> bool:
        """True when step ``k`` becomes the newest (an older or equal step: False).
        ``now``: the receiver's monotonic clock (used on the realtime clock only)."""
        if self.newest is None:
            return self._take(k, now, new_clock=True)
        if k <= self.newest:
            return False
        if self._follows(k, now, self.newest, self.lead_s):
            return self._take(k, now)
        if self.candidate is not None and self.candidate < k and self._follows(
                k, now, self.candidate, self.candidate_lead_s):
            return self._take(k, now, new_clock=True)  # a second step confirms the jump
        self.candidate = k
        if self.period_s is not None:
            self.candidate_lead_s = k * self.period_s - now
        self.held += 1
        return False

    def within(self, k: int, ahead: int) -> bool:
        """Whether ``k`` is at most ``ahead`` steps past the newest (nothing accepted
        yet: anything is)."""
        return self.newest is None or k <= self.newest + ahead


# -- the receiver's own clock: how far ahead any step or seq can possibly be -----------

SEQ_SLACK = 2  # a stream's seq may run this far past its step (an initial share: seq 0 at k = -1)
# realtime: how far a sender's clock may run ahead of ours (hosts share wall time by NTP,
# within milliseconds on a LAN; t = 0 is ``ctl/start``'s wall-clock instant). A host whose
# clock is further ahead has its real messages refused: the agent says so on stderr
CLOCK_SKEW_S = 0.1
DEADLINE_MARGIN = 0.9  # lockstep: a plant's deadline wait measured on our clock, with room


@dataclass
class OwnClock:
    """The newest step any sender of this run can have reached, judged on the
    receiver's own clock (docs/hardening.md: a message is judged against the receiver's
    clock, not only against the sender's history, which a forger writes).

    - lockstep (``deadline_s`` set): the plant publishes step k + 1 only once every
      command of step k is in or its step deadline has passed. So once we answered
      step ``answered`` at ``answered_at`` (our monotonic clock), the plant can be at
      most at ``answered + 1``, plus one step per deadline since: a sample (and a
      neighbour's share of it) for a later step cannot be real yet.
    - realtime (``t0_s`` set: t = 0 of the run on our clock, from ``ctl/start`` or a
      rejoin): no sender runs ahead of the wall clock by more than the hosts'
      skew, ``CLOCK_SKEW_S``.
    - neither known yet (a realtime agent rejoining before its first sample): no
      bound (:class:`StepGuard` still holds far jumps for confirmation).

    ``seq``: every stream of the control path sends at most one message per step,
    so a sender's seq (from 0 at its start) is at most its step + ``SEQ_SLACK``;
    a restarted sender numbers from 0 again and is heard, a seq far ahead is
    refused. Nothing orders messages by seq (the step does): this only counts.
    """

    dt: float
    deadline_s: float | None = None
    answered: int = -1
    answered_at: float = 0.0
    t0_s: float | None = None

    def answer(self, k: int, now: float) -> None:
        """Lockstep: we answered step ``k`` at ``now`` (the initial share: k = -1).

        The bound never goes back: an answer to an old sample (one a link held while it
        was down, delivered when it came back) says nothing of where the plant went
        meanwhile, one step per deadline. Reset to that old step, the bound refused every
        newer sample as ahead of our clock, the agent answered none, and the plant waited
        its deadline for each while the bound crept up 0.11 step per deadline: 20-30 s
        of a 50 ms deadline after a 3 s cut (tests/e2e/test_netns.py)."""
        if self.deadline_s is not None and self.answered >= 0:
            k = max(k, self.latest(now) - 1)
        self.answered, self.answered_at = k, now

    def latest(self, now: float) -> int | None:
        """The newest step a sender can be at now (None: no bound known)."""
        if self.deadline_s is not None:
            waited = max(0.0, now - self.answered_at)
            return self.answered + 1 + int(waited / (self.deadline_s * DEADLINE_MARGIN))
        if self.t0_s is not None:
            # never below -1: the initial shares (k = -1) go out at the handshake, before
            # t = 0, and one still queued when t = 0 is known was refused as ahead (the
            # bound was int() of a negative time: -18 at 0.3 s before t = 0, 100 Hz)
            return max(-1, math.floor((now - self.t0_s + CLOCK_SKEW_S) / self.dt) + 1)
        return None

    def refusal(self, k: int, seq: int, now: float, ahead: int = 0) -> str | None:
        """Why a message for step ``k`` with ``seq`` cannot be real now (None: it can).
        ``ahead``: steps a stream legitimately runs ahead of the plant (the leader's
        batches)."""
        latest = self.latest(now)
        if latest is None:
            return None
        if k > latest + ahead:
            return "step ahead of our clock"
        if seq > latest + ahead + SEQ_SLACK:
            return "seq ahead of our clock"
        return None
