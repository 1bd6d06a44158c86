"""One agent's law on C doubles: the whole control step of agents/core.py.

Formation reference (13), (16); behaviors (15)-(25); supervisor and null-space fusion (26);
explicit limits and degradation (agents/degradation.py); the safety filter (S1), (S2)
(agents/safety_filter.py); the fully actuated law (36), (40)-(42); the ESO (39) and the
leader estimator (14); and the look-ahead's predicted steps (agents/look_ahead.py).
Each equation is written here once, as plain loops and floats, next to its number, one
section a file in agents/law_kernel_sections/ (included below). The modules named above
keep the gains and the documentation of each equation and of our deviations (errata,
docs/errata.md); tests/paper_oracle.py writes the law again in the paper's matrix form
(numpy), the independent form the tests hold this kernel to, section by section through
their own build of it (tests/law_probe) and step by step through this module.

Why compiled: the same arithmetic as Python floats cost ~45 µs a step (the call and
allocation overhead of a few hundred small operations); here a step costs a few µs
(docs/bench-history.md, "The compiled kernels"). A diverging law does not raise: non-finite
values propagate and the caller (AgentCore) zeroes the torques and restarts the state.
"""

DEF _SOURCE = AGENTS_LAW_KERNEL_SHA256  # given by setup.py at build time
BUILT_FROM = _SOURCE  # the sha256 of the .pyx this module was built from (plant/kernels.py)


from libc.math cimport sqrt, hypot, cos, sin, tanh, pow, fabs, ceil, erf, exp, isfinite, INFINITY, M_PI, atan2, fmod, copysign
from libc.stdlib cimport malloc, realloc, free
from libc.string cimport memcpy

from plant.fleet_kernel cimport Model, model_from, rk4, saturate_velocity

import numpy as np

cdef double _TINY = 1e-12
cdef double _TOL = 1e-9  # m/s: a safety-filter candidate this close to a boundary is on it
cdef double _MIN_GAP = 1e-3  # avoidance: distance floored at contact + this (behaviors.py)

# behavior names, in the order of their codes
cdef enum:
    FDB = 0
    FOCB = 1
    FRCB = 2
NAMES = ("FDB", "FOCB", "FRCB")

# the smooth step of a scale change (agents/formation.py smooth_step): a normal CDF cut at
# +-_Z standard deviations, rescaled to run exactly from 0 to 1
cdef double _Z = 4.0  # the window spans +-4 sigma
cdef double _CDF_LO = 0.5 * (1.0 + erf(-_Z / sqrt(2.0)))
cdef double _CDF_SPAN = 1.0 - 2.0 * _CDF_LO


cdef struct Task:
    int name            # FDB, FOCB or FRCB
    double gx, gy       # gradient of the task's first row, J = [[gx, gy, 0], [0, 0, 1], [0, 0, 0]]
    double inv_g2       # 1/|g|^2 (0 for a zero row): J^+ = J^T diag(1/|row|^2)
    double vx, vy, vw   # the behavior's velocity v = J^+ (...) (19), (22), (25)
    double task_error
    double gap          # surface gap to the guarded body (ordering: nearest first)
    long body           # ident of the guarded body; 0 for FDB
    bint engaged


cdef struct Line:       # n . v >= b, a barrier (S1)/(S2) of the safety filter
    double nx, ny, b


cdef struct Disc:       # |v - c| <= r: the acceleration and speed limits of the filter
    double cx, cy, r


# The sections, each in a file of its own beside the equations it cites, included in this
# one module: one translation unit, so the C compiler still inlines the small maps (sig,
# the implicit sign, the closing speed) into every section that calls them, and one
# BUILT_FROM covers them all (setup.py, plant/kernels.py). Cython resolves a name from a
# later section (the supervisor's Law) as it does within one file.
include "law_kernel_sections/signals.pxi"
include "law_kernel_sections/safety.pxi"
include "law_kernel_sections/behaviours.pxi"
include "law_kernel_sections/fusion.pxi"
include "law_kernel_sections/controller.pxi"
include "law_kernel_sections/formation.pxi"
include "law_kernel_sections/estimator.pxi"
include "law_kernel_sections/eso.pxi"
include "law_kernel_sections/degradation.pxi"
include "law_kernel_sections/law.pxi"
include "law_kernel_sections/leader_path.pxi"
