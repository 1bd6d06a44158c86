"""Mecanum-wheel robot model, paper eqs. (1)-(4), derived from first principles.

Pure math, no I/O. Everything here is a function of the robot's physical
parameters (:class:`RobotParams`) and, where needed, the heading ``phi``.

Derivation (full text in ``docs/dynamics.md``)
----------------------------------------------
Generalised coordinates q = [x, y, phi] (world frame). No-slip rollers give the
inverse kinematics theta_dot = (1/R) P T(phi)^T q_dot  (inverse of eq. 1).
Kinetic energy  K = 1/2 m |xy_dot|^2 + 1/2 I_z phi_dot^2 + 1/2 I_w |theta_dot|^2.
Because P^T P = diag(4, 4, 4(l+w)^2), the inertia seen in q is

    M_q = diag(m + 4 I_w/R^2, m + 4 I_w/R^2, I_z + 4 I_w (l+w)^2/R^2),

isotropic in x, y: it commutes with T(phi), so the world-frame equations have
no Coriolis/centripetal term. Virtual work of wheel torques tau gives the
generalised force (1/R) T P^T tau. Hence

    q_ddot = -A0 q_dot - A1 + B (u + h_d),          (eq. 4 with d = B h_d)
    B  = (1/R) M_q^-1 T P^T = R T P^+ M^-1           (paper's B, identical)
    A0 = C_theta R^2 T P^+ M^-1 P T^-1 = C_theta R^2 Lambda^-1   (constant)
    A1 = R T P^+ M^-1 tau_c(theta_dot)

with M the paper's 4x4 wheel-space inertia (third printing in the paper; the
columns of P are eigenvectors of M with eigenvalues Lambda). C_theta is taken,
as the paper's R^2 factor implies, as a viscous force coefficient at the rim
(wheel torque C_theta R^2 theta_dot); C_f as a rolling-resistance coefficient on
a quarter of the weight per wheel (wheel torque C_f m g R / 4 sign(theta_dot)).

Where the paper differs (checked in ``tests/unit/test_mecanum.py``):
* A0 contains T(phi) d/dt T^-1(phi) = phi_dot [[0,1,0],[-1,0,0],[0,0,0]]. That
  term does not exist in the world frame for an isotropic M_q (momentum of a
  free robot is conserved); it is dropped here.
* A1 = R^2 T P^+ M^-1 C_f m g is a 3x4 matrix times a scalar, not a vector; the
  Coulomb torque vector tau_c above is what it stands for. sign() is smoothed
  with tanh(theta_dot / omega_s) so the plant stays integrable.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import cos, sin

import numpy as np

GRAVITY_MPS2 = 9.81


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of one mecanum robot (paper Table 1/Table 2)."""

    wheel_radius_m: float = 0.0375  # R
    mass_kg: float = 1.2  # m
    inertia_z_kgm2: float = 0.01  # I_z
    inertia_wheel_kgm2: float = 0.02  # I_w
    half_wheelbase_m: float = 0.03  # l
    half_track_m: float = 0.02  # w
    static_friction: float = 0.125  # C_f
    viscous_friction: float = 0.2  # C_theta
    body_radius_m: float = 0.5  # r
    coulomb_smoothing_radps: float = 0.5  # omega_s in tanh(theta_dot/omega_s)


def wheel_matrix(p: RobotParams) -> np.ndarray:
    """P of eq. (2): wheel speeds (times R) from body twist."""
    lw = p.half_wheelbase_m + p.half_track_m
    return np.array(
        [[1.0, -1.0, -lw], [1.0, 1.0, lw], [1.0, 1.0, -lw], [1.0, -1.0, lw]]
    )


