"""Elementary behaviors, eqs. (15)-(25), and erratum 2 (the FRCB task function).

Oracles: the paper's printed task functions (20) and (23), finite differences of the
task, numpy.linalg.pinv, and the CLIK law's task-space rate (eqs. 19, 22, 25).
"""

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from paper_oracle import avoidance_behavior, avoidance_task, formation_behavior, pinv_task_jacobian

R_BODY = 0.5  # r, Table 2
R_A = 2.0  # FOCB safety threshold
R_C = 1.6  # FRCB safety threshold
FOCB = (R_BODY, R_A)  # (contact, safe): a point obstacle touches at d = r
FRCB = (2 * R_BODY, R_C)  # two robots of radius r touch at d = 2r
GEOMETRIES = pytest.mark.parametrize("contact,safe", [FOCB, FRCB], ids=["FOCB", "FRCB"])
SETTINGS = settings(max_examples=40, deadline=None)

coord = st.floats(-10.0, 10.0, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)


def printed_focb_rho(d, R, r):
    """rho_a of eq. (23) exactly as printed."""
    return R - R * math.sin((d + R - 2 * r) / (2 * R - 2 * r) * math.pi)


def printed_frcb_rho(d, R, r):
    """rho_c of eq. (20) exactly as printed."""
    return R - R * math.sin((d + R - 4 * r) / (4 * R - 2 * r) * math.pi)


