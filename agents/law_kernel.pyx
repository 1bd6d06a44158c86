"""One agent's law on C doubles: the whole control step of agents/core.py.

Formation reference (13), (16); behaviors (15)-(25); supervisor and null-space fusion (26);
explicit limits and degradation (agents/degradation.py); the safety filter (S1), (S2)
(agents/safety_filter.py); the fully actuated law (36), (40)-(42); the ESO (39) and the
leader estimator (14); and the look-ahead's predicted steps (agents/look_ahead.py).
Each equation is written here once, as plain loops and floats, next to its number. The
modules named above keep the paper's matrix form (numpy) as the reference that
tests/unit/test_hot_path.py checks this kernel against, and the documentation of each
equation and of our deviations (errata, docs/errata.md).

Why compiled: the same arithmetic as Python floats cost ~45 µs a step (the call and
allocation overhead of a few hundred small operations); here a step costs a few µs
(docs/bench-history.md, "The compiled kernels"). A diverging law does not raise: non-finite
values propagate and the caller (AgentCore) zeroes the torques and restarts the state.
"""

DEF _SOURCE = AGENTS_LAW_KERNEL_SHA256  # given by setup.py at build time
BUILT_FROM = _SOURCE  # the sha256 of the .pyx this module was built from (plant/kernels.py)


from libc.math cimport sqrt, hypot, cos, sin, tanh, pow, fabs, ceil, erf, exp, isfinite, INFINITY, M_PI
from libc.stdlib cimport malloc, realloc, free
from libc.string cimport memcpy

from plant.fleet_kernel cimport Model, model_from, rk4, saturate_velocity

import numpy as np

cdef double _TINY = 1e-12
cdef double _TOL = 1e-9  # m/s: a safety-filter candidate this close to a boundary is on it
cdef double _MIN_GAP = 1e-3  # avoidance: distance floored at contact + this (behaviors.py)

# behavior names, in the order of their codes
cdef enum:
    FDB = 0
    FOCB = 1
    FRCB = 2
NAMES = ("FDB", "FOCB", "FRCB")

# the smooth step of a scale change (agents/formation.py smooth_step): a normal CDF cut at
# +-_Z standard deviations, rescaled to run exactly from 0 to 1
cdef double _Z = 4.0  # the window spans +-4 sigma
cdef double _CDF_LO = 0.5 * (1.0 + erf(-_Z / sqrt(2.0)))
cdef double _CDF_SPAN = 1.0 - 2.0 * _CDF_LO


cdef struct Task:
    int name            # FDB, FOCB or FRCB
    double gx, gy       # gradient of the task's first row, J = [[gx, gy, 0], [0, 0, 1], [0, 0, 0]]
    double inv_g2       # 1/|g|^2 (0 for a zero row): J^+ = J^T diag(1/|row|^2)
    double vx, vy, vw   # the behavior's velocity v = J^+ (...) (19), (22), (25)
    double task_error
    double gap          # surface gap to the guarded body (ordering: nearest first)
    long body           # ident of the guarded body; 0 for FDB
    bint engaged


cdef struct Line:       # n . v >= b, a barrier (S1)/(S2) of the safety filter
    double nx, ny, b


cdef struct Disc:       # |v - c| <= r: the acceleration and speed limits of the filter
    double cx, cy, r


cdef inline double sig(double x, double power) noexcept nogil:
    """sig^r(x) = |x|^r sign(x), sign(0) = 0 (Notation 1); NaN stays NaN."""
    if x > 0.0:
        return pow(x, power)
    if x < 0.0:
        return -pow(-x, power)
    return x * 0.0


cdef inline double implicit_sign(double e, double reach) noexcept nogil:
    """sign(e) of eq. (14) discretised implicitly: e / reach clipped to [-1, 1]
    (agents/estimator.py; reach = deg iota dt); the plain sign when reach <= 0."""
    cdef double x
    if reach <= 0.0:
        return sig(e, 0.0)
    x = e / reach
    return -1.0 if x < -1.0 else (1.0 if x > 1.0 else x)


cdef inline void smooth_step(double t, double start, double end, double* value,
                             double* rate) noexcept nogil:
    """(value, derivative) of a 0 -> 1 step over [start, end], exactly 0/1 outside."""
    cdef double sigma, z
    if t <= start:
        value[0] = 0.0
        rate[0] = 0.0
        return
    if t >= end:
        value[0] = 1.0
        rate[0] = 0.0
        return
    sigma = (end - start) / (2.0 * _Z)
    z = (t - 0.5 * (start + end)) / sigma
    value[0] = (0.5 * (1.0 + erf(z / sqrt(2.0))) - _CDF_LO) / _CDF_SPAN
    rate[0] = exp(-0.5 * z * z) / (sqrt(2.0 * M_PI) * sigma * _CDF_SPAN)


cdef inline double closing_speed_limit(double gap, double brake, double h,
                                       double exit_time) noexcept nogil:
    """c_max(d) of (S1): the largest closing speed from which one more period and then
    braking at ``brake`` stop within ``gap``; negative (leave) inside the margin."""
    cdef double ah
    if gap < 0.0:
        return gap / exit_time
    if not isfinite(brake):
        return gap / h
    ah = brake * h
    return -ah + sqrt(ah * ah + 2.0 * brake * gap)


cdef inline double stopping_distance(double closing, double brake, double h) noexcept nogil:
    """The gap used up by one more period at ``closing`` and braking at ``brake`` after
    it: the left side of (S1), whose inverse is closing_speed_limit."""
    if closing <= 0.0:
        return 0.0
    return closing * h + (closing * closing / (2.0 * brake) if isfinite(brake) else 0.0)


cdef inline double inverse_square_norm(double gx, double gy) noexcept nogil:
    """1/|g|^2, the pseudo-inverse's factor for the row [g_x, g_y, 0]; 0 for a zero row."""
    cdef double g2 = gx * gx + gy * gy
    return 1.0 / g2 if g2 > _TINY else 0.0


cdef void formation_task(Task* t, double qx, double qy, double qw, const double* q_fd,
                         const double* v_fd, double k_f, double k_phi) noexcept nogil:
    """FDB, eqs. (15)-(19): rho_f = |x - x_fd|, desired 0; heading row to phi_fd.
    v = J^+ [-d rho/dt + k (0 - rho), phi_fd_dot + k_phi (phi_fd - phi), 0]
        + (I - J^+ J) [v_fd_xy, 0]  (the task's own null space carries the rest of the
    formation velocity: behaviors.py, formation_behavior)."""
    cdef double dx = qx - q_fd[0], dy = qy - q_fd[1]
    cdef double dist = hypot(dx, dy)
    cdef double gx = 0.0, gy = 0.0
    if dist > _TINY:
        gx = dx / dist
        gy = dy / dist
    cdef double inv = inverse_square_norm(gx, gy)
    cdef double vfx = v_fd[0], vfy = v_fd[1]
    cdef double g_vfd = gx * vfx + gy * vfy  # -d rho/dt, and J [v_fd_xy, 0]
    cdef double rate = g_vfd + k_f * (0.0 - dist)
    t.name = FDB
    t.gx, t.gy, t.inv_g2 = gx, gy, inv
    t.vx = gx * inv * rate + (vfx - gx * inv * g_vfd)
    t.vy = gy * inv * rate + (vfy - gy * inv * g_vfd)
    t.vw = v_fd[2] + k_phi * (q_fd[2] - qw)  # heading row: phi_d_dot + k_phi (phi_d - phi)
    t.task_error = dist
    t.gap = 0.0
    t.body = 0
    t.engaged = False


cdef bint avoidance_task(Task* t, int name, double qx, double qy, double qw, double ox,
                         double oy, double contact, double safe, double phi_d,
                         double phi_d_dot, double k_a, double k_phi, long body) noexcept nogil:
    """FOCB (23)-(25) / FRCB (20)-(22) against the body at (ox, oy); False if inactive
    (d >= R). Task (erratum 2): rho(d) = R - R sin(pi (d + R - 2 d0) / (2 (R - d0))),
    0 at contact d0, R at d = R; the distance is floored at contact + 1 mm so the push
    stays outwards inside contact. v = J^+ [k (R - rho), heading row, 0]."""
    cdef double dx = qx - ox, dy = qy - oy
    cdef double d = hypot(dx, dy)
    cdef double ux = 1.0, uy = 0.0, k, arg, rho, drho, d_eff, gx, gy, inv, rate
    if d >= safe:
        return False
    if d > _TINY:
        ux = dx / d
        uy = dy / d
    d_eff = d if d > contact + _MIN_GAP else contact + _MIN_GAP
    k = M_PI / (2.0 * (safe - contact))
    arg = k * (d_eff + safe - 2.0 * contact)
    rho = safe - safe * sin(arg)
    drho = -safe * k * cos(arg)
    gx = drho * ux
    gy = drho * uy
    inv = inverse_square_norm(gx, gy)
    rate = k_a * (safe - rho)  # Lambda (rho_d - rho), rho_d = R
    t.name = name
    t.gx, t.gy, t.inv_g2 = gx, gy, inv
    t.vx = gx * inv * rate
    t.vy = gy * inv * rate
    t.vw = phi_d_dot + k_phi * (phi_d - qw)
    t.task_error = safe - rho
    t.body = body
    t.engaged = False
    return True


cdef inline void fuse(const Task* tasks, int n, bint only_engaged, double* v) noexcept nogil:
    """Eq. (26) for the chain, highest priority first: v = v_1 + N_1 (v_2 + N_2 (...)),
    N v = v - J^+ (J v) (the heading row takes out the whole yaw component). With
    ``only_engaged``, avoidance tasks that are not engaged are left out (supervisor)."""
    cdef double vx = 0.0, vy = 0.0, vw = 0.0, k
    cdef int i
    for i in range(n - 1, -1, -1):
        if only_engaged and tasks[i].name != FDB and not tasks[i].engaged:
            continue
        k = tasks[i].inv_g2 * (tasks[i].gx * vx + tasks[i].gy * vy)
        vx = tasks[i].vx + (vx - tasks[i].gx * k)
        vy = tasks[i].vy + (vy - tasks[i].gy * k)
        vw = tasks[i].vw + 0.0
    v[0], v[1], v[2] = vx, vy, vw


cdef inline bint _on_line_side(const Line* lines, int nl, const Disc* discs, int nd,
                               double x, double y) noexcept nogil:
    cdef int i
    for i in range(nl):
        if lines[i].nx * x + lines[i].ny * y < lines[i].b - _TOL:
            return False
    for i in range(nd):
        if (x - discs[i].cx) * (x - discs[i].cx) + (y - discs[i].cy) * (y - discs[i].cy) \
                > (discs[i].r + _TOL) * (discs[i].r + _TOL):
            return False
    return True


