# The safety filter (S1), (S2) (agents/safety_filter.py, docs/safety.md): the closing speed
# a gap allows and the stopping distance at the braking limit, the barriers as lines and
# discs, the closest feasible velocity, and the filter itself.
# Included by agents/law_kernel.pyx (one module: see its docstring).

cdef inline double closing_speed_limit(double gap, double brake, double h,
                                       double exit_time) noexcept nogil:
    """c_max(d) of (S1): the largest closing speed from which one more period and then
    braking at ``brake`` stop within ``gap``; negative (leave) inside the margin."""
    cdef double ah
    if gap < 0.0:
        return gap / exit_time
    if not isfinite(brake):
        return gap / h
    ah = brake * h
    return -ah + sqrt(ah * ah + 2.0 * brake * gap)


cdef inline double stopping_distance(double closing, double brake, double h) noexcept nogil:
    """The gap used up by one more period at ``closing`` and braking at ``brake`` after
    it: the left side of (S1), whose inverse is closing_speed_limit."""
    if closing <= 0.0:
        return 0.0
    return closing * h + (closing * closing / (2.0 * brake) if isfinite(brake) else 0.0)

cdef inline bint _on_line_side(const Line* lines, int nl, const Disc* discs, int nd,
                               double x, double y) noexcept nogil:
    cdef int i
    for i in range(nl):
        if lines[i].nx * x + lines[i].ny * y < lines[i].b - _TOL:
            return False
    for i in range(nd):
        if (x - discs[i].cx) * (x - discs[i].cx) + (y - discs[i].cy) * (y - discs[i].cy) \
                > (discs[i].r + _TOL) * (discs[i].r + _TOL):
            return False
    return True


cdef inline void _consider(const Line* lines, int nl, const Disc* discs, int nd, double x,
                           double y, double vnx, double vny, double* best, double* cost,
                           bint* found) noexcept nogil:
    cdef double c = (x - vnx) * (x - vnx) + (y - vny) * (y - vny)
    if c < cost[0] and _on_line_side(lines, nl, discs, nd, x, y):
        best[0], best[1], cost[0], found[0] = x, y, c, True


cdef bint closest_feasible(double vnx, double vny, const Line* lines, int nl,
                           const Disc* discs, int nd, double* out) noexcept nogil:
    """argmin |v - v_nom| over {n . v >= b for every line, |v - c| <= r for every disc};
    False when the set is empty. Exact: the optimum of this convex 2-D problem is v_nom or
    lies on one boundary (the projection of v_nom on it) or on two (where they meet), so
    the feasible candidate of least cost among those is the solution."""
    cdef int i, j
    cdef double s, dx, dy, dist, det, fx, fy, half, d, along, mx, my
    cdef double cost = INFINITY
    cdef bint found = False
    if _on_line_side(lines, nl, discs, nd, vnx, vny):
        out[0], out[1] = vnx, vny
        return True
    for i in range(nl):  # projection on a line (|n| = 1)
        s = lines[i].b - (lines[i].nx * vnx + lines[i].ny * vny)
        _consider(lines, nl, discs, nd, vnx + s * lines[i].nx, vny + s * lines[i].ny, vnx, vny,
                  out, &cost, &found)
    for i in range(nd):  # projection on a circle
        dx, dy = vnx - discs[i].cx, vny - discs[i].cy
        dist = hypot(dx, dy)
        if dist > 0:
            _consider(lines, nl, discs, nd, discs[i].cx + discs[i].r * dx / dist,
                      discs[i].cy + discs[i].r * dy / dist, vnx, vny, out, &cost, &found)
        else:
            _consider(lines, nl, discs, nd, discs[i].cx + discs[i].r, discs[i].cy, vnx, vny,
                      out, &cost, &found)
    for i in range(nl):  # line meets line
        for j in range(i + 1, nl):
            det = lines[i].nx * lines[j].ny - lines[i].ny * lines[j].nx
            if fabs(det) > 1e-12:
                _consider(lines, nl, discs, nd,
                          (lines[i].b * lines[j].ny - lines[j].b * lines[i].ny) / det,
                          (lines[i].nx * lines[j].b - lines[j].nx * lines[i].b) / det,
                          vnx, vny, out, &cost, &found)
    for i in range(nl):  # line meets circle
        for j in range(nd):
            s = lines[i].b - (lines[i].nx * discs[j].cx + lines[i].ny * discs[j].cy)
            if fabs(s) > discs[j].r:
                continue
            fx, fy = discs[j].cx + s * lines[i].nx, discs[j].cy + s * lines[i].ny
            half = discs[j].r * discs[j].r - s * s
            half = sqrt(half if half > 0.0 else 0.0)
            _consider(lines, nl, discs, nd, fx - half * lines[i].ny, fy + half * lines[i].nx,
                      vnx, vny, out, &cost, &found)
            _consider(lines, nl, discs, nd, fx + half * lines[i].ny, fy - half * lines[i].nx,
                      vnx, vny, out, &cost, &found)
    for i in range(nd):  # circle meets circle
        for j in range(i + 1, nd):
            dx, dy = discs[j].cx - discs[i].cx, discs[j].cy - discs[i].cy
            d = hypot(dx, dy)
            if d < 1e-12 or d > discs[i].r + discs[j].r or d < fabs(discs[i].r - discs[j].r):
                continue
            along = (discs[i].r * discs[i].r - discs[j].r * discs[j].r + d * d) / (2.0 * d)
            half = discs[i].r * discs[i].r - along * along
            half = sqrt(half if half > 0.0 else 0.0)
            mx, my = discs[i].cx + along * dx / d, discs[i].cy + along * dy / d
            _consider(lines, nl, discs, nd, mx - half * dy / d, my + half * dx / d, vnx, vny,
                      out, &cost, &found)
            _consider(lines, nl, discs, nd, mx + half * dy / d, my - half * dx / d, vnx, vny,
                      out, &cost, &found)
    return found


