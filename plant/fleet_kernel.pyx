"""The plant's per-step arithmetic on C doubles: eq. (4) integrated for the whole fleet
(RK4 sub-steps, the disturbance h_d(t) of eq. 49 inside), the pybullet plant's wheel forces
between its calls to Bullet (and its loop over the sub-steps, which calls the pybullet
functions the plant hands it: this module imports no pybullet), and what each robot
perceives of the discs around it. One pass over the fleet per step, no Python object per
robot.

Why compiled: as numpy over 3-vectors a robot-step of RK4 cost ~100 µs, almost all of it
the per-call overhead of ~400 numpy calls on arrays of 3-12 elements; the same loops on C
doubles cost about 1 µs (docs/bench-history.md, "The compiled kernels").
"""

DEF _SOURCE = PLANT_FLEET_KERNEL_SHA256  # given by setup.py at build time
BUILT_FROM = _SOURCE  # the sha256 of the .pyx this module was built from (plant/kernels.py)


from libc.math cimport cos, sin, tanh, hypot, isfinite, isnan

import numpy as np

# disturbance kinds, as make_disturbance names them (plant/disturbance.py)
DISTURBANCE_KINDS = ("none", "constant", "paper")
# Bullet keeps a contact point only while its bodies are within its contact breaking
# threshold (0.02 m; measured: none at 0.019 m, tests/integration/test_pybullet_plant.py):
# a sub-step that starts with every robot more than this gap (5x that threshold) from
# every other body finds none, so no constraint acts in it: it is the free step of (P2),
# computed without calling Bullet (FleetDynamics.bullet_step)
CONTACT_QUERY_GAP_M = 0.1


cdef void model_from(Model* m, object model):
    """Fill ``m`` from a plant.mecanum.MecanumModel."""
    cdef int i, j
    P, B0, A0 = model.P.tolist(), model.body_input.tolist(), model.A0.tolist()
    for i in range(4):
        for j in range(3):
            m.P[i][j] = P[i][j]
    for i in range(3):
        for j in range(4):
            m.B0[i][j] = B0[i][j]
        for j in range(3):
            m.A0[i][j] = A0[i][j]
    m.inv_R = 1.0 / model.params.wheel_radius_m
    m.coulomb = model.coulomb_torque_nm
    m.inv_smooth = 1.0 / model.params.coulomb_smoothing_radps
    m.viscous = model.viscous_torque_per_radps


cdef void acceleration(const Model* m, double phi, const double* qd, const double* u,
                       double* acc) noexcept nogil:
    """q_ddot of eq. (4), -A0 q_dot - A1 + B(phi) (u + h_d), with u the wheel torques
    including h_d. In the body frame: b = T(phi)^T q_dot, theta_dot = P b / R, the
    Coulomb torques tau_c = C tanh(theta_dot / omega_s) (A1 = B tau_c), then
    q_ddot = T(phi) B0 (u - tau_c) - A0 q_dot."""
    cdef double c = cos(phi), s = sin(phi)
    cdef double bx = c * qd[0] + s * qd[1], by = c * qd[1] - s * qd[0], bw = qd[2]
    cdef double net[4]
    cdef int j
    for j in range(4):
        net[j] = u[j] - m.coulomb * tanh(
            (m.P[j][0] * bx + m.P[j][1] * by + m.P[j][2] * bw) * m.inv_R * m.inv_smooth)
    cdef double ax = m.B0[0][0] * net[0] + m.B0[0][1] * net[1] + m.B0[0][2] * net[2] + m.B0[0][3] * net[3]
    cdef double ay = m.B0[1][0] * net[0] + m.B0[1][1] * net[1] + m.B0[1][2] * net[2] + m.B0[1][3] * net[3]
    cdef double aw = m.B0[2][0] * net[0] + m.B0[2][1] * net[1] + m.B0[2][2] * net[2] + m.B0[2][3] * net[3]
    acc[0] = c * ax - s * ay - (m.A0[0][0] * qd[0] + m.A0[0][1] * qd[1] + m.A0[0][2] * qd[2])
    acc[1] = s * ax + c * ay - (m.A0[1][0] * qd[0] + m.A0[1][1] * qd[1] + m.A0[1][2] * qd[2])
    acc[2] = aw - (m.A0[2][0] * qd[0] + m.A0[2][1] * qd[1] + m.A0[2][2] * qd[2])


