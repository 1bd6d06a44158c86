"""Where each robot should be: the leader plus its formation offset rho_i (eq. (9)),
with the true leader heading; the formation error of the metrics, the figures and the
plots is measured against it."""

from __future__ import annotations

import numpy as np

from agents.formation import offsets, scale_at
from deploy.contract.scenario import Scenario


class FormationTargets:
    """x_0 + rho_i with the true leader heading (for the formation error metric)."""

    def __init__(self, sc: Scenario) -> None:
        self.initial = [sc.initial_scale(i) for i in range(sc.n)]  # each robot's own S(t)
        self.changes = [sc.scale_changes(i) for i in range(sc.n)]
        self.r = [np.array(r.offset, float) for r in sc.spec.robots]

    def at(self, t: float, q0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        out = np.empty((len(self.r), 2))
        for i, r_i in enumerate(self.r):
            s, sd = scale_at(t, self.initial[i], self.changes[i])
            zeta, _ = offsets(r_i, 0.0, float(q0[2]), float(v0[2]), s, sd)
            out[i] = q0[:2] + zeta[:2]
        return out
