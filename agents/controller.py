"""Fully actuated sliding-mode behavioral controller, eqs. (34)-(36), (40)-(42).

Tracking error e = q - q_d, where q_d integrates the fused velocity v_d
(CLIK reference of eq. 11). Discretisation: the controller holds each torque for
one period (zero-order hold), so it can realise a constant acceleration over
[t_k, t_k+1], not a jump. q_d(t) is therefore the first-order hold of the v_d
samples delayed by one period: q_d_dot(t_k) = v_d(k-1), q_d_ddot = (v_d(k) -
v_d(k-1))/dt on [t_k, t_k+1], q_d(t_k+1) = q_d(t_k) + dt (v_d(k-1) + v_d(k))/2;
at k = 0, v_d(-1) = v_d(0), so the initial error e_dot(0) = q_dot(0) - v_d(0) is
left to the sliding-mode term, as in the paper. (A plain backward difference
with q_d_dot(t_k) = v_d(k) lags the feed-forward by one period: every jump of
v_d at a behavior switch then shows up as a tracking error of the jump's size.)

Sliding surface (40) and predefined-time term (41), gamma_p = 2/(alpha mu T_p):
    s      = e_dot + psi(e)
    psi(e) = gamma_p (|e|^-alpha + mu^2 |e|^alpha) e
Control term (42):
    Gamma  = -gamma_p ((1/2)^((2-alpha)/2) |s|^-alpha + (1/2)^((2+alpha)/2) mu^2 |s|^alpha) s
             - z2_hat - psi_dot(e) - s / (2 upsilon^2)
Allocation (36), with B_bar = [B; n^T] (erratum 3) and the sign of Gamma that
gives the closed loop (37) e_ddot = Gamma + D used by the proof (44):
    u = B_bar^-1 [q_d_ddot + A0 q_dot + A1 + Gamma; 0]
(the printed (36), u = -B_bar^-1(... + Gamma), would give e_ddot = -Gamma + D,
which contradicts (37) and (44); we follow (37)).

Erratum 5: psi_dot is the true derivative, (d psi / d e) e_dot, with
d psi/de = gamma_p [(n^-a + mu^2 n^a) I + a (mu^2 n^(a-2) - n^(-a-2)) e e^T].
|e|^-alpha is not differentiable at 0, so n = sqrt(|e|^2 + eps^2) (eps from the
scenario, ``controller.psi_epsilon``) replaces |e| in psi and its Jacobian.

The 4th (internal-torque) component of the augmented error, ESO state and
Gamma is identically zero (n^T u = 0), so those are kept as 3-vectors.

The arithmetic is the compiled law's (agents/law_kernel_sections/controller.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the gains, and the constants the kernel takes.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ControllerGains:
    alpha: float = 0.5  # alpha_p
    mu: float = 30.0  # mu_p
    T_p: float = 4.0  # predefined time; settling bound sqrt(2) T_p
    upsilon: float = 1.5
    psi_epsilon: float = 1e-3

    @property
    def gamma_p(self) -> float:
        return 2.0 / (self.alpha * self.mu * self.T_p)


@dataclass(frozen=True)
class ControlConstants:
    """:class:`ControllerGains` as the floats that eqs. (40)-(42) multiply by."""

    gamma_p: float
    alpha: float
    mu2: float  # mu^2
    eps2: float  # psi_epsilon^2 (erratum 5)
    reach_low: float  # (1/2)^((2-alpha)/2)
    reach_high: float  # (1/2)^((2+alpha)/2) mu^2
    s_div: float  # 2 upsilon^2

    @classmethod
    def from_gains(cls, g: ControllerGains) -> ControlConstants:
        a = g.alpha
        return cls(
            gamma_p=g.gamma_p, alpha=a, mu2=g.mu**2, eps2=g.psi_epsilon * g.psi_epsilon,
            reach_low=0.5 ** ((2.0 - a) / 2.0), reach_high=0.5 ** ((2.0 + a) / 2.0) * g.mu**2,
            s_div=2.0 * g.upsilon**2,
        )
