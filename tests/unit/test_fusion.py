"""Null-space priority fusion, eq. (26), and the behavior supervisor (erratum 8).

Oracles: the defining properties of an orthogonal projector, strict priority of the
top task (J_1 N_1 = 0), numpy.linalg.pinv, and geometric facts about the commands.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from paper_oracle import (
    avoidance_behavior,
    formation_behavior,
    fuse,
    null_space_projector,
    order_by_priority,
    saturate_velocity,
    supervise,
)

from agents.fusion import DEFAULT_PRIORITY

R_BODY, R_A, R_C = 0.5, 2.0, 1.6
SETTINGS = settings(max_examples=40, deadline=None)

angle = st.floats(-math.pi, math.pi, allow_nan=False)
frac = st.floats(0.05, 0.95)
coord = st.floats(-10.0, 10.0, allow_nan=False)


def _focb(q, bearing, f, phi_d=0.3):
    d = R_BODY + f * (R_A - R_BODY)
    obstacle = q[:2] + d * np.array([math.cos(bearing), math.sin(bearing)])
    return avoidance_behavior("FOCB", q, obstacle, R_BODY, R_A, phi_d, 0.1, (24.0, 0.25))


def _frcb(q, bearing, f, phi_d=0.3):
    d = 2 * R_BODY + f * (R_C - 2 * R_BODY)
    other = q[:2] + d * np.array([math.cos(bearing), math.sin(bearing)])
    return avoidance_behavior("FRCB", q, other, 2 * R_BODY, R_C, phi_d, 0.1, (32.0, 0.25))


def _fdb(q, target, v_fd=(0.0, 0.0, 0.0)):
    return formation_behavior(q, np.asarray(target, float), np.asarray(v_fd, float), (12.0, 0.25))


def _inactive(name="FOCB"):
    q = np.array([0.0, 0.0, 0.0])
    out = avoidance_behavior(name, q, np.array([10.0, 0.0]), R_BODY, R_A, 0.0, 0.0, (24.0, 0.25))
    assert not out.active
    return out


configurations = st.fixed_dictionaries(
    {
        "q": st.tuples(coord, coord, angle).map(np.array),
        "b_obs": angle,
        "f_obs": frac,
        "b_rob": angle,
        "f_rob": frac,
        "target": st.tuples(coord, coord, angle),
        "v_fd": st.tuples(coord, coord, st.floats(-2.0, 2.0)),
    }
)


def _three(c):
    return (
        _focb(c["q"], c["b_obs"], c["f_obs"]),
        _frcb(c["q"], c["b_rob"], c["f_rob"]),
        _fdb(c["q"], c["target"], c["v_fd"]),
    )


# --- projector ---------------------------------------------------------------------


@SETTINGS
@given(magnitude=st.floats(1e-5, 1e3), direction=angle, zero_row=st.booleans())
def test_null_space_projector_is_an_orthogonal_projector_onto_null_J(magnitude, direction, zero_row):
    """N = I - J^+ J is idempotent, symmetric, J N = 0, and equals I - pinv(J) J
    (|g| >= 1e-5: shorter gradients count as zero by design, see test_behaviors)."""
    g = np.zeros(2) if zero_row else magnitude * np.array([math.cos(direction), math.sin(direction)])
    J = np.array([[g[0], g[1], 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    N = null_space_projector(J)
    scale = 1.0 + magnitude
    np.testing.assert_allclose(N @ N, N, atol=1e-12)
    np.testing.assert_allclose(N, N.T, atol=1e-12)
    np.testing.assert_allclose(J @ N, 0.0, atol=1e-12 * scale)
    np.testing.assert_allclose(N, np.eye(3) - np.linalg.pinv(J) @ J, atol=1e-12)


def test_inactive_behavior_projector_is_identity():
    """An inactive behavior's zero Jacobian gives N = I (it blocks nothing)."""
    np.testing.assert_array_equal(null_space_projector(_inactive().jacobian), np.eye(3))


