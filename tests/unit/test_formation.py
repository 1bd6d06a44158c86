"""Time-varying formation: scale steps, offsets (13)/(48), desired reference (16); errata 1 and 4.

Oracles: finite differences in time, pairwise distances of the printed and the
authors' offsets, and the fixed-point property of an achieved formation.
"""

import itertools
import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from paper_oracle import desired_formation, offsets

from agents.formation import ScaleChange, scale_at, smooth_step

SETTINGS = settings(max_examples=40, deadline=None)
R_BODY = 0.5
AUTHORS_R = [np.array([0.0, 0.0]), np.array([-4.0, -4.0]), np.array([-4.0, 4.0])]  # erratum 1
PRINTED_R = [np.array(c) for c in np.array([[0.0, -4.0, -4.0], [0.0, -4.0, -4.0]]).T]  # eq. (48)
PAPER_CHANGES = (
    ScaleChange(9.84, 10.84, (1.0, 0.5)),
    ScaleChange(11.04, 12.04, (1.0, 0.0)),
    ScaleChange(15.0, 16.0, (1.0, 1.0)),
)


def central(f, t, h=1e-6):
    return (np.asarray(f(t + h)) - np.asarray(f(t - h))) / (2 * h)


# --- smooth_step ----------------------------------------------------------------


def test_smooth_step_is_0_before_1_after_and_monotone():
    """0 up to the window start, 1 from its end, non-decreasing in between, derivative >= 0."""
    start, end = 2.0, 3.5
    for t in (-5.0, 0.0, start):
        assert smooth_step(t, start, end) == (0.0, 0.0)
    for t in (end, 4.0, 100.0):
        assert smooth_step(t, start, end) == (1.0, 0.0)
    ts = np.linspace(start, end, 3001)
    values = np.array([smooth_step(t, start, end)[0] for t in ts])
    rates = np.array([smooth_step(t, start, end)[1] for t in ts])
    assert np.all(np.diff(values) >= 0.0)
    assert np.all(rates >= 0.0)
    assert smooth_step(0.5 * (start + end), start, end)[0] == pytest.approx(0.5, abs=1e-12)


@SETTINGS
@given(start=st.floats(-10.0, 10.0), width=st.floats(0.1, 5.0), frac=st.floats(0.01, 0.99))
def test_smooth_step_derivative_matches_finite_difference(start, width, frac):
    """The returned rate is d value / dt inside the window."""
    end = start + width
    t = start + frac * width
    fd = central(lambda x: smooth_step(x, start, end)[0], t, 1e-6 * width)
    assert smooth_step(t, start, end)[1] == pytest.approx(float(fd), rel=1e-5, abs=1e-7)


@pytest.mark.parametrize("start,end", [(0.0, 1.0), (9.84, 10.84), (-3.0, 7.0)])
def test_smooth_step_is_continuous_at_window_edges(start, end):
    """No jump in the value at either edge: the inner limits equal 0 and 1."""
    tiny = 1e-9 * (end - start)
    assert smooth_step(start + tiny, start, end)[0] == pytest.approx(0.0, abs=1e-9)
    assert smooth_step(end - tiny, start, end)[0] == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("start,end", [(0.0, 1.0), (9.84, 10.84), (-3.0, 7.0)])
def test_smooth_step_rate_jump_at_edges_is_tiny(start, end):
    """The rate is not exactly continuous at the edges (a Gaussian truncated at +-4 sigma):
    just inside, it is exp(-8) = 3.4e-4 of the peak rate, and 0 outside."""
    tiny = 1e-9 * (end - start)
    peak = smooth_step(0.5 * (start + end), start, end)[1]
    for t in (start + tiny, end - tiny):
        assert smooth_step(t, start, end)[1] == pytest.approx(math.exp(-8.0) * peak, rel=1e-6)


def test_scale_follows_the_paper_passages():
    """S = diag(1,1) normal, diag(1,0.5) middle, diag(1,0) narrow, back to diag(1,1) (Section 4)."""
    for t, expected in ((0.0, (1, 1)), (10.9, (1, 0.5)), (13.0, (1, 0)), (20.0, (1, 1))):
        s, s_dot = scale_at(t, (1.0, 1.0), PAPER_CHANGES)
        np.testing.assert_allclose(s, expected, atol=1e-12)
        np.testing.assert_allclose(s_dot, 0.0, atol=1e-12)


@pytest.mark.parametrize("t", [9.9, 10.3, 10.8, 11.5, 15.5])
def test_scale_rate_matches_finite_difference(t):
    """S_dot = d S / dt inside the transition windows."""
    fd = central(lambda x: scale_at(x, (1.0, 1.0), PAPER_CHANGES)[0], t)
    np.testing.assert_allclose(scale_at(t, (1.0, 1.0), PAPER_CHANGES)[1], fd, rtol=1e-5, atol=1e-7)


# --- offsets zeta (13)/(48) -----------------------------------------------------------------


@SETTINGS
@given(
    t=st.floats(9.0, 16.5),
    psi0=st.floats(-math.pi, math.pi),
    psi_rate=st.floats(-2.0, 2.0),
    rx=st.floats(-5.0, 5.0),
    ry=st.floats(-5.0, 5.0),
    xi=st.floats(-1.0, 1.0),
)
def test_offset_rate_matches_finite_difference_in_time(t, psi0, psi_rate, rx, ry, xi):
    """zeta_dot = d zeta / dt while the formation turns (psi(t) = psi0 + psi_rate t) and its
    scale S(t) changes through the paper's passages (away from the window edges, where S_dot
    has the small jump of test_smooth_step_rate_jump_at_edges_is_tiny)."""
    edges = [e for c in PAPER_CHANGES for e in (c.start_s, c.end_s)]
    assume(min(abs(t - e) for e in edges) > 1e-4)
    r = np.array([rx, ry])

    def zeta_at(time):
        s, s_dot = scale_at(time, (1.0, 1.0), PAPER_CHANGES)
        return offsets(r, xi, psi0 + psi_rate * time, psi_rate, s, s_dot)

    fd = central(lambda time: zeta_at(time)[0], t)
    np.testing.assert_allclose(zeta_at(t)[1], fd, rtol=1e-5, atol=1e-6)