def rotation(phi: float) -> np.ndarray:
    """T(phi) of eq. (3)."""
    c, s = cos(phi), sin(phi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def wheel_inertia_matrix(p: RobotParams) -> np.ndarray:
    """The paper's M (4x4 wheel-space inertia), consistent third printing."""
    R, lw = p.wheel_radius_m, p.half_wheelbase_m + p.half_track_m
    m1 = p.mass_kg * R**2 / 8.0
    m2 = p.inertia_z_kgm2 * R**2 / (16.0 * lw**2)
    m3 = m1 + m2 + p.inertia_wheel_kgm2
    m4 = m1 - m2
    return np.array(
        [[m3, -m2, m2, m4], [-m2, m3, m4, m2], [m2, m4, m3, -m2], [m4, m2, -m2, m3]]
    )


def generalised_inertia(p: RobotParams) -> np.ndarray:
    """M_q = diag(m + 4I_w/R^2, m + 4I_w/R^2, I_z + 4I_w(l+w)^2/R^2) (derived)."""
    R, lw = p.wheel_radius_m, p.half_wheelbase_m + p.half_track_m
    mt = p.mass_kg + 4.0 * p.inertia_wheel_kgm2 / R**2
    it = p.inertia_z_kgm2 + 4.0 * p.inertia_wheel_kgm2 * lw**2 / R**2
    return np.diag([mt, mt, it])


def internal_force_direction(p: RobotParams) -> np.ndarray:
    """Unit n with P^T n = 0: wheel torques along n move nothing (null space of B)."""
    P = wheel_matrix(p)
    # The last right-singular vector of P^T spans its null space.
    n = np.linalg.svd(P.T)[2][-1]
    return n / np.linalg.norm(n) * (1.0 if n[0] >= 0 else -1.0)


@dataclass(frozen=True)
class MecanumModel:
    """Precomputed constant parts of eq. (4) for one parameter set."""

    params: RobotParams
    P: np.ndarray
    body_input: np.ndarray  # B in the body frame: B(phi) = T(phi) @ body_input
    A0: np.ndarray  # constant in the world frame (see module docstring)
    n: np.ndarray  # null direction of B (internal wheel torque)
    inv_Mq: np.ndarray
    coulomb_torque_nm: float
    viscous_torque_per_radps: float

    @classmethod
    def from_params(cls, p: RobotParams) -> MecanumModel:
        R = p.wheel_radius_m
        P = wheel_matrix(p)
        inv_Mq = np.linalg.inv(generalised_inertia(p))
        body_input = inv_Mq @ P.T / R
        visc = p.viscous_friction * R**2
        A0 = visc * inv_Mq @ P.T @ P / R**2
        return cls(
            params=p,
            P=P,
            body_input=body_input,
            A0=A0,
            n=internal_force_direction(p),
            inv_Mq=inv_Mq,
            coulomb_torque_nm=p.static_friction * p.mass_kg * GRAVITY_MPS2 * R / 4.0,
            viscous_torque_per_radps=visc,
        )

    def B(self, phi: float) -> np.ndarray:
        """Input matrix B(phi) of eq. (4), 3x4."""
        return rotation(phi) @ self.body_input

    def wheel_speeds(self, phi: float, q_dot: np.ndarray) -> np.ndarray:
        """theta_dot = (1/R) P T(phi)^T q_dot (inverse of eq. 1)."""
        return self.P @ (rotation(phi).T @ q_dot) / self.params.wheel_radius_m

    def body_twist(self, wheel_speeds: np.ndarray) -> np.ndarray:
        """v_r = R P^+ theta_dot, eq. (1)."""
        return self.params.wheel_radius_m * np.linalg.pinv(self.P) @ wheel_speeds

    def coulomb_torques(self, phi: float, q_dot: np.ndarray) -> np.ndarray:
        """Smoothed Coulomb wheel torques tau_c(theta_dot) (stand-in for A1's C_f m g)."""
        w = self.wheel_speeds(phi, q_dot)
        return self.coulomb_torque_nm * np.tanh(w / self.params.coulomb_smoothing_radps)

    def A1(self, phi: float, q_dot: np.ndarray) -> np.ndarray:
        """A1 of eq. (4) as a 3-vector: B(phi) tau_c."""
        return self.B(phi) @ self.coulomb_torques(phi, q_dot)

    def acceleration(
        self, q: np.ndarray, q_dot: np.ndarray, torques: np.ndarray, disturbance: np.ndarray
    ) -> np.ndarray:
        """q_ddot from eq. (4): q_ddot = -A0 q_dot - A1 + B (u + h_d)."""
        phi = float(q[2])
        return -self.A0 @ q_dot - self.A1(phi, q_dot) + self.B(phi) @ (torques + disturbance)

    def augmented_input(self, phi: float) -> np.ndarray:
        """B_bar of eq. (34), erratum 3: [B; n^T] instead of [B; 0].

        The printed B_bar = [B; 0_{1x4}] is singular. Appending the internal-force
        direction n (P^T n = 0) and demanding n^T u = 0 makes B_bar invertible,
        and B_bar^-1 [v; 0] is then exactly the minimum-norm allocation B^+ v.
        """
        return np.vstack([self.B(phi), self.n])


def paper_A0(p: RobotParams, phi: float, phi_dot: float) -> np.ndarray:
    """A0 exactly as printed under eq. (4), for comparison with the derivation."""
    R = p.wheel_radius_m
    T = rotation(phi)
    Pp = np.linalg.pinv(wheel_matrix(p))
    Minv = np.linalg.inv(wheel_inertia_matrix(p))
    T_dT_inv = phi_dot * np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    return T_dT_inv + p.viscous_friction * R**2 * T @ Pp @ Minv @ wheel_matrix(p) @ T.T


def paper_B(p: RobotParams, phi: float) -> np.ndarray:
    """B exactly as printed under eq. (4): R T P^+ M^-1."""
    R = p.wheel_radius_m
    return R * rotation(phi) @ np.linalg.pinv(wheel_matrix(p)) @ np.linalg.inv(
        wheel_inertia_matrix(p)
    )
