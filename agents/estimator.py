"""Distributed leader estimator, eq. (14).

Each agent i keeps (q0_hat_i, v0_hat_i), its estimate of the virtual leader's
pose q0 = [x0, y0, phi0] and velocity v0, and updates it from its in-neighbours'
estimates (a_ij != 0) and, iff b_i != 0, from the leader itself:

    e_q = sum_j a_ij (q0_hat_i - q0_hat_j) + b_i (q0_hat_i - q0)
    e_v = sum_j a_ij (v0_hat_i - v0_hat_j) + b_i (v0_hat_i - v0)
    q0_hat_i' = -iota1 sig^eta1(e_q) - iota2 sign(e_q) + v0_hat_i
    v0_hat_i' = -iota3 sig^eta2(e_v) - iota4 sign(e_v)

Discretisation of sign(): explicit Euler of iota sign(e) overshoots e = 0 by
up to deg iota dt every step (deg = sum_j a_ij + b_i, how fast e moves with the
agent's own estimate), and that chatter reaches the torques through the
formation velocity (at 200 Hz, iota4 = 6: +-0.03 m/s on v0_hat each step,
+-1.5 N m on the lab robot's wheels). The implicit (backward Euler) treatment of
the set-valued sign (Acary & Brogliato, 2010) stops exactly at 0 instead:
sign(e) -> clip(e / (deg iota dt), -1, 1). It is sign() wherever |e| exceeds
one step's reach, and tends to sign() as dt -> 0.

Erratum 7: the printed A has a_11 = 1. A self loop cancels here (q_i - q_i)
but not in eq. (16); the scenario loader zeroes the diagonal for both.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from agents.signals import sig


@dataclass(frozen=True)
class EstimatorGains:
    iota: tuple[float, float, float, float] = (0.1, 0.1, 25.0, 6.0)
    eta: tuple[float, float] = (1.5, 1.5)


def consensus_errors(
    own: np.ndarray,
    neighbours: Sequence[np.ndarray],
    weights: Sequence[float],
    leader_weight: float,
    leader: np.ndarray | None,
) -> np.ndarray:
    """sum_j a_ij (own - x_j) + b_i (own - x_leader), the bracket of eq. (14)."""
    err = np.zeros_like(own)
    for w, x in zip(weights, neighbours, strict=False):
        err += w * (own - x)
    if leader_weight != 0.0 and leader is not None:
        err += leader_weight * (own - leader)
    return err


def implicit_sign(e: np.ndarray, reach: float) -> np.ndarray:
    """sign(e) discretised implicitly: e / reach clipped to [-1, 1] (reach > 0)."""
    if reach <= 0.0:
        return np.sign(e)
    return np.clip(e / reach, -1.0, 1.0)


def estimator_rates(
    q_hat: np.ndarray,
    v_hat: np.ndarray,
    e_q: np.ndarray,
    e_v: np.ndarray,
    gains: EstimatorGains,
    sign_reach: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Right-hand side of eq. (14) given the consensus errors.

    ``sign_reach`` = (deg iota2 dt, deg iota4 dt) selects the implicit sign; zeros
    give the plain sign of the continuous-time law.
    """
    i1, i2, i3, i4 = gains.iota
    n1, n2 = gains.eta
    q_rate = -i1 * sig(e_q, n1) - i2 * implicit_sign(e_q, sign_reach[0]) + v_hat
    v_rate = -i3 * sig(e_v, n2) - i4 * implicit_sign(e_v, sign_reach[1])
    return q_rate, v_rate


def estimator_step(
    q_hat: np.ndarray,
    v_hat: np.ndarray,
    neighbour_q: Sequence[np.ndarray],
    neighbour_v: Sequence[np.ndarray],
    weights: Sequence[float],
    leader_weight: float,
    leader_q: np.ndarray | None,
    leader_v: np.ndarray | None,
    gains: EstimatorGains,
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """One explicit-Euler step of eq. (14); returns the new (q0_hat, v0_hat)."""
    e_q = consensus_errors(q_hat, neighbour_q, weights, leader_weight, leader_q)
    e_v = consensus_errors(v_hat, neighbour_v, weights, leader_weight, leader_v)
    deg = float(sum(weights)) + (leader_weight if leader_q is not None else 0.0)
    reach = (deg * gains.iota[1] * dt, deg * gains.iota[3] * dt)
    q_rate, v_rate = estimator_rates(q_hat, v_hat, e_q, e_v, gains, reach)
    return q_hat + dt * q_rate, v_hat + dt * v_rate
