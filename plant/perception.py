"""What robot i senses: the other robots and the obstacles within r_det.

A body is seen when the distance from robot i's centre to the body's surface is
at most r_det. Pure function of positions; both plants call it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from agents.core import Body


def sense(
    i: int,
    positions: np.ndarray,
    velocities: np.ndarray,
    robot_radii: Sequence[float],
    robot_ids: Sequence[int],
    obstacles: Sequence[Body],
    detection_range_m: float,
) -> tuple[list[Body], list[Body]]:
    """(robots, obstacles) seen by the robot at row ``i`` of ``positions``."""
    me = positions[i]
    robots: list[Body] = []
    for j in range(len(positions)):
        if j == i:
            continue
        if float(np.hypot(*(positions[j] - me))) - robot_radii[j] <= detection_range_m:
            robots.append(Body(robot_ids[j], positions[j].copy(), velocities[j].copy(), robot_radii[j]))
    seen = [
        o for o in obstacles
        if float(np.hypot(*(o.position - me))) - o.radius <= detection_range_m
    ]
    return robots, seen
