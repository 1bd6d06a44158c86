"""What torque a bridge may put on the bus, decided from the newest command and
the drivers' health. Pure logic, no I/O (docs/hardware.md, docs/faults.md):

- a command older than ``command_timeout_s`` (or none yet) -> zero torque, and
  the axes go idle: a dead agent must not leave a robot pushing;
- an e-stop -> zero torque and idle until the bridge is restarted;
- a faulted robot (a driver error, a missing heartbeat) -> zero torque;
- otherwise the commanded torques, each clamped to the scenario's limit; a
  non-finite torque never reaches the bus (the whole command is refused);
- a period with no new command (asked with ``due_step``): the look-ahead torques
  the newest command predicted for the overdue step (agents/look_ahead.py), and
  past its plan the last of them, held until the timeout.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from plant.command import torques_at

ZERO = (0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Decision:
    torques: tuple[float, float, float, float]
    armed: bool  # axes should be in closed loop
    reason: str  # "command", "look-ahead", "no command", "stale", "estop", "faulted",
    # "non-finite"


class CommandGate:
    def __init__(self, command_timeout_s: float, max_torque_nm: float) -> None:
        if not command_timeout_s > 0:
            raise ValueError("command timeout must be positive")
        self.command_timeout_s = command_timeout_s
        self.max_torque_nm = max_torque_nm
        self.estopped = False
        self._torques: tuple[float, ...] | None = None
        self._received_at = -math.inf
        self._k = 0
        self._plan: list[tuple[float, ...]] = []

    def command(self, torques: tuple[float, ...], now_s: float, k: int = 0,
                plan: Sequence[Sequence[float]] = ()) -> None:
        """A fresh command arrived (already validated on the wire): its torques, the
        step it answers and its look-ahead torques for the steps after."""
        self._torques = tuple(float(x) for x in torques)
        self._received_at = now_s
        self._k = k
        self._plan = [tuple(float(x) for x in u) for u in plan]

    def command_age_s(self, now_s: float) -> float:
        """How old the newest command is (inf: none yet)."""
        return now_s - self._received_at

    def estop(self) -> None:
        self.estopped = True

    def decide(self, now_s: float, faulted: bool, due_step: int | None = None) -> Decision:
        """``due_step``: the step whose command is overdue (None: the newest command
        is the one to apply)."""
        if self.estopped:
            return Decision(ZERO, False, "estop")
        if self._torques is None:
            return Decision(ZERO, False, "no command")
        if self.command_age_s(now_s) > self.command_timeout_s:
            return Decision(ZERO, False, "stale")
        if faulted:
            return Decision(ZERO, False, "faulted")
        torques, reason = self._torques, "command"
        if due_step is not None:
            # past the plan its last entry is held, as a plant holds it
            planned = torques_at(self._k, torques, self._plan, due_step)
            if planned is not None and planned is not torques:
                torques, reason = planned, "look-ahead"
        if not all(math.isfinite(x) for x in torques):
            return Decision(ZERO, False, "non-finite")
        lim = self.max_torque_nm
        t = tuple(max(-lim, min(lim, x)) for x in torques)
        return Decision(t, True, reason)  # type: ignore[arg-type]