# --- fusion (26) --------------------------------------------------------------------


@SETTINGS
@given(c=configurations)
def test_single_behavior_fuses_to_its_own_velocity(c):
    """fuse([b]) = v_b for each behavior alone."""
    for b in _three(c):
        np.testing.assert_array_equal(fuse([b]), b.velocity)


@SETTINGS
@given(c=configurations)
def test_top_priority_task_is_unaffected_by_lower_ones(c):
    """J_1 fuse([b1, b2, b3]) = J_1 v_1 for every priority order: strict priority of eq. (26)."""
    behaviors = _three(c)
    for order in ((0, 1, 2), (1, 0, 2), (2, 0, 1), (2, 1, 0)):
        chain = [behaviors[k] for k in order]
        top = chain[0]
        v = fuse(chain)
        scale = 1.0 + np.abs(top.jacobian).max() * (np.abs(v).max() + np.abs(top.velocity).max())
        np.testing.assert_allclose(top.jacobian @ v, top.jacobian @ top.velocity, atol=1e-9 * scale)


@SETTINGS
@given(q=st.tuples(coord, coord, angle).map(np.array), bearing=angle, f=frac,
       turn=st.sampled_from([-1.0, 1.0]), dist=st.floats(0.5, 20.0))
def test_compatible_lower_task_is_fully_achieved(q, bearing, f, turn, dist):
    """If the FDB target lies perpendicular to the obstacle gradient, FDB's task-space rate is
    reached exactly below FOCB: J_fdb[0] v = J_fdb[0] v_fdb (tasks compatible), and the
    command's radial component w.r.t. the obstacle is FOCB's."""
    focb = _focb(q, bearing, f)
    perpendicular = turn * np.array([-math.sin(bearing), math.cos(bearing)])
    fdb = _fdb(q, (*(q[:2] + dist * perpendicular), 0.0))
    v = fuse([focb, fdb])
    assert fdb.jacobian[0] @ v == pytest.approx(fdb.jacobian[0] @ fdb.velocity, rel=1e-9)
    assert focb.jacobian[0] @ v == pytest.approx(focb.jacobian[0] @ focb.velocity, rel=1e-9)


def test_second_priority_is_not_strict_with_three_tasks_in_printed_26():
    """Eq. (26) nests N_1 (v_2 + N_2 v_3), not the augmented projector: the second task sees
    the third through J_2 N_1 N_2 v_3 (checked with numpy.linalg.pinv). So only the top task
    is strictly protected; J_2 v != J_2 (v_1 + N_1 v_2) in general."""
    q = np.array([0.0, 0.0, 0.2])
    b1 = avoidance_behavior("FOCB", q, np.array([1.2, 0.3]), R_BODY, R_A, 0.1, 0.0, (24.0, 0.25))
    b2 = avoidance_behavior("FRCB", q, np.array([-0.4, 1.1]), 2 * R_BODY, R_C, 0.1, 0.0, (32.0, 0.25))
    b3 = _fdb(q, (5.0, -3.0, 0.4), (1.0, 2.0, 0.1))
    v = fuse([b1, b2, b3])
    N1 = np.eye(3) - np.linalg.pinv(b1.jacobian) @ b1.jacobian
    N2 = np.eye(3) - np.linalg.pinv(b2.jacobian) @ b2.jacobian
    leak = b2.jacobian @ N1 @ N2 @ b3.velocity
    assert np.linalg.norm(leak) > 1.0
    np.testing.assert_allclose(
        b2.jacobian @ v, b2.jacobian @ (b1.velocity + N1 @ b2.velocity) + leak, rtol=1e-9, atol=1e-9
    )


