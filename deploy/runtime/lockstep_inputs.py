"""What a consumer uses at lockstep step k when its links are faulty.

A fault-free lockstep consumer uses, at step k, the sample of step k (its
state, perception, leader, command) or k-1 (a neighbour's share). On a faulty
edge the sample of step k - lag is used if the edge lets it through
(deploy/runtime/fault_model.py), else the last one that got through is held, and the
consumer is told its age. The in-process runner and the distributed nodes
both use these classes, so they use the same samples at the same steps.

In a distributed lockstep run the message of step k is still what tells a
consumer that step k has come (its arrival is the clock); only its content is
subject to the fault. The result equals waiting out a deadline for a message
that never comes, without the wall time and without the race.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

from agents.degradation import InputAges
from deploy.contract.wire import LEADER_ROLE, PLANT_ROLE, agent_role
from deploy.runtime.fault_model import EdgeFaults, FaultModel

T = TypeVar("T")


@dataclass
class HeldInput(Generic[T]):
    """One input of one consumer: the sample it last used, and from which step.

    ``first_k``: the first step that has a sample; earlier steps (asked for
    through a delay) use it. ``exempt_first``: the first sample is part of the
    start handshake and always gets through (a robot's first state, the
    initial shares), so every consumer starts with a value.
    """

    model: FaultModel
    edge: EdgeFaults | None
    first_k: int = 0
    exempt_first: bool = True
    value: T | None = None
    k_value: int | None = None

    def take(self, k_nominal: int, lookup: Callable[[int], T | None]) -> tuple[T | None, int]:
        """The sample to use where a fault-free run uses step ``k_nominal``'s,
        and its age in steps (0: that very sample)."""
        e = self.edge
        idx = k_nominal - (e.lag_steps if e is not None else 0)
        idx = max(idx, self.first_k)
        if self.k_value is None or idx > self.k_value:
            judged = e is not None and not (self.exempt_first and idx == self.first_k)
            if not judged or self.model.judge(e, idx):
                sample = lookup(idx)
                if sample is not None:
                    self.value, self.k_value = sample, idx
        age = k_nominal - self.k_value if self.k_value is not None else 0
        return self.value, age

    def take_present(self, k: int, sample: T) -> bool:
        """What :meth:`take` does with step ``k``'s own sample in hand on a link without
        faults (it is used, age 0), without a lookup; False, nothing taken, on a faulty
        link or before the first step (:meth:`take` decides then)."""
        if self.edge is not None or k < self.first_k:
            return False
        self.value, self.k_value = sample, k
        return True


W = TypeVar("W")  # what the plant sends a robot (state and perception together)
L = TypeVar("L")  # a leader sample
S = TypeVar("S")  # a neighbour's share


class AgentLinks(Generic[W, L, S]):
    """All inputs of agent ``robot_id`` in lockstep: world (plant -> agent),
    leader (iff b_i != 0) and each neighbour's share."""

    def __init__(self, model: FaultModel, robot_id: int, neighbours: list[int],
                 hears_leader: bool) -> None:
        me = agent_role(robot_id)
        self.model = model
        self.world: HeldInput[W] = HeldInput(model, model.edge(PLANT_ROLE, me))
        self.leader: HeldInput[L] | None = (
            HeldInput(model, model.edge(LEADER_ROLE, me)) if hears_leader else None)
        self.shares: dict[int, HeldInput[S]] = {
            j: HeldInput(model, model.edge(agent_role(j), me), first_k=-1) for j in neighbours}

    def take(self, k: int, world: Callable[[int], W | None], leader: Callable[[int], L | None],
             share: Callable[[tuple[int, int]], S | None], dt: float,
             ) -> tuple[W | None, L | None, dict[int, S | None], InputAges | None]:
        """Step k's inputs and their ages (None when the run has no fault plan:
        the agent then runs exactly the fault-free law). ``share``: a neighbour's share
        by (robot, step)."""
        w, w_age = self.world.take(k, world)
        ld, l_age = self.leader.take(k, leader) if self.leader is not None else (None, 0)
        shares: dict[int, S | None] = {}
        share_ages: dict[int, float] = {}
        for j, held in self.shares.items():
            shares[j], age = held.take(k - 1, lambda idx, j=j: share((j, idx)))
            share_ages[j] = age * dt
        if self.model.plan is None:
            return w, ld, shares, None
        return w, ld, shares, InputAges(w_age * dt, l_age * dt, share_ages)