cdef inline void _consider(const Line* lines, int nl, const Disc* discs, int nd, double x,
                           double y, double vnx, double vny, double* best, double* cost,
                           bint* found) noexcept nogil:
    cdef double c = (x - vnx) * (x - vnx) + (y - vny) * (y - vny)
    if c < cost[0] and _on_line_side(lines, nl, discs, nd, x, y):
        best[0], best[1], cost[0], found[0] = x, y, c, True


cdef bint closest_feasible(double vnx, double vny, const Line* lines, int nl,
                           const Disc* discs, int nd, double* out) noexcept nogil:
    """argmin |v - v_nom| over {n . v >= b for every line, |v - c| <= r for every disc};
    False when the set is empty. Exact: the optimum of this convex 2-D problem is v_nom or
    lies on one boundary (the projection of v_nom on it) or on two (where they meet), so
    the feasible candidate of least cost among those is the solution."""
    cdef int i, j
    cdef double s, dx, dy, dist, det, fx, fy, half, d, along, mx, my
    cdef double cost = INFINITY
    cdef bint found = False
    if _on_line_side(lines, nl, discs, nd, vnx, vny):
        out[0], out[1] = vnx, vny
        return True
    for i in range(nl):  # projection on a line (|n| = 1)
        s = lines[i].b - (lines[i].nx * vnx + lines[i].ny * vny)
        _consider(lines, nl, discs, nd, vnx + s * lines[i].nx, vny + s * lines[i].ny, vnx, vny,
                  out, &cost, &found)
    for i in range(nd):  # projection on a circle
        dx, dy = vnx - discs[i].cx, vny - discs[i].cy
        dist = hypot(dx, dy)
        if dist > 0:
            _consider(lines, nl, discs, nd, discs[i].cx + discs[i].r * dx / dist,
                      discs[i].cy + discs[i].r * dy / dist, vnx, vny, out, &cost, &found)
        else:
            _consider(lines, nl, discs, nd, discs[i].cx + discs[i].r, discs[i].cy, vnx, vny,
                      out, &cost, &found)
    for i in range(nl):  # line meets line
        for j in range(i + 1, nl):
            det = lines[i].nx * lines[j].ny - lines[i].ny * lines[j].nx
            if fabs(det) > 1e-12:
                _consider(lines, nl, discs, nd,
                          (lines[i].b * lines[j].ny - lines[j].b * lines[i].ny) / det,
                          (lines[i].nx * lines[j].b - lines[j].nx * lines[i].b) / det,
                          vnx, vny, out, &cost, &found)
    for i in range(nl):  # line meets circle
        for j in range(nd):
            s = lines[i].b - (lines[i].nx * discs[j].cx + lines[i].ny * discs[j].cy)
            if fabs(s) > discs[j].r:
                continue
            fx, fy = discs[j].cx + s * lines[i].nx, discs[j].cy + s * lines[i].ny
            half = discs[j].r * discs[j].r - s * s
            half = sqrt(half if half > 0.0 else 0.0)
            _consider(lines, nl, discs, nd, fx - half * lines[i].ny, fy + half * lines[i].nx,
                      vnx, vny, out, &cost, &found)
            _consider(lines, nl, discs, nd, fx + half * lines[i].ny, fy - half * lines[i].nx,
                      vnx, vny, out, &cost, &found)
    for i in range(nd):  # circle meets circle
        for j in range(i + 1, nd):
            dx, dy = discs[j].cx - discs[i].cx, discs[j].cy - discs[i].cy
            d = hypot(dx, dy)
            if d < 1e-12 or d > discs[i].r + discs[j].r or d < fabs(discs[i].r - discs[j].r):
                continue
            along = (discs[i].r * discs[i].r - discs[j].r * discs[j].r + d * d) / (2.0 * d)
            half = discs[i].r * discs[i].r - along * along
            half = sqrt(half if half > 0.0 else 0.0)
            mx, my = discs[i].cx + along * dx / d, discs[i].cy + along * dy / d
            _consider(lines, nl, discs, nd, mx - half * dy / d, my + half * dx / d, vnx, vny,
                      out, &cost, &found)
            _consider(lines, nl, discs, nd, mx + half * dy / d, my - half * dx / d, vnx, vny,
                      out, &cost, &found)
    return found


cdef struct Filtered:      # what the safety filter did (agents/safety_filter.py SafetyResult)
    double vx, vy
    bint active
    int binding
    bint infeasible
    double dv


cdef Filtered safety_filter(double vnx, double vny, bint has_prev, double pvx, double pvy,
                            double px, double py, double radius, const double* bodies,
                            int nb, int n_obstacles, double margin, double brake,
                            double max_speed, double exit_time, double h,
                            double horizon, Line* lines) noexcept nogil:
    """The command closest to v_nom that keeps every barrier: (S1) for an obstacle,
    n . v >= n . v_j - c_max(d_j); (S2) for a robot (reciprocal), n . v >= max((S1),
    -c_max / 2); within |v - v_prev| <= a h and |v| <= v_max (agents/safety_filter.py).
    ``bodies``: rows (ident, x, y, vx, vy, radius), the first ``n_obstacles`` obstacles.
    ``h``: the step (how far v may move from v_prev); ``horizon``: how long the command
    will act before the next one can brake (the period, or longer when the loop runs late:
    the barrier's "one more period"). ``lines``: room for nb barriers."""
    cdef Filtered r
    cdef Disc discs[2]
    cdef int nd = 0, i, binding = 0
    cdef double dx, dy, dist, nx, ny, gap, c_max, b, tx, ty, step
    cdef const double* row
    for i in range(nb):
        row = bodies + 6 * i
        dx, dy = px - row[1], py - row[2]
        dist = hypot(dx, dy)
        nx, ny = 1.0, 0.0
        if dist > 1e-12:
            nx, ny = dx / dist, dy / dist
        gap = dist - radius - row[5] - margin
        c_max = closing_speed_limit(gap, brake, horizon, exit_time)
        b = nx * row[3] + ny * row[4] - c_max  # (S1)
        if i >= n_obstacles and b < -0.5 * c_max:
            b = -0.5 * c_max  # (S2)
        lines[i].nx, lines[i].ny, lines[i].b = nx, ny, b
        if nx * vnx + ny * vny < b:
            binding += 1
    r.vx, r.vy, r.active, r.binding, r.infeasible, r.dv = vnx, vny, False, 0, False, 0.0
    if binding == 0:
        return r
    if has_prev and isfinite(brake):
        discs[nd].cx, discs[nd].cy, discs[nd].r = pvx, pvy, brake * h
        nd += 1
    if isfinite(max_speed):
        discs[nd].cx, discs[nd].cy, discs[nd].r = 0.0, 0.0, max_speed
        nd += 1
    cdef double v[2]
    if closest_feasible(vnx, vny, lines, nb, discs, nd, v):
        r.infeasible = False
    else:
        # no command meets the barriers within the limits: brake as hard as allowed
        # toward the barriers' own solution (or a standstill relative to the world)
        r.infeasible = True
        if not closest_feasible(vnx, vny, lines, nb, discs, 0, v):
            v[0], v[1] = 0.0, 0.0
        if nd > 0 and has_prev:
            tx, ty = v[0] - pvx, v[1] - pvy
            dist = hypot(tx, ty)
            step = brake * h
            if dist > step:
                v[0], v[1] = pvx + step / dist * tx, pvy + step / dist * ty
    r.vx, r.vy, r.active, r.binding = v[0], v[1], True, binding
    r.dv = hypot(v[0] - vnx, v[1] - vny)
    return r


cdef void control_term(const double* e, const double* e_dot, const double* z2,
                       double gamma_p, double a, double mu2, double eps2, double reach_low,
                       double reach_high, double s_div, double* gamma,
                       double* s) noexcept nogil:
    """(Gamma, s) of eqs. (40)-(42):
    s = e_dot + psi(e), psi(e) = gamma_p (n^-a + mu^2 n^a) e, n = sqrt(|e|^2 + eps^2)
    (erratum 5: regularised at 0);
    psi_dot = gamma_p [(n^-a + mu^2 n^a) e_dot + a (mu^2 n^(a-2) - n^(-a-2)) e (e . e_dot)]
    (erratum 5: the true derivative);
    Gamma = -gamma_p ((1/2)^((2-a)/2) |s|^-a + (1/2)^((2+a)/2) mu^2 |s|^a) s - z2_hat
            - psi_dot - s / (2 upsilon^2)."""
    cdef double n = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + eps2)
    cdef double scalar = pow(n, -a) + mu2 * pow(n, a)
    cdef double p = gamma_p * scalar
    cdef int j
    for j in range(3):
        s[j] = e_dot[j] + p * e[j]
    cdef double radial = a * (mu2 * pow(n, a - 2.0) - pow(n, -a - 2.0)) * (
        e[0] * e_dot[0] + e[1] * e_dot[1] + e[2] * e_dot[2])
    cdef double ns = sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    cdef double r = gamma_p * (reach_low * pow(ns, -a) + reach_high * pow(ns, a)) if ns != 0.0 else 0.0
    for j in range(3):
        gamma[j] = -r * s[j] - z2[j] - gamma_p * (scalar * e_dot[j] + radial * e[j]) - s[j] / s_div


cdef void scale_at(double t, double s0x, double s0y, const double* changes, int n,
                   double* scale, double* rate) noexcept nogil:
    """S(t) and S_dot(t) (diagonals): each change moves S from its previous value to its
    target over its window by a smooth step (agents/formation.py scale_at).
    ``changes``: n rows (start, end, to_x, to_y)."""
    cdef double sx = s0x, sy = s0y, dx = 0.0, dy = 0.0, frac, r, tx, ty
    cdef int i
    for i in range(n):
        tx, ty = changes[4 * i + 2], changes[4 * i + 3]
        smooth_step(t, changes[4 * i], changes[4 * i + 1], &frac, &r)
        dx += (tx - sx) * r
        dy += (ty - sy) * r
        sx += (tx - sx) * frac
        sy += (ty - sy) * frac
    scale[0], scale[1], rate[0], rate[1] = sx, sy, dx, dy


cdef void offsets(double rx, double ry, double heading_offset, double psi, double psi_dot,
                  const double* scale, const double* scale_dot, double* zeta,
                  double* zeta_dot) noexcept nogil:
    """zeta_i = [W r_i, Xi_i] and zeta_i_dot, eq. (13)/(48): W = Rot(psi) S,
    W_dot = psi_dot Rot(psi + pi/2) S + Rot(psi) S_dot, Rot(psi + pi/2) = [[-s, -c], [c, -s]]."""
    cdef double c = cos(psi), s = sin(psi)
    cdef double ax = scale[0] * rx, ay = scale[1] * ry          # S r_i
    cdef double bx = scale_dot[0] * rx, by = scale_dot[1] * ry  # S_dot r_i
    zeta[0], zeta[1], zeta[2] = c * ax - s * ay, s * ax + c * ay, heading_offset
    zeta_dot[0] = -psi_dot * s * ax - psi_dot * c * ay + (c * bx - s * by)
    zeta_dot[1] = psi_dot * c * ax - psi_dot * s * ay + (s * bx + c * by)
    zeta_dot[2] = 0.0