@SETTINGS
@given(c=configurations)
def test_inactive_behaviors_change_nothing(c):
    """Inactive behaviors anywhere in the chain leave the fused velocity unchanged."""
    focb, frcb, fdb = _three(c)
    off = _inactive("FRCB")
    np.testing.assert_array_equal(fuse([_inactive(), fdb]), fuse([fdb]))
    np.testing.assert_array_equal(fuse([focb, off, fdb]), fuse([focb, fdb]))
    np.testing.assert_array_equal(fuse([focb, frcb, fdb, off]), fuse([focb, frcb, fdb]))
    np.testing.assert_array_equal(fuse([off, _inactive()]), np.zeros(3))


# --- supervisor ------------------------------------------------------------------------


def test_order_by_priority_follows_the_configured_order():
    """Behaviors are sorted FOCB > FRCB > FDB by default and by any configured order."""
    q = np.array([0.0, 0.0, 0.0])
    outs = [_fdb(q, (3.0, 0.0, 0.0)), _frcb(q, 0.5, 0.5), _focb(q, 1.0, 0.5)]
    assert [b.name for b in order_by_priority(outs, DEFAULT_PRIORITY)] == ["FOCB", "FRCB", "FDB"]
    custom = ("FDB", "FOCB", "FRCB")
    assert [b.name for b in order_by_priority(outs, custom)] == list(custom)


@SETTINGS
@given(
    q=st.tuples(coord, coord, angle).map(np.array), bearing=angle, f=frac,
    target=st.tuples(coord, coord, angle),
)
def test_approaching_supervisor_never_moves_towards_an_active_obstacle(q, bearing, f, target):
    """Set-based engagement: with one obstacle inside R_a, the fused command never approaches
    it (J_focb[0] v >= 0); FOCB is left out exactly when FDB alone already moves away."""
    focb, fdb = _focb(q, bearing, f), _fdb(q, target)
    chain = supervise([focb, fdb], "approaching")
    v = fuse(chain)
    assert focb.jacobian[0] @ v >= -1e-9 * (1.0 + np.abs(v).max())
    assert ("FOCB" in [b.name for b in chain]) == (focb.jacobian[0] @ fdb.velocity < 0.0)


def test_inside_supervisor_keeps_all_active_behaviors():
    """engage = 'inside' (as printed): every active behavior takes part, inactive ones do not."""
    q = np.array([0.0, 0.0, 0.0])
    outs = [_focb(q, 1.0, 0.5), _inactive("FRCB"), _fdb(q, (3.0, 0.0, 0.0))]
    assert [b.name for b in supervise(outs, "inside")] == ["FOCB", "FDB"]
    with pytest.raises(ValueError):
        supervise(outs, "sometimes")


# --- explicit limits ------------------------------------------------------------------------


@SETTINGS
@given(v=st.tuples(coord, coord, coord).map(np.array), vmax=st.floats(0.1, 5.0), wmax=st.floats(0.1, 5.0))
def test_saturate_velocity_caps_speed_and_yaw_rate_keeping_direction(v, vmax, wmax):
    """|v_xy| <= max_speed with the xy direction kept; |w| <= max_yaw_rate with its sign kept;
    commands inside the limits pass unchanged."""
    out = saturate_velocity(v, vmax, wmax)
    speed = float(np.hypot(v[0], v[1]))
    assert np.hypot(out[0], out[1]) <= vmax * (1 + 1e-12)
    assert abs(out[2]) <= wmax
    assert out[0] * v[1] - out[1] * v[0] == pytest.approx(0.0, abs=1e-9)  # parallel
    assert out[:2] @ v[:2] >= 0.0
    if speed <= vmax:
        np.testing.assert_array_equal(out[:2], v[:2])
    else:
        assert np.hypot(out[0], out[1]) == pytest.approx(vmax, rel=1e-12)
    assert out[2] == (v[2] if abs(v[2]) <= wmax else math.copysign(wmax, v[2]))
    np.testing.assert_array_equal(saturate_velocity(v, math.inf, math.inf), v)

