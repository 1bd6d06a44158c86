# The behaviours (15)-(25) (agents/behaviors.py): the formation task (FDB) and the obstacle
# and robot avoidance tasks (FOCB, FRCB) with their Jacobians' pseudo-inverses.
# Included by agents/law_kernel.pyx (one module: see its docstring).

cdef inline double inverse_square_norm(double gx, double gy) noexcept nogil:
    """1/|g|^2, the pseudo-inverse's factor for the row [g_x, g_y, 0]; 0 for a zero row."""
    cdef double g2 = gx * gx + gy * gy
    return 1.0 / g2 if g2 > _TINY else 0.0


cdef void formation_task(Task* t, double qx, double qy, double qw, const double* q_fd,
                         const double* v_fd, double k_f, double k_phi) noexcept nogil:
    """FDB, eqs. (15)-(19): rho_f = |x - x_fd|, desired 0; heading row to phi_fd.
    v = J^+ [-d rho/dt + k (0 - rho), phi_fd_dot + k_phi (phi_fd - phi), 0]
        + (I - J^+ J) [v_fd_xy, 0]  (the task's own null space carries the rest of the
    formation velocity: docs/errata.md, "FDB null space")."""
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
