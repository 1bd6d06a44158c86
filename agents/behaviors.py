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
"""

from __future__ import annotations

from dataclasses import dataclass
from math import cos, pi, sin

import numpy as np

from agents.law_kernel import avoidance_task_of_ as _avoidance
from agents.law_kernel import formation_task_of
from agents.signals import Vec2, Vec3

_TINY = 1e-12


@dataclass(frozen=True)
class BehaviorOutput:
    """Velocity, Jacobian and task error of one behavior at one instant."""

    name: str
    active: bool
    velocity: np.ndarray  # v (3,)
    jacobian: np.ndarray  # J (3, 3)
    task_error: float  # |rho_d - rho| of the first task row
    body: int = 0  # the body an avoidance behavior guards (its ident); 0 for FDB


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


# --- the compiled law's reduced tasks (agents/law_kernel.pyx; tests/unit/test_hot_path.py
# checks them against formation_behavior and avoidance_behavior above) -------------------


@dataclass(slots=True)
class Task:
    """An active behavior in reduced form, as the compiled law holds it.

    J = [[g_x, g_y, 0], [0, 0, 1], [0, 0, 0]] is fixed by the gradient g, and
    J^+ = J^T diag(1/|row|^2) (:func:`pinv_task_jacobian`) by g and inv_g2.
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
            _task_jacobian(np.array((self.gx, self.gy))), self.task_error, self.body,
        )


def formation_task(q: Vec3, q_fd: Vec3, v_fd: Vec3, gains: tuple[float, float]) -> Task:
    """:func:`formation_behavior` reduced: FDB, eqs. (15)-(19)."""
    return Task("FDB", *formation_task_of(q, q_fd, v_fd, gains))


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
    """:func:`avoidance_behavior` reduced: FOCB (23)-(25) / FRCB (20)-(22); None if inactive.
    ``body``: the ident of the body guarded (kept on the task for the supervisor)."""
    reduced = _avoidance(name, q, other_xy, contact_distance, safe_distance, phi_d, phi_d_dot,
                         gains, body)
    return None if reduced is None else Task(name, *reduced, body)
