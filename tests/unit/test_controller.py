"""Fully actuated sliding-mode controller: eqs. (36), (37), (40)-(42), Theorem 3.3, errata 3 and 5.

Oracles: finite differences (psi's Jacobian), the Lyapunov identity of eqs. (45)/(47),
hand-evaluated numbers for eq. (42), the predefined-time claim sqrt(2) T_p of
Theorem 3.3 on the closed loop (37), and numpy.linalg.pinv for the allocation.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from kernel_forms import control_term_vec
from paper_oracle import (
    allocate,
    control_term,
    psi,
    psi_jacobian,
    reaching_term,
    saturate_torques,
    sliding_surface,
)

from agents.controller import ControlConstants, ControllerGains
from plant.mecanum import MecanumModel, RobotParams

G = ControllerGains()  # Table 2: alpha_p = 0.5, mu_p = 30, T_p = 4, upsilon = 1.5
SETTLING_BOUND_S = math.sqrt(2.0) * G.T_p  # 5.657 s, Theorem 3.3
SETTINGS = settings(max_examples=40, deadline=None)

comp = st.floats(-3.0, 3.0, allow_nan=False)
vec3 = st.tuples(comp, comp, comp).map(np.array)


def fd_jacobian(f, x, h):
    cols = []
    for k in range(x.size):
        dx = np.zeros_like(x)
        dx[k] = h
        cols.append((f(x + dx) - f(x - dx)) / (2 * h))
    return np.array(cols).T


def test_paper_gains_and_gamma_p():
    """Defaults are Table 2's controller parameters and gamma_p = 2 / (alpha mu T_p) = 1/30."""
    assert (G.alpha, G.mu, G.T_p, G.upsilon) == (0.5, 30.0, 4.0, 1.5)
    assert G.gamma_p == pytest.approx(1.0 / 30.0, rel=1e-15)


# --- psi and its derivative (erratum 5) ---------------------------------------------


@SETTINGS
@given(e=vec3)
def test_psi_jacobian_matches_finite_differences(e):
    """d psi / d e (used for psi_dot in (42)) equals the central-difference Jacobian of psi."""
    J = psi_jacobian(e, G)
    fd = fd_jacobian(lambda x: psi(x, G), e, 1e-6)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-6 * np.abs(J).max())


@SETTINGS
@given(direction=st.tuples(comp, comp, comp), size=st.floats(1e-5, 1e-3))
def test_psi_jacobian_matches_finite_differences_near_zero(direction, size):
    """Near e = 0 (|e| ~ 1e-5..1e-3, where the eps = 1e-3 regularisation matters) too."""
    d = np.array(direction)
    if np.linalg.norm(d) < 1e-3:
        d = np.array([1.0, -0.5, 0.2])
    e = size * d / np.linalg.norm(d)
    J = psi_jacobian(e, G)
    fd = fd_jacobian(lambda x: psi(x, G), e, 1e-9)
    np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-6 * np.abs(J).max())


def test_psi_is_finite_and_zero_at_origin():
    """psi(0) = 0 and psi, d psi/de are finite at e = 0 (regularised ||e||^-alpha, erratum 5)."""
    zero = np.zeros(3)
    np.testing.assert_array_equal(psi(zero, G), zero)
    J0 = psi_jacobian(zero, G)
    assert np.all(np.isfinite(J0))
    np.testing.assert_allclose(J0, J0[0, 0] * np.eye(3))  # isotropic at 0
    np.testing.assert_array_equal(sliding_surface(zero, zero, G), zero)


def test_psi_is_odd_and_radial():
    """psi(e) is parallel to e with a positive gain, and psi(-e) = -psi(e) (eq. 41)."""
    e = np.array([1.0, -0.5, 0.2])
    p = psi(e, G)
    np.testing.assert_allclose(np.cross(p, e), 0.0, atol=1e-12)
    assert p @ e > 0
    np.testing.assert_allclose(psi(-e, G), -p)


