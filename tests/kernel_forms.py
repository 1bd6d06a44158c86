"""The compiled law's sections (agents/law_kernel.pyx) called on floats, for the tests that
check each against its numpy reference (agents/*.py) or use it alone: thin adapters of the
kernel's ``*_of`` exports that unpack the gains as the kernel takes them. They live with
the tests because nothing else calls them: the agents run the kernel's whole step."""

from __future__ import annotations

from collections.abc import Sequence

from agents.law_kernel import (
    control_term_of,
    desired_formation_of,
    eso_advance_of,
    estimator_step_of,
    implicit_sign_of,
    offsets_of,
    scale_at_of,
    sig_of,
)

from agents.controller import ControlConstants
from agents.eso import EsoGains
from agents.estimator import EstimatorGains
from agents.formation import ScaleChange

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


def sig_scalar(x: float, power: float) -> float:
    """sig^r(x) of one float, |x|^r sign(x) with sign(0) = 0 (NaN stays NaN)."""
    return sig_of(x, power)


def implicit_sign_scalar(e: float, reach: float) -> float:
    """The estimator's implicit sign() of one float (eq. 14, erratum 7)."""
    return implicit_sign_of(e, reach)


def estimator_step_vec(q_hat: Vec3, v_hat: Vec3, neighbour_q: Sequence[Vec3],
                       neighbour_v: Sequence[Vec3], weights: Sequence[float],
                       leader_weight: float, leader_q: Vec3 | None, leader_v: Vec3 | None,
                       gains: EstimatorGains, dt: float) -> tuple[Vec3, Vec3]:
    """One explicit-Euler step of eq. (14) on float triples."""
    return estimator_step_of(q_hat, v_hat, neighbour_q, neighbour_v, weights, leader_weight,
                             leader_q, leader_v, gains.iota, gains.eta, dt)


def eso_advance_vec(z1_hat: Vec3, z2_hat: Vec3, z1_measured: Vec3, gamma: Vec3,
                    gains: EsoGains, dt: float, max_step: float) -> tuple[Vec3, Vec3]:
    """Eq. (39) over ``dt`` in explicit-Euler sub-steps of at most ``max_step`` (the
    control period), the measurement and Gamma held: what a realtime agent whose state
    arrives late integrates (one step when dt is the period)."""
    return eso_advance_of(z1_hat, z2_hat, z1_measured, gamma, gains.mu1, gains.mu2, gains.r1,
                          gains.r2, dt, max_step)


def eso_step_vec(z1_hat: Vec3, z2_hat: Vec3, z1_measured: Vec3, gamma: Vec3, gains: EsoGains,
                 dt: float) -> tuple[Vec3, Vec3]:
    """One explicit-Euler step of eq. (39) on float triples."""
    return eso_advance_vec(z1_hat, z2_hat, z1_measured, gamma, gains, dt, dt)


def scale_at_vec(t: float, initial: Vec2, changes: Sequence[ScaleChange]
                 ) -> tuple[Vec2, Vec2]:
    """The formation's scale and its rate at t (eq. 48): ((sx, sy), (sx_dot, sy_dot))."""
    return scale_at_of(t, initial, changes)


def offsets_vec(r_i: Vec2, heading_offset: float, psi: float, psi_dot: float, scale: Vec2,
                scale_dot: Vec2) -> tuple[Vec3, Vec3]:
    """zeta_i = [W r_i, Xi_i] and zeta_i_dot, eq. (13)/(48)."""
    return offsets_of(r_i, heading_offset, psi, psi_dot, scale, scale_dot)


def desired_formation_vec(kappa1: float, kappa2: float, q0_hat: Vec3, v0_hat: Vec3,
                          zeta: Vec3, zeta_dot: Vec3, weights: Sequence[float],
                          neighbour_q: Sequence[Vec3], neighbour_q_dot: Sequence[Vec3],
                          neighbour_zeta: Sequence[Vec3], neighbour_zeta_dot: Sequence[Vec3]
                          ) -> tuple[Vec3, Vec3]:
    """q_fd,i of eq. (16) and its velocity, on float triples."""
    return desired_formation_of(kappa1, kappa2, q0_hat, v0_hat, zeta, zeta_dot, weights,
                                neighbour_q, neighbour_q_dot, neighbour_zeta,
                                neighbour_zeta_dot)


def control_term_vec(e: Vec3, e_dot: Vec3, z2_hat: Vec3, k: ControlConstants
                     ) -> tuple[Vec3, Vec3]:
    """(Gamma, s) of eq. (42) on float triples."""
    return control_term_of(e, e_dot, z2_hat, k.gamma_p, k.alpha, k.mu2, k.eps2, k.reach_low,
                           k.reach_high, k.s_div)
