# The formation reference (13), (16), (48) (agents/formation.py): the scale at t, the
# offsets zeta_i, and q_fd,i with its velocity.
# Included by agents/law_kernel.pyx (one module: see its docstring).

cdef void scale_at(double t, double s0x, double s0y, const double* changes, int n,
                   double* scale, double* rate) noexcept nogil:
    """S(t) and S_dot(t) (diagonals): each change moves S from its previous value to its
    target over its window by a smooth step (agents/formation.py scale_at).
    ``changes``: n rows (start, end, to_x, to_y)."""
    cdef double sx = s0x, sy = s0y, dx = 0.0, dy = 0.0, frac, r, tx, ty
    cdef int i
    for i in range(n):
        tx, ty = changes[4 * i + 2], changes[4 * i + 3]
        smooth_step(t, changes[4 * i], changes[4 * i + 1], &frac, &r)
        dx += (tx - sx) * r
        dy += (ty - sy) * r
        sx += (tx - sx) * frac
        sy += (ty - sy) * frac
    scale[0], scale[1], rate[0], rate[1] = sx, sy, dx, dy


cdef void offsets(double rx, double ry, double heading_offset, double psi, double psi_dot,
                  const double* scale, const double* scale_dot, double* zeta,
                  double* zeta_dot) noexcept nogil:
    """zeta_i = [W r_i, Xi_i] and zeta_i_dot, eq. (13)/(48): W = Rot(psi) S,
    W_dot = psi_dot Rot(psi + pi/2) S + Rot(psi) S_dot, Rot(psi + pi/2) = [[-s, -c], [c, -s]]."""
    cdef double c = cos(psi), s = sin(psi)
    cdef double ax = scale[0] * rx, ay = scale[1] * ry          # S r_i
    cdef double bx = scale_dot[0] * rx, by = scale_dot[1] * ry  # S_dot r_i
    zeta[0], zeta[1], zeta[2] = c * ax - s * ay, s * ax + c * ay, heading_offset
    zeta_dot[0] = -psi_dot * s * ax - psi_dot * c * ay + (c * bx - s * by)
    zeta_dot[1] = psi_dot * c * ax - psi_dot * s * ay + (s * bx + c * by)
    zeta_dot[2] = 0.0


cdef bint desired_formation(double kappa1, double kappa2, const double* q0h, const double* v0h,
                            const double* zeta, const double* zeta_dot, int n,
                            const double* weights, const double* nbr, double* q_fd,
                            double* v_fd) noexcept nogil:
    """q_fd,i of eq. (16) and its velocity, erratum 4 applied:
    q_fd,i = gamma (kappa1 (q0_hat_i + zeta_i) + kappa2 sum_j a_ij (q_j - zeta_j + zeta_i)),
    gamma = 1 / (kappa1 + kappa2 sum_j a_ij). ``nbr``: n rows (q 3, q_dot 3, zeta 3,
    zeta_dot 3). False when gamma's denominator is not positive."""
    cdef double denom, k = 0.0
    cdef int i, j
    cdef const double* row
    for i in range(n):
        k += weights[i]
    denom = kappa1 + kappa2 * k
    if not denom > 0.0:
        return False
    for j in range(3):
        q_fd[j] = kappa1 * (q0h[j] + zeta[j])
        v_fd[j] = kappa1 * (v0h[j] + zeta_dot[j])
    if kappa2 != 0.0:
        for i in range(n):
            row = nbr + 12 * i
            k = kappa2 * weights[i]
            for j in range(3):
                q_fd[j] += k * (row[j] - row[6 + j] + zeta[j])
                v_fd[j] += k * (row[3 + j] - row[9 + j] + zeta_dot[j])
    for j in range(3):
        q_fd[j] = q_fd[j] / denom
        v_fd[j] = v_fd[j] / denom
    return True


def smooth_step_of(double t, double start, double end):
    """(value, derivative) of the scale change's smooth step at t (agents/formation.py
    smooth_step: a law of the lab's schedules its scale with it, agents/plugged.py)."""
    cdef double value, rate
    smooth_step(t, start, end, &value, &rate)
    return value, rate