cdef bint desired_formation(double kappa1, double kappa2, const double* q0h, const double* v0h,
                            const double* zeta, const double* zeta_dot, int n,
                            const double* weights, const double* nbr, double* q_fd,
                            double* v_fd) noexcept nogil:
    """q_fd,i of eq. (16) and its velocity, erratum 4 applied:
    q_fd,i = gamma (kappa1 (q0_hat_i + zeta_i) + kappa2 sum_j a_ij (q_j - zeta_j + zeta_i)),
    gamma = 1 / (kappa1 + kappa2 sum_j a_ij). ``nbr``: n rows (q 3, q_dot 3, zeta 3,
    zeta_dot 3). False when gamma's denominator is not positive."""
    cdef double denom, k = 0.0
    cdef int i, j
    cdef const double* row
    for i in range(n):
        k += weights[i]
    denom = kappa1 + kappa2 * k
    if not denom > 0.0:
        return False
    for j in range(3):
        q_fd[j] = kappa1 * (q0h[j] + zeta[j])
        v_fd[j] = kappa1 * (v0h[j] + zeta_dot[j])
    if kappa2 != 0.0:
        for i in range(n):
            row = nbr + 12 * i
            k = kappa2 * weights[i]
            for j in range(3):
                q_fd[j] += k * (row[j] - row[6 + j] + zeta[j])
                v_fd[j] += k * (row[3 + j] - row[9 + j] + zeta_dot[j])
    for j in range(3):
        q_fd[j] = q_fd[j] / denom
        v_fd[j] = v_fd[j] / denom
    return True


cdef void estimator_step(double* q0h, double* v0h, int n, const double* weights,
                         const double* nbr, double leader_weight, bint has_leader,
                         const double* lq, const double* lv, const double* iota, double eta1,
                         double eta2, double h) noexcept nogil:
    """One explicit-Euler step of eq. (14), in place:
    e_q = sum_j a_ij (q0_hat_i - q0_hat_j) + b_i (q0_hat_i - q0), e_v alike;
    q0_hat' = -iota1 sig^eta1(e_q) - iota2 sign(e_q) + v0_hat,
    v0_hat' = -iota3 sig^eta2(e_v) - iota4 sign(e_v),
    sign() discretised implicitly with reach deg iota dt, deg = sum_j a_ij + b_i
    (agents/estimator.py). ``nbr``: n rows (q0_hat_j 3, v0_hat_j 3)."""
    cdef double eq[3]
    cdef double ev[3]
    cdef double deg = 0.0, rq, rv, qn
    cdef int i, j
    cdef const double* row
    for j in range(3):
        eq[j] = 0.0
        ev[j] = 0.0
    for i in range(n):
        row = nbr + 6 * i
        deg += weights[i]
        for j in range(3):
            eq[j] += weights[i] * (q0h[j] - row[j])
            ev[j] += weights[i] * (v0h[j] - row[3 + j])
    if has_leader and leader_weight != 0.0:
        deg += leader_weight
        for j in range(3):
            eq[j] += leader_weight * (q0h[j] - lq[j])
            ev[j] += leader_weight * (v0h[j] - lv[j])
    rq, rv = deg * iota[1] * h, deg * iota[3] * h  # reach of the implicit sign
    for j in range(3):
        qn = q0h[j] + h * (-iota[0] * sig(eq[j], eta1) - iota[1] * implicit_sign(eq[j], rq)
                           + v0h[j])
        v0h[j] = v0h[j] + h * (-iota[2] * sig(ev[j], eta2) - iota[3] * implicit_sign(ev[j], rv))
        q0h[j] = qn


cdef void eso_advance(double* z1, double* z2, const double* measured, const double* gamma,
                      double mu1, double mu2, double r1, double r2, double dt,
                      double max_step) noexcept nogil:
    """Eq. (39) over dt, in place, in explicit-Euler sub-steps of at most ``max_step`` (the
    control period), measurement and Gamma held (agents/eso.py):
    z1_hat' = Gamma + z2_hat + mu1 sig^r1(eps1), z2_hat' = mu2 sig^r2(eps1), eps1 = z1 - z1_hat."""
    cdef int n = 1, i, j
    cdef double hh, eps
    if max_step > 0.0:
        n = <int> ceil(dt / max_step - 1e-9)
        if n < 1:
            n = 1
    hh = dt / n
    for i in range(n):
        for j in range(3):
            eps = measured[j] - z1[j]
            z1[j] = z1[j] + hh * (gamma[j] + z2[j] + mu1 * sig(eps, r1))
            z2[j] = z2[j] + hh * (mu2 * sig(eps, r2))


cdef double next_speed_factor(double f, double age, double slow_after, double slow_ramp,
                              double h) noexcept nogil:
    """The degradation speed factor after a step of h with information ``age`` old: down
    as fast as the age says, up by at most h / slow_ramp (agents/degradation.py)."""
    cdef double target, step
    if slow_ramp <= 0.0:
        target = 0.0 if age > slow_after else 1.0
    else:
        target = 1.0 - (age - slow_after) / slow_ramp
        target = 0.0 if target < 0.0 else (1.0 if target > 1.0 else target)
    if target < f:
        return target
    step = h / slow_ramp if slow_ramp > 0.0 else 1.0
    return f + step if f + step < target else target


cdef void slow_down(double* v, double f, double degraded) noexcept nogil:
    """v_d scaled so that its planar speed blends from |v| (f = 1) to min(|v|, degraded)
    (f = 0); yaw rate scaled alike (agents/degradation.py)."""
    cdef double speed, cap, k
    if f >= 1.0:
        return
    speed = hypot(v[0], v[1])
    cap = 1.0 if speed <= degraded else degraded / speed
    k = f + (1.0 - f) * cap
    v[0], v[1], v[2] = v[0] * k, v[1] * k, v[2] * k


cdef bint reacquire(double* q, double* v, const double* q0, const double* v0, double tau,
                    double tol, double h) noexcept nogil:
    """One step of the blend toward the freshest leader information (q0, v0), in place, a
    first-order filter of time constant tau (agents/degradation.py); True while the
    position estimate is farther than ``tol``."""
    cdef double a = 1.0
    cdef int j
    if tau > 0.0:
        a = h / tau
        if a > 1.0:
            a = 1.0
    for j in range(3):
        q[j] = q[j] + a * (q0[j] - q[j])
        v[j] = v[j] + a * (v0[j] - v[j])
    return hypot(q0[0] - q[0], q0[1] - q[1]) > tol


cdef bint freshest(bint has_leader, const double* lq, const double* lv, double leader_age,
                   int n, const double* nbr, double* fq, double* fv, double* age) noexcept nogil:
    """The freshest source of leader information (agents/degradation.py freshest_source):
    the leader sample or a neighbour's estimate, whose age is its link age plus the age of
    its own information (ages add up along the graph); its pose predicted to now over the
    link age. ``nbr``: n rows (q0_hat 3, v0_hat 3, link age, information age)."""
    cdef bint found = False
    cdef double a
    cdef int i, j
    cdef const double* row
    if has_leader:
        found, age[0] = True, leader_age
        for j in range(3):
            fq[j] = lq[j] + lv[j] * leader_age if leader_age != 0.0 else lq[j]
            fv[j] = lv[j]
    for i in range(n):
        row = nbr + 8 * i
        a = row[6] + row[7]
        if not found or a < age[0]:
            found, age[0] = True, a
            for j in range(3):
                fq[j] = row[j] + row[3 + j] * row[6] if row[6] != 0.0 else row[j]
                fv[j] = row[3 + j]
    return found


cdef inline void predict(const double* x, const double* x_dot, double age,
                         double* out) noexcept nogil:
    """x + x_dot age: a sample carried forward by the velocity it was taken with
    (agents/degradation.py predict)."""
    cdef int j
    for j in range(3):
        out[j] = x[j] + x_dot[j] * age if age != 0.0 else x[j]


cdef void coulomb_term(const Model* m, double c, double s, const double* qd,
                       double* a1) noexcept nogil:
    """A1 of eq. (4): B(phi) tau_c(theta_dot), theta_dot = P T(phi)^T q_dot / R,
    tau_c = C tanh(theta_dot / omega_s); c, s = cos(phi), sin(phi)."""
    cdef double bx = c * qd[0] + s * qd[1], by = -s * qd[0] + c * qd[1]
    cdef double tau[4]
    cdef double f[3]
    cdef int i, j
    for j in range(4):
        tau[j] = m.coulomb * tanh((m.P[j][0] * bx + m.P[j][1] * by + m.P[j][2] * qd[2])
                                  * m.inv_R * m.inv_smooth)
    for i in range(3):
        f[i] = m.B0[i][0] * tau[0] + m.B0[i][1] * tau[1] + m.B0[i][2] * tau[2] + m.B0[i][3] * tau[3]
    a1[0], a1[1], a1[2] = c * f[0] - s * f[1], s * f[0] + c * f[1], f[2]  # T(phi) B0 tau_c


cdef void allocate(const double[4][3] alloc, double c, double s, const double* gen,
                   double* u) noexcept nogil:
    """u = B_bar(phi)^-1 [v; 0] (36) with B_bar = [B; n^T] (erratum 3): the minimum-norm
    wheel torques. B_bar(phi) = diag(T(phi), 1) B_bar(0), so B_bar(phi)^-1 [v; 0] =
    B_bar(0)^-1 [T(phi)^T v; 0]: ``alloc`` is B_bar(0)^-1 without its last column."""
    cdef double bx = c * gen[0] + s * gen[1], by = -s * gen[0] + c * gen[1]
    cdef int j
    for j in range(4):
        u[j] = alloc[j][0] * bx + alloc[j][1] * by + alloc[j][2] * gen[2]


cdef void _allocation_of(object model, double[4][3] alloc):
    """B_bar(0)^-1 without its last column, of a plant.mecanum.MecanumModel (erratum 3)."""
    cdef int i, j
    inverse = np.linalg.inv(model.augmented_input(0.0)).tolist()
    for i in range(4):
        for j in range(3):
            alloc[i][j] = inverse[i][j]


cdef void saturate_torques(double* u, double limit) noexcept nogil:
    """All four torques scaled by one factor so that max |u_k| <= limit: one common factor
    keeps the direction of the generalised force."""
    cdef double peak = 0.0, k
    cdef int j
    for j in range(4):
        if fabs(u[j]) > peak:
            peak = fabs(u[j])
    if peak > limit:
        k = limit / peak
        for j in range(4):
            u[j] = u[j] * k