cdef inline void _disturbance(int kind, double scale, const double* constant, double t,
                              double* out) noexcept nogil:
    """h_d(t): none, a constant, or eq. (49) (in N m, the 10^-2 factor applied), scaled."""
    if kind == 2:
        out[0] = scale * 1e-2 * (1.0 + 2.0 * cos(0.3 * t))
        out[1] = scale * 1e-2 * (2.0 + 1.5 * sin(0.3 * t) + 3.0 * cos(0.3 * t))
        out[2] = scale * 1e-2 * (3.0 + 2.0 * sin(0.2 * t))
        out[3] = scale * 1e-2 * (2.5 + sin(0.1 * t))
    elif kind == 1:
        out[0], out[1], out[2], out[3] = (scale * constant[0], scale * constant[1],
                                          scale * constant[2], scale * constant[3])
    else:
        out[0] = out[1] = out[2] = out[3] = 0.0


cdef inline void _wheel_force(const Model* m, const double* q, const double* qd,
                              const double* torques, const double* h_d,
                              double* out) noexcept nogil:
    """(P3)-(P5) of one robot: world-frame [F_x, F_y, M_z] into ``out`` from the wheel
    torques (plus h_d, when given) at state (q, qd)."""
    cdef int j
    cdef double w, fx, fy, fw
    cdef double tau[4]
    cdef double c = cos(q[2]), s = sin(q[2])
    cdef double bx = c * qd[0] + s * qd[1], by = c * qd[1] - s * qd[0], bw = qd[2]
    for j in range(4):
        w = (m.P[j][0] * bx + m.P[j][1] * by + m.P[j][2] * bw) * m.inv_R  # (P3)
        tau[j] = (torques[j] if h_d == NULL else torques[j] + h_d[j]) \
            - m.coulomb * tanh(w * m.inv_smooth) - m.viscous * w  # (P4)
    fx = (m.P[0][0] * tau[0] + m.P[1][0] * tau[1] + m.P[2][0] * tau[2] + m.P[3][0] * tau[3]) * m.inv_R
    fy = (m.P[0][1] * tau[0] + m.P[1][1] * tau[1] + m.P[2][1] * tau[2] + m.P[3][1] * tau[3]) * m.inv_R
    fw = (m.P[0][2] * tau[0] + m.P[1][2] * tau[1] + m.P[2][2] * tau[2] + m.P[3][2] * tau[3]) * m.inv_R
    out[0], out[1], out[2] = c * fx - s * fy, s * fx + c * fy, fw  # (P5)


