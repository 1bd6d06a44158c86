"""What a robot senses of the world: a body (another robot, an obstacle, or the nearest
point of a wall or polygon) as a disc with a velocity. Plants produce them
(perception), agents avoid them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Body:
    """A sensed body: another robot or an obstacle."""

    ident: int
    position: np.ndarray  # (2,)
    velocity: np.ndarray  # (2,)
    radius: float


NO_BODIES = np.empty((0, 6))
NO_BODIES.flags.writeable = False


def body_rows(bodies: Sequence[Body] | np.ndarray) -> np.ndarray:
    """Bodies as the kernels take them: a C-contiguous float array of rows
    (ident, x, y, vx, vy, radius). An array in that shape is passed through."""
    if isinstance(bodies, np.ndarray):
        if bodies.ndim != 2 or bodies.shape[1] != 6:
            raise ValueError(f"body rows must be (k, 6), got {bodies.shape}")
        return np.ascontiguousarray(bodies, dtype=float)
    if not bodies:
        return NO_BODIES
    return np.array([(b.ident, b.position[0], b.position[1], b.velocity[0], b.velocity[1],
                      b.radius) for b in bodies], dtype=float)


def bodies_of(rows: np.ndarray) -> list[Body]:
    """Rows (ident, x, y, vx, vy, radius) as Body objects."""
    return [Body(int(r[0]), np.array(r[1:3]), np.array(r[3:5]), float(r[5])) for r in rows]
