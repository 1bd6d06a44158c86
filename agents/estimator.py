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

The arithmetic is the compiled law's (agents/law_kernel_sections/estimator.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the gains.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EstimatorGains:
    iota: tuple[float, float, float, float] = (0.1, 0.1, 25.0, 6.0)
    eta: tuple[float, float] = (1.5, 1.5)