cdef void _rk4_disturbed(const Model* m, double* q, double* qd, const double* u,
                         const double* d0, const double* dh, const double* d1,
                         double h) noexcept nogil:
    """One classical RK4 step of eq. (4) over [t, t + h], torques u held (zero-order hold),
    h_d at the stages' times t, t + h/2, t + h given as d0, dh, d1 (NULL: none)."""
    cdef double k1q[3]
    cdef double k2q[3]
    cdef double k3q[3]
    cdef double k4q[3]
    cdef double k1v[3]
    cdef double k2v[3]
    cdef double k3v[3]
    cdef double k4v[3]
    cdef double x[3]
    cdef double ud[4]
    cdef int j
    cdef double half = 0.5 * h
    for j in range(4):  # stage 1 at t
        ud[j] = u[j] + d0[j] if d0 != NULL else u[j]
    for j in range(3):
        k1q[j] = qd[j]
    acceleration(m, q[2], qd, ud, k1v)
    for j in range(4):  # stages 2 and 3 at t + h/2
        ud[j] = u[j] + dh[j] if dh != NULL else u[j]
    for j in range(3):
        k2q[j] = qd[j] + half * k1v[j]
        x[j] = q[j] + half * k1q[j]
    acceleration(m, x[2], k2q, ud, k2v)
    for j in range(3):
        k3q[j] = qd[j] + half * k2v[j]
        x[j] = q[j] + half * k2q[j]
    acceleration(m, x[2], k3q, ud, k3v)
    for j in range(4):  # stage 4 at t + h
        ud[j] = u[j] + d1[j] if d1 != NULL else u[j]
    for j in range(3):
        k4q[j] = qd[j] + h * k3v[j]
        x[j] = q[j] + h * k3q[j]
    acceleration(m, x[2], k4q, ud, k4v)
    cdef double w = h / 6.0
    for j in range(3):
        q[j] = q[j] + w * (k1q[j] + 2.0 * k2q[j] + 2.0 * k3q[j] + k4q[j])
        qd[j] = qd[j] + w * (k1v[j] + 2.0 * k2v[j] + 2.0 * k3v[j] + k4v[j])


cdef void rk4(const Model* m, double* q, double* qd, const double* u, double h) noexcept nogil:
    """One RK4 step of eq. (4) without disturbance (the agent's look-ahead: h_d is unknown
    to it)."""
    _rk4_disturbed(m, q, qd, u, NULL, NULL, NULL, h)


cdef void saturate_velocity(double* v, double max_speed, double max_yaw) noexcept nogil:
    """(vx, vy) scaled into max_speed (direction kept), w clipped to max_yaw: the one rule
    for a velocity limit, the agent's on its command and a plant's on what it applies."""
    cdef double speed = hypot(v[0], v[1]), k
    if speed > max_speed:
        k = max_speed / speed
        v[0] = v[0] * k
        v[1] = v[1] * k
    v[2] = -max_yaw if v[2] < -max_yaw else (max_yaw if v[2] > max_yaw else v[2])


def saturate_velocity_of(v, double max_speed, double max_yaw_rate):
    """:c:func:`saturate_velocity` on a 3-vector: a tuple of floats."""
    cdef double w[3]
    w[0], w[1], w[2] = v[0], v[1], v[2]
    saturate_velocity(w, max_speed, max_yaw_rate)
    return (w[0], w[1], w[2])


def acceleration_of(model, q, q_dot, torques):
    """q_ddot of eq. (4) for one robot (torques including h_d), as the plant integrates it."""
    cdef Model m
    cdef double qd[3]
    cdef double u[4]
    cdef double acc[3]
    cdef int j
    model_from(&m, model)
    for j in range(3):
        qd[j] = q_dot[j]
    for j in range(4):
        u[j] = torques[j]
    acceleration(&m, q[2], qd, u, acc)
    return (acc[0], acc[1], acc[2])


def disturbance_at(str kind, double scale, constant, double t):
    """h_d(t) (4 wheel torques, N m) as the model plant applies it (plant/disturbance.py)."""
    cdef double c[4]
    cdef double out[4]
    cdef int j
    for j in range(4):
        c[j] = constant[j] if kind == "constant" else 0.0
    _disturbance(DISTURBANCE_KINDS.index(kind), scale, c, t, out)
    return np.array([out[0], out[1], out[2], out[3]])


