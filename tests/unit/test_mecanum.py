"""Mecanum robot model, paper eqs. (1)-(4), erratum 3 and docs/dynamics.md (no Coriolis term).

Every check here uses an oracle that does not come from the code under test:
the paper's printed matrices, numpy.linalg.pinv, closed-form singular values,
Newton's first law for a free body, and the power balance of the wheel torques.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plant.mecanum import (
    MecanumModel,
    RobotParams,
    generalised_inertia,
    paper_A0,
    paper_B,
    rotation,
    wheel_inertia_matrix,
    wheel_matrix,
)

PAPER = RobotParams()
MODEL = MecanumModel.from_params(PAPER)
FRICTIONLESS = RobotParams(static_friction=0.0, viscous_friction=0.0)
VISCOUS_ONLY = RobotParams(static_friction=0.0)

HEADINGS = np.linspace(-math.pi, math.pi, 360, endpoint=False)

angles = st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False)
speeds = st.floats(-5.0, 5.0, allow_nan=False)
twists = st.tuples(speeds, speeds, speeds).map(np.array)
torques = st.tuples(speeds, speeds, speeds, speeds).map(np.array)
SETTINGS = settings(max_examples=40, deadline=None)


def _rk4(f, x, dt):
    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


def _free_flight(model, q_dot0, torque, duration=2.0, dt=1e-3):
    """RK4 of eq. (4) with constant wheel torques and no disturbance; states [q, q_dot]."""
    zero = np.zeros(4)

    def f(x):
        return np.concatenate([x[3:], model.acceleration(x[:3], x[3:], torque, zero)])

    x = np.concatenate([np.zeros(3), q_dot0])
    states = [x]
    for _ in range(int(round(duration / dt))):
        x = _rk4(f, x, dt)
        states.append(x)
    return np.array(states)


def _kinetic_energy(q_dot):
    return 0.5 * q_dot @ generalised_inertia(PAPER) @ q_dot


# --- paper's printed matrices ------------------------------------------------------------


def test_paper_table2_defaults():
    """RobotParams() holds Table 2: R, m, I_z, I_w, 2l, 2w, C_f, C_theta, r."""
    p = PAPER
    assert p.wheel_radius_m == 0.0375
    assert p.mass_kg == 1.2
    assert p.inertia_z_kgm2 == 0.01
    assert p.inertia_wheel_kgm2 == 0.02
    assert 2 * p.half_wheelbase_m == pytest.approx(0.06)
    assert 2 * p.half_track_m == pytest.approx(0.04)
    assert p.static_friction == 0.125
    assert p.viscous_friction == 0.2
    assert p.body_radius_m == 0.5


def test_derived_B_equals_paper_B_for_all_headings():
    """The Euler-Lagrange B(phi) equals the printed B = R T P^+ M^-1 (eq. 4) at 360 headings."""
    for phi in HEADINGS:
        np.testing.assert_allclose(MODEL.B(phi), paper_B(PAPER, phi), rtol=1e-12, atol=1e-12)


def test_derived_A0_equals_paper_viscous_term():
    """Without the T dT^-1/dt term, the printed A0 (eq. 4) equals the derived constant A0."""
    for phi in HEADINGS[::10]:
        np.testing.assert_allclose(paper_A0(PAPER, phi, 0.0), MODEL.A0, rtol=1e-12, atol=1e-15)


def test_printed_pseudo_inverse_formula_is_not_evaluable_but_pinv_is_a_left_inverse():
    """P is 4x3: the printed P^+ = P^T (P P^T)^-1 (under eq. 1) needs a singular 4x4 inverse.

    The left inverse (P^T P)^-1 P^T is the Moore-Penrose inverse and recovers the
    twist: P^+ P = I.
    """
    P = wheel_matrix(PAPER)
    assert np.linalg.matrix_rank(P @ P.T) == 3
    left = np.linalg.inv(P.T @ P) @ P.T
    np.testing.assert_allclose(left, np.linalg.pinv(P), atol=1e-12)
    np.testing.assert_allclose(left @ P, np.eye(3), atol=1e-12)


# --- kinematics, eqs. (1)-(3) ------------------------------------------------------------


@SETTINGS
@given(phi=angles, q_dot=twists)
def test_kinematics_round_trip(phi, q_dot):
    """body_twist(wheel_speeds(phi, q_dot)) = T(phi)^T q_dot: eq. (1) with v_w = T v_r (eq. 3)."""
    v_r = MODEL.body_twist(MODEL.wheel_speeds(phi, q_dot))
    np.testing.assert_allclose(v_r, rotation(phi).T @ q_dot, atol=1e-10)


def test_wheel_speed_patterns_of_pure_motions():
    """Closed form of eq. (2): driving forward turns all wheels at v/R; strafing left and
    spinning give the X-pattern signs (-,+,+,-) and (l+w)/R (-,+,-,+)."""
    R, lw = PAPER.wheel_radius_m, PAPER.half_wheelbase_m + PAPER.half_track_m
    np.testing.assert_allclose(MODEL.wheel_speeds(0.0, np.array([1.0, 0, 0])), np.full(4, 1 / R))
    np.testing.assert_allclose(
        MODEL.wheel_speeds(0.0, np.array([0, 1.0, 0])), np.array([-1, 1, 1, -1]) / R
    )
    np.testing.assert_allclose(
        MODEL.wheel_speeds(0.0, np.array([0, 0, 1.0])), lw * np.array([-1, 1, -1, 1]) / R
    )
    # heading pi/2: a world-frame +x velocity is a body-frame -y (strafe right)
    np.testing.assert_allclose(
        MODEL.wheel_speeds(math.pi / 2, np.array([1.0, 0, 0])),
        np.array([1, -1, -1, 1]) / R,
        atol=1e-12,
    )


# --- internal force direction and B_bar (erratum 3) --------------------------------------


def test_internal_force_direction_is_the_null_space_of_B():
    """n: P^T n = 0, |n| = 1 and B(phi) n = 0 for every heading (wheel torques that move nothing)."""
    n = MODEL.n
    assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(wheel_matrix(PAPER).T @ n, 0.0, atol=1e-12)
    for phi in HEADINGS[::7]:
        np.testing.assert_allclose(MODEL.B(phi) @ n, 0.0, atol=1e-12)


def _closed_form_singular_values(p):
    """Singular values of [B; n^T]: rows of B are orthogonal, |column k of P| / (R M_q,kk)."""
    R, lw = p.wheel_radius_m, p.half_wheelbase_m + p.half_track_m
    m_t = p.mass_kg + 4 * p.inertia_wheel_kgm2 / R**2
    i_t = p.inertia_z_kgm2 + 4 * p.inertia_wheel_kgm2 * lw**2 / R**2
    return np.sort([2 / (R * m_t), 2 / (R * m_t), 2 * lw / (R * i_t), 1.0])


def test_augmented_input_is_invertible_and_equally_conditioned_at_all_headings():
    """B_bar = [B; n^T] (erratum 3) is invertible and its condition number does not depend on phi.

    B_bar(phi) = diag(T(phi), 1) B_bar(0) and diag(T, 1) is orthogonal, so the singular
    values are those of B_bar(0), which have the closed form of _closed_form_singular_values
    (about 19.08 for Table 2). The max over 360 headings must equal that value.
    """
    expected = _closed_form_singular_values(PAPER)
    expected_cond = expected[-1] / expected[0]
    conds = []
    for phi in HEADINGS:
        Bb = MODEL.augmented_input(phi)
        assert Bb.shape == (4, 4)
        np.testing.assert_allclose(np.sort(np.linalg.svd(Bb, compute_uv=False)), expected, rtol=1e-12)
        conds.append(np.linalg.cond(Bb))
    assert max(conds) == pytest.approx(np.linalg.cond(MODEL.augmented_input(0.0)), rel=1e-9)
    assert max(conds) == pytest.approx(expected_cond, rel=1e-9)
    assert expected_cond < 20.0


@SETTINGS
@given(phi=angles, v=twists)
def test_augmented_solve_is_the_minimum_norm_allocation(phi, v):
    """solve([B; n^T], [v; 0]) = pinv(B) v: the minimum-norm wheel torques (erratum 3)."""
    u = np.linalg.solve(MODEL.augmented_input(phi), np.append(v, 0.0))
    B = MODEL.B(phi)
    np.testing.assert_allclose(u, np.linalg.pinv(B) @ v, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(B @ u, v, rtol=1e-9, atol=1e-9)


def test_printed_B_bar_with_zero_row_is_singular():
    """The printed B_bar = [B; 0_{1x4}] of eq. (34) has rank 3 (erratum 3): it has no inverse."""
    for phi in (0.0, 0.7, 2.0):
        printed = np.vstack([paper_B(PAPER, phi), np.zeros(4)])
        assert np.linalg.matrix_rank(printed) == 3
        assert abs(np.linalg.det(printed)) < 1e-12


# --- dynamics, eq. (4) ----------------------------------------------------------------


def test_wheel_space_energy_equals_generalised_energy():
    """1/2 theta_dot^T M theta_dot (paper's M) = 1/2 q_dot^T M_q q_dot (derived M_q) for
    theta_dot = wheel_speeds(phi, q_dot): the paper's M and the Lagrangian agree."""
    M = wheel_inertia_matrix(PAPER)
    Mq = generalised_inertia(PAPER)
    rng = np.random.default_rng(1)
    for _ in range(50):
        phi = rng.uniform(-math.pi, math.pi)
        q_dot = rng.normal(size=3) * np.array([2.0, 2.0, 5.0])
        theta_dot = MODEL.wheel_speeds(phi, q_dot)
        assert 0.5 * theta_dot @ M @ theta_dot == pytest.approx(0.5 * q_dot @ Mq @ q_dot, rel=1e-12)


def test_free_spinning_robot_keeps_momentum_and_energy():
    """No torque, no friction: a robot spinning at 3 rad/s keeps its world-frame linear
    velocity and its kinetic energy (Newton's first law; RK4, 2 s)."""
    model = MecanumModel.from_params(FRICTIONLESS)
    q_dot0 = np.array([1.0, 0.5, 3.0])
    states = _free_flight(model, q_dot0, np.zeros(4))
    assert abs(states[-1, 2] - 6.0) < 1e-9  # it did spin: phi = 3 rad/s * 2 s
    np.testing.assert_allclose(states[:, 3:], np.tile(q_dot0, (len(states), 1)), atol=1e-6)
    energy = np.array([_kinetic_energy(x[3:]) for x in states])
    np.testing.assert_allclose(energy, _kinetic_energy(q_dot0), atol=1e-6)
    np.testing.assert_allclose(states[-1, :2], 2.0 * q_dot0[:2], atol=1e-6)  # straight line


def test_paper_A0_would_accelerate_a_free_spinning_robot():
    """The printed A0 contains T dT^-1/dt = phi_dot [[0,1,0],[-1,0,0],[0,0,0]]: for the same free
    robot, -A0_paper q_dot is nonzero (it would turn the world-frame velocity with the body),
    which is why the derived model drops it (module docstring, docs/dynamics.md)."""
    q_dot = np.array([1.0, 0.5, 3.0])
    model = MecanumModel.from_params(FRICTIONLESS)
    paper_acc = -paper_A0(FRICTIONLESS, 0.3, q_dot[2]) @ q_dot
    assert np.linalg.norm(paper_acc) > 1.0
    np.testing.assert_allclose(paper_acc, [-1.5, 3.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(
        model.acceleration(np.array([0, 0, 0.3]), q_dot, np.zeros(4), np.zeros(4)), 0.0, atol=1e-12
    )


@SETTINGS
@given(phi=angles, q_dot=twists, u=torques)
def test_power_of_wheel_torques_equals_rate_of_kinetic_energy(phi, q_dot, u):
    """Virtual work (frictionless): q_dot^T M_q q_ddot = theta_dot^T u for any torques u."""
    model = MecanumModel.from_params(FRICTIONLESS)
    acc = model.acceleration(np.array([0.0, 0.0, phi]), q_dot, u, np.zeros(4))
    power_in = model.wheel_speeds(phi, q_dot) @ u
    dK = q_dot @ generalised_inertia(FRICTIONLESS) @ acc
    assert dK == pytest.approx(power_in, rel=1e-9, abs=1e-9)


@SETTINGS
@given(phi=angles, q_dot=twists)
def test_viscous_friction_dissipates_C_theta_R2_theta_dot_squared(phi, q_dot):
    """Zero torque, viscous friction only: dK/dt = -C_theta R^2 |theta_dot|^2 (rim viscous torque)."""
    model = MecanumModel.from_params(VISCOUS_ONLY)
    acc = model.acceleration(np.array([0.0, 0.0, phi]), q_dot, np.zeros(4), np.zeros(4))
    theta_dot = model.wheel_speeds(phi, q_dot)
    dK = q_dot @ generalised_inertia(VISCOUS_ONLY) @ acc
    expected = -VISCOUS_ONLY.viscous_friction * VISCOUS_ONLY.wheel_radius_m**2 * theta_dot @ theta_dot
    assert dK == pytest.approx(expected, rel=1e-9, abs=1e-12)


@SETTINGS
@given(phi=angles, q_dot=twists)
def test_full_friction_never_adds_energy(phi, q_dot):
    """Zero torque, Table 2 friction (viscous + smoothed Coulomb): dK/dt <= 0."""
    acc = MODEL.acceleration(np.array([0.0, 0.0, phi]), q_dot, np.zeros(4), np.zeros(4))
    assert q_dot @ generalised_inertia(PAPER) @ acc <= 1e-12


def test_viscous_friction_energy_decreases_monotonically_at_the_first_principles_rate():
    """A coasting robot with viscous friction only loses kinetic energy at every step (RK4, 2 s).

    First principles: every wheel turns at v/R (translation) or (l+w) w/R (spin), each
    rim torque C_theta R^2 theta_dot, so v decays at 4 C_theta / m_t and w at
    4 C_theta (l+w)^2 / I_t (P's columns are orthogonal, the modes do not mix).
    """
    p = VISCOUS_ONLY
    model = MecanumModel.from_params(p)
    q_dot0 = np.array([1.0, 0.5, 3.0])
    dt = 2e-3
    states = _free_flight(model, q_dot0, np.zeros(4), duration=2.0, dt=dt)
    Mq = generalised_inertia(p)
    energy = np.array([0.5 * x[3:] @ Mq @ x[3:] for x in states])
    assert np.all(np.diff(energy) < 0.0)

    R, lw = p.wheel_radius_m, p.half_wheelbase_m + p.half_track_m
    m_t = p.mass_kg + 4 * p.inertia_wheel_kgm2 / R**2
    i_t = p.inertia_z_kgm2 + 4 * p.inertia_wheel_kgm2 * lw**2 / R**2
    a_xy, a_phi = 4 * p.viscous_friction / m_t, 4 * p.viscous_friction * lw**2 / i_t
    t = dt * np.arange(len(states))
    translation = 0.5 * m_t * (q_dot0[:2] @ q_dot0[:2]) * np.exp(-2 * a_xy * t)
    spin = 0.5 * i_t * q_dot0[2] ** 2 * np.exp(-2 * a_phi * t)
    expected = translation + spin
    np.testing.assert_allclose(energy, expected, rtol=1e-9)


@SETTINGS
@given(phi=angles, q_dot=twists, u=torques, c=st.floats(-50.0, 50.0, allow_nan=False))
def test_internal_torque_does_not_change_acceleration(phi, q_dot, u, c):
    """Adding c n (internal wheel torque, P^T n = 0) to any torques leaves q_ddot unchanged."""
    q = np.array([0.3, -0.2, phi])
    base = MODEL.acceleration(q, q_dot, u, np.zeros(4))
    np.testing.assert_allclose(MODEL.acceleration(q, q_dot, u + c * MODEL.n, np.zeros(4)), base, atol=1e-9)
    np.testing.assert_allclose(
        MODEL.acceleration(q, q_dot, c * MODEL.n, np.zeros(4)),
        MODEL.acceleration(q, q_dot, np.zeros(4), np.zeros(4)),
        atol=1e-9,
    )
