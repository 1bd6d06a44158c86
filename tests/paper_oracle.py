"""The paper's law in numpy: the independent form the compiled law is checked against.

The product computes every equation once, in the compiled kernel (agents/law_kernel.pyx
and its sections in agents/law_kernel_sections/, one per part of the law). This module
writes the same equations again in the paper's matrix form (numpy arrays, the Jacobians
and projectors as matrices, no shared code with the kernel), so that the tests can hold
the kernel to something that was not derived from it: tests/unit/test_hot_path.py checks
each section at its own boundary (through the tests' build of the kernel, tests/law_probe)
and the whole step (:class:`ReferenceCore`) against the forms here, and the modules
tests/unit/test_{formation,behaviors,fusion,controller,estimator,eso}.py check these forms
against the paper's claims and physical facts. Why the numpy form is worth keeping beside
the kernel: a slip in a hand-expanded C loop (a sign, an index, a missed term of the
Jacobian) shows up as a difference here, while a test of the kernel against itself would
pass. Nothing in the product imports this module.

The modules of agents/ named in each part below hold the gains, the types and the prose of
each equation with its errata (docs/errata.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from math import cos, pi, sin

import numpy as np
from kernel_forms import Guarded, SafetyLimits, safety_filter, stopping_distance

from agents.behaviors import BehaviorOutput
from agents.controller import ControllerGains
from agents.core import AgentConfig, AgentOutput, Share
from agents.eso import EsoGains
from agents.estimator import EstimatorGains
from agents.formation import scale_at

# --- the small maps (agents/signals.py): Notation 1 and the smooth norm of eqs. (41)-(42) ---

def sig(x: np.ndarray, power: float) -> np.ndarray:
    """sig^r(x) = |x|^r sign(x), element-wise (Notation 1 of the paper)."""
    return np.abs(x) ** power * np.sign(x)


def smooth_norm(x: np.ndarray, eps: float) -> float:
    """||x||_eps = sqrt(||x||^2 + eps^2): a norm that is smooth at 0.

    Used where the paper divides by ||x|| with a negative power (eqs. 41-42).
    """
    return float(np.sqrt(float(x @ x) + eps * eps))


# --- the formation (agents/formation.py): offsets (13)/(48), the reference (16) -----------

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


# --- the leader estimator (agents/estimator.py): eq. (14), its implicit sign --------------

def consensus_errors(
    own: np.ndarray,
    neighbours: Sequence[np.ndarray],
    weights: Sequence[float],
    leader_weight: float,
    leader: np.ndarray | None,
) -> np.ndarray:
    """sum_j a_ij (own - x_j) + b_i (own - x_leader), the bracket of eq. (14)."""
    err = np.zeros_like(own)
    for w, x in zip(weights, neighbours, strict=False):
        err += w * (own - x)
    if leader_weight != 0.0 and leader is not None:
        err += leader_weight * (own - leader)
    return err


def implicit_sign(e: np.ndarray, reach: float) -> np.ndarray:
    """sign(e) discretised implicitly: e / reach clipped to [-1, 1] (reach > 0)."""
    if reach <= 0.0:
        return np.sign(e)
    return np.clip(e / reach, -1.0, 1.0)


def estimator_rates(
    q_hat: np.ndarray,
    v_hat: np.ndarray,
    e_q: np.ndarray,
    e_v: np.ndarray,
    gains: EstimatorGains,
    sign_reach: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Right-hand side of eq. (14) given the consensus errors.

    ``sign_reach`` = (deg iota2 dt, deg iota4 dt) selects the implicit sign; zeros
    give the plain sign of the continuous-time law.
    """
    i1, i2, i3, i4 = gains.iota
    n1, n2 = gains.eta
    q_rate = -i1 * sig(e_q, n1) - i2 * implicit_sign(e_q, sign_reach[0]) + v_hat
    v_rate = -i3 * sig(e_v, n2) - i4 * implicit_sign(e_v, sign_reach[1])
    return q_rate, v_rate


