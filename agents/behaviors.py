"""Elementary behaviors in fully actuated form, eqs. (15)-(25).

Every behavior has a task rho_bar = [rho, phi, 0] (eqs. 17, 21, 24), a 3x3
Jacobian J = d rho_bar / d q with rows [grad_xy rho, 0], [0, 0, 1], [0, 0, 0],
and a CLIK velocity (eqs. 19, 22, 25)

    v = J^+ (rho_bar_d_dot - d rho_bar/dt + Lambda (rho_bar_d - rho_bar)).

In FDB the explicit-time term d rho_bar/dt carries the motion of the formation
point, x_fd_dot = v0_hat + zeta_dot (eq. 16 differentiated, kappa2 = 0): the
leader estimate's velocity and the offset rate of the rotating, rescaling
formation. The authors' public script feeds forward only the first (its
formation feed-forward leaves out zeta_dot), so its robots lag their formation
points while psi(t) turns or S(t) changes (docs/errata.md, differences from the
script). The avoidance behaviors use rho_d_dot = 0 as printed: feeding the other
robot's velocity forward in FRCB makes two robots that avoid each other
compensate each other's motion, a loop with no restoring force on their common
radial velocity that the one-step delay turns unstable (seen at 1 kHz in the
paper scenario).
The heading row of every behavior tracks the formation heading phi_fd, so the
behaviors never fight over the heading.

Avoidance task (erratum 2): for contact distance d0 (sum of the two radii) and
safety threshold R > d0,

    rho(d) = R - R sin(pi (d + R - 2 d0) / (2 (R - d0)))

is 0 at contact (d = d0), R at d = R and increasing between. With d0 = r (point
obstacle, robot radius r) this is FOCB (23) as printed; with d0 = 2r it is FRCB
(20) with the denominator 2R - 4r (the printed 4R - 2r is neither 0 at contact
nor R at d = R). Desired value rho_d = R.

The arithmetic is the compiled law's (agents/law_kernel_sections/behaviours.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the behaviors' output type, which a lab's own law returns too
(agents/law_api.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BehaviorOutput:
    """Velocity, Jacobian and task error of one behavior at one instant."""

    name: str
    active: bool
    velocity: np.ndarray  # v (3,)
    jacobian: np.ndarray  # J (3, 3)
    task_error: float  # |rho_d - rho| of the first task row
    body: int = 0  # the body an avoidance behavior guards (its ident); 0 for FDB
