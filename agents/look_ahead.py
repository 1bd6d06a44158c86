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
touched. Cost: H extra agent steps per step, in the compiled law
(agents/law_kernel.pyx, ``Law.plan``; the RK4 of eq. 4 is the model plant's own,
plant/fleet_kernel.pyx).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from agents.core import AgentCore, AgentOutput, Bodies, Share
from agents.degradation import InputAges
from agents.signals import Vec4

Torques = Vec4


class LookAhead:
    """Predicts one agent's next ``horizon`` torques."""

    def __init__(self, core: AgentCore, horizon: int) -> None:
        if horizon < 0:
            raise ValueError(f"horizon must be >= 0, got {horizon}")
        self.horizon = horizon

    def plan(
        self,
        core: AgentCore,
        out: AgentOutput,
        t: float,
        q: np.ndarray,
        q_dot: np.ndarray,
        shares: Mapping[int, Share],
        leader: tuple[np.ndarray, np.ndarray] | None,
        obstacles: Bodies = (),
        robots: Bodies = (),
        ages: InputAges | None = None,
    ) -> list[Torques]:
        """The torques for steps k+1 .. k+H, after ``core`` made ``out`` at step k
        from these inputs (the same arguments as its step). One entry per plant
        period (the scenario's dt, also in realtime). Shorter than H when a
        predicted step is not finite: nothing is sent past it."""
        if self.horizon == 0 or out.nonfinite:
            return []
        return core.plan(out, t, q, q_dot, shares, leader, obstacles, robots, ages,
                         self.horizon)
