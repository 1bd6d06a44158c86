# The virtual leader on an analytic harmonic path, tangent heading (Section 4; erratum 6):
# agents/leader.py, whose generator's batch calls this. The same operations in the same
# order as its step-by-step path (Harmonic.with_derivatives, LeaderGenerator._harmonic,
# state_floats, advance; x % m as Python takes it for floats), so the two agree bit for bit
# (tests/unit/test_leader.py). Why here: the leader publishes its states in batches ahead
# of need and, at every wake after a sleep, the Python calls of a state cost ~8 µs; its
# budget is 20 µs a step (docs/bench-history.md, "The bridge on floats").


cdef inline double _python_mod(double x, double m) noexcept nogil:
    """x % m for floats as Python computes it (the sign of m; CPython's float_rem)."""
    cdef double r = fmod(x, m)
    if r != 0.0:
        if (m < 0.0) != (r < 0.0):
            r += m
    else:
        r = copysign(0.0, m)
    return r


cdef inline void _harmonic_at(bint is_sin, double amp, double freq, double phase,
                              double offset, double th, double* out) noexcept nogil:
    """(value, first, second derivative) of amp fn(freq th + phase) + offset."""
    cdef double a = freq * th + phase
    cdef double s = sin(a), c = cos(a)
    if is_sin:
        out[0] = amp * s + offset
        out[1] = amp * freq * c
        out[2] = -amp * pow(freq, 2.0) * s
    else:
        out[0] = amp * c + offset
        out[1] = amp * freq * -s
        out[2] = -amp * pow(freq, 2.0) * c


def leader_batch_of(tuple x_path, tuple y_path, double theta0, double rate, double dt,
                    long k, tuple now, int count):
    """The leader's states (q0, v0) of steps k .. k + count - 1, and where the generator
    stands after them. ``x_path``, ``y_path``: (is_sin, amp, freq, phase, offset);
    ``now``: (x, y, heading, vx, vy, ax, ay) at step k. Returns (qs, vs, after) with
    ``after`` as ``now`` at step k + count."""
    cdef bint xs = x_path[0], ys = y_path[0]
    cdef double xa = x_path[1], xf = x_path[2], xp = x_path[3], xo = x_path[4]
    cdef double ya = y_path[1], yf = y_path[2], yp = y_path[3], yo = y_path[4]
    cdef double px = now[0], py = now[1], heading = now[2]
    cdef double vx = now[3], vy = now[4], ax = now[5], ay = now[6]
    cdef double n2, th
    cdef double hx[3]
    cdef double hy[3]
    cdef double two_pi = 2.0 * M_PI
    cdef int i
    qs, vs = [], []
    for i in range(count):
        n2 = vx * vx + vy * vy  # the heading's rate at step k (_heading_rate)
        qs.append((px, py, heading))
        vs.append((vx, vy, 0.0 if n2 == 0.0 else (vx * ay - vy * ax) / n2))
        k += 1  # advance(): the path at step k + 1, the heading unwrapped to its tangent
        th = theta0 + rate * (<double> k * dt)
        _harmonic_at(xs, xa, xf, xp, xo, th, hx)
        _harmonic_at(ys, ya, yf, yp, yo, th, hy)
        px, py = hx[0], hy[0]
        vx, vy = rate * hx[1], rate * hy[1]
        ax, ay = rate * rate * hx[2], rate * rate * hy[2]
        heading += _python_mod(atan2(vy, vx) - heading + M_PI, two_pi) - M_PI
    return qs, vs, (px, py, heading, vx, vy, ax, ay)
