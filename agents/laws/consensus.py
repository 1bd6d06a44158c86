"""``consensus``: first-order consensus tracking of a virtual leader (Ren and Beard) with
artificial-potential avoidance (Khatib), at the behavior level: a baseline beside the
paper's law, on the same robots and scenarios (docs/laws.md).

Formation as consensus (Ren and Beard, *Distributed Consensus in Multi-vehicle
Cooperative Control*, Springer 2008, Sec. 3.3, consensus tracking with a time-varying
reference state): robot i's *formation point* xi_i = p_i - delta_i (its planar position
less its offset, rotated with the formation's heading) tracks the leader's position
xi_0 = p_0 by

    (C1)  xi_i_dot = [ sum_j a_ij (xi_j_dot - gamma (xi_i - xi_j))
                       + b_i (xi_0_dot - gamma (xi_i - xi_0)) ] / (sum_j a_ij + b_i),

which, for a directed graph with a spanning tree rooted at the leader, drives every
xi_i - xi_0 to 0 exponentially (ibid., Theorem 3.8). The formation's heading and yaw
rate are each robot's leader estimate (C2): the leader's own where b_i != 0, else the
weighted mean of its neighbours' estimates (their shares), each predicted to now by
its age (x + x_dot age). The heading is held by psi_dot = psi0_dot + k_psi wrap(psi_f +
Xi_i - psi) (C3).

Avoidance (Khatib, "Real-time obstacle avoidance for manipulators and mobile robots",
IJRR 5(1), 1986): a body at surface gap rho < rho0 pushes the robot away along the
line between their centres at

    (C4)  v_rep = k_rep (1/rho - 1/rho0) / rho^2,  at most max_rep,

the gradient of the FIRAS potential U = k_rep/2 (1/rho - 1/rho0)^2. The command is
v_d = (xi_i_dot + delta_i_dot + sum v_rep, psi_dot). The runtime's explicit limits and
safety filter apply after it, as to the paper's fused velocity.

Share: q0_hat, v0_hat the leader estimate (C2); q, q_dot the robot's state; zeta = (delta_i,
Xi_i), zeta_dot = (delta_i_dot, 0): what (C1) and (C2) read of a neighbour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from agents.core import Share
from agents.law_api import BehaviorLaw, BehaviorOutput, LawInputs


@dataclass(frozen=True)
class ConsensusParams:
    gamma: float = 2.0  # consensus gain of (C1), 1/s
    k_psi: float = 2.0  # heading gain of (C3), 1/s
    k_rep: float = 0.05  # repulsion gain of (C4), m^3/s
    rho0: float = 0.6  # influence distance of (C4): gap beyond which a body is ignored, m
    max_rep: float = 1.5  # largest repulsion speed, m/s


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _turned(r: tuple[float, float], psi: float) -> tuple[float, float]:
    c, s = math.cos(psi), math.sin(psi)
    return c * r[0] - s * r[1], s * r[0] + c * r[1]


def _delta(x: LawInputs, psi: float, psi_dot: float) -> tuple[float, float, float, float]:
    """delta_i = Rot(psi) S(t) r_i of eq. (13) and its rate: the offset turns with the
    formation and follows its scale."""
    dx, dy = _turned(x.offset, psi)
    rx, ry = _turned(x.offset_rate, psi)
    return dx, dy, rx - psi_dot * dy, ry + psi_dot * dx


class ConsensusLaw(BehaviorLaw):
    name = "consensus"
    Params = ConsensusParams

    def _estimate(self, x: LawInputs) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(C2): the leader's pose and velocity, as this robot knows them now."""
        if x.leader is not None and self.cfg.leader_weight != 0.0:
            return tuple(x.leader[0]), tuple(x.leader[1])
        total, q0, v0 = 0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        for j, a in self.cfg.neighbours:
            s = x.shares.get(j)
            if s is None:
                continue
            age = x.share_ages_s.get(j, 0.0)
            for k in range(3):
                q0[k] += a * (s.q0_hat[k] + s.v0_hat[k] * age)
                v0[k] += a * s.v0_hat[k]
            total += a
        if total == 0.0:  # nothing heard yet: hold where we are
            return tuple(x.q), (0.0, 0.0, 0.0)
        return tuple(v / total for v in q0), tuple(v / total for v in v0)

    def start(self, q, q_dot, q0_hat, v0_hat) -> Share:
        dx, dy = _turned(self.cfg.offset, q0_hat[2])
        return Share(q0_hat, v0_hat, q, q_dot, (dx, dy, self.cfg.heading_offset),
                     (-v0_hat[2] * dy, v0_hat[2] * dx, 0.0))

    def step(self, x: LawInputs) -> BehaviorOutput:
        p = self.params
        q0, v0 = self._estimate(x)
        dx, dy, ddx, ddy = _delta(x, q0[2], v0[2])
        xi = (x.q[0] - dx, x.q[1] - dy)
        num = [0.0, 0.0]
        eta = 0.0
        for j, a in self.cfg.neighbours:  # (C1), the neighbours' terms
            sh = x.shares.get(j)
            if sh is None:
                continue
            age = x.share_ages_s.get(j, 0.0)
            for k in range(2):
                xi_j = sh.q[k] + sh.q_dot[k] * age - sh.zeta[k]
                xi_j_dot = sh.q_dot[k] - sh.zeta_dot[k]
                num[k] += a * (xi_j_dot - p.gamma * (xi[k] - xi_j))
            eta += a
        b = self.cfg.leader_weight if x.leader is not None else 0.0
        for k in range(2):  # (C1), the leader's term
            num[k] += b * (x.leader[1][k] - p.gamma * (xi[k] - x.leader[0][k])) if b else 0.0
        eta += b
        xi_dot = (num[0] / eta, num[1] / eta) if eta > 0.0 else (v0[0], v0[1])
        vx, vy = xi_dot[0] + ddx, xi_dot[1] + ddy
        for body in (*x.obstacles, *x.robots):  # (C4)
            ex, ey = x.q[0] - body[1], x.q[1] - body[2]
            dist = math.hypot(ex, ey)
            rho = dist - self.cfg.robot_radius_m - body[5]
            if 0.0 < rho < p.rho0 and dist > 0.0:
                push = min(p.k_rep * (1.0 / rho - 1.0 / p.rho0) / (rho * rho), p.max_rep)
                vx, vy = vx + push * ex / dist, vy + push * ey / dist
            elif rho <= 0.0 and dist > 0.0:  # touching: straight out
                vx, vy = vx + p.max_rep * ex / dist, vy + p.max_rep * ey / dist
        w = v0[2] + p.k_psi * _wrap(q0[2] + self.cfg.heading_offset - x.q[2])  # (C3)
        share = Share(q0, v0, x.q, x.q_dot, (dx, dy, self.cfg.heading_offset),
                      (ddx, ddy, 0.0))
        return BehaviorOutput((vx, vy, w), share, target=(q0[0] + dx, q0[1] + dy, q0[2]))
