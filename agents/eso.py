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

The arithmetic is the compiled law's (agents/law_kernel_sections/eso.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the gains.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EsoGains:
    mu1: float = 0.6
    mu2: float = 0.2
    r1: float = 0.7

    @property
    def r2(self) -> float:
        return 2.0 * self.r1 - 1.0
