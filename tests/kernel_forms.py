"""The compiled law's sections (agents/law_kernel.pyx) called on Python floats, for the tests
that check each at its own boundary against the numpy oracle (tests/paper_oracle.py) or use
it alone (the safety filter, the degradation): thin adapters of the ``*_of`` functions of
the tests' build of the kernel (tests/law_probe: the product's sections, each callable),
which unpack the gains as the kernel takes them. They live with the tests because nothing
else calls them: the agents run the kernel's whole step."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from math import inf

import numpy as np
from law_probe import load

from agents.behaviors import BehaviorOutput
from agents.controller import ControlConstants
from agents.degradation import DegradationConfig
from agents.eso import EsoGains
from agents.estimator import EstimatorGains
from agents.formation import ScaleChange
from agents.safety_filter import SafetyResult

_probe = load()  # built at the first import (law_probe)
Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


def sig_scalar(x: float, power: float) -> float:
    """sig^r(x) of one float, |x|^r sign(x) with sign(0) = 0 (NaN stays NaN)."""
    return _probe.sig_of(x, power)


def implicit_sign_scalar(e: float, reach: float) -> float:
    """The estimator's implicit sign() of one float (eq. 14, erratum 7)."""
    return _probe.implicit_sign_of(e, reach)


def estimator_step_vec(q_hat: Vec3, v_hat: Vec3, neighbour_q: Sequence[Vec3],
                       neighbour_v: Sequence[Vec3], weights: Sequence[float],
                       leader_weight: float, leader_q: Vec3 | None, leader_v: Vec3 | None,
                       gains: EstimatorGains, dt: float) -> tuple[Vec3, Vec3]:
    """One explicit-Euler step of eq. (14) on float triples."""
    return _probe.estimator_step_of(q_hat, v_hat, neighbour_q, neighbour_v, weights, leader_weight,
                             leader_q, leader_v, gains.iota, gains.eta, dt)


def eso_advance_vec(z1_hat: Vec3, z2_hat: Vec3, z1_measured: Vec3, gamma: Vec3,
                    gains: EsoGains, dt: float, max_step: float) -> tuple[Vec3, Vec3]:
    """Eq. (39) over ``dt`` in explicit-Euler sub-steps of at most ``max_step`` (the
    control period), the measurement and Gamma held: what a realtime agent whose state
    arrives late integrates (one step when dt is the period)."""
    return _probe.eso_advance_of(z1_hat, z2_hat, z1_measured, gamma, gains.mu1, gains.mu2, gains.r1,
                          gains.r2, dt, max_step)


def eso_step_vec(z1_hat: Vec3, z2_hat: Vec3, z1_measured: Vec3, gamma: Vec3, gains: EsoGains,
                 dt: float) -> tuple[Vec3, Vec3]:
    """One explicit-Euler step of eq. (39) on float triples."""
    return eso_advance_vec(z1_hat, z2_hat, z1_measured, gamma, gains, dt, dt)


def scale_at_vec(t: float, initial: Vec2, changes: Sequence[ScaleChange]
                 ) -> tuple[Vec2, Vec2]:
    """The formation's scale and its rate at t (eq. 48): ((sx, sy), (sx_dot, sy_dot))."""
    return _probe.scale_at_of(t, initial, changes)


def offsets_vec(r_i: Vec2, heading_offset: float, psi: float, psi_dot: float, scale: Vec2,
                scale_dot: Vec2) -> tuple[Vec3, Vec3]:
    """zeta_i = [W r_i, Xi_i] and zeta_i_dot, eq. (13)/(48)."""
    return _probe.offsets_of(r_i, heading_offset, psi, psi_dot, scale, scale_dot)


def desired_formation_vec(kappa1: float, kappa2: float, q0_hat: Vec3, v0_hat: Vec3,
                          zeta: Vec3, zeta_dot: Vec3, weights: Sequence[float],
                          neighbour_q: Sequence[Vec3], neighbour_q_dot: Sequence[Vec3],
                          neighbour_zeta: Sequence[Vec3], neighbour_zeta_dot: Sequence[Vec3]
                          ) -> tuple[Vec3, Vec3]:
    """q_fd,i of eq. (16) and its velocity, on float triples."""
    return _probe.desired_formation_of(kappa1, kappa2, q0_hat, v0_hat, zeta, zeta_dot, weights,
                                neighbour_q, neighbour_q_dot, neighbour_zeta,
                                neighbour_zeta_dot)