def test_offset_is_rotated_scaled_nominal_position():
    """zeta = [Rot(psi) S r, Xi]: r = (-4, 4), S = diag(1, 0.5), psi = pi/2 gives (-2, -4)."""
    zeta, _ = offsets(np.array([-4.0, 4.0]), 0.25, math.pi / 2, 0.0, np.array([1.0, 0.5]), np.zeros(2))
    np.testing.assert_allclose(zeta, [-2.0, -4.0, 0.25], atol=1e-12)


def _positions(rs, scale=(1.0, 1.0), psi=0.0):
    return [offsets(r, 0.0, psi, 0.0, np.array(scale), np.zeros(2))[0][:2] for r in rs]


def test_authors_offsets_keep_robots_apart_and_printed_ones_do_not():
    """Erratum 1: with r = (0,0), (-4,-4), (-4,4) and S = I every pair of slots is farther apart
    than 2r = 1 m (at any formation heading); the printed r puts robots 2 and 3 on one spot."""
    for psi in np.linspace(-math.pi, math.pi, 13):
        pos = _positions(AUTHORS_R, psi=psi)
        for a, b in itertools.combinations(pos, 2):
            assert np.linalg.norm(a - b) > 2 * R_BODY
    printed = _positions(PRINTED_R)
    assert np.linalg.norm(printed[1] - printed[2]) == 0.0


# --- desired reference (16), erratum 4 ------------------------------------------------


def _zeta(r):
    return offsets(r, 0.1, 0.6, 0.3, np.array([1.0, 0.5]), np.array([0.0, -0.2]))


def test_desired_formation_kappa2_zero_is_leader_plus_offset():
    """kappa1 = 1, kappa2 = 0 (the authors' setting): q_fd = q0_hat + zeta, v_fd = v0_hat + zeta_dot."""
    q0_hat, v0_hat = np.array([3.0, -2.0, 0.4]), np.array([1.0, 0.5, 0.1])
    zeta, zeta_dot = _zeta(AUTHORS_R[1])
    neighbour = (np.array([100.0, 100.0, 0.0]), np.ones(3), *_zeta(AUTHORS_R[0]))
    q_fd, v_fd = desired_formation(
        1.0, 0.0, q0_hat, v0_hat, zeta, zeta_dot, [1.0],
        [neighbour[0]], [neighbour[1]], [neighbour[2]], [neighbour[3]],
    )
    np.testing.assert_allclose(q_fd, q0_hat + zeta)
    np.testing.assert_allclose(v_fd, v0_hat + zeta_dot)


@pytest.mark.parametrize("kappa1,kappa2", [(0.5, 0.5), (0.2, 0.8), (0.0, 1.0), (1.0, 1.0)])
def test_achieved_formation_is_a_fixed_point_of_eq_16(kappa1, kappa2):
    """Neighbours exactly in formation (q_j = q0 + zeta_j, q_j_dot = v0 + zeta_j_dot) and
    q0_hat = q0: q_fd,i = q0 + zeta_i and v_fd,i = v0 + zeta_i_dot for any kappa1, kappa2
    (erratum 4's reading of (16); the printed kappa2 twice would weight q0 wrongly)."""
    q0, v0 = np.array([3.0, -2.0, 0.4]), np.array([1.0, 0.5, 0.1])
    zeta_i, zeta_i_dot = _zeta(AUTHORS_R[2])
    weights, nq, nqd, nz, nzd = [], [], [], [], []
    for r, w in ((AUTHORS_R[0], 1.0), (AUTHORS_R[1], 0.7)):
        z, zd = _zeta(r)
        weights.append(w)
        nq.append(q0 + z)
        nqd.append(v0 + zd)
        nz.append(z)
        nzd.append(zd)
    q_fd, v_fd = desired_formation(kappa1, kappa2, q0, v0, zeta_i, zeta_i_dot, weights, nq, nqd, nz, nzd)
    np.testing.assert_allclose(q_fd, q0 + zeta_i, atol=1e-12)
    np.testing.assert_allclose(v_fd, v0 + zeta_i_dot, atol=1e-12)


def test_desired_formation_is_a_convex_combination():
    """With kappa2 > 0, q_fd lies between the leader-based and the neighbour-based slots with
    weights kappa1 : kappa2 sum a_ij (gamma_fd normalisation of eq. 16)."""
    q0_hat = np.zeros(3)
    zeta = np.array([1.0, 0.0, 0.0])
    q_j, zeta_j = np.array([10.0, 0.0, 0.0]), np.zeros(3)  # neighbour says: my slot + zeta = (11, 0)
    q_fd, _ = desired_formation(
        1.0, 1.0, q0_hat, np.zeros(3), zeta, np.zeros(3), [3.0], [q_j], [np.zeros(3)], [zeta_j], [np.zeros(3)]
    )
    np.testing.assert_allclose(q_fd, (1.0 * np.array([1.0, 0, 0]) + 3.0 * np.array([11.0, 0, 0])) / 4.0)


def test_desired_formation_rejects_zero_normalisation():
    """kappa1 + kappa2 sum_j a_ij = 0 leaves gamma_fd undefined: ValueError."""
    with pytest.raises(ValueError):
        desired_formation(0.0, 1.0, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), [], [], [], [], [])
