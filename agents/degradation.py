"""Graceful degradation of one agent when its inputs go stale (docs/faults.md).

Every input reaches the step with its age: how much older it is than what a
fault-free run would use at that step (0 in a fault-free lockstep run; in
realtime, measured on the step indices of the messages). The agent then:

1. **Predicts** a stale sample to the present with the velocity it carries
   (first-order hold): the leader's pose q0 + v0 a, a neighbour's estimate
   q0_hat_j + v0_hat_j a and pose q_j + q_dot_j a. Eq. (14) then compares
   estimates of the same instant.
2. **Leaves out** of eq. (14) an input older than ``stale_after_s``: with no
   input left the estimator integrates its own velocity estimate
   (q0_hat' = v0_hat, v0_hat' = 0), which is what eq. (14) gives with an empty
   neighbour set and b_i = 0.
3. **Slows down** when its freshest information about the leader (the leader
   itself, or any neighbour, whose share says how old its own information is:
   ages add up along the graph) or its own state is older than ``slow_after_s``:
   the speed factor f falls linearly to 0 over ``slow_ramp_s``, and the fused
   velocity v_d (after eq. 26 and the speed limits) is scaled so that its
   planar speed tends to ``degraded_speed_mps`` (never raised). When the inputs
   come back f rises at the same rate, no faster, so the reference q_d, and with
   it the torque of eq. (40), does not jump.
4. **Re-acquires** when fresh information comes back after a loss (its
   information was older than ``stale_after_s``):
   eq. (14)'s position gains are made for an estimate that starts right (with
   the paper's iota1 = iota2 = 0.1 a 50 m error takes about 11 s to close), so
   for as long as the estimate is farther than ``reacquire_tol_m`` from the
   freshest source's, it is also blended toward it with time constant
   ``reacquire_tau_s`` (a first-order filter: fast, but no jump), for at least
   ``reacquire_min_s`` (a neighbour that is itself re-acquiring starts next to
   us and moves away). This is ours, not the paper's, and runs only after a loss.

The arithmetic is the compiled law's (agents/law_kernel_sections/degradation.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the configuration, the inputs' ages and the prediction of a stale sample
to now (the realtime agent's).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from agents.signals import Vec3

MAX_COMMAND_HORIZON = 16  # steps; the wire refuses longer plans


@dataclass(frozen=True)
class DegradationConfig:
    stale_after_s: float = 0.2
    slow_after_s: float = 0.5
    slow_ramp_s: float = 1.0
    degraded_speed_mps: float = 0.3
    reacquire_tau_s: float = 0.25
    reacquire_tol_m: float = 0.05
    reacquire_min_s: float = 1.0
    command_horizon: int = 2  # steps of predicted torques sent with each command (look_ahead.py)


@dataclass(frozen=True)
class InputAges:
    """Ages of the inputs of one step, s (0: as fresh as in a fault-free run)."""

    state_s: float = 0.0
    leader_s: float = 0.0
    shares_s: Mapping[int, float] = field(default_factory=dict)

    @property
    def fresh(self) -> bool:
        return self.state_s == 0.0 and self.leader_s == 0.0 and not any(self.shares_s.values())


def predict(x: Vec3, x_dot: Vec3, age_s: float) -> Vec3:
    """x + x_dot age: a sample carried forward by the velocity it was taken with."""
    if age_s == 0.0:
        return x
    return x[0] + x_dot[0] * age_s, x[1] + x_dot[1] * age_s, x[2] + x_dot[2] * age_s
