"""Distributed leader estimator, eq. (14), on the paper's graph (eq. 49), and erratum 7.

Oracles: the fixed-time bound of the scalar law e' = -iota1 sig^eta1(e) - iota2 sign(e)
(agent 1 hears the leader directly), convergence to the true leader state, and the
algebra of the consensus bracket.
"""

import math

import numpy as np
import pytest
from kernel_forms import estimator_step_vec
from paper_oracle import consensus_errors, estimator_step

from agents.estimator import EstimatorGains

GAINS = EstimatorGains()  # Table 2: iota = (0.1, 0.1, 25, 6), eta = (1.5, 1.5)
A = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])  # eq. (49) with the self loop removed
B = np.array([1.0, 0, 0])
DT = 1e-3
Q0 = np.array([2.0, -1.0, 0.3])
START_OFFSETS = [np.array([5.0, -4.0, 3.0]), np.array([-3.0, 4.0, -2.0]), np.array([4.0, 3.0, -3.0])]
START_VELOCITIES = [np.zeros(3), np.array([1.0, -1.0, 0.5]), np.array([-2.0, 1.0, 0.0])]


def fixed_time_bound(i1, i2, eta):
    """Upper bound on the time for e' = -i1 |e|^eta sign(e) - i2 sign(e) to reach 0 from ANY e(0),
    for i1 = i2: (1/i1) int_0^inf dx / (1 + x^eta) = (1/i1) (pi/eta) / sin(pi/eta)."""
    assert i1 == i2
    return (math.pi / eta) / math.sin(math.pi / eta) / i1


def _run(v0, duration):
    """Synchronous Euler of (14) for the 3 agents, in the compiled form the agents run
    (``estimator_step_vec``; tests/unit/test_hot_path.py checks it equals
    ``estimator_step``, 35,000 steps of which took 4 s); returns times, position and
    velocity errors."""
    q_hat = [tuple(Q0 + off) for off in START_OFFSETS]
    v_hat = [tuple(v) for v in START_VELOCITIES]
    leader_v = tuple(float(x) for x in v0)
    nbrs = [[j for j in range(3) if A[i, j] != 0.0] for i in range(3)]
    steps = int(round(duration / DT))
    times = np.arange(steps) * DT
    q_err, v_err = np.empty((steps, 3)), np.empty((steps, 3))
    for k in range(steps):
        leader_q = tuple(Q0 + v0 * times[k])
        q_err[k] = [math.dist(q, leader_q) for q in q_hat]
        v_err[k] = [math.dist(v, leader_v) for v in v_hat]
        new = [estimator_step_vec(
            q_hat[i], v_hat[i], [q_hat[j] for j in nbrs[i]], [v_hat[j] for j in nbrs[i]],
            [float(A[i, j]) for j in nbrs[i]], float(B[i]), leader_q if B[i] else None,
            leader_v if B[i] else None, GAINS, DT) for i in range(3)]
        q_hat = [n[0] for n in new]
        v_hat = [n[1] for n in new]
    return times, q_err, v_err


@pytest.fixture(scope="module")
def static_run():
    return _run(np.zeros(3), 35.0)


@pytest.fixture(scope="module")
def moving_run():
    return _run(np.array([1.5, -0.8, 0.2]), 35.0)


def test_fixed_time_bound_value():
    """For Table 2 (iota1 = iota2 = 0.1, eta1 = 1.5) the bound is 10 (2 pi/3)/sin(2 pi/3) = 24.18 s."""
    assert fixed_time_bound(0.1, 0.1, 1.5) == pytest.approx(24.18, abs=0.01)


def test_static_leader_agent1_converges_within_fixed_time(static_run):
    """Agent 1 (b_1 = 1) starts 7 m off; per component e' = -0.1 sig^1.5(e) - 0.1 sign(e) reaches
    0 before the fixed-time bound 24.18 s: its error is < 0.05 m from then on."""
    t, q_err, _ = static_run
    assert q_err[0, 0] > 5.0
    t_f = fixed_time_bound(GAINS.iota[0], GAINS.iota[1], GAINS.eta[0])
    assert np.all(q_err[t >= t_f, 0] < 0.05)


def test_static_leader_all_agents_converge_and_stay(static_run):
    """All three estimates, 5-7 m off at t = 0, are within 0.05 m of q0 after 30 s (measured
    about 19 s) until the end, and the velocity estimates equal v0 = 0 within 0.02."""
    t, q_err, v_err = static_run
    late = t >= 30.0
    assert np.all(q_err[0] > 5.0)
    assert np.all(q_err[late] < 0.05)
    assert np.all(v_err[late] < 0.02)


def test_constant_velocity_leader_is_tracked(moving_run):
    """A leader moving at v0 = [1.5, -0.8, 0.2]: positions within 0.05 m and velocities within
    0.02 of v0 after 30 s for every agent (eq. 14's sign terms dominate the motion)."""
    t, q_err, v_err = moving_run
    late = t >= 30.0
    assert np.all(q_err[late] < 0.05)
    assert np.all(v_err[late] < 0.02)
    assert np.all(v_err[t >= 5.0] < 0.02)  # velocity estimates settle first (iota3 = 25)


def test_self_loop_cancels_in_consensus_errors():
    """a_ii (own - own) = 0: a self loop leaves the bracket of eq. (14) unchanged (erratum 7)."""
    own = np.array([1.0, 2.0, -0.5])
    others = [np.array([0.5, 2.5, 0.0])]
    leader = np.array([1.2, 1.9, -0.4])
    without = consensus_errors(own, others, [2.0], 0.7, leader)
    with_loop = consensus_errors(own, [own.copy(), *others], [1.0, 2.0], 0.7, leader)
    np.testing.assert_array_equal(with_loop, without)
    # and the bracket itself: 2 (own - x_2) + 0.7 (own - x_0)
    np.testing.assert_allclose(without, [1.0 - 0.14, -1.0 + 0.07, -1.0 - 0.07])


def test_no_leader_means_no_leader_term():
    """b_i = 0, or no leader sample, drops the leader term of the bracket."""
    own = np.array([1.0, 2.0, -0.5])
    others = [np.array([0.5, 2.5, 0.0])]
    np.testing.assert_array_equal(
        consensus_errors(own, others, [1.0], 0.0, np.zeros(3)), own - others[0]
    )
    np.testing.assert_array_equal(consensus_errors(own, others, [1.0], 1.0, None), own - others[0])


@pytest.mark.xfail(
    strict=True,
    reason="estimator_step counts a self-loop weight in deg = sum_j a_ij + b_i, the reach of its "
    "implicit sign(), although a_ii does not move e (it cancels in eq. 14); a self loop therefore "
    "changes the discrete step near convergence. Harmless for scenarios (the loader zeroes the "
    "diagonal), but the function does not honour erratum 7 by itself.",
)
def test_self_loop_does_not_change_the_estimator_step():
    """Erratum 7: a self loop cancels in eq. (14), so one step with it equals one step without it."""
    own_q, own_v = np.array([1.0 + 2e-5, 2.0, -0.5]), np.array([0.1, 0.0, 3e-4])
    leader_q, leader_v = np.array([1.0, 2.0, -0.5]), np.array([0.1, 0.0, 0.0])
    without = estimator_step(own_q, own_v, [], [], [], 1.0, leader_q, leader_v, GAINS, DT)
    with_loop = estimator_step(
        own_q, own_v, [own_q.copy()], [own_v.copy()], [1.0], 1.0, leader_q, leader_v, GAINS, DT
    )
    np.testing.assert_allclose(with_loop[0], without[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(with_loop[1], without[1], rtol=0, atol=1e-12)
