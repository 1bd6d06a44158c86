"""What a robot senses of the world: a body (another robot, an obstacle, or the nearest
point of a wall or polygon) as a disc with a velocity. Plants produce them
(perception), agents avoid them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Body:
    """A sensed body: another robot or an obstacle."""

    ident: int
    position: np.ndarray  # (2,)
    velocity: np.ndarray  # (2,)
    radius: float
