# The law of one agent (class Law): its state, its inputs and outputs, and the whole step
# through the sections above in the order of agents/core.py, and the look-ahead's predicted
# steps (agents/look_ahead.py).
# Included by agents/law_kernel.pyx (one module: see its docstring).

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
    cdef double lag             # this step's h beyond the period (_to_sample_time)
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
        self.lag = 0.0
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

    cdef void _to_sample_time(self, double h) noexcept nogil:
        """A step ``h`` after the last one, and h longer than the period the last one
        advanced the leader estimate (14) and the reference (11) by: a realtime agent's
        first step after a stall. Both are carried to this sample's time first, at the
        rates they had (degradation.predict's first order), so that the step's formation
        reference (16) and tracking error are of now; the step then advances them by the
        period. Computed from the estimate and the reference as they were, the step after
        a 20 ms stall of ``paper``'s agents at 1 kHz commanded ~9 m/s less for one period
        (FDB's gain times the leader's 20 ms), and the next one's feed-forward turned that
        back into torques 250x the steady ones (docs/bench-history.md). Lockstep and
        in-process steps are one period long: nothing changes there."""
        cdef int j
        self.lag = 0.0
        if self.has_vdp and h > self.dt * (1.0 + 1e-9):
            self.lag = h - self.dt
            for j in range(3):
                self.q0h[j] = self.q0h[j] + self.v0h[j] * self.lag
                self.qref[j] = self.qref[j] + self.vdp[j] * self.lag

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
        # both over the period once a late step's lag was carried (_to_sample_time)
        eso_advance(self.z1, self.z2, e_dot, gamma, self.mu1, self.mu2_eso, self.r1, self.r2,
                    h - self.lag, self.dt)
        for j in range(3):
            o.q_d[j] = self.qref[j]
            self.qref[j] = self.qref[j] + 0.5 * (h - self.lag) * (v_ref[j] + v_d[j])
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
        self._to_sample_time(h)
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
                       has_lq, lq, x.lv, self.iota, self.eta1, self.eta2, h - self.lag)
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
        self._to_sample_time(h)
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
