"""A leader steered from outside (a ROS 2 teleop, nav2): the virtual leader's pose
integrated from a commanded body twist, in place of the paper's path (Section 4).

The command v_b = [vx, vy, wz] (body frame, REP 103: x forward) is bounded before use:
its linear part to ``max_speed_mps`` (scaled, direction kept), its yaw rate to
``max_yaw_rate_radps``; a command older than ``timeout_s`` is no command (the leader
stops). Then, with T(psi) of eq. (3), explicit Euler as the path follower's:

    q0_dot = T(psi) v_b,    q0(t + dt) = q0(t) + dt q0_dot.

The state at step k is what the agents estimate (eq. 14); a step's command is the newest
one received before that step is computed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class SteeredSpec:
    start: tuple[float, float, float]  # [x, y, psi] at t = 0
    max_speed_mps: float
    max_yaw_rate_radps: float
    timeout_s: float  # a command older than this: stop


def bounded(spec: SteeredSpec, v: tuple[float, float, float]) -> tuple[float, float, float]:
    """``v`` within the spec's limits (finite input assumed: the sender refuses others)."""
    vx, vy, wz = v
    speed = math.hypot(vx, vy)
    if speed > spec.max_speed_mps:
        scale = spec.max_speed_mps / speed
        vx, vy = vx * scale, vy * scale
    return vx, vy, max(-spec.max_yaw_rate_radps, min(spec.max_yaw_rate_radps, wz))


class SteeredLeader:
    """The interface of agents.leader.LeaderGenerator (``state``, ``state_floats``,
    ``advance``, ``t``), plus :meth:`steer`."""

    def __init__(self, spec: SteeredSpec, dt: float) -> None:
        self.spec, self.dt, self.k = spec, dt, 0
        self._pose = tuple(map(float, spec.start))
        self._command = (0.0, 0.0, 0.0)
        self._command_t = -math.inf  # the run's time the command was received at

    @property
    def t(self) -> float:
        return self.k * self.dt

    def steer(self, v_body: tuple[float, float, float], t_received: float) -> None:
        """The newest command, received at the run's time ``t_received``."""
        self._command, self._command_t = bounded(self.spec, v_body), t_received

    def _velocity(self) -> tuple[float, float, float]:
        """q0_dot at t_k: T(psi) v_b, zero once the command is older than the timeout."""
        if self.t - self._command_t > self.spec.timeout_s:
            return 0.0, 0.0, 0.0
        vx, vy, wz = self._command
        c, s = math.cos(self._pose[2]), math.sin(self._pose[2])
        return c * vx - s * vy, s * vx + c * vy, wz

    def state_floats(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        return self._pose, self._velocity()  # type: ignore[return-value]

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        q0, v0 = self.state_floats()
        return np.array(q0), np.array(v0)

    def batch(self, count: int) -> tuple[list[tuple[float, float, float]],
                                         list[tuple[float, float, float]]]:
        """The states of the next ``count`` steps (the leader node's batch)."""
        return states_one_by_one(self, count)

    def advance(self) -> None:
        v = self._velocity()
        x, y, psi = self._pose
        self._pose = (x + self.dt * v[0], y + self.dt * v[1], psi + self.dt * v[2])
        self.k += 1


def states_one_by_one(generator: Any, count: int
                      ) -> tuple[list[tuple[float, float, float]], list[tuple[float, float, float]]]:
    """``count`` rounds of ``state_floats`` then ``advance`` on a leader generator: its
    states (q0, v0) of the next ``count`` steps."""
    qs, vs = [], []
    for _ in range(count):
        q, v = generator.state_floats()
        qs.append(q)
        vs.append(v)
        generator.advance()
    return qs, vs