cdef class FleetDynamics:
    """Eq. (4) for every robot of a fleet, integrated with RK4 sub-steps."""

    cdef Model* _models
    cdef int n
    cdef int substeps
    cdef int kind
    cdef double scale
    cdef double constant[4]
    cdef object _keep
    cdef double* _mass  # M_q's diagonal (P1), robot after robot: what Bullet's joints carry
    cdef object _keep_mass
    # Bullet's joints hold an older state than the plant's q, qd: sub-steps with nothing
    # near ran here without Bullet (bullet_step); catch_up_bullet sets them
    cdef public bint bullet_behind

    def __cinit__(self, models, str disturbance_kind, double disturbance_scale,
                  disturbance_constant, int substeps):
        cdef int i, j
        self.n = len(models)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        self.substeps = substeps
        self.kind = DISTURBANCE_KINDS.index(disturbance_kind)
        self.scale = disturbance_scale
        for i in range(4):
            self.constant[i] = disturbance_constant[i] if self.kind == 1 else 0.0
        self._keep = bytearray(sizeof(Model) * max(self.n, 1))
        self._models = <Model*> <char*> self._keep
        for i in range(self.n):
            model_from(&self._models[i], models[i])
        from plant.mecanum import generalised_inertia

        self._keep_mass = bytearray(sizeof(double) * 3 * max(self.n, 1))
        self._mass = <double*> <char*> self._keep_mass
        for i in range(self.n):
            m_q = generalised_inertia(models[i].params)
            for j in range(3):
                self._mass[3 * i + j] = float(m_q[j, j])

    def wheel_forces(self, const double[:, ::1] q, const double[:, ::1] qd,
                     const double[:, ::1] wheel_torques, double[:, ::1] out):
        """The wheels' generalised force on each chassis (plant/pybullet_plant.py, (P3)-(P5)):
        theta_dot = P T(phi)^T q_dot / R; tau_w = u + h_d - tau_c(theta_dot) - C_theta R^2
        theta_dot; F = T(phi) P^T tau_w / R, world frame [F_x, F_y, M_z], into ``out``."""
        cdef int i
        for i in range(self.n):
            _wheel_force(&self._models[i], &q[i, 0], &qd[i, 0], &wheel_torques[i, 0], NULL,
                         &out[i, 0])

    cdef void _check_state(self, double[:, ::1] q, double[:, ::1] qd) except *:
        if q.shape[0] != self.n or qd.shape[0] != self.n or q.shape[1] != 3 or qd.shape[1] != 3:
            raise ValueError("q, q_dot must be (n, 3)")

    cdef void _read_states(self, tuple states, double[:, ::1] q, double[:, ::1] qd) except *:
        """getJointStates' tuples (x, y, yaw of each robot in turn; position and velocity
        first) into q and qd."""
        cdef int i, j, n = self.n
        cdef tuple joint
        if len(states) != 3 * n:
            raise ValueError(f"{len(states)} joint states for {n} robots")
        for i in range(n):
            for j in range(3):
                joint = <tuple?> states[3 * i + j]
                q[i, j], qd[i, j] = joint[0], joint[1]

    cdef list _forces(self, const double[:, ::1] torques, double t, double[:, ::1] q,
                      double[:, ::1] qd):
        """The wheels' forces (P3)-(P5) at (q, qd) from torques + h_d(t), the flat list
        [F_x, F_y, M_z, ...] setJointMotorControlArray takes; ValueError (before anything
        is computed) unless every torque is finite."""
        cdef int i, j, n = self.n
        cdef double d[4]
        cdef double f[3]
        cdef const double* h_d = NULL  # none: the torques as given
        if torques.shape[0] != n or torques.shape[1] != 4:
            raise ValueError("torques must be (n, 4)")
        for i in range(n):
            for j in range(4):
                if not isfinite(torques[i, j]):
                    raise ValueError("torques must be finite")
        if self.kind != 0:
            _disturbance(self.kind, self.scale, self.constant, t, d)
            h_d = d
        forces = [None] * (3 * n)
        for i in range(n):
            _wheel_force(&self._models[i], &q[i, 0], &qd[i, 0], &torques[i, 0], h_d, f)
            forces[3 * i], forces[3 * i + 1], forces[3 * i + 2] = f[0], f[1], f[2]
        return forces

    cdef void _free(self, list forces, double h, double[:, ::1] q, double[:, ::1] qd) except *:
        """v += h M_q^-1 F, q += h v of (P2), in place: Bullet's free sub-step."""
        cdef int i, j, n = self.n
        cdef double v
        if len(forces) != 3 * n:
            raise ValueError(f"{len(forces)} forces for {n} robots")
        for i in range(n):
            for j in range(3):
                v = qd[i, j] + h * (<double> forces[3 * i + j] / self._mass[3 * i + j])
                qd[i, j] = v
                q[i, j] = q[i, j] + h * v

    def bullet_substep(self, tuple states, const double[:, ::1] torques, double t,
                       double[:, ::1] q, double[:, ::1] qd):
        """The arithmetic of a pybullet plant's sub-step (plant/pybullet_plant.py): the joint
        states Bullet returned (getJointStates' tuples for x, y, yaw of each robot in turn,
        position and velocity first) into ``q`` and ``qd`` (``states`` None: they hold the
        state already); then, unless ``torques`` is None, the wheels' forces (P3)-(P5) there
        from torques + h_d(t) (this kernel's disturbance) as the flat list [F_x, F_y, M_z,
        ...] that setJointMotorControlArray takes. Torques that are not all finite raise
        ValueError before any force is computed. :meth:`bullet_step` runs a whole step of
        these; this is one, for the tests."""
        self._check_state(q, qd)
        if torques is not None and (torques.shape[0] != self.n or torques.shape[1] != 4):
            raise ValueError("torques must be (n, 4)")  # before q and qd are written
        if states is not None:
            self._read_states(states, q, qd)
        return None if torques is None else self._forces(torques, t, q, qd)

    def bullet_free_substep(self, list forces, double h, double[:, ::1] q, double[:, ::1] qd):
        """A sub-step in which Bullet found no contact point (so no constraint acted, its
        joints being free of limits, damping and motors), as Bullet integrates it: the
        semi-implicit Euler step v += h M_q^-1 F, q += h v of (P2) with the forces ``forces``
        (the flat list the sub-step applied), in place. Bullet's articulated-body pass
        rounds M_q^-1 F its own way: the velocities agree to ~1e-13 relative, not bit for
        bit (docs/bench-history.md). :meth:`bullet_step` takes it for every sub-step without a
        contact, with Bullet stepped or not."""
        self._check_state(q, qd)
        self._free(forces, h, q, qd)

    cdef void _put_states(self, object put_states, list bodies, int cid,
                          const double[:, ::1] q, const double[:, ::1] qd) except *:
        """q, qd into Bullet's joints (x, y, yaw of each robot in turn), one
        resetJointStatesMultiDof a body; Bullet's collision shapes move with them."""
        cdef tuple body
        cdef int first, end, r
        for body in bodies:
            first, end = <int> body[2], <int> body[3]
            put_states(body[0], body[1],
                       [[q[r // 3, r % 3]] for r in range(first, end)],
                       [[qd[r // 3, r % 3]] for r in range(first, end)], cid)
        self.bullet_behind = False

    def catch_up_bullet(self, tuple bullet, list bodies, double[:, ::1] q, double[:, ::1] qd):
        """Bullet's joints to q, qd when sub-steps ran without it (:meth:`bullet_step`);
        nothing otherwise. Before anything reads Bullet's world (its queries, its view)."""
        if self.bullet_behind:
            self._check_state(q, qd)
            *_, cid, put_states = bullet  # as bullet_step unpacks it
            self._put_states(put_states, bodies, cid, q, qd)

    def bullet_step(self, tuple bullet, list bodies, const double[:, ::1] torques,
                    object other, double[:, ::1] wheel_torques, double t, double h,
                    int substeps, double[:, ::1] q, double[:, ::1] qd,
                    const double[::1] radii=None, const double[:, ::1] discs=None):
        """A pybullet plant's whole step (plant/pybullet_plant.py ``step``), ``substeps``
        sub-steps of ``h`` from the state (q, qd) at ``t``, in place. Each sub-step: the
        wheels' forces (P3)-(P5) from the torques (plus ``other(ts)``, a disturbance other
        than this kernel's, added into ``wheel_torques``, when given); then, where a
        contact can happen, Bullet: its joints caught up when earlier sub-steps ran without
        it, the forces into its joints, its step, its contact points; the state after a
        sub-step in which Bullet found a contact point, and after the last, read back from
        Bullet. After one without, the state is Bullet's free step, computed
        (:meth:`bullet_free_substep`). ``bullet``: pybullet's (setJointMotorControlArray,
        stepSimulation, getContactPoints, getJointStates, TORQUE_CONTROL, client id,
        resetJointStatesMultiDof), so that this module needs no pybullet; ``bodies``:
        (body, joint indices, first, end) per multibody, its slice of the forces. Returns
        each sub-step's contact points. Torques that are not all finite raise ValueError
        before Bullet is called.

        ``radii`` (each robot's collision radius) and ``discs`` (rows x, y, radius: every
        other body of the world, static discs), when given: a sub-step that starts with
        every robot more than ``CONTACT_QUERY_GAP_M`` from every other body (Bullet finds
        contact points at the sub-step's start, within its 0.02 m breaking threshold) has
        no contact, so no constraint acts: it is the free step, and Bullet is not called
        (:attr:`bullet_behind` is set). Without them (a world with other shapes), Bullet
        steps every sub-step."""
        cdef int k, last = substeps - 1
        cdef const double[:, ::1] u = torques
        cdef tuple states = None
        cdef tuple body
        cdef list forces, seen = [None] * substeps
        cdef double ts
        cdef bint query = True
        self._check_state(q, qd)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        if (radii is None) != (discs is None) or radii is not None and (
                radii.shape[0] != self.n or discs.shape[1] != 3):
            raise ValueError("radii and discs: both or neither, (n,) and (m, 3)")
        set_forces, step_bullet, contact_points, joint_states, mode, cid, put_states = bullet
        for k in range(substeps):
            ts = t + k * h
            if states is not None:
                self._read_states(states, q, qd)
            if other is not None:
                np.add(torques, other(ts), out=np.asarray(wheel_torques))
                u = wheel_torques
            forces = self._forces(u, ts, q, qd)
            if radii is not None:  # where the robots are as this sub-step starts
                query = not _apart(q, radii, discs, CONTACT_QUERY_GAP_M)
            if not query:  # nothing near: the free step, (P2), without Bullet
                self._free(forces, h, q, qd)
                states = None
                seen[k] = ()
                self.bullet_behind = True
                continue
            if self.bullet_behind:  # the sub-steps before ran without Bullet
                self._put_states(put_states, bodies, cid, q, qd)
            for body in bodies:
                f = forces[<int> body[2]:<int> body[3]]
                set_forces(body[0], body[1], mode, f, f, f, f, f, cid)
            step_bullet(cid)
            points = contact_points(-1, -1, -2, -2, cid)
            seen[k] = points
            if points or k == last:  # Bullet's own state: a contact acted, or the step's end
                states = ()
                for body in bodies:
                    states += joint_states(body[0], body[1], cid)
            else:  # no contact point, no constraint: Bullet's free step, (P2), predicted
                self._free(forces, h, q, qd)
                states = None
        if states is not None:
            self._read_states(states, q, qd)
        return seen

    def step(self, double t, double dt, double[:, ::1] q, double[:, ::1] qd,
             const double[:, ::1] torques, const double[:, :, ::1] stage_disturbance=None,
             const double[::1] start=None):
        """Advance every robot by ``dt`` (in place), torques held over the period, in
        ``substeps`` RK4 steps of h = dt / substeps. The disturbance: the kind given at
        construction, or, when ``stage_disturbance`` is given, h_d of each robot at the
        stages' times t + j h / 2, j = 0 .. 2 substeps (shape (2 substeps + 1, n, 4)).
        ``start`` (n,): each robot feels the kind given on its own clock, h_d(t - start_i),
        none while start_i is NaN (a drive emulator's robots: from their first arming)."""
        cdef int i, k, n = self.n
        cdef double h = dt / self.substeps
        cdef double ts
        cdef double d[3][4]
        if q.shape[0] != n or qd.shape[0] != n or torques.shape[0] != n \
                or q.shape[1] != 3 or qd.shape[1] != 3 or torques.shape[1] != 4:
            raise ValueError("q, q_dot, torques must be (n, 3), (n, 3), (n, 4)")
        if stage_disturbance is not None and (
                stage_disturbance.shape[0] != 2 * self.substeps + 1
                or stage_disturbance.shape[1] != n or stage_disturbance.shape[2] != 4):
            raise ValueError("stage_disturbance must be (2 substeps + 1, n, 4)")
        if start is not None and (stage_disturbance is not None or start.shape[0] != n):
            raise ValueError("start must be (n,), and not given with stage_disturbance")
        with nogil:
            for k in range(self.substeps):
                ts = t + k * h
                if stage_disturbance is None and start is None:
                    _disturbance(self.kind, self.scale, self.constant, ts, d[0])
                    _disturbance(self.kind, self.scale, self.constant, ts + 0.5 * h, d[1])
                    _disturbance(self.kind, self.scale, self.constant, ts + h, d[2])
                for i in range(n):
                    if start is not None:
                        if isnan(start[i]):  # not started: no disturbance yet
                            _rk4_disturbed(&self._models[i], &q[i, 0], &qd[i, 0],
                                           &torques[i, 0], NULL, NULL, NULL, h)
                            continue
                        # at the stages' times as for the scenario's h_d (above), on its clock
                        _disturbance(self.kind, self.scale, self.constant, ts - start[i], d[0])
                        _disturbance(self.kind, self.scale, self.constant,
                                     (ts + 0.5 * h) - start[i], d[1])
                        _disturbance(self.kind, self.scale, self.constant,
                                     (ts + h) - start[i], d[2])
                    if stage_disturbance is None:
                        _rk4_disturbed(&self._models[i], &q[i, 0], &qd[i, 0], &torques[i, 0],
                                       d[0], d[1], d[2], h)
                    else:
                        _rk4_disturbed(&self._models[i], &q[i, 0], &qd[i, 0], &torques[i, 0],
                                       &stage_disturbance[2 * k, i, 0],
                                       &stage_disturbance[2 * k + 1, i, 0],
                                       &stage_disturbance[2 * k + 2, i, 0], h)


cdef bint _apart(const double[:, ::1] q, const double[::1] radii, const double[:, ::1] discs,
                 double gap) noexcept:
    """Every robot (rows of ``q``, radii ``radii``) more than ``gap`` from every other robot
    and every disc (rows x, y, radius), surface to surface; a non-finite position is not."""
    cdef Py_ssize_t i, j, n = q.shape[0], m = discs.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            if not hypot(q[j, 0] - q[i, 0], q[j, 1] - q[i, 1]) - radii[i] - radii[j] > gap:
                return False
        for j in range(m):
            if not hypot(discs[j, 0] - q[i, 0], discs[j, 1] - q[i, 1]) - radii[i] - discs[j, 2] > gap:
                return False
    return True


cdef (int, int) _sense(int i, const double[:, ::1] positions, const double[:, ::1] velocities,
                       const double[::1] radii, const long[::1] ids,
                       const double[:, ::1] obstacles, const long[::1] obstacle_ids,
                       double detection_range_m, double[:, ::1] r, double[:, ::1] o) noexcept:
    """Robot ``i``'s discs into the rows of ``r`` (robots) and ``o`` (obstacles); returns
    how many of each (see :func:`sense_discs`)."""
    cdef int n = positions.shape[0], m = obstacles.shape[0], j, nr = 0, no = 0
    cdef double mx = positions[i, 0], my = positions[i, 1]
    for j in range(n):
        if j == i:
            continue
        if hypot(positions[j, 0] - mx, positions[j, 1] - my) - radii[j] <= detection_range_m:
            r[nr, 0] = ids[j]
            r[nr, 1], r[nr, 2] = positions[j, 0], positions[j, 1]
            r[nr, 3], r[nr, 4] = velocities[j, 0], velocities[j, 1]
            r[nr, 5] = radii[j]
            nr += 1
    for j in range(m):
        if hypot(obstacles[j, 0] - mx, obstacles[j, 1] - my) - obstacles[j, 4] <= detection_range_m:
            o[no, 0] = obstacle_ids[j]
            o[no, 1], o[no, 2] = obstacles[j, 0], obstacles[j, 1]
            o[no, 3], o[no, 4] = obstacles[j, 2], obstacles[j, 3]
            o[no, 5] = obstacles[j, 4]
            no += 1
    return nr, no


cdef void _check_discs(const double[:, ::1] positions, const double[:, ::1] velocities,
                       const double[::1] radii, const long[::1] ids,
                       const double[:, ::1] obstacles, const long[::1] obstacle_ids) except *:
    """The shapes :func:`_sense` reads within (the kernel runs without bounds checks)."""
    cdef Py_ssize_t n = positions.shape[0]
    if positions.shape[1] < 2 or velocities.shape[1] < 2 or velocities.shape[0] != n:
        raise ValueError(f"positions and velocities must be (n, 2+) alike, got "
                         f"({n}, {positions.shape[1]}) and ({velocities.shape[0]}, {velocities.shape[1]})")
    if radii.shape[0] != n or ids.shape[0] != n:
        raise ValueError(f"{n} robots, {radii.shape[0]} radii, {ids.shape[0]} ids")
    if obstacles.shape[1] < 5 or obstacle_ids.shape[0] != obstacles.shape[0]:
        raise ValueError("obstacles must be (m, 5) rows (x, y, vx, vy, radius), one id each")


def sense_discs(int i, const double[:, ::1] positions, const double[:, ::1] velocities,
                const double[::1] radii, const long[::1] ids, const double[:, ::1] obstacles,
                const long[::1] obstacle_ids, double detection_range_m):
    """The discs robot ``i`` perceives (plant/perception.py): the other robots and the
    obstacles whose surface is within r_det of its centre, each as (ident, x, y, vx, vy,
    radius); ``obstacles`` rows are (x, y, vx, vy, radius). Returns (robots, obstacles),
    two (k, 6) arrays in the order of their inputs. ``positions`` and ``velocities``:
    (n, 2 or more), only their first two columns read (a plant's (n, 3) state as it is)."""
    _check_discs(positions, velocities, radii, ids, obstacles, obstacle_ids)
    if not 0 <= i < positions.shape[0]:
        raise IndexError(f"robot row {i} of {positions.shape[0]}")
    robots = np.empty((max(positions.shape[0] - 1, 0), 6))
    seen = np.empty((obstacles.shape[0], 6))
    nr, no = _sense(i, positions, velocities, radii, ids, obstacles, obstacle_ids,
                    detection_range_m, robots, seen)
    return robots[:nr], seen[:no]


def sense_fleet(const double[:, ::1] positions, const double[:, ::1] velocities,
                const double[::1] radii, const long[::1] ids, const double[:, ::1] obstacles,
                const long[::1] obstacle_ids, double detection_range_m):
    """:func:`sense_discs` for every robot in one pass: a list of (robots, obstacles),
    views into two arrays filled at once (one allocation each, the inputs read once)."""
    _check_discs(positions, velocities, radii, ids, obstacles, obstacle_ids)
    cdef int n = positions.shape[0], m = obstacles.shape[0], i, nr, no
    robots = np.empty((n, max(n - 1, 0), 6))
    seen = np.empty((n, m, 6))
    cdef double[:, :, ::1] r = robots
    cdef double[:, :, ::1] o = seen
    out = []
    for i in range(n):
        nr, no = _sense(i, positions, velocities, radii, ids, obstacles, obstacle_ids,
                        detection_range_m, r[i], o[i])
        out.append((robots[i, :nr], seen[i, :no]))
    return out