def estimator_step(
    q_hat: np.ndarray,
    v_hat: np.ndarray,
    neighbour_q: Sequence[np.ndarray],
    neighbour_v: Sequence[np.ndarray],
    weights: Sequence[float],
    leader_weight: float,
    leader_q: np.ndarray | None,
    leader_v: np.ndarray | None,
    gains: EstimatorGains,
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """One explicit-Euler step of eq. (14); returns the new (q0_hat, v0_hat)."""
    e_q = consensus_errors(q_hat, neighbour_q, weights, leader_weight, leader_q)
    e_v = consensus_errors(v_hat, neighbour_v, weights, leader_weight, leader_v)
    deg = float(sum(weights)) + (leader_weight if leader_q is not None else 0.0)
    reach = (deg * gains.iota[1] * dt, deg * gains.iota[3] * dt)
    q_rate, v_rate = estimator_rates(q_hat, v_hat, e_q, e_v, gains, reach)
    return q_hat + dt * q_rate, v_hat + dt * v_rate


# --- the behaviors (agents/behaviors.py): FDB (15)-(19), FRCB (20)-(22), FOCB (23)-(25) ---

_TINY = 1e-12


def pinv_task_jacobian(J: np.ndarray) -> np.ndarray:
    """Moore-Penrose inverse of a task Jacobian whose rows are mutually orthogonal.

    All three behaviors have rows [g_x, g_y, 0], [0, 0, 1], [0, 0, 0], so
    J^+ = J^T diag(1/|row|^2) (zero rows stay zero). ``tests`` check this
    against numpy.linalg.pinv.
    """
    norms = np.einsum("ij,ij->i", J, J)
    inv = np.where(norms > _TINY, 1.0 / np.where(norms > _TINY, norms, 1.0), 0.0)
    return J.T * inv


def heading_row_rate(phi: float, phi_d: float, phi_d_dot: float, gain: float) -> float:
    """Heading row of every behavior: phi_d_dot + lambda_phi (phi_d - phi)."""
    return phi_d_dot + gain * (phi_d - phi)


def _task_jacobian(gradient_xy: np.ndarray) -> np.ndarray:
    return np.array(
        [[gradient_xy[0], gradient_xy[1], 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]
    )


def formation_behavior(
    q: np.ndarray,
    q_fd: np.ndarray,
    v_fd: np.ndarray,
    gains: tuple[float, float],
) -> BehaviorOutput:
    """FDB, eqs. (15)-(19): rho_f = ||x - x_fd||, desired 0; heading to phi_fd."""
    diff = q[:2] - q_fd[:2]
    dist = float(np.hypot(diff[0], diff[1]))
    grad = diff / dist if dist > _TINY else np.zeros(2)  # J undefined at 0: zero row
    J = _task_jacobian(grad)
    # d rho/dt = -grad . x_fd_dot (moving target), so -d rho/dt = grad . x_fd_dot
    rate = np.array(
        [
            float(grad @ v_fd[:2]) + gains[0] * (0.0 - dist),
            heading_row_rate(q[2], q_fd[2], v_fd[2], gains[1]),
            0.0,
        ]
    )
    J_pinv = pinv_task_jacobian(J)
    # The task's own null space carries the rest of the formation velocity:
    # J (I - J^+ J) = 0, so the task dynamics of (19) are unchanged, but without
    # it v_f = g g^T x_fd_dot - k (x - x_fd) jumps wherever g = (x - x_fd)/|x - x_fd|
    # turns, i.e. all the time once the robot sits on its target, and the fused
    # command chatters at the control rate (docs/errata.md, "FDB null space").
    own_null = np.array([v_fd[0], v_fd[1], 0.0])
    own_null = own_null - J_pinv @ (J @ own_null)
    return BehaviorOutput("FDB", True, J_pinv @ rate + own_null, J, dist)


def avoidance_task(d: float, safe: float, contact: float) -> tuple[float, float]:
    """(rho, d rho / d d) of the avoidance task (erratum 2), valid for d > contact."""
    k = pi / (2.0 * (safe - contact))
    arg = k * (d + safe - 2.0 * contact)
    return safe - safe * sin(arg), -safe * k * cos(arg)


def avoidance_behavior(
    name: str,
    q: np.ndarray,
    other_xy: np.ndarray,
    contact_distance: float,
    safe_distance: float,
    phi_d: float,
    phi_d_dot: float,
    gains: tuple[float, float],
    min_gap: float = 1e-3,
    body: int = 0,
) -> BehaviorOutput:
    """FOCB (23)-(25) / FRCB (20)-(22) against one body at ``other_xy`` (ident ``body``).

    Active only inside the safety threshold (d < R). Inside contact the task
    would fold back (sin is symmetric about contact) and push inwards; the
    distance is floored at contact + ``min_gap`` so the push stays outwards.
    """
    diff = q[:2] - other_xy
    d = float(np.hypot(diff[0], diff[1]))
    if d >= safe_distance:
        return BehaviorOutput(name, False, np.zeros(3), np.zeros((3, 3)), 0.0, body)
    direction = diff / d if d > _TINY else np.array([1.0, 0.0])
    d_eff = max(d, contact_distance + min_gap)
    rho, drho_dd = avoidance_task(d_eff, safe_distance, contact_distance)
    grad = drho_dd * direction
    J = _task_jacobian(grad)
    rate = np.array(
        [
            gains[0] * (safe_distance - rho),
            heading_row_rate(q[2], phi_d, phi_d_dot, gains[1]),
            0.0,
        ]
    )
    return BehaviorOutput(name, True, pinv_task_jacobian(J) @ rate, J, safe_distance - rho, body)


# --- the supervisor and the null-space fusion (agents/fusion.py): eq. (26) ----------------

def null_space_projector(J: np.ndarray) -> np.ndarray:
    return np.eye(J.shape[1]) - pinv_task_jacobian(J) @ J


def fuse(ordered: Sequence[BehaviorOutput]) -> np.ndarray:
    """Eq. (26) for any number of behaviors, highest priority first."""
    v = np.zeros(3)
    for b in reversed([b for b in ordered if b.active]):
        v = b.velocity + null_space_projector(b.jacobian) @ v
    return v


AVOIDANCE = ("FOCB", "FRCB")


def supervise(ordered: Sequence[BehaviorOutput], engage: str,
              limit: Callable[[np.ndarray], np.ndarray] | None = None) -> list[BehaviorOutput]:
    """The behaviors that take part in (26), highest priority first. ``limit``: what
    the agent does to the fused velocity before commanding it; "approaching" judges
    J v < 0 on the limited velocity (as the kernel's supervisor does:
    tests/kernel_forms.py supervise_tasks)."""
    lim = limit or (lambda v: v)
    active = [b for b in ordered if b.active]
    if engage == "inside":
        return active
    if engage != "approaching":
        raise ValueError(f"unknown avoidance engage mode {engage!r}")
    engaged: set[tuple[str, int]] = set()
    while True:  # `engaged` only grows, at most once per avoidance behavior and body
        chain = [b for b in active if b.name not in AVOIDANCE or (b.name, b.body) in engaged]
        fused = fuse(chain)
        v = lim(fused)
        now = engaged | {
            (b.name, b.body) for b in active
            if b.name in AVOIDANCE and min(float(b.jacobian[0] @ fused), float(b.jacobian[0] @ v)) < 0.0
        }
        if now == engaged:
            return chain
        engaged = now


def order_by_priority(
    outputs: Sequence[BehaviorOutput], priority: Sequence[str]
) -> list[BehaviorOutput]:
    rank = {name: k for k, name in enumerate(priority)}
    return sorted(outputs, key=lambda b: rank[b.name])


def saturate_velocity(v: np.ndarray, max_speed: float, max_yaw_rate: float) -> np.ndarray:
    """Explicit scenario limit on the fused command: |v_xy| <= max_speed, |w| <= max_yaw_rate."""
    out = v.copy()
    speed = float(np.hypot(v[0], v[1]))
    if speed > max_speed:
        out[:2] *= max_speed / speed
    out[2] = float(np.clip(v[2], -max_yaw_rate, max_yaw_rate))
    return out


# --- the fully actuated law (agents/controller.py): eqs. (36), (40)-(42) ------------------

def psi(e: np.ndarray, g: ControllerGains) -> np.ndarray:
    """psi(e) of eq. (41), regularised at 0 (erratum 5)."""
    n = smooth_norm(e, g.psi_epsilon)
    return g.gamma_p * (n ** (-g.alpha) + g.mu**2 * n**g.alpha) * e


def psi_jacobian(e: np.ndarray, g: ControllerGains) -> np.ndarray:
    """d psi / d e, so that psi_dot = psi_jacobian(e) @ e_dot (erratum 5)."""
    a, mu2 = g.alpha, g.mu**2
    n = smooth_norm(e, g.psi_epsilon)
    scalar = n ** (-a) + mu2 * n**a
    radial = a * (mu2 * n ** (a - 2.0) - n ** (-a - 2.0))
    return g.gamma_p * (scalar * np.eye(e.size) + radial * np.outer(e, e))


def sliding_surface(e: np.ndarray, e_dot: np.ndarray, g: ControllerGains) -> np.ndarray:
    """s of eq. (40)."""
    return e_dot + psi(e, g)


def reaching_term(s: np.ndarray, g: ControllerGains) -> np.ndarray:
    """The first term of eq. (42) (without the minus sign)."""
    ns = float(np.linalg.norm(s))
    if ns == 0.0:
        return np.zeros_like(s)
    a = g.alpha
    k = 0.5 ** ((2.0 - a) / 2.0) * ns ** (-a) + 0.5 ** ((2.0 + a) / 2.0) * g.mu**2 * ns**a
    return g.gamma_p * k * s


def control_term(
    e: np.ndarray, e_dot: np.ndarray, z2_hat: np.ndarray, g: ControllerGains
) -> tuple[np.ndarray, np.ndarray]:
    """(Gamma, s) of eq. (42)."""
    s = sliding_surface(e, e_dot, g)
    psi_dot = psi_jacobian(e, g) @ e_dot
    gamma = -reaching_term(s, g) - z2_hat - psi_dot - s / (2.0 * g.upsilon**2)
    return gamma, s


def allocate(B_bar: np.ndarray, generalised: np.ndarray) -> np.ndarray:
    """u = B_bar^-1 [generalised; 0]: the minimum-norm wheel torques (eq. 36)."""
    return np.linalg.solve(B_bar, np.append(generalised, 0.0))


def saturate_torques(u: np.ndarray, limit: float) -> np.ndarray:
    """Scale all four torques by one factor so that max |u_k| <= limit.

    One common factor keeps the direction of the generalised force.
    """
    peak = float(np.max(np.abs(u)))
    if peak > limit:
        return u * (limit / peak)
    return u


# --- the extended state observer (agents/eso.py): eq. (39) --------------------------------

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


# --- the whole step: AgentCore.step composed of the forms above ---------------------------

class ReferenceCore:
    """AgentCore.step composed of the numpy forms above (as it was first written with them);
    the safety filter, which has no matrix form, is the kernel's (tests/kernel_forms.py)."""

    def __init__(self, cfg: AgentConfig, q_init, q_dot_init, q0_hat_init, v0_hat_init) -> None:
        self.cfg = cfg
        self.q0_hat, self.v0_hat = np.array(q0_hat_init, float), np.array(v0_hat_init, float)
        self.q_d = np.array(q_init, float)
        self.v_d_prev = self.z1_hat = self.last_h = None
        self.z2_hat = np.zeros(3)
        self.r_i = np.array(cfg.offset, float)
        self.weights = [w for _, w in cfg.neighbours]

    def offsets(self, t):
        cfg = self.cfg
        s, sd = scale_at(t, cfg.initial_scale, cfg.scale_changes)
        return offsets(self.r_i, cfg.heading_offset, float(self.q0_hat[2]), float(self.v0_hat[2]), s, sd)

    def behaviors(self, q, q_dot, q_fd, v_fd, obstacles, robots, h):
        cfg = self.cfg
        out = [formation_behavior(q, q_fd, v_fd, cfg.fdb_gains)] if "FDB" in cfg.enabled else []
        for name, bodies, safe, surface, gains in (
            ("FOCB", obstacles, cfg.obstacle_safe_m, True, cfg.focb_gains),
            ("FRCB", robots, cfg.robot_safe_m, False, cfg.frcb_gains),
        ):
            if name not in cfg.enabled or not bodies:
                continue
            if cfg.guard != "every":
                bodies = [min(bodies, key=lambda b: float(np.hypot(*(q[:2] - b.position))) - b.radius)]
            tasks = []
            for b in bodies:
                contact = cfg.robot_radius_m + b.radius
                n = (q[:2] - b.position) / np.linalg.norm(q[:2] - b.position)
                closing = max(float(-n @ (v[:2] - b.velocity)) for v in
                              ([q_dot] if self.v_d_prev is None else [q_dot, self.v_d_prev]))
                engage = contact + cfg.safety_margin_m + stopping_distance(closing, cfg.max_accel_mps2, h)
                out_b = avoidance_behavior(name, q, b.position, contact,
                                           max(safe + (b.radius if surface else 0.0), engage),
                                           float(q_fd[2]), float(v_fd[2]), gains, body=b.ident)
                if out_b.active:
                    tasks.append((float(np.linalg.norm(q[:2] - b.position)) - b.radius, out_b))
            out.extend(b for _, b in sorted(tasks, key=lambda gb: gb[0]))
        return out

    def limited(self, v, h):
        cfg = self.cfg
        v = saturate_velocity(v, cfg.max_speed_mps, cfg.max_yaw_rate_radps)
        if self.v_d_prev is not None and (math.isfinite(cfg.max_accel_mps2)
                                          or math.isfinite(cfg.max_yaw_accel_radps2)):
            v = self.v_d_prev + saturate_velocity(v - self.v_d_prev, cfg.max_accel_mps2 * h,
                                                  cfg.max_yaw_accel_radps2 * h)
        return v

    def filtered(self, v_d, q, obstacles, robots, h):
        cfg = self.cfg
        bodies = [Guarded(*b.position, *b.velocity, b.radius) for b in obstacles]
        bodies += [Guarded(*b.position, *b.velocity, b.radius, True) for b in robots]
        if not cfg.safety_filter or not bodies:
            return v_d
        prev = None if self.v_d_prev is None else tuple(self.v_d_prev[:2])
        lim = SafetyLimits(cfg.safety_margin_m, cfg.max_accel_mps2, cfg.max_speed_mps,
                           cfg.safety_exit_time_s)
        r = safety_filter(tuple(v_d[:2]), prev, float(q[0]), float(q[1]), cfg.robot_radius_m,
                          bodies, lim, h)
        return np.array([*r.v, v_d[2]])

    def step(self, t, q, q_dot, shares, leader, obstacles=(), robots=(), dt=None,
             own_torques=True) -> AgentOutput:
        cfg, model = self.cfg, self.cfg.model
        h = cfg.dt if dt is None else dt
        if not own_torques or (self.last_h is not None and h != self.last_h):
            self.z1_hat = None  # the observer restarts from the measurement (AgentCore.step)
        self.last_h = h
        # a step later than the period the last one advanced by: the estimate and the
        # reference carried to now at their rates, then advanced by the period
        lag = h - cfg.dt if self.v_d_prev is not None and h > cfg.dt * (1.0 + 1e-9) else 0.0
        if lag:
            self.q0_hat = self.q0_hat + self.v0_hat * lag
            self.q_d = self.q_d + self.v_d_prev * lag
        advance = h - lag
        nbr = [shares[j] for j, _ in cfg.neighbours]
        zeta, zeta_dot = self.offsets(t)
        q_fd, v_fd = desired_formation(
            cfg.kappa1, cfg.kappa2, self.q0_hat, self.v0_hat, zeta, zeta_dot, self.weights,
            *[[np.asarray(getattr(s, f), float) for s in nbr] for f in ("q", "q_dot", "zeta", "zeta_dot")],
        )
        chain = supervise(order_by_priority(self.behaviors(q, q_dot, q_fd, v_fd, obstacles, robots, h),
                                            cfg.priority), cfg.avoidance_engage,
                          lambda v: self.limited(v, h))
        v_d = self.filtered(self.limited(fuse(chain), h), q, obstacles, robots, h)
        phi = float(q[2])
        v_ref = v_d if self.v_d_prev is None else self.v_d_prev
        e = q - self.q_d
        if np.linalg.norm(e) > cfg.max_tracking_error:  # anti-windup: q_d within the bound
            self.q_d = q - e * (cfg.max_tracking_error / np.linalg.norm(e))
            e = q - self.q_d
        e_dot = q_dot - v_ref
        if self.z1_hat is None:
            self.z1_hat = e_dot.copy()
        gamma, s = control_term(e, e_dot, self.z2_hat, cfg.controller)
        generalised = (v_d - v_ref) / h + model.A0 @ q_dot + model.A1(phi, q_dot) + gamma
        torques = saturate_torques(allocate(model.augmented_input(phi), generalised), cfg.max_wheel_torque_nm)
        nonfinite = not bool(np.all(np.isfinite(torques)))
        if nonfinite:
            torques = np.zeros(4)
        n = max(1, math.ceil(advance / cfg.dt - 1e-9))  # (39) in sub-steps of at most the period
        for _ in range(n):
            self.z1_hat, self.z2_hat = eso_step(self.z1_hat, self.z2_hat, e_dot, gamma, cfg.eso,
                                                advance / n)
        q_d_now = self.q_d
        self.q_d = self.q_d + 0.5 * advance * (v_ref + v_d)
        self.v_d_prev = v_d
        lq, lv = leader if leader is not None else (None, None)
        self.q0_hat, self.v0_hat = estimator_step(
            self.q0_hat, self.v0_hat, [np.asarray(s.q0_hat, float) for s in nbr],
            [np.asarray(s.v0_hat, float) for s in nbr],
            self.weights, cfg.leader_weight, lq, lv, cfg.estimator, advance,
        )
        share = Share(self.q0_hat.copy(), self.v0_hat.copy(), q.copy(), q_dot.copy(), zeta, zeta_dot)
        if not bool(np.all(np.isfinite(v_d))):
            nonfinite, v_d = True, np.zeros(3)
        errors: dict[str, float] = {}
        for b in chain:
            errors.setdefault(b.name, b.task_error)
        return AgentOutput(torques, v_d, share, e, s, q_d_now, q_fd,
                           tuple(dict.fromkeys(b.name for b in chain)), errors, self.z2_hat,
                           nonfinite)