cdef void supervise(Task* tasks, int n, bint approaching, Law limiter, double h,
                    double* v):
    """The supervisor (erratum 8, agents/fusion.py): which avoidance tasks take part in
    (26), and the velocity of that chain after ``limiter``'s limits (none: None).
    "inside": every active task; "approaching": an avoidance task engages when the fused
    velocity or the limited one closes on its body (J_1 v < 0); engaged tasks stay
    engaged; repeat until nothing changes. Sets each task's ``engaged``."""
    cdef double fused[3]
    cdef bint changed, avoiding = False
    cdef int i, j
    for i in range(n):
        if tasks[i].name != FDB:
            avoiding = True
    if not approaching or not avoiding:
        for i in range(n):
            tasks[i].engaged = True
        fuse(tasks, n, False, fused)
        v[0], v[1], v[2] = fused[0], fused[1], fused[2]
        if limiter is not None:
            limiter._limited(v, h)
        return
    while True:  # engagement only grows, at most once per avoidance task
        fuse(tasks, n, True, fused)
        v[0], v[1], v[2] = fused[0], fused[1], fused[2]
        if limiter is not None:
            limiter._limited(v, h)
        changed = False
        for i in range(n):
            if tasks[i].name == FDB or tasks[i].engaged:
                continue
            if tasks[i].gx * fused[0] + tasks[i].gy * fused[1] < 0.0 \
                    or tasks[i].gx * v[0] + tasks[i].gy * v[1] < 0.0:
                changed = True
                for j in range(n):  # every task on the same (behavior, body)
                    if tasks[j].name == tasks[i].name and tasks[j].body == tasks[i].body:
                        tasks[j].engaged = True
        if not changed:
            return


cdef struct Inputs:
    # one step's inputs, as the step uses them
    double t, h
    double horizon          # how long this command will act (>= h: a late loop holds it longer)
    double speed_cap        # 1, or the planar speed scale of a loop that cannot keep its period
    double q[3]             # own pose as sampled
    double qd[3]            # own velocity
    bint has_ages
    double state_age, leader_age
    bint has_leader
    double lq[3]
    double lv[3]
    int n_nbr
    double* nbr             # per neighbour (cfg order): q0_hat 3, v0_hat 3, q 3, q_dot 3, zeta 3,
                            # zeta_dot 3, info_age, link age
    int n_obs, n_rob
    double* bodies          # rows (ident, x, y, vx, vy, radius): obstacles, then robots


DEF NBR_W = 20   # doubles per neighbour row of Inputs.nbr
DEF OUT_N = 40   # doubles of Outputs.values

cdef struct Outputs:
    double torques[4]
    double v_cmd[3]
    double e[3]
    double s[3]
    double q_d[3]           # the reference at this step (before its integration)
    double q_fd[3]
    double zeta[3]
    double zeta_dot[3]
    double info_age
    double input_age
    int left_out
    bint nonfinite
    bint filtered           # the safety filter ran (a body was perceived, the filter on)
    Filtered safety


cdef int _copy_bodies(bodies, double* out) except -1:
    """Perceived bodies into rows (ident, x, y, vx, vy, radius) at ``out``: a (k, 6) float
    array as it is, or objects with ``ident``, ``position``, ``velocity`` and ``radius``
    (the wire's sensed bodies: read here, with no numpy array built for them)."""
    cdef const double[:, ::1] arr
    cdef int r
    cdef double* row
    if isinstance(bodies, np.ndarray):
        arr = bodies
        if arr.shape[0] and arr.shape[1] != 6:
            raise ValueError("perceived bodies must be rows (ident, x, y, vx, vy, radius)")
        if arr.shape[0]:
            memcpy(out, &arr[0, 0], sizeof(double) * 6 * arr.shape[0])
        return 0
    for r, b in enumerate(bodies):
        row = out + 6 * r
        p, v = b.position, b.velocity
        row[0], row[1], row[2], row[3], row[4], row[5] = b.ident, p[0], p[1], v[0], v[1], b.radius
    return 0


