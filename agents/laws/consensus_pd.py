"""``consensus-pd``: second-order (PD) consensus tracking with artificial-potential
avoidance, at the torque level: the robot's acceleration by consensus, its wheel torques
by the inverse of eq. (4), with no sliding mode and no observer (docs/laws.md). A
baseline for what the paper's fully actuated controller adds.

Second-order consensus with a reference (Ren and Atkins, "Distributed multi-vehicle
coordination control via local information exchange", Int. J. Robust Nonlinear Control
17(10-11), 2007; W. Ren, "Second-order consensus algorithm with extensions to switching
topologies and reference models", ACC 2007): with formation points xi_i = p_i - delta_i
as in ``consensus``,

    (P1)  xi_i_ddot = - sum_j a_ij [ k_p (xi_i - xi_j) + k_d (xi_i_dot - xi_j_dot) ]
                      - b_i [ k_p (xi_i - xi_0) + k_d (xi_i_dot - xi_0_dot) ],

which for a directed spanning tree rooted at the leader and k_d^2 / k_p large enough
drives xi_i - xi_0 to 0 for a leader at constant velocity (a steady lag when it
accelerates: no feed-forward of the leader's acceleration, which the shares do not
carry). The heading: psi_ddot = k_psi wrap(psi_f + Xi_i - psi) + k_dpsi (psi_f_dot -
psi_dot) (P2), with psi_f the leader estimate of ``consensus`` (C2). Avoidance adds the
FIRAS gradient of ``consensus`` (C4) as an acceleration, less a damping of the closing
speed (P3). The wheel torques are the minimum-norm ones that give that acceleration by
eq. (4): u = B(psi)^+ (q_ddot + A0 q_dot + A1(q_dot)) (P4). The runtime's safety filter
and torque limit apply after it (agents/plugged.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agents.core import Share
from agents.law_api import LawInputs, TorqueLaw, TorqueOutput
from agents.laws.consensus import ConsensusLaw, _delta, _wrap


@dataclass(frozen=True)
class ConsensusPdParams:
    k_p: float = 4.0  # (P1), 1/s^2
    k_d: float = 4.0  # (P1), 1/s
    k_psi: float = 8.0  # (P2), 1/s^2
    k_dpsi: float = 5.0  # (P2), 1/s
    k_rep: float = 0.2  # (P3): the FIRAS gain, as an acceleration, m^4/s^2
    rho0: float = 0.6  # (P3): influence distance, m
    max_rep: float = 4.0  # (P3): largest repulsion acceleration, m/s^2


class ConsensusPdLaw(TorqueLaw):
    name = "consensus-pd"
    Params = ConsensusPdParams

    # the leader estimate (C2) and the initial share, as consensus does them
    _estimate = ConsensusLaw._estimate
    start = ConsensusLaw.start

    def step(self, x: LawInputs) -> TorqueOutput:
        p, cfg = self.params, self.cfg
        q0, v0 = self._estimate(x)
        dx, dy, ddx, ddy = _delta(x, q0[2], v0[2])
        xi = (x.q[0] - dx, x.q[1] - dy)
        xi_dot = (x.q_dot[0] - ddx, x.q_dot[1] - ddy)
        acc = [0.0, 0.0]
        for j, a in cfg.neighbours:  # (P1), the neighbours' terms
            sh = x.shares.get(j)
            if sh is None:
                continue
            age = x.share_ages_s.get(j, 0.0)
            for k in range(2):
                xi_j = sh.q[k] + sh.q_dot[k] * age - sh.zeta[k]
                acc[k] -= a * (p.k_p * (xi[k] - xi_j)
                               + p.k_d * (xi_dot[k] - (sh.q_dot[k] - sh.zeta_dot[k])))
        if x.leader is not None and cfg.leader_weight != 0.0:  # (P1), the leader's term
            for k in range(2):
                acc[k] -= cfg.leader_weight * (p.k_p * (xi[k] - x.leader[0][k])
                                               + p.k_d * (xi_dot[k] - x.leader[1][k]))
        for body in (*x.obstacles, *x.robots):  # (P3)
            ex, ey = x.q[0] - body[1], x.q[1] - body[2]
            dist = math.hypot(ex, ey)
            rho = dist - cfg.robot_radius_m - body[5]
            if dist <= 0.0 or rho >= p.rho0:
                continue
            nx, ny = ex / dist, ey / dist
            push = p.max_rep if rho <= 0.0 else min(
                p.k_rep * (1.0 / rho - 1.0 / p.rho0) / (rho * rho), p.max_rep)
            closing = min(0.0, (x.q_dot[0] - body[3]) * nx + (x.q_dot[1] - body[4]) * ny)
            acc[0] += (push - p.k_d * closing) * nx
            acc[1] += (push - p.k_d * closing) * ny
        psi_dd = (p.k_psi * _wrap(q0[2] + cfg.heading_offset - x.q[2])  # (P2)
                  + p.k_dpsi * (v0[2] - x.q_dot[2]))
        torques = self._torques(x, (acc[0], acc[1], psi_dd))
        share = Share(q0, v0, x.q, x.q_dot, (dx, dy, cfg.heading_offset), (ddx, ddy, 0.0))
        return TorqueOutput(torques, share, target=(q0[0] + dx, q0[1] + dy, q0[2]))

    def _torques(self, x: LawInputs, q_ddot: tuple[float, float, float]
                 ) -> tuple[float, float, float, float]:
        """(P4): u = B(psi)^+ (q_ddot + A0 q_dot + A1), the minimum-norm allocation
        (the augmented input of eq. 34, erratum 3, with zero internal torque)."""
        m = self.cfg.model
        qd = np.asarray(x.q_dot, dtype=float)
        rhs = np.asarray(q_ddot, dtype=float) + m.A0 @ qd + m.A1(x.q[2], qd)
        u = np.linalg.solve(m.augmented_input(x.q[2]), np.append(rhs, 0.0))
        return tuple(float(v) for v in u)  # type: ignore[return-value]