def central_difference(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


def _check_task_shape(contact, safe):
    assert avoidance_task(contact, safe, contact)[0] == pytest.approx(0.0, abs=1e-12)
    assert avoidance_task(safe, safe, contact)[0] == pytest.approx(safe, rel=1e-12)
    grid = np.linspace(contact, safe, 2001)[1:-1]
    rho = np.array([avoidance_task(d, safe, contact)[0] for d in grid])
    assert np.all(np.diff(rho) > 0.0)
    assert np.all((rho > 0.0) & (rho < safe))
    h = 1e-6 * (safe - contact)
    for d in grid[::100]:
        fd = central_difference(lambda x: avoidance_task(x, safe, contact)[0], d, h)
        assert avoidance_task(d, safe, contact)[1] == pytest.approx(fd, rel=1e-6, abs=1e-8)


# --- the avoidance task function (erratum 2) --------------------------------------------


@GEOMETRIES
def test_avoidance_task_is_zero_at_contact_R_at_threshold_and_increasing(contact, safe):
    """rho(contact) = 0, rho(R) = R, strictly increasing on (contact, R), d rho/dd = finite difference."""
    _check_task_shape(contact, safe)


@SETTINGS
@given(contact=st.floats(0.05, 3.0), margin=st.floats(0.05, 5.0))
def test_avoidance_task_shape_for_any_radii(contact, margin):
    """The same properties for any contact distance and safety threshold R > contact."""
    _check_task_shape(contact, contact + margin)


def test_printed_frcb_formula_fails_both_boundary_conditions():
    """Eq. (20) as printed, with r = 0.5, R = 1.6: rho(2r) != 0 and rho(R) != R (erratum 2)."""
    r, R = R_BODY, R_C
    assert printed_frcb_rho(2 * r, R, r) == pytest.approx(1.6 * (1 - math.sin(math.pi / 9)), rel=1e-12)
    assert abs(printed_frcb_rho(2 * r, R, r)) > 1.0
    assert abs(printed_frcb_rho(R, R, r) - R) > 1.0


@pytest.mark.parametrize("R,r", [(R_A, R_BODY), (3.0, 0.4), (1.2, 0.2)])
def test_printed_focb_formula_equals_task_with_contact_r(R, r):
    """Eq. (23) as printed (denominator 2R - 2r) is the task with contact distance r."""
    for d in np.linspace(r, R, 57):
        assert avoidance_task(d, R, r)[0] == pytest.approx(printed_focb_rho(d, R, r), abs=1e-12)


# --- Jacobians of the task functions (18) -------------------------------------------


def _fd_gradient(f, xy, h=1e-6):
    return np.array(
        [
            central_difference(lambda x: f(np.array([x, xy[1]])), xy[0], h),
            central_difference(lambda y: f(np.array([xy[0], y])), xy[1], h),
        ]
    )


@GEOMETRIES
@SETTINGS
@given(x=coord, y=coord, phi=angle, bearing=angle, frac=st.floats(0.05, 0.95))
def test_avoidance_jacobian_matches_finite_differences(contact, safe, x, y, phi, bearing, frac):
    """Row 1 of J is d rho / d (x, y) by finite differences; row 2 is [0,0,1]; row 3 is zero."""
    d = contact + frac * (safe - contact)
    q = np.array([x, y, phi])
    other = q[:2] - d * np.array([math.cos(bearing), math.sin(bearing)])
    out = avoidance_behavior("X", q, other, contact, safe, 0.0, 0.0, (24.0, 0.25))
    assert out.active

    def rho_at(xy):
        return avoidance_task(float(np.linalg.norm(xy - other)), safe, contact)[0]

    grad = _fd_gradient(rho_at, q[:2])
    np.testing.assert_allclose(out.jacobian[0], [grad[0], grad[1], 0.0], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(out.jacobian[1], [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(out.jacobian[2], [0.0, 0.0, 0.0])


def test_focb_jacobian_matches_printed_formula_gradient():
    """For FOCB the gradient of the printed (23) by finite differences is J's first row."""
    q = np.array([1.0, 2.0, 0.3])
    obstacle = np.array([2.1, 1.3])
    out = avoidance_behavior("FOCB", q, obstacle, R_BODY, R_A, 0.0, 0.0, (24.0, 0.25))
    grad = _fd_gradient(lambda xy: printed_focb_rho(float(np.linalg.norm(xy - obstacle)), R_A, R_BODY), q[:2])
    np.testing.assert_allclose(out.jacobian[0, :2], grad, rtol=1e-6)


@SETTINGS
@given(x=coord, y=coord, phi=angle, tx=coord, ty=coord)
def test_formation_jacobian_matches_finite_differences(x, y, phi, tx, ty):
    """FDB (15)/(17): row 1 of J is the gradient of |x - x_fd|; row 2 is [0,0,1]; row 3 is zero."""
    q, q_fd = np.array([x, y, phi]), np.array([tx, ty, 0.2])
    assume(np.linalg.norm(q[:2] - q_fd[:2]) > 1e-2)
    out = formation_behavior(q, q_fd, np.zeros(3), (12.0, 0.25))
    grad = _fd_gradient(lambda xy: float(np.linalg.norm(xy - q_fd[:2])), q[:2])
    np.testing.assert_allclose(out.jacobian[0], [grad[0], grad[1], 0.0], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(out.jacobian[1:], [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])


# --- pseudo-inverse (Remark 1) --------------------------------------------------------


@SETTINGS
@given(magnitude=st.floats(1e-5, 1e3), direction=angle, zero_row=st.booleans())
def test_pinv_task_jacobian_equals_numpy_pinv(magnitude, direction, zero_row):
    """pinv_task_jacobian = numpy.linalg.pinv for J = [[gx, gy, 0], [0, 0, 1], [0, 0, 0]],
    including a zero first row (where the printed J^T (J J^T)^-1 does not exist).

    Gradients shorter than 1e-6 are treated as zero by design (a singular-value cutoff,
    like pinv's rcond), so |g| >= 1e-5 here.
    """
    g = np.zeros(2) if zero_row else magnitude * np.array([math.cos(direction), math.sin(direction)])
    J = np.array([[g[0], g[1], 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    oracle = np.linalg.pinv(J)
    np.testing.assert_allclose(pinv_task_jacobian(J), oracle, rtol=1e-9, atol=1e-12 * np.abs(oracle).max())


# --- behavior velocities, CLIK (19), (22), (25) ----------------------------------------


@GEOMETRIES
@SETTINGS
@given(x=coord, y=coord, phi=angle, bearing=angle, frac=st.floats(0.02, 0.98),
       phi_d=angle, phi_d_dot=st.floats(-3.0, 3.0))
def test_active_avoidance_velocity_drives_task_to_R(
    contact, safe, x, y, phi, bearing, frac, phi_d, phi_d_dot
):
    """Inside R: J[0] v = Lambda_1 (R - rho) > 0 (task rate of the CLIK law), J[1] v is the heading
    rate phi_d_dot + Lambda_2 (phi_d - phi), and v moves the robot away from the body."""
    gains = (24.0, 0.25)
    d = contact + frac * (safe - contact)
    q = np.array([x, y, phi])
    away = np.array([math.cos(bearing), math.sin(bearing)])
    other = q[:2] - d * away
    out = avoidance_behavior("X", q, other, contact, safe, phi_d, phi_d_dot, gains)
    rho = avoidance_task(float(np.linalg.norm(q[:2] - other)), safe, contact)[0]
    assert out.active
    assert out.jacobian[0] @ out.velocity == pytest.approx(gains[0] * (safe - rho), rel=1e-7)
    assert out.velocity[2] == pytest.approx(phi_d_dot + gains[1] * (phi_d - phi), rel=1e-9, abs=1e-12)
    assert out.velocity[:2] @ away > 0.0
    # the commanded motion is purely radial: no sideways component
    assert abs(out.velocity[0] * away[1] - out.velocity[1] * away[0]) <= 1e-9 * np.linalg.norm(out.velocity)


@GEOMETRIES
@pytest.mark.parametrize("extra", [0.0, 1e-9, 0.5, 30.0])
def test_avoidance_inactive_at_and_beyond_threshold(contact, safe, extra):
    """d >= R: the behavior is inactive and commands nothing."""
    q = np.array([0.0, 0.0, 0.4])
    out = avoidance_behavior("X", q, np.array([safe + extra, 0.0]), contact, safe, 1.0, 1.0, (24.0, 0.25))
    assert out.active is False
    np.testing.assert_array_equal(out.velocity, np.zeros(3))


@SETTINGS
@given(x=coord, y=coord, phi=angle, tx=coord, ty=coord, phi_fd=angle)
def test_fdb_velocity_with_static_target_points_at_it(x, y, phi, tx, ty, phi_fd):
    """v_fd = 0: v_xy = -k_f (x - x_fd) (towards the target, speed k_f * distance) and
    w = Lambda_2 (phi_fd - phi)."""
    gains = (12.0, 0.25)
    q, q_fd = np.array([x, y, phi]), np.array([tx, ty, phi_fd])
    assume(np.linalg.norm(q[:2] - q_fd[:2]) > 1e-6)
    out = formation_behavior(q, q_fd, np.zeros(3), gains)
    np.testing.assert_allclose(out.velocity[:2], -gains[0] * (q[:2] - q_fd[:2]), rtol=1e-9, atol=1e-9)
    assert out.velocity[2] == pytest.approx(gains[1] * (phi_fd - phi), rel=1e-9, abs=1e-12)
    assert out.task_error == pytest.approx(float(np.linalg.norm(q[:2] - q_fd[:2])), rel=1e-12)


@SETTINGS
@given(x=coord, y=coord, phi=angle, tx=coord, ty=coord, phi_fd=angle,
       vx=coord, vy=coord, w=st.floats(-3.0, 3.0))
def test_fdb_distance_to_moving_target_decays_at_rate_k_f(x, y, phi, tx, ty, phi_fd, vx, vy, w):
    """Moving target: d/dt |x - x_fd| = -k_f |x - x_fd| when x moves with v and x_fd with v_fd
    (eq. 19 with the explicit-time term), checked by a finite step; heading rate = w_fd +
    Lambda_2 (phi_fd - phi)."""
    gains = (12.0, 0.25)
    q, q_fd, v_fd = np.array([x, y, phi]), np.array([tx, ty, phi_fd]), np.array([vx, vy, w])
    dist = float(np.linalg.norm(q[:2] - q_fd[:2]))
    assume(dist > 0.1)
    v = formation_behavior(q, q_fd, v_fd, gains).velocity
    h = 1e-7

    def gap(t):
        return float(np.linalg.norm((q[:2] + t * v[:2]) - (q_fd[:2] + t * v_fd[:2])))

    rate = central_difference(gap, 0.0, h)
    assert rate == pytest.approx(-gains[0] * dist, rel=1e-5, abs=1e-5)
    assert v[2] == pytest.approx(w + gains[1] * (phi_fd - phi), rel=1e-9, abs=1e-12)