cdef class Law:
    """One agent's law: its constants (from an AgentConfig) and its state."""

    # constants
    cdef public double dt
    cdef int n_nbr
    cdef double* weights
    cdef double leader_weight
    cdef double rx, ry, heading_offset, scale0x, scale0y
    cdef int n_changes
    cdef double* changes        # per change: start, end, to_x, to_y
    cdef double kappa1, kappa2
    cdef bint en[3]
    cdef int rank[3]
    cdef bint approaching
    cdef double gain_k[3]
    cdef double gain_phi[3]
    cdef double R_a, R_c, radius
    cdef bint guard_every, use_filter
    cdef double margin, exit_time
    cdef double iota[4]
    cdef double eta1, eta2
    cdef double mu1, mu2_eso, r1, r2
    cdef double gamma_p, alpha, mu2, eps2, reach_low, reach_high, s_div
    cdef Model model
    cdef double alloc[4][3]     # B_bar(0)^-1 without its last column (36), erratum 3
    cdef double max_speed, max_yaw, max_torque, max_accel, max_yaw_accel, max_tracking_error
    cdef bint limits_rate
    cdef double stale_after, slow_after, slow_ramp, degraded_speed
    cdef double reacquire_tau, reacquire_tol, reacquire_min
    # state
    cdef double q0h[3]
    cdef double v0h[3]
    cdef double qref[3]         # q_d, the CLIK reference (11)
    cdef double vdp[3]          # v_d of the last step
    cdef bint has_vdp
    cdef double z1[3]
    cdef bint has_z1
    cdef double z2[3]
    cdef double speed_factor
    cdef bint info_lost, reacquiring
    cdef double reacquire_s
    cdef double speed_cap       # this step's (Inputs.speed_cap)
    cdef int n_tasks            # tasks of the last step (the chain: FDB and the engaged ones)
    # work buffers
    cdef Task* tasks
    cdef int task_cap
    cdef Line* lines
    cdef int line_cap
    cdef double* nbr_buf
    cdef int nbr_cap
    cdef double* body_buf
    cdef int body_cap
    cdef double* work_buf       # per neighbour: up to 12 doubles of step-local rows
    cdef double* kept_w         # the weights of the neighbours kept in eq. (14)
    cdef int work_cap

    def __cinit__(self):
        self.weights = self.changes = NULL
        self.tasks = NULL
        self.lines = NULL
        self.nbr_buf = self.body_buf = self.work_buf = self.kept_w = NULL
        self.task_cap = self.line_cap = self.nbr_cap = self.body_cap = self.work_cap = 0

    def __dealloc__(self):
        free(self.weights)
        free(self.changes)
        free(self.tasks)
        free(self.lines)
        free(self.nbr_buf)
        free(self.body_buf)
        free(self.work_buf)
        free(self.kept_w)

    def __init__(self, cfg, law):
        """``cfg``: agents.core.AgentConfig; ``law``: agents.controller.ControlConstants."""
        cdef int i, j
        self.dt = cfg.dt
        self.n_nbr = len(cfg.neighbours)
        self.weights = <double*> malloc(sizeof(double) * max(self.n_nbr, 1))
        for i, (_, w) in enumerate(cfg.neighbours):
            self.weights[i] = w
        self.leader_weight = cfg.leader_weight
        self.rx, self.ry = cfg.offset
        self.heading_offset = cfg.heading_offset
        self.scale0x, self.scale0y = cfg.initial_scale
        self.n_changes = len(cfg.scale_changes)
        self.changes = <double*> malloc(sizeof(double) * 4 * max(self.n_changes, 1))
        for i, ch in enumerate(cfg.scale_changes):
            self.changes[4 * i] = ch.start_s
            self.changes[4 * i + 1] = ch.end_s
            self.changes[4 * i + 2] = ch.to[0]
            self.changes[4 * i + 3] = ch.to[1]
        self.kappa1, self.kappa2 = cfg.kappa1, cfg.kappa2
        if self.kappa1 + self.kappa2 * sum(w for _, w in cfg.neighbours) <= 0.0:
            raise ValueError("kappa1 + kappa2 * sum_j a_ij must be positive (eq. 16)")
        for i, name in enumerate(NAMES):
            self.en[i] = name in cfg.enabled
            self.rank[i] = list(cfg.priority).index(name) if name in cfg.priority else 99
        if cfg.avoidance_engage not in ("inside", "approaching"):
            raise ValueError(f"unknown avoidance engage mode {cfg.avoidance_engage!r}")
        self.approaching = cfg.avoidance_engage == "approaching"
        for i, g in enumerate((cfg.fdb_gains, cfg.focb_gains, cfg.frcb_gains)):
            self.gain_k[i], self.gain_phi[i] = g
        self.R_a, self.R_c, self.radius = cfg.obstacle_safe_m, cfg.robot_safe_m, cfg.robot_radius_m
        if cfg.guard not in ("every", "nearest"):
            raise ValueError(f"unknown guard {cfg.guard!r}")
        self.guard_every = cfg.guard == "every"
        self.use_filter = cfg.safety_filter
        self.margin, self.exit_time = cfg.safety_margin_m, cfg.safety_exit_time_s
        for i in range(4):
            self.iota[i] = cfg.estimator.iota[i]
        self.eta1, self.eta2 = cfg.estimator.eta
        self.mu1, self.mu2_eso, self.r1 = cfg.eso.mu1, cfg.eso.mu2, cfg.eso.r1
        self.r2 = cfg.eso.r2
        self.gamma_p, self.alpha, self.mu2, self.eps2 = law.gamma_p, law.alpha, law.mu2, law.eps2
        self.reach_low, self.reach_high, self.s_div = law.reach_low, law.reach_high, law.s_div
        model_from(&self.model, cfg.model)
        _allocation_of(cfg.model, self.alloc)
        self.max_speed, self.max_yaw = cfg.max_speed_mps, cfg.max_yaw_rate_radps
        self.max_torque = cfg.max_wheel_torque_nm
        self.max_accel, self.max_yaw_accel = cfg.max_accel_mps2, cfg.max_yaw_accel_radps2
        self.limits_rate = isfinite(self.max_accel) or isfinite(self.max_yaw_accel)
        self.max_tracking_error = cfg.max_tracking_error
        d = cfg.degradation
        self.stale_after, self.slow_after, self.slow_ramp = d.stale_after_s, d.slow_after_s, d.slow_ramp_s
        self.degraded_speed = d.degraded_speed_mps
        self.reacquire_tau, self.reacquire_tol, self.reacquire_min = (
            d.reacquire_tau_s, d.reacquire_tol_m, d.reacquire_min_s)
        self.has_vdp = self.has_z1 = False
        self.z2[0] = self.z2[1] = self.z2[2] = 0.0
        self.speed_factor = 1.0
        self.speed_cap = 1.0
        self.info_lost = self.reacquiring = False
        self.reacquire_s = 0.0

    # -- state, for AgentCore (its properties, recovery and forks) --------------------
    def set_state(self, q0_hat, v0_hat, q_d):
        cdef int j
        for j in range(3):
            self.q0h[j], self.v0h[j], self.qref[j] = q0_hat[j], v0_hat[j], q_d[j]

    def state(self):
        """The state as floats: {name: value}, vectors as tuples, None where unset."""
        return {
            "q0_hat": (self.q0h[0], self.q0h[1], self.q0h[2]),
            "v0_hat": (self.v0h[0], self.v0h[1], self.v0h[2]),
            "q_d": (self.qref[0], self.qref[1], self.qref[2]),
            "v_d_prev": (self.vdp[0], self.vdp[1], self.vdp[2]) if self.has_vdp else None,
            "z1_hat": (self.z1[0], self.z1[1], self.z1[2]) if self.has_z1 else None,
            "z2_hat": (self.z2[0], self.z2[1], self.z2[2]),
            "speed_factor": self.speed_factor,
        }

    def restore(self, str name, value):
        """Set one part of the state (AgentCore.recover): None unsets v_d_prev / z1_hat."""
        cdef int j
        if name == "q0_hat":
            for j in range(3):
                self.q0h[j] = value[j]
        elif name == "v0_hat":
            for j in range(3):
                self.v0h[j] = value[j]
        elif name == "q_d":
            for j in range(3):
                self.qref[j] = value[j]
        elif name == "v_d_prev":
            self.has_vdp = value is not None
            if value is not None:
                for j in range(3):
                    self.vdp[j] = value[j]
        elif name == "z1_hat":
            self.has_z1 = value is not None
            if value is not None:
                for j in range(3):
                    self.z1[j] = value[j]
        elif name == "z2_hat":
            for j in range(3):
                self.z2[j] = value[j]
        elif name == "speed_factor":
            self.speed_factor = value
        else:
            raise KeyError(name)

    def state_finite(self):
        """The integrators' and observers' state holds no NaN/Inf."""
        cdef double total = 0.0
        cdef int j
        for j in range(3):
            total += self.q0h[j] + self.v0h[j] + self.qref[j] + self.z2[j]
            if self.has_z1:
                total += self.z1[j]
            if self.has_vdp:
                total += self.vdp[j]
        return bool(isfinite(total + self.speed_factor))

    def offsets(self, double t):
        """(zeta, zeta_dot) of eq. (13)/(48) at t, from the present leader estimate."""
        cdef double z[3]
        cdef double zd[3]
        self._offsets(t, z, zd)
        return (z[0], z[1], z[2]), (zd[0], zd[1], zd[2])

    cpdef Law fork(self):
        """An independent copy of this law (its state; the constants are copied too)."""
        cdef Law c = Law.__new__(Law)
        # every plain field, then the owned arrays again
        memcpy(<char*> &c.dt, <char*> &self.dt, <size_t> (<char*> &self.tasks - <char*> &self.dt))
        c.weights = <double*> malloc(sizeof(double) * max(self.n_nbr, 1))
        memcpy(c.weights, self.weights, sizeof(double) * max(self.n_nbr, 1))
        c.changes = <double*> malloc(sizeof(double) * 4 * max(self.n_changes, 1))
        memcpy(c.changes, self.changes, sizeof(double) * 4 * max(self.n_changes, 1))
        c.tasks, c.lines, c.nbr_buf, c.body_buf = NULL, NULL, NULL, NULL
        c.work_buf, c.kept_w = NULL, NULL
        c.task_cap = c.line_cap = c.nbr_cap = c.body_cap = c.work_cap = 0
        return c

    # -- buffers ----------------------------------------------------------------------
    cdef double* _nbr(self, int n) except NULL:
        if n > self.nbr_cap:
            self.nbr_buf = <double*> realloc(self.nbr_buf, sizeof(double) * NBR_W * max(n, 1))
            if self.nbr_buf == NULL:
                raise MemoryError()
            self.nbr_cap = n
        return self.nbr_buf if self.nbr_buf != NULL else <double*> malloc(8)

    cdef double* _bodies(self, int n) except NULL:
        if n > self.body_cap or self.body_buf == NULL:
            self.body_buf = <double*> realloc(self.body_buf, sizeof(double) * 6 * max(n, 1))
            if self.body_buf == NULL:
                raise MemoryError()
            self.body_cap = max(n, 1)
        return self.body_buf

    cdef double* _work(self, int n) except NULL:
        if n > self.work_cap or self.work_buf == NULL:
            self.work_buf = <double*> realloc(self.work_buf, sizeof(double) * 12 * max(n, 1))
            self.kept_w = <double*> realloc(self.kept_w, sizeof(double) * max(n, 1))
            if self.work_buf == NULL or self.kept_w == NULL:
                raise MemoryError()
            self.work_cap = max(n, 1)
        return self.work_buf

    cdef int _room(self, int n_tasks, int n_lines) except -1:
        if n_tasks > self.task_cap or self.tasks == NULL:
            self.tasks = <Task*> realloc(self.tasks, sizeof(Task) * max(n_tasks, 1))
            if self.tasks == NULL:
                raise MemoryError()
            self.task_cap = max(n_tasks, 1)
        if n_lines > self.line_cap or self.lines == NULL:
            self.lines = <Line*> realloc(self.lines, sizeof(Line) * max(n_lines, 1))
            if self.lines == NULL:
                raise MemoryError()
            self.line_cap = max(n_lines, 1)
        return 0

    # -- the step ---------------------------------------------------------------------
    cdef void _offsets(self, double t, double* zeta, double* zeta_dot) noexcept nogil:
        """zeta_i and its rate (13)/(48), psi the estimated formation heading."""
        cdef double scale[2]
        cdef double rate[2]
        scale_at(t, self.scale0x, self.scale0y, self.changes, self.n_changes, scale, rate)
        offsets(self.rx, self.ry, self.heading_offset, self.q0h[2], self.v0h[2], scale, rate,
                zeta, zeta_dot)

    cdef void _limited(self, double* v, double h) noexcept nogil:
        """The fused velocity as commanded: the explicit speed limit, the degradation
        slow-down, and the acceleration limit from the last command (ours: v_d moves toward
        the fused command no faster than the torque limit can follow, so the reference q_d
        does not run ahead of the robot at a behavior switch)."""
        cdef double dv[3]
        saturate_velocity(v, self.max_speed, self.max_yaw)
        if self.speed_cap < 1.0:  # a loop that cannot keep its period slows its robot
            v[0], v[1], v[2] = v[0] * self.speed_cap, v[1] * self.speed_cap, v[2] * self.speed_cap
        if self.speed_factor < 1.0:
            slow_down(v, self.speed_factor, self.degraded_speed)
        if self.has_vdp and self.limits_rate:
            dv[0], dv[1], dv[2] = v[0] - self.vdp[0], v[1] - self.vdp[1], v[2] - self.vdp[2]
            saturate_velocity(dv, self.max_accel * h, self.max_yaw_accel * h)
            v[0], v[1], v[2] = self.vdp[0] + dv[0], self.vdp[1] + dv[1], self.vdp[2] + dv[2]

    cdef double _engage_distance(self, double qx, double qy, const double* qd,
                                 const double* row, double contact, double h) noexcept nogil:
        """Centre distance at which avoiding a body must begin (docs/safety.md): contact,
        the margin, and the gap that closing at the present speed uses up before braking
        at the acceleration limit stops it; the closing speed is the larger of the
        command's (the last v_d) and the robot's measured one, relative to the body."""
        cdef double dx = qx - row[1], dy = qy - row[2]
        cdef double dist = hypot(dx, dy), ux, uy, closing, c2
        if dist < 1e-12:
            return contact
        ux, uy = dx / dist, dy / dist
        closing = -(ux * (qd[0] - row[3]) + uy * (qd[1] - row[4]))
        if self.has_vdp:
            c2 = -(ux * (self.vdp[0] - row[3]) + uy * (self.vdp[1] - row[4]))
            if c2 > closing:
                closing = c2
        return contact + self.margin + stopping_distance(closing, self.max_accel, h)

    cdef int _behaviors(self, double qx, double qy, double qw, const double* qd,
                        const double* q_fd, const double* v_fd, const double* bodies,
                        int n_obs, int n_rob, double horizon) noexcept nogil:
        """The active tasks into self.tasks, highest priority first; within FOCB and FRCB
        one task per guarded body, nearest (smallest surface gap) first. R_a is measured
        from an obstacle's surface (the paper's obstacles are points), R_c from the other
        robot's centre. Returns how many."""
        cdef int n = 0, kind, first, count, i, j, best
        cdef double safe, contact, threshold, engage, gap, best_gap
        cdef bint surface
        cdef const double* row
        cdef Task tmp
        if self.en[FDB]:
            formation_task(&self.tasks[0], qx, qy, qw, q_fd, v_fd, self.gain_k[FDB],
                           self.gain_phi[FDB])
            n = 1
        for kind in range(FOCB, FRCB + 1):
            if kind == FOCB:
                first, count = 0, n_obs
            else:
                first, count = n_obs, n_rob
            if not self.en[kind] or count == 0:
                continue
            safe = self.R_a if kind == FOCB else self.R_c
            surface = kind == FOCB
            best = -1
            if not self.guard_every:  # only the nearest body (the authors' script)
                best_gap = 0.0
                for i in range(first, first + count):
                    row = bodies + 6 * i
                    gap = hypot(qx - row[1], qy - row[2]) - row[5]
                    if best < 0 or gap < best_gap:
                        best, best_gap = i, gap
            j = n
            for i in range(first, first + count):
                if best >= 0 and i != best:
                    continue
                row = bodies + 6 * i
                contact = self.radius + row[5]
                threshold = safe + (row[5] if surface else 0.0)
                engage = self._engage_distance(qx, qy, qd, row, contact, horizon)
                if engage > threshold:
                    threshold = engage
                if avoidance_task(&self.tasks[n], kind, qx, qy, qw, row[1], row[2], contact,
                                  threshold, q_fd[2], v_fd[2], self.gain_k[kind],
                                  self.gain_phi[kind], <long> row[0]):
                    self.tasks[n].gap = hypot(qx - row[1], qy - row[2]) - row[5]
                    n += 1
            # nearest first within the behavior (stable insertion sort)
            for i in range(j + 1, n):
                tmp = self.tasks[i]
                best = i - 1
                while best >= j and self.tasks[best].gap > tmp.gap:
                    self.tasks[best + 1] = self.tasks[best]
                    best -= 1
                self.tasks[best + 1] = tmp
        # by priority, stable: nearest first within one behavior
        for i in range(1, n):
            tmp = self.tasks[i]
            best = i - 1
            while best >= 0 and self.rank[self.tasks[best].name] > self.rank[tmp.name]:
                self.tasks[best + 1] = self.tasks[best]
                best -= 1
            self.tasks[best + 1] = tmp
        return n

    cdef void _drive(self, Inputs* x, const double* qv, double* v_d, double* e, double* s,
                     Outputs* o):
        """From the commanded velocity ``v_d`` (after the explicit limits) to the wheel
        torques: the safety filter, the dynamic level (36), (40)-(42), the observer (39) and
        the reference's integration (11). The paper's step runs it after its behaviors;
        a law of the behavior level (agents/law_api.py) after its own (``drive``).
        ``qv``: the own pose the step uses; ``e``, ``s``: the tracking error and the
        sliding variable, out."""
        cdef double h = x.h
        cdef double v_ref[3]
        cdef double e_dot[3]
        cdef double gamma[3]
        cdef double gen[3]
        cdef double a1[3]
        cdef double u[4]
        cdef double c, sphi, e_norm, pull
        cdef int j
        o.filtered = self.use_filter and (x.n_obs + x.n_rob) > 0
        if o.filtered:
            o.safety = safety_filter(v_d[0], v_d[1], self.has_vdp, self.vdp[0], self.vdp[1],
                                     qv[0], qv[1], self.radius, x.bodies, x.n_obs + x.n_rob,
                                     x.n_obs, self.margin, self.max_accel, self.max_speed,
                                     self.exit_time, h, x.horizon, self.lines)
            if o.safety.active:
                v_d[0], v_d[1] = o.safety.vx, o.safety.vy

        # dynamic level, eqs. (36), (40)-(42). The reference q_d(t) is the first-order
        # hold of the v_d samples, one period late (controller.py): velocity v_d(k-1) at
        # t_k, constant acceleration q_d_ddot over [t_k, t_k+1]
        c, sphi = cos(qv[2]), sin(qv[2])
        for j in range(3):
            v_ref[j] = self.vdp[j] if self.has_vdp else v_d[j]
            e[j] = qv[j] - self.qref[j]
        e_norm = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        if e_norm > self.max_tracking_error:
            # anti-windup on the reference (ours, not the paper's): eq. (11) integrates q_d
            # open loop, so a robot held back left q_d running ahead; q_d is kept within
            # the bound of the robot
            pull = 1.0 - self.max_tracking_error / e_norm
            for j in range(3):
                self.qref[j] = self.qref[j] + pull * e[j]
                e[j] = qv[j] - self.qref[j]
        for j in range(3):
            e_dot[j] = x.qd[j] - v_ref[j]
        if not self.has_z1:  # the ESO starts at the first measurement (eso.py)
            self.has_z1 = True
            for j in range(3):
                self.z1[j] = e_dot[j]
        control_term(e, e_dot, self.z2, self.gamma_p, self.alpha, self.mu2, self.eps2,
                     self.reach_low, self.reach_high, self.s_div, gamma, s)
        # u = B_bar^-1 [q_d_ddot + A0 q_dot + A1 + Gamma; 0], q_d_ddot = (v_d - v_ref) / h
        coulomb_term(&self.model, c, sphi, x.qd, a1)
        for j in range(3):
            gen[j] = (v_d[j] - v_ref[j]) / h + (self.model.A0[j][0] * x.qd[0]
                     + self.model.A0[j][1] * x.qd[1] + self.model.A0[j][2] * x.qd[2]) \
                     + a1[j] + gamma[j]
        allocate(self.alloc, c, sphi, gen, u)
        saturate_torques(u, self.max_torque)
        o.nonfinite = not (isfinite(u[0]) and isfinite(u[1]) and isfinite(u[2]) and isfinite(u[3]))
        for j in range(4):
            o.torques[j] = 0.0 if o.nonfinite else u[j]

        # observer (39) and reference integration (CLIK, eq. 11: the trapezoid of the
        # first-order hold)
        eso_advance(self.z1, self.z2, e_dot, gamma, self.mu1, self.mu2_eso, self.r1, self.r2,
                    h, self.dt)
        for j in range(3):
            o.q_d[j] = self.qref[j]
            self.qref[j] = self.qref[j] + 0.5 * h * (v_ref[j] + v_d[j])
            self.vdp[j] = v_d[j]
        self.has_vdp = True


    cdef void _step(self, Inputs* x, Outputs* o):
        """One control step (agents/core.py AgentCore.step says what comes in and out)."""
        cdef double h = x.h
        cdef double qv[3]
        cdef double zeta[3]
        cdef double zeta_dot[3]
        cdef double q_fd[3]
        cdef double v_fd[3]
        cdef double v_d[3]
        cdef double v_ref[3]
        cdef double e[3]
        cdef double e_dot[3]
        cdef double gamma[3]
        cdef double s[3]
        cdef double gen[3]
        cdef double a1[3]
        cdef double lq[3]
        cdef double fq[3]
        cdef double fv[3]
        cdef double u[4]
        cdef double c, sphi, k, info_age = 0.0, age, input_age, e_norm, pull
        cdef int i, j, nt, kept, left_out = 0
        cdef bint has_fresh = False, has_lq
        cdef double* row
        cdef double* work = self._work(x.n_nbr)
        # own state, predicted over its age (degradation.py)
        predict(x.q, x.qd, x.state_age if x.has_ages else 0.0, qv)
        # the freshest leader information (degradation.py): ages add up along the graph
        if x.has_ages:
            for i in range(x.n_nbr):
                row = x.nbr + NBR_W * i
                for j in range(6):
                    work[8 * i + j] = row[j]
                work[8 * i + 6], work[8 * i + 7] = row[19], row[18]
            has_fresh = freshest(x.has_leader and self.leader_weight != 0.0, x.lq, x.lv,
                                 x.leader_age, x.n_nbr, work, fq, fv, &info_age)
            if not has_fresh:
                info_age = 0.0
            if info_age > self.stale_after:
                self.info_lost, self.reacquiring = True, False
            elif self.info_lost:
                self.info_lost, self.reacquiring, self.reacquire_s = False, True, 0.0

        # formation reference, eqs. (13), (16); stale neighbours predicted to now
        self._offsets(x.t, zeta, zeta_dot)
        if self.kappa2 != 0.0:
            for i in range(x.n_nbr):
                row = x.nbr + NBR_W * i
                age = row[19] if x.has_ages else 0.0
                predict(row + 6, row + 9, age, work + 12 * i)          # q_j
                for j in range(3):
                    work[12 * i + 3 + j] = row[9 + j]                  # q_dot_j
                predict(row + 12, row + 15, age, work + 12 * i + 6)   # zeta_j
                for j in range(3):
                    work[12 * i + 9 + j] = row[15 + j]                 # zeta_dot_j
        desired_formation(self.kappa1, self.kappa2, self.q0h, self.v0h, zeta, zeta_dot,
                          x.n_nbr if self.kappa2 != 0.0 else 0, self.weights, work, q_fd, v_fd)

        # behaviors (15)-(25), supervisor + fusion (26) after the explicit limits (the
        # supervisor judges engagement on the command after them), safety filter
        input_age = 0.0
        if x.has_ages:
            input_age = info_age if info_age > x.state_age else x.state_age
        if x.has_ages or self.speed_factor < 1.0:  # degraded, or recovering
            self.speed_factor = next_speed_factor(self.speed_factor, input_age, self.slow_after,
                                                  self.slow_ramp, h)
        self.speed_cap = x.speed_cap
        nt = self._behaviors(qv[0], qv[1], qv[2], x.qd, q_fd, v_fd, x.bodies, x.n_obs,
                             x.n_rob, x.horizon)
        supervise(self.tasks, nt, self.approaching, self, h, v_d)
        self.n_tasks = nt
        self._drive(x, qv, v_d, e, s, o)

        # leader estimator (14), advanced to k+1 and shared; stale inputs predicted to
        # now, those older than stale_after left out (degradation.py)
        has_lq = x.has_leader
        for j in range(3):
            lq[j] = x.lq[j]
        if x.has_ages and has_lq:
            if x.leader_age > self.stale_after:
                has_lq = False
                left_out += 1
            else:
                predict(x.lq, x.lv, x.leader_age, lq)
        kept = 0
        for i in range(x.n_nbr):
            row = x.nbr + NBR_W * i
            age = row[19] if x.has_ages else 0.0
            if x.has_ages and age > self.stale_after:
                left_out += 1
                continue
            predict(row, row + 3, age, work + 6 * kept)
            for j in range(3):
                work[6 * kept + 3 + j] = row[3 + j]
            self.kept_w[kept] = self.weights[i]
            kept += 1
        estimator_step(self.q0h, self.v0h, kept, self.kept_w, work, self.leader_weight,
                       has_lq, lq, x.lv, self.iota, self.eta1, self.eta2, h)
        if self.reacquiring and has_fresh:
            self.reacquiring = reacquire(self.q0h, self.v0h, fq, fv, self.reacquire_tau,
                                         self.reacquire_tol, h)
            self.reacquire_s += h
            self.reacquiring = self.reacquiring or self.reacquire_s < self.reacquire_min

        for j in range(3):
            o.zeta[j], o.zeta_dot[j] = zeta[j], zeta_dot[j]
            o.e[j], o.s[j], o.q_fd[j] = e[j], s[j], q_fd[j]
            o.v_cmd[j] = v_d[j]
        if not (isfinite(v_d[0]) and isfinite(v_d[1]) and isfinite(v_d[2])):
            o.nonfinite = True  # a kinematic plant takes v_cmd: never a NaN either
            o.v_cmd[0] = o.v_cmd[1] = o.v_cmd[2] = 0.0
        o.info_age = info_age
        o.input_age = input_age
        o.left_out = left_out

    # -- the Python face --------------------------------------------------------------
    cdef int _inputs(self, Inputs* x, double t, q, q_dot, nbr, ages, leader,
                     obstacles, robots, double h, double horizon=0.0,
                     double speed_cap=1.0) except -1:
        cdef int i, j
        cdef double* row
        self._own_inputs(x, t, q, q_dot, obstacles, robots, h, horizon, speed_cap)
        x.has_ages = ages is not None
        x.state_age = ages[0] if ages is not None else 0.0
        x.leader_age = ages[1] if ages is not None else 0.0
        x.has_leader = leader is not None
        if leader is not None:
            lq, lv = leader
            for j in range(3):
                x.lq[j], x.lv[j] = lq[j], lv[j]
        else:
            for j in range(3):
                x.lq[j] = x.lv[j] = 0.0
        x.n_nbr = self.n_nbr
        x.nbr = self._nbr(self.n_nbr)
        for i in range(self.n_nbr):
            sh = nbr[i]
            row = x.nbr + NBR_W * i
            for j, part in enumerate((sh.q0_hat, sh.v0_hat, sh.q, sh.q_dot, sh.zeta, sh.zeta_dot)):
                row[3 * j], row[3 * j + 1], row[3 * j + 2] = part[0], part[1], part[2]
            row[18] = sh.info_age_s
            row[19] = ages[2][i] if ages is not None else 0.0
        return 0

    cdef int _own_inputs(self, Inputs* x, double t, q, q_dot, obstacles, robots, double h,
                         double horizon, double speed_cap) except -1:
        """The inputs every step takes (its own state, the bodies it senses, the step's
        times), for ``step`` and ``drive`` alike."""
        cdef int j, n_obs, n_rob
        x.t, x.h = t, h
        x.horizon = horizon if horizon > h else h
        x.speed_cap = speed_cap if speed_cap < 1.0 else 1.0
        for j in range(3):
            x.q[j] = q[j]
            x.qd[j] = q_dot[j]
        n_obs, n_rob = len(obstacles), len(robots)
        x.n_obs, x.n_rob = n_obs, n_rob
        x.bodies = self._bodies(n_obs + n_rob)
        _copy_bodies(obstacles, x.bodies)
        _copy_bodies(robots, x.bodies + 6 * n_obs)
        self._room(1 + n_obs + n_rob, n_obs + n_rob)
        return 0

    def step(self, double t, q, q_dot, nbr, ages, leader, obstacles, robots, double h,
             double horizon=0.0, double speed_cap=1.0):
        """One control step. ``q``, ``q_dot``: 3 floats each; ``nbr``: the neighbours'
        shares in the configuration's order (objects with q0_hat, v0_hat, q, q_dot, zeta,
        zeta_dot of 3 floats and info_age_s); ``ages``: None (all fresh) or (state age,
        leader age, per-neighbour link ages); ``leader``: None or (q0, v0);
        ``obstacles``, ``robots``: (k, 6) float arrays of rows (ident, x, y, vx, vy,
        radius); ``h``: the time to the next step; ``horizon``: how long the command will
        act (at least h); ``speed_cap``: a planar speed scale (1: none). Returns the output
        tuple that agents/core.py unpacks (AgentOutput)."""
        cdef Inputs x
        cdef Outputs o
        self._inputs(&x, t, q, q_dot, nbr, ages, leader, obstacles, robots, h, horizon,
                     speed_cap)
        self._step(&x, &o)
        return self._outputs(&o)

    def drive(self, double t, q, q_dot, v_d, obstacles, robots, double h,
              double horizon=0.0, double speed_cap=1.0):
        """A law of the behavior level (agents/law_api.py) made ``v_d`` (3 floats, the
        world-frame velocity it wants) from these inputs: the explicit limits, the safety
        filter, the dynamic level, the observer and the reference, as the paper's own step
        runs them after its behaviors (``_drive``). Returns (torques, v_cmd, e, s, q_d,
        z2_hat, nonfinite, safety), safety as ``step`` gives it."""
        cdef Inputs x
        cdef Outputs o
        cdef double v[3]
        cdef double e[3]
        cdef double s[3]
        cdef int j
        self._own_inputs(&x, t, q, q_dot, obstacles, robots, h, horizon, speed_cap)
        for j in range(3):
            v[j] = v_d[j]
        x.has_ages, x.has_leader, x.n_nbr, x.nbr = False, False, 0, NULL
        x.state_age = x.leader_age = 0.0
        self.speed_cap = x.speed_cap
        self.n_tasks = 0
        self._limited(v, h)
        self._drive(&x, x.q, v, e, s, &o)
        if not (isfinite(v[0]) and isfinite(v[1]) and isfinite(v[2])):
            o.nonfinite = True
            v[0] = v[1] = v[2] = 0.0
        safety = None
        if o.filtered:
            safety = ((o.safety.vx, o.safety.vy), bool(o.safety.active), o.safety.binding,
                      bool(o.safety.infeasible), o.safety.dv)
        return ((o.torques[0], o.torques[1], o.torques[2], o.torques[3]), (v[0], v[1], v[2]),
                (e[0], e[1], e[2]), (s[0], s[1], s[2]), (o.q_d[0], o.q_d[1], o.q_d[2]),
                (self.z2[0], self.z2[1], self.z2[2]), bool(o.nonfinite), safety)

    def predicted(self, q, q_dot, torques, double h):
        """The robot's (q, q_dot) after ``h`` under ``torques``: eq. (4), RK4, no disturbance
        (the model the look-ahead predicts with, ``plan``)."""
        cdef double xq[3]
        cdef double xv[3]
        cdef double u[4]
        cdef int j
        for j in range(3):
            xq[j], xv[j] = q[j], q_dot[j]
        for j in range(4):
            u[j] = torques[j]
        rk4(&self.model, xq, xv, u, h)
        return (xq[0], xq[1], xq[2]), (xv[0], xv[1], xv[2])

    cdef object _outputs(self, Outputs* o):
        cdef int i
        cdef Task* tk
        order = []
        errors = {}
        for i in range(self.n_tasks):  # the chain: highest priority first
            tk = &self.tasks[i]
            if tk.name != FDB and not tk.engaged:
                continue
            name = NAMES[tk.name]
            if name not in errors:  # each behavior once, with its nearest task's error
                order.append(name)
                errors[name] = tk.task_error
        safety = None
        if o.filtered:
            safety = ((o.safety.vx, o.safety.vy), bool(o.safety.active), o.safety.binding,
                      bool(o.safety.infeasible), o.safety.dv)
        return (
            (o.torques[0], o.torques[1], o.torques[2], o.torques[3]),
            (o.v_cmd[0], o.v_cmd[1], o.v_cmd[2]),
            (o.e[0], o.e[1], o.e[2]), (o.s[0], o.s[1], o.s[2]),
            (o.q_d[0], o.q_d[1], o.q_d[2]), (o.q_fd[0], o.q_fd[1], o.q_fd[2]),
            (o.zeta[0], o.zeta[1], o.zeta[2]), (o.zeta_dot[0], o.zeta_dot[1], o.zeta_dot[2]),
            (self.q0h[0], self.q0h[1], self.q0h[2]), (self.v0h[0], self.v0h[1], self.v0h[2]),
            (self.z2[0], self.z2[1], self.z2[2]),
            tuple(order), errors,
            bool(o.nonfinite), o.info_age, o.input_age, self.speed_factor, o.left_out, safety,
        )

    def plan(self, torques, double t, q, q_dot, nbr, ages, leader, obstacles, robots,
             int horizon):
        """The torques of steps k+1 .. k+H after this law made ``torques`` at step k from
        these inputs (agents/look_ahead.py): a fork steps H times on its own state
        integrated with eq. (4) (RK4, no disturbance) under the torques just computed and
        then each predicted one, the same leader and neighbour samples older by m periods,
        and the perceived bodies moved on at the velocity they were seen with. Shorter
        than H when a predicted step is not finite."""
        cdef Law sim = self.fork()
        cdef Inputs x
        cdef Outputs o
        cdef double h = self.dt, ahead, state_age
        cdef double xq[3]
        cdef double xv[3]
        cdef double u[4]
        cdef double base_leader
        cdef int m, i, j, nb
        planned = []
        if horizon <= 0:
            return planned
        sim._inputs(&x, t, q, q_dot, nbr, ages, leader, obstacles, robots, h)
        nb = x.n_obs + x.n_rob
        # the state the agent used: its sample carried to now (degradation.predict)
        state_age = x.state_age if x.has_ages else 0.0
        for j in range(3):
            xq[j] = x.q[j] + state_age * x.qd[j]
            xv[j] = x.qd[j]
        for j in range(4):
            u[j] = torques[j]
        base_leader = x.leader_age
        links = [x.nbr[NBR_W * i + 19] for i in range(x.n_nbr)]
        for m in range(1, horizon + 1):
            rk4(&self.model, xq, xv, u, h)
            ahead = m * h
            x.t = t + ahead
            for j in range(3):
                x.q[j], x.qd[j] = xq[j], xv[j]
            x.has_ages = True
            x.state_age = 0.0
            x.leader_age = base_leader + ahead
            for i in range(x.n_nbr):
                x.nbr[NBR_W * i + 19] = links[i] + ahead
            for i in range(nb):  # bodies moved on by one more period
                x.bodies[6 * i + 1] += h * x.bodies[6 * i + 3]
                x.bodies[6 * i + 2] += h * x.bodies[6 * i + 4]
            sim._step(&x, &o)
            if o.nonfinite:
                break
            for j in range(4):
                u[j] = o.torques[j]
            planned.append((u[0], u[1], u[2], u[3]))
        return planned


