# Small maps every section uses: sig^r(x) (Notation 1), the leader estimator's implicit
# sign() (eq. 14, erratum 7: agents/estimator.py), and the smooth step of a scale change
# (eq. 48, agents/formation.py).
# Included by agents/law_kernel.pyx (one module: see its docstring).

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
