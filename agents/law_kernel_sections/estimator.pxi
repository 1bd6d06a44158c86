# The distributed leader estimator (14) (agents/estimator.py).
# Included by agents/law_kernel.pyx (one module: see its docstring).

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