# --- the equations one by one, for the tests (tests/unit/test_hot_path.py checks each
# against the numpy reference form of its module) and the modules' float forms ----------

cdef void _v3(object x, double* out):
    out[0], out[1], out[2] = x[0], x[1], x[2]


cdef tuple _t3(const double* x):
    return (x[0], x[1], x[2])


def sig_of(double x, double power):
    return sig(x, power)


def implicit_sign_of(double e, double reach):
    return implicit_sign(e, reach)


def smooth_step_of(double t, double start, double end):
    cdef double value, rate
    smooth_step(t, start, end, &value, &rate)
    return value, rate


def scale_at_of(double t, initial, changes):
    """(S, S_dot) at t; ``changes``: objects with start_s, end_s, to."""
    cdef int n = len(changes), i
    cdef double scale[2]
    cdef double rate[2]
    cdef double* rows = <double*> malloc(sizeof(double) * 4 * max(n, 1))
    try:
        for i, ch in enumerate(changes):
            rows[4 * i], rows[4 * i + 1] = ch.start_s, ch.end_s
            rows[4 * i + 2], rows[4 * i + 3] = ch.to[0], ch.to[1]
        scale_at(t, initial[0], initial[1], rows, n, scale, rate)
    finally:
        free(rows)
    return (scale[0], scale[1]), (rate[0], rate[1])