cdef struct Filtered:      # what the safety filter did (agents/safety_filter.py SafetyResult)
    double vx, vy
    bint active
    int binding
    bint infeasible
    double dv


cdef Filtered safety_filter(double vnx, double vny, bint has_prev, double pvx, double pvy,
                            double px, double py, double radius, const double* bodies,
                            int nb, int n_obstacles, double margin, double brake,
                            double max_speed, double exit_time, double h,
                            double horizon, Line* lines) noexcept nogil:
    """The command closest to v_nom that keeps every barrier: (S1) for an obstacle,
    n . v >= n . v_j - c_max(d_j); (S2) for a robot (reciprocal), n . v >= max((S1),
    -c_max / 2); within |v - v_prev| <= a h and |v| <= v_max (agents/safety_filter.py).
    ``bodies``: rows (ident, x, y, vx, vy, radius), the first ``n_obstacles`` obstacles.
    ``h``: the step (how far v may move from v_prev); ``horizon``: how long the command
    will act before the next one can brake (the period, or longer when the loop runs late:
    the barrier's "one more period"). ``lines``: room for nb barriers."""
    cdef Filtered r
    cdef Disc discs[2]
    cdef int nd = 0, i, binding = 0
    cdef double dx, dy, dist, nx, ny, gap, c_max, b, tx, ty, step
    cdef const double* row
    for i in range(nb):
        row = bodies + 6 * i
        dx, dy = px - row[1], py - row[2]
        dist = hypot(dx, dy)
        nx, ny = 1.0, 0.0
        if dist > 1e-12:
            nx, ny = dx / dist, dy / dist
        gap = dist - radius - row[5] - margin
        c_max = closing_speed_limit(gap, brake, horizon, exit_time)
        b = nx * row[3] + ny * row[4] - c_max  # (S1)
        if i >= n_obstacles and b < -0.5 * c_max:
            b = -0.5 * c_max  # (S2)
        lines[i].nx, lines[i].ny, lines[i].b = nx, ny, b
        if nx * vnx + ny * vny < b:
            binding += 1
    r.vx, r.vy, r.active, r.binding, r.infeasible, r.dv = vnx, vny, False, 0, False, 0.0
    if binding == 0:
        return r
    if has_prev and isfinite(brake):
        discs[nd].cx, discs[nd].cy, discs[nd].r = pvx, pvy, brake * h
        nd += 1
    if isfinite(max_speed):
        discs[nd].cx, discs[nd].cy, discs[nd].r = 0.0, 0.0, max_speed
        nd += 1
    cdef double v[2]
    if closest_feasible(vnx, vny, lines, nb, discs, nd, v):
        r.infeasible = False
    else:
        # no command meets the barriers within the limits: brake as hard as allowed
        # toward the barriers' own solution (or a standstill relative to the world)
        r.infeasible = True
        if not closest_feasible(vnx, vny, lines, nb, discs, 0, v):
            v[0], v[1] = 0.0, 0.0
        if nd > 0 and has_prev:
            tx, ty = v[0] - pvx, v[1] - pvy
            dist = hypot(tx, ty)
            step = brake * h
            if dist > step:
                v[0], v[1] = pvx + step / dist * tx, pvy + step / dist * ty
    r.vx, r.vy, r.active, r.binding = v[0], v[1], True, binding
    r.dv = hypot(v[0] - vnx, v[1] - vny)
    return r
