"""A rehearsal of the paper's law just before a realtime run starts (ours, not the paper's).

A realtime agent sleeps through the start's lead (~0.3 s) and then steps a law that has not
run in that time. On one core (`taskset -c 0`) the fleet's first steps cost 1-2 ms of CPU
per process against ~0.1 ms a few steps later, so the agents answered their first sample
only at steps 1-8 (4-12 ms after t = 0), each at a different step. The paper's law is
deadbeat at 1 kHz: its feed-forward q_d_ddot = (v_d(k) - v_d(k-1)) / h, eqs. (36), (40)-(42),
turns a neighbour's share that comes after such a gap into a one-step torque spike of 3-5x
(1.55e5 N m between 3.6e4 and 1.7e4), and `paper` on one core diverged (a robot past
1000 m/s 9-18 ms after t = 0) in about a third of its runs. Three steps of the law on a
scratch core 20 ms before t = 0, side by side in alternating pairs of 0.3 s runs: 6 of 120
diverged against 25 of 120, the states unanswered in time fewer in 58 of 65 pairs
(docs/bench-history.md, "The start on one core"). Rehearsed 5 ms before t = 0 the
rehearsals crowded the start (12 of 20 diverged); 0.3 s before, nothing changed. In a slow
hour the rehearsals themselves took 2-9 ms of CPU each (the first touch of what the fork
server's heap shares with the agent, and cold caches) and no longer sufficed (13 of 25
diverged against 18 of 25, with the leader's first batches early too). Found after: much
of what the feed-forward differentiated at the start was the loop's own speed scale, capped
by the median of the start's first few intervals and then jumping from step to step
(agents/pace.py now waits for a full window and moves the scale gradually).

The rehearsal steps a core of its own, built from the run's configuration and initial
state, and is discarded: the agent's own core, and every result of the run, stay as they
were. Only the paper's compiled law is rehearsed: a lab's own law (agents/plugged.py) is
stepped by the run alone, whatever its instances hold or do.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from agents.core import AgentConfig, Bodies, Share
from agents.look_ahead import LookAhead
from agents.plugged import make_core

REHEARSAL_STEPS = 3
REHEARSAL_LEAD_S = 0.02  # before t = 0 (as good as 50 ms; 5 ms crowded the start)


def rehearsal_wait(t0_s: float, now_s: float) -> float | None:
    """How long to wait before rehearsing (both times on one clock), or None: t = 0 is
    less than half the lead away (an agent that heard the start late), where a rehearsal
    would take the CPU from the run's first steps (rehearsed 5 ms before t = 0, 12 of 20
    runs diverged against 1 of 20 at 20 ms)."""
    left = t0_s - now_s
    if left < 0.5 * REHEARSAL_LEAD_S:
        return None
    return max(0.0, left - REHEARSAL_LEAD_S)


def rehearse(cfg: AgentConfig, q: Sequence[float], q_dot: Sequence[float],
             q0_hat: Sequence[float], v0_hat: Sequence[float], shares: Mapping[int, Share],
             leader: tuple | None, obstacles: Bodies, horizon: int) -> int:
    """Step a scratch core of the paper's law ``REHEARSAL_STEPS`` times from the robot's
    initial state (its look-ahead plan too, ``horizon`` steps, none for 0); the number of
    steps rehearsed. ``leader``: (q, q_dot) as the first step would take it, None for an
    agent that does not hear the leader."""
    core = make_core(cfg, None, None, q, q_dot, q0_hat, v0_hat)
    look = LookAhead(core, horizon) if horizon else None
    dt = cfg.dt
    for n in range(REHEARSAL_STEPS):
        t = n * dt
        out = core.step(t, q, q_dot, shares, leader, obstacles, (), dt)
        if look is not None:
            look.plan(core, out, t, q, q_dot, shares, leader, obstacles, (), None)
    return REHEARSAL_STEPS
