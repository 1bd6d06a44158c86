"""Time-varying formation: affine offsets (13)/(48) and the desired reference (16).

    rho_i(t) = W(t) r_i + b(t),   W(t) = Rot(psi(t)) S(t),   b(t) = 0
    zeta_i   = [rho_i, Xi_i]   (position offset and heading offset)

Erratum 1: the printed r = [[0,-4,-4],[0,-4,-4]] puts robots 2 and 3 on one spot;
scenarios use the authors' offsets (0,0), (-4,-4), (-4,4).
Erratum 6: psi(t) is the leader's path tangent (unwrapped), not the polar angle
of its position; each agent uses its own estimate of the leader heading.
S(t) = diag(sx, sy) changes smoothly between (normal / middle / narrow passage)
values; each change is the double integral of a Gaussian-derivative pulse
(sigma = window/8) centred in its window, i.e. a normalised Gaussian CDF.

The arithmetic is the compiled law's (agents/law_kernel_sections/formation.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the scale schedule's type, and the schedule itself for a lab's own law
(agents/plugged.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from agents.law_kernel import smooth_step_of


@dataclass(frozen=True)
class ScaleChange:
    """S moves from its previous value to ``to`` over [start_s, end_s]."""

    start_s: float
    end_s: float
    to: tuple[float, float]


def smooth_step(t: float, start: float, end: float) -> tuple[float, float]:
    """(value, derivative) of a 0 -> 1 step over [start, end], exactly 0/1 outside: a
    Gaussian CDF of sigma = window/8 cut at +-4 sigma and rescaled (the compiled law's,
    agents/law_kernel.pyx)."""
    return smooth_step_of(t, start, end)


def scale_at(
    t: float, initial: tuple[float, float], changes: Sequence[ScaleChange]
) -> tuple[np.ndarray, np.ndarray]:
    """(S, S_dot) as 2-vectors of the diagonal at time t."""
    s = np.array(initial, dtype=float)
    s_dot = np.zeros(2)
    for ch in changes:
        target = np.array(ch.to, dtype=float)
        frac, rate = smooth_step(t, ch.start_s, ch.end_s)
        s_dot = s_dot + (target - s) * rate
        s = s + (target - s) * frac
    return s, s_dot