def control_term_vec(e: Vec3, e_dot: Vec3, z2_hat: Vec3, k: ControlConstants
                     ) -> tuple[Vec3, Vec3]:
    """(Gamma, s) of eq. (42) on float triples."""
    return _probe.control_term_of(e, e_dot, z2_hat, k.gamma_p, k.alpha, k.mu2, k.eps2, k.reach_low,
                           k.reach_high, k.s_div)


# --- the behaviors in reduced form (agents/law_kernel_sections/behaviours.pxi) ------------

@dataclass(slots=True)
class Task:
    """An active behavior in reduced form, as the compiled law holds it.

    J = [[g_x, g_y, 0], [0, 0, 1], [0, 0, 0]] is fixed by the gradient g, and
    J^+ = J^T diag(1/|row|^2) (paper_oracle.pinv_task_jacobian) by g and inv_g2.
    """

    name: str
    gx: float
    gy: float
    inv_g2: float  # 1/|g|^2, 0 for a zero row
    velocity: Vec3  # v
    task_error: float
    body: int = 0  # the body an avoidance task guards (its ident); 0 for FDB

    def to_output(self) -> BehaviorOutput:
        """The same behavior as a :class:`BehaviorOutput`."""
        return BehaviorOutput(
            self.name, True, np.array(self.velocity),
            np.array([[self.gx, self.gy, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]), self.task_error, self.body,
        )


def formation_task(q: Vec3, q_fd: Vec3, v_fd: Vec3, gains: tuple[float, float]) -> Task:
    """paper_oracle.formation_behavior reduced: FDB, eqs. (15)-(19)."""
    return Task("FDB", *_probe.formation_task_of(q, q_fd, v_fd, gains))


def avoidance_task_of(
    name: str,
    q: Vec3,
    other_xy: Vec2,
    contact_distance: float,
    safe_distance: float,
    phi_d: float,
    phi_d_dot: float,
    gains: tuple[float, float],
    body: int = 0,
) -> Task | None:
    """paper_oracle.avoidance_behavior reduced: FOCB (23)-(25) / FRCB (20)-(22); None if inactive.
    ``body``: the ident of the body guarded (kept on the task for the supervisor)."""
    reduced = _probe.avoidance_task_of_(name, q, other_xy, contact_distance, safe_distance, phi_d, phi_d_dot,
                         gains, body)
    return None if reduced is None else Task(name, *reduced, body)


# --- the supervisor and the fusion (agents/law_kernel_sections/fusion.pxi) ----------------

def fuse_tasks(ordered: Sequence[Task]) -> Vec3:
    """paper_oracle.fuse for active tasks, highest priority first: eq. (26)."""
    return _probe.fuse_of(list(ordered))


def supervise_tasks(ordered: Sequence[Task], engage: str) -> tuple[list[Task], Vec3]:
    """paper_oracle.supervise for active tasks (no limits), and the velocity of the chain it
    returns. "approaching" engages a task when the fused velocity closes on its body,
    J v < 0; each avoidance task guards one body (``Task.body``)."""
    tasks = list(ordered)
    chain, v = _probe.supervise_of(tasks, engage)
    return [tasks[i] for i in chain], v


# --- the safety filter (S1), (S2) (agents/law_kernel_sections/safety.pxi) -----------------

@dataclass(frozen=True)
class Guarded:
    """A perceived body as the filter needs it: centre, velocity, radius."""

    x: float
    y: float
    vx: float
    vy: float
    radius: float
    reciprocal: bool = False  # a robot that runs the filter too: (S2) instead of (S1)


@dataclass(frozen=True)
class SafetyLimits:
    """What the filter keeps and what it may ask of the robot (from the scenario)."""

    margin_m: float  # kept on top of contact (robot radius + body radius)
    brake_mps2: float  # a: how hard the reference may brake (inf: no limit)
    max_speed_mps: float = inf
    exit_time_s: float = 0.5  # inside the margin: leave it at (gap / exit_time) m/s


def closing_speed_limit(gap: float, brake: float, h: float, exit_time_s: float) -> float:
    """c_max(d) of (S1): the largest closing speed from which one more period and then
    braking at ``brake`` stop within ``gap``; negative (leave) inside the margin."""
    return _probe.closing_speed_limit_of(gap, brake, h, exit_time_s)


def stopping_distance(closing: float, brake: float, h: float) -> float:
    """The gap used up by one more period at ``closing`` m/s and braking at ``brake``
    after it: the left side of (S1), whose inverse is :func:`closing_speed_limit`."""
    return _probe.stopping_distance_of(closing, brake, h)


def safety_filter(v_nom: Vec2, v_prev: Vec2 | None, px: float, py: float, radius: float,
                  bodies: Sequence[Guarded], lim: SafetyLimits, h: float) -> SafetyResult:
    """The command closest to ``v_nom`` that keeps every barrier (agents/safety_filter.py); the
    bodies that run the filter too (``reciprocal``) by (S2)."""
    ordered = [b for b in bodies if not b.reciprocal] + [b for b in bodies if b.reciprocal]
    rows = [(0.0, b.x, b.y, b.vx, b.vy, b.radius) for b in ordered]
    n_obstacles = sum(1 for b in bodies if not b.reciprocal)
    v, active, binding, infeasible, dv = _probe.safety_filter_of(
        v_nom, v_prev, px, py, radius, rows, n_obstacles, lim.margin_m, lim.brake_mps2,
        lim.max_speed_mps, lim.exit_time_s, h)
    return SafetyResult(v if active else v_nom, active, binding, infeasible, dv)


def closest_feasible(v_nom: Vec2, lines: Sequence[tuple[float, float, float]],
                     discs: Sequence[tuple[float, float, float]]) -> Vec2 | None:
    """argmin |v - v_nom| over {n . v >= b for every line, |v - c| <= R for every disc};
    None when the set is empty. Exact: the optimum of this convex 2-D problem is v_nom
    or lies on one boundary (the projection of v_nom on it) or on two (where they meet)."""
    return _probe.closest_feasible_of(v_nom, lines, discs)


# --- the degradation (agents/law_kernel_sections/degradation.pxi) -------------------------

@dataclass(frozen=True)
class Freshest:
    """The agent's freshest source of leader information."""

    age_s: float  # link age plus the age of the source's own information
    q0: Vec3  # its leader pose (estimate), predicted to now over the link age
    v0: Vec3


def freshest_source(leader: tuple[Vec3, Vec3] | None, leader_age_s: float,
                    shares: list[tuple[Vec3, Vec3, float, float]]) -> Freshest | None:
    """Among the leader sample (if heard) and the neighbours' estimates, given as
    (q0_hat, v0_hat, link age, the neighbour's own information age), the one
    whose information is freshest. A neighbour's estimate is only as fresh as
    what it was built from: ages add up along the graph."""
    found = _probe.freshest_of(leader, leader_age_s, shares)
    return None if found is None else Freshest(*found)


def next_speed_factor(f: float, age_s: float, cfg: DegradationConfig, h: float) -> float:
    """The speed factor after a step of h with information ``age_s`` old:
    down as fast as the age says, up by at most h / slow_ramp_s."""
    return _probe.next_speed_factor_of(f, age_s, cfg.slow_after_s, cfg.slow_ramp_s, h)


def slow_down(v: Vec3, f: float, degraded_speed: float) -> Vec3:
    """v_d scaled so that its planar speed blends from |v| (f = 1) to
    min(|v|, degraded_speed) (f = 0); yaw rate scaled alike."""
    return v if f >= 1.0 else _probe.slow_down_of(v, f, degraded_speed)


def reacquire(q_hat: Vec3, v_hat: Vec3, q0: Vec3, v0: Vec3, cfg: DegradationConfig,
              h: float) -> tuple[Vec3, Vec3, bool]:
    """One step of the blend toward the leader (q0, v0); the third value is
    False once the position estimate is within ``reacquire_tol_m``."""
    return _probe.reacquire_of(q_hat, v_hat, q0, v0, cfg.reacquire_tau_s, cfg.reacquire_tol_m, h)
