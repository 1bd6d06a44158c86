# The fully actuated law (36), (40)-(42) (agents/controller.py): Gamma and the sliding
# variable s of eq. (42), the Coulomb term and the allocation of eq. (2), the torque limit.
# Included by agents/law_kernel.pyx (one module: see its docstring).

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
