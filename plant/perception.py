"""What robot i senses: the other robots and the obstacles within r_det.

A body is seen when the distance from robot i's centre to the body's surface is
at most r_det. Pure function of positions; both plants call it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from agents.core import Body

if TYPE_CHECKING:
    from deploy.scenario import Scenario

Sensor = Callable[[int], tuple[list[Body], list[Body]]]


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


def sensor_for(plant, sc: Scenario) -> Sensor:
    """i -> (robots, obstacles) robot i senses now: the plant's own world query when
    it has one (pybullet), else :func:`sense` on the plant's positions."""
    det = sc.spec.behaviors.detection_range_m
    if hasattr(plant, "perceive"):
        return lambda i: plant.perceive(i, det)
    radii = [sc.spec.robot.body_radius_m] * sc.n
    ids, obstacles = sc.robot_ids, sc.obstacle_bodies()
    return lambda i: sense(i, plant.q[:, :2], plant.q_dot[:, :2], radii, ids, obstacles, det)
