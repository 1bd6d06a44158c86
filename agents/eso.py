"""Extended state observer, eq. (39).

z1 = e_bar_dot (measured), z2 = D (total uncertainty of eq. 37). With
eps1 = z1 - z1_hat:

    z1_hat' = Gamma + z2_hat + mu1 sig^r1(eps1)
    z2_hat' = mu2 sig^r2(eps1),        r2 = 2 r1 - 1

Initial condition: z1_hat(0) = the first measured e_dot, z2_hat(0) = 0. The
paper starts both at 0; then eps1(0) = e_dot(0) = -v_d(0), which in the paper
scenario is tens to hundreds of m/s, and with the paper's slow gains
(mu2 = 0.2) that mismatch integrates into a bias on z2_hat of several m/s^2
that takes tens of seconds to decay and drives the tracking error away
(measured in tests/unit/test_eso.py). Starting at the measurement removes it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agents.signals import sig


@dataclass(frozen=True)
class EsoGains:
    mu1: float = 0.6
    mu2: float = 0.2
    r1: float = 0.7

    @property
    def r2(self) -> float:
        return 2.0 * self.r1 - 1.0


def eso_step(
    z1_hat: np.ndarray,
    z2_hat: np.ndarray,
    z1_measured: np.ndarray,
    gamma: np.ndarray,
    gains: EsoGains,
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """One explicit-Euler step of eq. (39); returns the new (z1_hat, z2_hat)."""
    eps1 = z1_measured - z1_hat
    z1_rate = gamma + z2_hat + gains.mu1 * sig(eps1, gains.r1)
    z2_rate = gains.mu2 * sig(eps1, gains.r2)
    return z1_hat + dt * z1_rate, z2_hat + dt * z2_rate
