"""Which received step may become a node's newest (issue 21: one forged message must
cost at most itself).

A plant's samples, a neighbour's replies and the leader's states arrive step after
step: the newest moves forward by one step, a few when messages are lost. A message
stamped far ahead of the newest is not believed at once: it is held as a candidate,
and adopted only when a second one confirms it (a step within ``jump_ok`` after the
candidate), as the real stream does after a pause, a cut link or a restart. A single
forged step (2^62, or a huge seq) therefore never becomes the newest, and the real
messages after it keep flowing; a forged step within ``jump_ok`` costs at most
``jump_ok`` steps. Pure logic: the nodes call it, the tests drive it directly.
"""

from __future__ import annotations

from dataclasses import dataclass

JUMP_OK = 3  # steps the newest may move at once without a confirmation


@dataclass
class StepGuard:
    """The newest accepted step of one stream, and a candidate for a far jump."""

    newest: int | None = None  # None: nothing accepted yet (the first step is taken)
    jump_ok: int = JUMP_OK
    candidate: int | None = None
    held: int = 0  # steps held back as unconfirmed jumps (counted as refused)

    def admit(self, k: int) -> bool:
        """True when step ``k`` becomes the newest (an older or equal step: False)."""
        if self.newest is None or self.newest < k <= self.newest + self.jump_ok:
            self.newest, self.candidate = k, None
            return True
        if k <= self.newest:
            return False
        if self.candidate is not None and self.candidate < k <= self.candidate + self.jump_ok:
            self.newest, self.candidate = k, None  # a second step confirms the jump
            return True
        self.candidate = k
        self.held += 1
        return False

    def within(self, k: int, ahead: int) -> bool:
        """Whether ``k`` is at most ``ahead`` steps past the newest (nothing accepted
        yet: anything is)."""
        return self.newest is None or k <= self.newest + ahead