def test_scalar_gain_reading_of_psi_dot_is_wrong_for_radial_motion():
    """Reading psi_dot as gamma (|e|^-a + mu^2 |e|^a) e_dot (psi's scalar gain times e_dot) is not
    the time derivative of psi(e(t)) when e_dot has a radial part (erratum 5); the Jacobian is."""
    e = np.array([1.0, -0.5, 0.2])
    e_dot = np.array([0.4, -0.2, 0.08])  # radial: e_dot parallel to e
    h = 1e-6
    true_rate = (psi(e + h * e_dot, G) - psi(e - h * e_dot, G)) / (2 * h)
    n = math.sqrt(e @ e + G.psi_epsilon**2)
    scalar = G.gamma_p * (n**-G.alpha + G.mu**2 * n**G.alpha) * e_dot
    np.testing.assert_allclose(psi_jacobian(e, G) @ e_dot, true_rate, rtol=1e-7)
    assert np.linalg.norm(scalar - true_rate) > 0.3 * np.linalg.norm(true_rate)
    # tangential motion: both readings agree (the radial term a (...) e e^T vanishes)
    tangential = np.cross(e, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(
        psi_jacobian(e, G) @ tangential,
        G.gamma_p * (n**-G.alpha + G.mu**2 * n**G.alpha) * tangential,
        rtol=1e-12,
    )


# --- the reaching term of (42) -----------------------------------------------------------


@SETTINGS
@given(s=vec3)
def test_reaching_term_satisfies_the_lyapunov_identity_of_eq_47(s):
    """s^T r(s) = gamma_p (V^(1 - a/2) + mu^2 V^(1 + a/2)), V = |s|^2 / 2 (eqs. 45, 47): > 0 for s != 0."""
    # V^p written as |s|^(2p) / 2^p with |s| from a scaled norm: |s|^2 underflows to 0 for
    # |s| ~ 1e-200 where s^T r(s) does not (a hypothesis example failed so)
    n = float(np.linalg.norm(s))
    a = G.alpha
    expected = G.gamma_p * (n ** (2 - a) / 2 ** (1 - a / 2) + G.mu**2 * n ** (2 + a) / 2 ** (1 + a / 2))
    got = float(s @ reaching_term(s, G))
    if n < 1e-100:  # s^T r(s) ~ |s|^1.5 is near the float range's bottom: only its sign holds
        assert got >= 0.0
        return
    assert got == pytest.approx(expected, rel=1e-10, abs=1e-300)
    assert got > 0.0


def test_reaching_term_zero_at_origin_and_hand_value():
    """r(0) = 0; for s = [3, 4, 0] (|s| = 5) eq. (42)'s first term, evaluated by hand, is
    (1/30) (0.5^0.75 / sqrt(5) + 0.5^1.25 * 900 * sqrt(5)) s = [84.6401..., 112.8535..., 0]."""
    np.testing.assert_array_equal(reaching_term(np.zeros(3), G), np.zeros(3))
    np.testing.assert_allclose(
        reaching_term(np.array([3.0, 4.0, 0.0]), G), [84.64016107392858, 112.85354809857144, 0.0], rtol=1e-12
    )


# --- closed loop (37) and Theorem 3.3 --------------------------------------------------


def _closed_loop(e0, D, duration, dt=1e-4):
    """Euler integration of e_ddot = Gamma + D with z2_hat = D (perfect ESO); returns (t, |e|, |s|).
    Gamma from the compiled form the agents use (control_term_vec, equal to control_term:
    tests/unit/test_hot_path.py): 56,570 steps a run, 8x faster than the numpy form."""
    k_consts = ControlConstants.from_gains(G)
    d = tuple(float(x) for x in D)
    e, e_dot = tuple(float(x) for x in e0), (0.0, 0.0, 0.0)
    n = int(round(duration / dt)) + 1
    es, ss = np.empty(n), np.empty(n)
    for k in range(n):
        gamma, s = control_term_vec(e, e_dot, d, k_consts)
        es[k] = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        ss[k] = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
        e = (e[0] + dt * e_dot[0], e[1] + dt * e_dot[1], e[2] + dt * e_dot[2])
        e_dot = (e_dot[0] + dt * (gamma[0] + d[0]), e_dot[1] + dt * (gamma[1] + d[1]),
                 e_dot[2] + dt * (gamma[2] + d[2]))
    return np.arange(n) * dt, es, ss


def _first_time_below(t, values, bound):
    """Earliest time after which ``values`` stay below ``bound`` (inf if they end above it)."""
    above = np.nonzero(values >= bound)[0]
    if above.size == 0:
        return 0.0
    if above[-1] + 1 == t.size:
        return math.inf
    return float(t[above[-1] + 1])


@pytest.fixture(scope="module")
def settling_runs():
    D = np.array([0.3, -0.2, 0.1])
    e0 = np.array([1.0, -0.5, 0.2])
    small = _closed_loop(e0, D, SETTLING_BOUND_S)
    large = _closed_loop(20.0 * e0 / np.linalg.norm(e0), D, SETTLING_BOUND_S)
    return small, large


@pytest.mark.parametrize("which", [0, 1], ids=["|e0|=1.14", "|e0|=20"])
def test_tracking_error_settles_before_sqrt2_Tp(settling_runs, which):
    """Theorem 3.3: with the disturbance known (z2_hat = D), e and s are inside a small region
    (1e-3) before sqrt(2) T_p = 5.657 s, and stay there, from |e0| = 1.14 and from |e0| = 20."""
    t, e, s = settling_runs[which]
    bound = 1e-3
    assert _first_time_below(t, e, bound) < SETTLING_BOUND_S
    assert _first_time_below(t, s, bound) < SETTLING_BOUND_S
    assert e[-1] < 1e-4 and s[-1] < 1e-6


def test_settling_time_is_practically_independent_of_initial_error(settling_runs):
    """Predefined time: a 17x larger initial error changes the time to |e| < 1e-3 by < 0.3 s."""
    (t1, e1, _), (t2, e2, _) = settling_runs
    assert e2[0] / e1[0] > 17
    assert abs(_first_time_below(t1, e1, 1e-3) - _first_time_below(t2, e2, 1e-3)) < 0.3


def test_allocation_realises_the_closed_loop_37_on_the_model():
    """u = B_bar^-1 [q_d_ddot + A0 q_dot + A1 + Gamma; 0] (36, sign of 37, erratum 3) gives
    q_ddot - q_d_ddot = Gamma on the derived plant, with zero internal torque n^T u = 0, and
    u equals the minimum-norm pinv(B) solution."""
    model = MecanumModel.from_params(RobotParams())
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = np.array([*rng.normal(size=2), rng.uniform(-math.pi, math.pi)])
        q_dot, q_d_ddot = rng.normal(size=3), rng.normal(size=3)
        gamma, _ = control_term(rng.normal(size=3), rng.normal(size=3), np.zeros(3), G)
        phi = float(q[2])
        generalised = q_d_ddot + model.A0 @ q_dot + model.A1(phi, q_dot) + gamma
        u = allocate(model.augmented_input(phi), generalised)
        acc = model.acceleration(q, q_dot, u, np.zeros(4))
        np.testing.assert_allclose(acc - q_d_ddot, gamma, rtol=1e-9, atol=1e-9 * np.abs(gamma).max())
        assert abs(model.n @ u) < 1e-9 * np.abs(u).max()
        np.testing.assert_allclose(u, np.linalg.pinv(model.B(phi)) @ generalised, rtol=1e-9)


# --- torque limit ------------------------------------------------------------------------


@SETTINGS
@given(u=st.tuples(comp, comp, comp, comp).map(lambda x: 10.0 * np.array(x)), limit=st.floats(0.1, 20.0))
def test_saturate_torques_scales_uniformly(u, limit):
    """max |u_k| <= limit; one common factor in (0, 1] (the direction of u, hence of B u, is kept);
    torques already inside the limit pass unchanged."""
    out = saturate_torques(u, limit)
    assert np.abs(out).max() <= limit * (1 + 1e-12)
    if np.abs(u).max() <= limit:
        np.testing.assert_array_equal(out, u)
    else:
        factor = limit / np.abs(u).max()
        np.testing.assert_allclose(out, factor * u, rtol=1e-12)
        assert np.abs(out).max() == pytest.approx(limit, rel=1e-12)