def offsets_of(r_i, double heading_offset, double psi, double psi_dot, scale, scale_dot):
    cdef double sc[2]
    cdef double sd[2]
    cdef double z[3]
    cdef double zd[3]
    sc[0], sc[1], sd[0], sd[1] = scale[0], scale[1], scale_dot[0], scale_dot[1]
    offsets(r_i[0], r_i[1], heading_offset, psi, psi_dot, sc, sd, z, zd)
    return _t3(z), _t3(zd)


def desired_formation_of(double kappa1, double kappa2, q0_hat, v0_hat, zeta, zeta_dot,
                         weights, neighbour_q, neighbour_q_dot, neighbour_zeta,
                         neighbour_zeta_dot):
    cdef int n = len(weights), i, j
    cdef double q0h[3]
    cdef double v0h[3]
    cdef double z[3]
    cdef double zd[3]
    cdef double qf[3]
    cdef double vf[3]
    cdef double* w = <double*> malloc(sizeof(double) * max(n, 1))
    cdef double* rows = <double*> malloc(sizeof(double) * 12 * max(n, 1))
    try:
        _v3(q0_hat, q0h)
        _v3(v0_hat, v0h)
        _v3(zeta, z)
        _v3(zeta_dot, zd)
        for i in range(n):
            w[i] = weights[i]
            if kappa2 != 0.0:
                for j, part in enumerate((neighbour_q[i], neighbour_q_dot[i], neighbour_zeta[i],
                                          neighbour_zeta_dot[i])):
                    _v3(part, rows + 12 * i + 3 * j)
        if not desired_formation(kappa1, kappa2, q0h, v0h, z, zd, n if kappa2 != 0.0 else 0,
                                 w, rows, qf, vf):
            if not kappa1 + kappa2 * sum(weights) > 0.0:
                raise ValueError("kappa1 + kappa2 * sum_j a_ij must be positive (eq. 16)")
    finally:
        free(w)
        free(rows)
    return _t3(qf), _t3(vf)


