# Degradation (agents/degradation.py, docs/faults.md): the speed factor of stale inputs,
# the slow-down, the leader estimate's re-acquisition, the freshest input, and an input
# predicted by its age.
# Included by agents/law_kernel.pyx (one module: see its docstring).

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
    """The freshest source of leader information (agents/degradation.py):
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
