"""Bring your own law: what a control law of the agent implements (docs/laws.md).

A law is a class. It is built once per robot with the scenario's configuration for that
robot (:class:`agents.core.AgentConfig`: its id, the period, the graph weights a_ij and b_i,
its formation offset r_i, the robot's geometry and limits) and its own parameters (a
dataclass the class declares as ``Params``; the scenario's ``[law] params`` fill it, each
name checked). It keeps its own state between steps and is stepped once a control period
with the step's inputs (:class:`LawInputs`, copies: nothing a law does reaches the
runtime). It says which of two levels it works at:

- ``behavior``: it returns the world-frame velocity v_d = (x_dot, y_dot, psi_dot) the
  robot should move at (:class:`BehaviorOutput`). The paper's dynamic level turns it into
  wheel torques as it turns the paper's own fused velocity: the explicit limits (speed,
  acceleration), the safety filter, the fully actuated sliding-mode controller of eqs.
  (36), (40)-(42) with the extended state observer of eq. (39);
- ``torque``: it returns the four wheel torques itself (:class:`TorqueOutput`). The safety
  layer still has the last word: the velocity those torques would reach in one period
  (eq. 4) is put to the safety filter, and where the filter would change it the paper's
  controller brakes to the filtered velocity instead; every torque is clamped to the
  scenario's limit.

Either way it also returns its **share**: what the agents that listen to it read
(:class:`agents.core.Share`, seven fields: q0_hat, v0_hat, q, q_dot, zeta, zeta_dot,
info_age_s). Their meaning is the law's own, but q and q_dot should be the robot's state,
as every law's neighbours may take them so. For the look-ahead plan (agents/look_ahead.py)
the runtime forks a law (:meth:`ControlLaw.fork`, a deep copy unless a law knows better)
and steps the fork on predicted states; the fork's outputs are torques never applied.

A law that raises, or returns a NaN or an absurd value, is contained by the runtime
(agents/plugged.py): its robot brakes that step, the error is counted and named, and the
run's verdict fails naming the law. Pure Python: no I/O, no clock.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from agents.signals import Vec3, Vec4

if TYPE_CHECKING:  # the configuration a law is built with
    from agents.core import AgentConfig, Share

BEHAVIOR, TORQUE = "behavior", "torque"
LEVELS = (BEHAVIOR, TORQUE)

# a perceived body, as perception gives it: (ident, x, y, vx, vy, radius); ident is the
# robot's id, or -(obstacle index + 1) for an obstacle (radius 0: a wall's nearest point)
Sensed = tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class LawInputs:
    """One step's inputs, as the paper's law takes them (copies)."""

    t: float  # the sample's time, s (the run's clock: lockstep or wall)
    h: float  # the time this step's command acts: the period, more when samples were missed
    q: Vec3  # own pose (x, y, psi), world frame
    q_dot: Vec3  # own velocity, world frame
    leader: tuple[Vec3, Vec3] | None  # the leader's (q0, v0) where b_i != 0 and heard, else None
    shares: Mapping[int, Share]  # the shares of the neighbours j with a_ij != 0, by id
    obstacles: tuple[Sensed, ...]  # obstacles within the detection range
    robots: tuple[Sensed, ...]  # other robots within it
    # how much older each input is than in a fault-free run, s (0: fresh): the leader's, and
    # each neighbour's share (a law may predict them to now with the velocity they carry)
    leader_age_s: float = 0.0
    share_ages_s: Mapping[int, float] = dataclasses.field(default_factory=dict)
    # the robot's formation offset now, in the formation's frame: S(t) r_i of eq. (13) (the
    # scenario's offset r_i under its time-varying scale S(t)), and its rate S_dot(t) r_i;
    # a law turns it with its own heading of the formation (the paper: the leader's)
    offset: tuple[float, float] = (0.0, 0.0)
    offset_rate: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class BehaviorOutput:
    v_d: Vec3  # the velocity the robot should move at, world frame (m/s, m/s, rad/s)
    share: Share
    target: Vec3 | None = None  # where the law wants the robot (telemetry: q_fd), if it says


@dataclass(frozen=True)
class TorqueOutput:
    torques: Vec4  # wheel torques, N m, in the wheel order of plant/mecanum.py
    share: Share
    target: Vec3 | None = None


@dataclass(frozen=True)
class NoParams:
    """A law without parameters."""


class ControlLaw:
    """The base of every law (see the module's docstring). Subclass
    :class:`BehaviorLaw` or :class:`TorqueLaw`."""

    level: ClassVar[str] = ""
    Params: ClassVar[type] = NoParams
    name: ClassVar[str] = ""  # its name in reports and figures (default: the class's)

    def __init__(self, cfg: AgentConfig, params: Any) -> None:
        self.cfg, self.params = cfg, params

    def start(self, q: Vec3, q_dot: Vec3, q0_hat: Vec3, v0_hat: Vec3) -> Share:
        """The share before the first step (the runtime publishes it at start-up):
        ``q0_hat``, ``v0_hat`` are the scenario's initial leader estimate for this robot.
        The default shares the estimate, the state and the formation offset."""
        from agents.core import Share

        r = self.cfg.offset
        return Share(q0_hat, v0_hat, q, q_dot, (r[0], r[1], self.cfg.heading_offset),
                     (0.0, 0.0, 0.0))

    def step(self, x: LawInputs) -> BehaviorOutput | TorqueOutput:
        raise NotImplementedError

    def fork(self) -> ControlLaw:
        """An independent copy to step ahead of this one (the look-ahead): a deep copy of
        the law's own state, its configuration and parameters shared (they are frozen)."""
        return copy.deepcopy(self, {id(self.cfg): self.cfg, id(self.params): self.params})

    @classmethod
    def law_name(cls) -> str:
        return cls.name or cls.__name__


class BehaviorLaw(ControlLaw):
    """A law of the behavior level: :meth:`step` returns a :class:`BehaviorOutput`."""

    level = BEHAVIOR

    def step(self, x: LawInputs) -> BehaviorOutput:
        raise NotImplementedError


class TorqueLaw(ControlLaw):
    """A law of the torque level: :meth:`step` returns a :class:`TorqueOutput`."""

    level = TORQUE

    def step(self, x: LawInputs) -> TorqueOutput:
        raise NotImplementedError
