"""What robot i senses: the other robots and the obstacles within r_det.

A body is seen when the distance from robot i's centre to the body's surface is
at most r_det. Pure function of positions; every plant calls it.

A wall or a convex polygon (plant/shapes.py) is seen as its point nearest robot i's
centre: a body of radius 0 at rest there, so the avoidance tasks and the safety
filter guard the closest point and its distance (docs/safety.md, "walls and
polygons"); as the robot moves the point slides along the wall.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from plant.bodies import Body
from plant.shapes import Polygon

Sensor = Callable[[int], tuple[list[Body], list[Body]]]


def sense(
    i: int,
    positions: np.ndarray,
    velocities: np.ndarray,
    robot_radii: Sequence[float],
    robot_ids: Sequence[int],
    obstacles: Sequence[Body],
    detection_range_m: float,
    shapes: Sequence[Polygon] = (),
) -> tuple[list[Body], list[Body]]:
    """(robots, obstacles) seen by the robot at row ``i`` of ``positions``: discs,
    then the nearest points of the walls and polygons (``shapes``) in range."""
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
    return robots, seen + shape_bodies(float(me[0]), float(me[1]), shapes, detection_range_m)


def shape_bodies(x: float, y: float, shapes: Sequence[Polygon],
                 detection_range_m: float) -> list[Body]:
    """Each wall or polygon whose nearest point to (x, y) is within r_det, as a body of
    radius 0 at rest at that point (plant/shapes.py, G1)."""
    out = []
    for poly in shapes:
        px, py, d = poly.nearest(x, y)
        if d <= detection_range_m:
            out.append(Body(poly.ident, np.array([px, py]), np.zeros(2), 0.0))
    return out
