"""Where each robot should be: the leader plus its formation offset rho_i (eq. (9)),
with the true leader heading; the formation error of the metrics, the figures and the
plots is measured against it. Computed for a whole run at once, after it (or for the rows
a live view shows), never on the control path."""

from __future__ import annotations

from math import erf, sqrt

import numpy as np

from deploy.contract.scenario import Scenario

_Z = 4.0  # agents/law_kernel.pyx smooth_step: a Gaussian CDF cut at +-4 sigma
_CDF_LO = 0.5 * (1.0 + erf(-_Z / sqrt(2.0)))
_CDF_SPAN = 1.0 - 2.0 * _CDF_LO


def _smooth_steps(t: np.ndarray, start: float, end: float) -> np.ndarray:
    """The scale change's smooth step (agents/formation.py smooth_step) at every t."""
    out = np.where(t >= end, 1.0, 0.0)
    inside = (t > start) & (t < end)
    if inside.any():
        sigma = (end - start) / (2.0 * _Z)
        z = (t[inside] - 0.5 * (start + end)) / sigma
        out[inside] = [(0.5 * (1.0 + erf(x / sqrt(2.0))) - _CDF_LO) / _CDF_SPAN for x in z]
    return out


class FormationTargets:
    """x_0 + rho_i with the true leader heading (for the formation error metric)."""

    def __init__(self, sc: Scenario) -> None:
        self.initial = [sc.initial_scale(i) for i in range(sc.n)]  # each robot's own S(t)
        self.changes = [sc.scale_changes(i) for i in range(sc.n)]
        self.r = [np.array(r.offset, float) for r in sc.spec.robots]

    def along(self, t: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """(k, n, 2) targets at the times ``t`` (k,) of leader poses ``q0`` (k, 3):
        x_0 + Rot(psi) S(t) r_i, eqs. (9), (13)."""
        t = np.asarray(t, float)
        q0 = np.asarray(q0, float).reshape(len(t), 3)
        c, s = np.cos(q0[:, 2]), np.sin(q0[:, 2])
        out = np.empty((len(t), len(self.r), 2))
        for i, r_i in enumerate(self.r):
            sx = np.full(len(t), float(self.initial[i][0]))
            sy = np.full(len(t), float(self.initial[i][1]))
            for ch in self.changes[i]:
                frac = _smooth_steps(t, ch.start_s, ch.end_s)
                sx = sx + (ch.to[0] - sx) * frac
                sy = sy + (ch.to[1] - sy) * frac
            ax, ay = sx * r_i[0], sy * r_i[1]
            out[:, i, 0] = q0[:, 0] + (c * ax - s * ay)
            out[:, i, 1] = q0[:, 1] + (s * ax + c * ay)
        return out

    def at(self, t: float, q0: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        """(n, 2) targets at one instant."""
        return self.along(np.array([t]), np.asarray(q0, float)[None, :])[0]
