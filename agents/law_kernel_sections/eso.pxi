# The extended state observer (39) (agents/eso.py), in sub-steps of the control period
# over a longer interval (a realtime agent whose state came late).
# Included by agents/law_kernel.pyx (one module: see its docstring).

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
