# The law kernel's sections one by one, callable from Python, for the tests only: each is
# checked at its own boundary against the numpy oracle (tests/paper_oracle.py) or used
# alone (tests/kernel_forms.py). Included by tests/law_probe/law_kernel_probe.pyx after the
# whole kernel; the product's module (agents/law_kernel.pyx) does not carry them.

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
