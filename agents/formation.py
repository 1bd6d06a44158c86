"""Time-varying formation: affine offsets (13)/(48) and the desired reference (16).

    rho_i(t) = W(t) r_i + b(t),   W(t) = Rot(psi(t)) S(t),   b(t) = 0
    zeta_i   = [rho_i, Xi_i]   (position offset and heading offset)

Erratum 1: the printed r = [[0,-4,-4],[0,-4,-4]] puts robots 2 and 3 on one spot;
scenarios use the authors' offsets (0,0), (-4,-4), (-4,4).
Erratum 6: psi(t) is the leader's path tangent (unwrapped), not the polar angle
of its position; each agent uses its own estimate of the leader heading.
S(t) = diag(sx, sy) changes smoothly between (normal / middle / narrow passage)
values; each change is the double integral of a Gaussian-derivative pulse
(sigma = window/8) centred in its window, i.e. a normalised Gaussian CDF.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from agents.law_kernel import smooth_step_of


@dataclass(frozen=True)
class ScaleChange:
    """S moves from its previous value to ``to`` over [start_s, end_s]."""

    start_s: float
    end_s: float
    to: tuple[float, float]


def smooth_step(t: float, start: float, end: float) -> tuple[float, float]:
    """(value, derivative) of a 0 -> 1 step over [start, end], exactly 0/1 outside: a
    Gaussian CDF of sigma = window/8 cut at +-4 sigma and rescaled (the compiled law's,
    agents/law_kernel.pyx)."""
    return smooth_step_of(t, start, end)


def scale_at(
    t: float, initial: tuple[float, float], changes: Sequence[ScaleChange]
) -> tuple[np.ndarray, np.ndarray]:
    """(S, S_dot) as 2-vectors of the diagonal at time t."""
    s = np.array(initial, dtype=float)
    s_dot = np.zeros(2)
    for ch in changes:
        target = np.array(ch.to, dtype=float)
        frac, rate = smooth_step(t, ch.start_s, ch.end_s)
        s_dot = s_dot + (target - s) * rate
        s = s + (target - s) * frac
    return s, s_dot


def rot2(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def offsets(
    r_i: np.ndarray,
    heading_offset: float,
    psi: float,
    psi_dot: float,
    scale: np.ndarray,
    scale_dot: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """zeta_i = [W r_i, Xi_i] and its time derivative, eq. (13)/(48)."""
    R = rot2(psi)
    R_dot = psi_dot * rot2(psi + 0.5 * np.pi)
    rho = R @ (scale * r_i)
    rho_dot = R_dot @ (scale * r_i) + R @ (scale_dot * r_i)
    zeta = np.array([rho[0], rho[1], heading_offset])
    zeta_dot = np.array([rho_dot[0], rho_dot[1], 0.0])
    return zeta, zeta_dot


def desired_formation(
    kappa1: float,
    kappa2: float,
    q0_hat: np.ndarray,
    v0_hat: np.ndarray,
    zeta: np.ndarray,
    zeta_dot: np.ndarray,
    weights: Sequence[float],
    neighbour_q: Sequence[np.ndarray],
    neighbour_q_dot: Sequence[np.ndarray],
    neighbour_zeta: Sequence[np.ndarray],
    neighbour_zeta_dot: Sequence[np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """q_fd,i of eq. (16) and its velocity, erratum 4 applied:

    q_fd,i = gamma (kappa1 (q0_hat_i + zeta_i) + kappa2 sum_j a_ij (q_j - zeta_j + zeta_i)),
    gamma = 1 / (kappa1 + kappa2 sum_j a_ij).  (printed: kappa2 twice, i in the sum)
    """
    denom = kappa1 + kappa2 * float(sum(weights))
    if denom <= 0.0:
        raise ValueError("kappa1 + kappa2 * sum_j a_ij must be positive (eq. 16)")
    pos = kappa1 * (q0_hat + zeta)
    vel = kappa1 * (v0_hat + zeta_dot)
    if kappa2 != 0.0:
        for w, qj, vj, zj, zdj in zip(
            weights, neighbour_q, neighbour_q_dot, neighbour_zeta, neighbour_zeta_dot, strict=False
        ):
            pos = pos + kappa2 * w * (qj - zj + zeta)
            vel = vel + kappa2 * w * (vj - zdj + zeta_dot)
    return pos / denom, vel / denom
