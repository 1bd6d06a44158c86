# Null-space fusion (26) and the supervisor (agents/fusion.py, erratum 8): which avoidance
# tasks take part, in their priority order, and the fused velocity after the limits.
# Included by agents/law_kernel.pyx (one module: see its docstring).

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
