"""Command look-ahead: the torques of the next steps, predicted and sent with
each command, so the plant has something right to apply when a command is lost.

This is packetized predictive control (Bemporad 1998; Quevedo and Nesic 2011):
over a lossy link the controller sends, with the input of step k, the inputs it
expects to send at k+1 .. k+H. The actuator that misses the command of step k+m
plays entry m of the newest command it has (plant/command.py), and falls back to
its missed-command policy only past the horizon.

Why the paper scenario needs it: its law (eqs. 36, 40-42) is unsaturated and
deadbeat at 1 kHz. When a behavior switches on (FOCB at the edge of the
avoidance band), v_d jumps by hundreds of m/s and the feed-forward
q_d_ddot = (v_d(k) - v_d(k-1)) / dt asks for that jump in one period (torques
near 4.5e5 N m). A robot whose command of that step is lost goes on at the old
velocity, 0.6 m per period, into the obstacle, where the avoidance barrier
steepens and the next command throws it off (at 30 % loss, seed 5 of the sweep
diverged within 25 ms). The look-ahead command of the step before holds the
jump, because the prediction crosses the band edge too.

The prediction: a fork of the agent (AgentCore.fork) steps H times on
- its own state, integrated with eq. (4) (RK4, no disturbance: it is unknown)
  under the torques just computed, then under each predicted one;
- the same leader and neighbour samples, older by h periods (the step itself
  predicts them with the velocity they carry, degradation.py);
- the perceived bodies moved on at the velocity they were seen with.
The fork's outputs are discarded except for the torques; the agent itself is not
touched. Cost: H extra agent steps per step.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from agents.controller import ModelTerms, acceleration_vec
from agents.core import AgentCore, AgentOutput, Share
from agents.degradation import InputAges
from agents.signals import Vec3, Vec4
from plant.bodies import Body

Torques = Vec4


def rk4_step(m: ModelTerms, q: Vec3, q_dot: Vec3, u: Vec4, h: float) -> tuple[Vec3, Vec3]:
    """One RK4 step of eq. (4) (no disturbance) under constant torques u."""
    def f(x: Vec3, v: Vec3) -> Vec3:
        return acceleration_vec(m, x, v, u)

    def add(a: Vec3, b: Vec3, k: float) -> Vec3:
        return a[0] + k * b[0], a[1] + k * b[1], a[2] + k * b[2]

    k1q, k1v = q_dot, f(q, q_dot)
    k2q = add(q_dot, k1v, h / 2)
    k2v = f(add(q, k1q, h / 2), k2q)
    k3q = add(q_dot, k2v, h / 2)
    k3v = f(add(q, k2q, h / 2), k3q)
    k4q = add(q_dot, k3v, h)
    k4v = f(add(q, k3q, h), k4q)
    w = h / 6
    q_next = tuple(q[i] + w * (k1q[i] + 2 * k2q[i] + 2 * k3q[i] + k4q[i]) for i in range(3))
    v_next = tuple(q_dot[i] + w * (k1v[i] + 2 * k2v[i] + 2 * k3v[i] + k4v[i]) for i in range(3))
    return q_next, v_next  # type: ignore[return-value]


class LookAhead:
    """Predicts one agent's next ``horizon`` torques."""

    def __init__(self, core: AgentCore, horizon: int) -> None:
        if horizon < 0:
            raise ValueError(f"horizon must be >= 0, got {horizon}")
        self.horizon = horizon
        self._terms = ModelTerms.from_model(core.cfg.model)

    def plan(
        self,
        core: AgentCore,
        out: AgentOutput,
        t: float,
        q: np.ndarray,
        q_dot: np.ndarray,
        shares: Mapping[int, Share],
        leader: tuple[np.ndarray, np.ndarray] | None,
        obstacles: Sequence[Body] = (),
        robots: Sequence[Body] = (),
        ages: InputAges | None = None,
    ) -> list[Torques]:
        """The torques for steps k+1 .. k+H, after ``core`` made ``out`` at step k
        from these inputs (the same arguments as its step). One entry per plant
        period (the scenario's dt, also in realtime). Shorter than H when a
        predicted step is not finite: nothing is sent past it."""
        if self.horizon == 0 or out.nonfinite:
            return []
        h = core.cfg.dt
        age = ages if ages is not None else InputAges()
        sim = core.fork()
        # the state the agent used: its sample carried to now (degradation.predict)
        x: Vec3 = tuple((np.asarray(q, float) + age.state_s * np.asarray(q_dot, float)).tolist())
        v: Vec3 = tuple(np.asarray(q_dot, float).tolist())
        u: Vec4 = tuple(out.torques.tolist())
        planned: list[Torques] = []
        for m in range(1, self.horizon + 1):
            x, v = rk4_step(self._terms, x, v, u, h)
            ahead = m * h
            nxt = sim.step(
                t + ahead, np.array(x), np.array(v), shares, leader,
                _moved(obstacles, ahead), _moved(robots, ahead), h,
                InputAges(0.0, age.leader_s + ahead,
                          {j: age.shares_s.get(j, 0.0) + ahead for j in shares}),
            )
            if nxt.nonfinite:
                break
            u = tuple(nxt.torques.tolist())
            planned.append(u)
        return planned


def _moved(bodies: Sequence[Body], ahead_s: float) -> list[Body]:
    return [Body(b.ident, b.position + ahead_s * b.velocity, b.velocity, b.radius)
            for b in bodies]