def estimator_step_of(q_hat, v_hat, neighbour_q, neighbour_v, weights, double leader_weight,
                      leader_q, leader_v, iota, eta, double dt):
    cdef int n = len(weights), i
    cdef double q[3]
    cdef double v[3]
    cdef double lq[3]
    cdef double lv[3]
    cdef double io[4]
    cdef double* w = <double*> malloc(sizeof(double) * max(n, 1))
    cdef double* rows = <double*> malloc(sizeof(double) * 6 * max(n, 1))
    try:
        _v3(q_hat, q)
        _v3(v_hat, v)
        for i in range(4):
            io[i] = iota[i]
        for i in range(n):
            w[i] = weights[i]
            _v3(neighbour_q[i], rows + 6 * i)
            _v3(neighbour_v[i], rows + 6 * i + 3)
        if leader_q is not None:
            _v3(leader_q, lq)
            _v3(leader_v, lv)
        estimator_step(q, v, n, w, rows, leader_weight, leader_q is not None, lq, lv, io,
                       eta[0], eta[1], dt)
    finally:
        free(w)
        free(rows)
    return _t3(q), _t3(v)


def eso_advance_of(z1_hat, z2_hat, z1_measured, gamma, double mu1, double mu2, double r1,
                   double r2, double dt, double max_step):
    cdef double z1[3]
    cdef double z2[3]
    cdef double m[3]
    cdef double g[3]
    _v3(z1_hat, z1)
    _v3(z2_hat, z2)
    _v3(z1_measured, m)
    _v3(gamma, g)
    eso_advance(z1, z2, m, g, mu1, mu2, r1, r2, dt, max_step)
    return _t3(z1), _t3(z2)


def formation_task_of(q, q_fd, v_fd, gains):
    """FDB's reduced task: (gx, gy, inv_g2, velocity, task_error)."""
    cdef Task t
    cdef double qf[3]
    cdef double vf[3]
    _v3(q_fd, qf)
    _v3(v_fd, vf)
    formation_task(&t, q[0], q[1], q[2], qf, vf, gains[0], gains[1])
    return t.gx, t.gy, t.inv_g2, (t.vx, t.vy, t.vw), t.task_error


def avoidance_task_of_(str name, q, other_xy, double contact, double safe, double phi_d,
                       double phi_d_dot, gains, long body=0):
    """An avoidance behavior's reduced task, or None when inactive."""
    cdef Task t
    if not avoidance_task(&t, NAMES.index(name), q[0], q[1], q[2], other_xy[0], other_xy[1],
                          contact, safe, phi_d, phi_d_dot, gains[0], gains[1], body):
        return None
    return t.gx, t.gy, t.inv_g2, (t.vx, t.vy, t.vw), t.task_error


cdef Task* _tasks_from(list tasks) except NULL:
    cdef Task* out = <Task*> malloc(sizeof(Task) * max(len(tasks), 1))
    cdef int i
    if out == NULL:
        raise MemoryError()
    for i, tk in enumerate(tasks):
        out[i].name = NAMES.index(tk.name)
        out[i].gx, out[i].gy, out[i].inv_g2 = tk.gx, tk.gy, tk.inv_g2
        out[i].vx, out[i].vy, out[i].vw = tk.velocity
        out[i].task_error, out[i].body, out[i].engaged, out[i].gap = tk.task_error, tk.body, False, 0.0
    return out


def fuse_of(list tasks):
    """Eq. (26) over reduced tasks (objects with name, gx, gy, inv_g2, velocity, body)."""
    cdef Task* ts = _tasks_from(tasks)
    cdef double v[3]
    try:
        fuse(ts, len(tasks), False, v)
    finally:
        free(ts)
    return _t3(v)


def supervise_of(list tasks, str engage):
    """The supervisor over reduced tasks, no limits: (indices of the chain, fused velocity)."""
    cdef Task* ts
    cdef double v[3]
    cdef int i
    if engage not in ("inside", "approaching"):
        raise ValueError(f"unknown avoidance engage mode {engage!r}")
    ts = _tasks_from(tasks)
    try:
        supervise(ts, len(tasks), engage == "approaching", None, 0.0, v)
        chain = [i for i in range(len(tasks)) if ts[i].name == FDB or ts[i].engaged]
    finally:
        free(ts)
    return chain, _t3(v)


def control_term_of(e, e_dot, z2_hat, double gamma_p, double alpha, double mu2, double eps2,
                    double reach_low, double reach_high, double s_div):
    cdef double ev[3]
    cdef double ed[3]
    cdef double z[3]
    cdef double g[3]
    cdef double s[3]
    _v3(e, ev)
    _v3(e_dot, ed)
    _v3(z2_hat, z)
    control_term(ev, ed, z, gamma_p, alpha, mu2, eps2, reach_low, reach_high, s_div, g, s)
    return _t3(g), _t3(s)


def coulomb_term_of(model, double phi, q_dot):
    cdef Model m
    cdef double qd[3]
    cdef double a1[3]
    model_from(&m, model)
    _v3(q_dot, qd)
    coulomb_term(&m, cos(phi), sin(phi), qd, a1)
    return _t3(a1)


def allocate_of(model, double phi, generalised):
    cdef double alloc[4][3]
    cdef double g[3]
    cdef double u[4]
    _allocation_of(model, alloc)
    _v3(generalised, g)
    allocate(alloc, cos(phi), sin(phi), g, u)
    return (u[0], u[1], u[2], u[3])


def saturate_torques_of(u, double limit):
    cdef double w[4]
    w[0], w[1], w[2], w[3] = u[0], u[1], u[2], u[3]
    saturate_torques(w, limit)
    return (w[0], w[1], w[2], w[3])


def closing_speed_limit_of(double gap, double brake, double h, double exit_time_s):
    return closing_speed_limit(gap, brake, h, exit_time_s)


def stopping_distance_of(double closing, double brake, double h):
    return stopping_distance(closing, brake, h)


def closest_feasible_of(v_nom, lines, discs):
    """argmin |v - v_nom| over the lines' half-planes and the discs; None when empty."""
    cdef int nl = len(lines), nd = len(discs), i
    cdef Line* ls = <Line*> malloc(sizeof(Line) * max(nl, 1))
    cdef Disc* ds = <Disc*> malloc(sizeof(Disc) * max(nd, 1))
    cdef double v[2]
    cdef bint found
    try:
        for i in range(nl):
            ls[i].nx, ls[i].ny, ls[i].b = lines[i]
        for i in range(nd):
            ds[i].cx, ds[i].cy, ds[i].r = discs[i]
        found = closest_feasible(v_nom[0], v_nom[1], ls, nl, ds, nd, v)
    finally:
        free(ls)
        free(ds)
    return (v[0], v[1]) if found else None


def safety_filter_of(v_nom, v_prev, double px, double py, double radius, bodies,
                     int n_obstacles, double margin, double brake, double max_speed,
                     double exit_time, double h):
    """The safety filter; ``bodies``: rows (ident, x, y, vx, vy, radius), the first
    ``n_obstacles`` guarded by (S1), the rest (robots) by (S2). Returns (v, active, binding,
    infeasible, dv)."""
    cdef int nb = len(bodies), i
    cdef double* rows = <double*> malloc(sizeof(double) * 6 * max(nb, 1))
    cdef Line* ls = <Line*> malloc(sizeof(Line) * max(nb, 1))
    cdef Filtered r
    try:
        for i in range(nb):
            for j in range(6):
                rows[6 * i + j] = bodies[i][j]
        r = safety_filter(v_nom[0], v_nom[1], v_prev is not None,
                          v_prev[0] if v_prev is not None else 0.0,
                          v_prev[1] if v_prev is not None else 0.0, px, py, radius, rows, nb,
                          n_obstacles, margin, brake, max_speed, exit_time, h, h, ls)
    finally:
        free(rows)
        free(ls)
    return (r.vx, r.vy), bool(r.active), r.binding, bool(r.infeasible), r.dv


def next_speed_factor_of(double f, double age, double slow_after, double slow_ramp, double h):
    return next_speed_factor(f, age, slow_after, slow_ramp, h)


def slow_down_of(v, double f, double degraded):
    cdef double w[3]
    _v3(v, w)
    slow_down(w, f, degraded)
    return _t3(w)


def reacquire_of(q_hat, v_hat, q0, v0, double tau, double tol, double h):
    cdef double q[3]
    cdef double v[3]
    cdef double a[3]
    cdef double b[3]
    cdef bint far
    _v3(q_hat, q)
    _v3(v_hat, v)
    _v3(q0, a)
    _v3(v0, b)
    far = reacquire(q, v, a, b, tau, tol, h)
    return _t3(q), _t3(v), bool(far)


def freshest_of(leader, double leader_age, shares):
    """(age, q0, v0) of the freshest source, or None; ``shares``: (q0_hat, v0_hat, link
    age, information age) per neighbour."""
    cdef int n = len(shares), i
    cdef double lq[3]
    cdef double lv[3]
    cdef double fq[3]
    cdef double fv[3]
    cdef double age = 0.0
    cdef double* rows = <double*> malloc(sizeof(double) * 8 * max(n, 1))
    cdef bint found
    try:
        if leader is not None:
            _v3(leader[0], lq)
            _v3(leader[1], lv)
        for i, (q0, v0, link, info) in enumerate(shares):
            _v3(q0, rows + 8 * i)
            _v3(v0, rows + 8 * i + 3)
            rows[8 * i + 6], rows[8 * i + 7] = link, info
        found = freshest(leader is not None, lq, lv, leader_age, n, rows, fq, fv, &age)
    finally:
        free(rows)
    return (age, _t3(fq), _t3(fv)) if found else None
