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

from plant.bodies import Body, bodies_of, body_rows
from plant.fleet_kernel import sense_discs, sense_fleet
from plant.shapes import Polygon

# () -> per robot, (robots, obstacles) it perceives now, as rows (ident, x, y, vx, vy, radius)
Sensor = Callable[[], list[tuple[np.ndarray, np.ndarray]]]


class Perception:
    """What every robot of a fleet senses, in one pass of the plant's kernel
    (plant/fleet_kernel.pyx ``sense_discs``): the world's constants kept as arrays."""

    def __init__(self, robot_radii: Sequence[float], robot_ids: Sequence[int],
                 obstacles: Sequence[Body], detection_range_m: float,
                 shapes: Sequence[Polygon] = ()) -> None:
        self.radii = np.ascontiguousarray(robot_radii, dtype=float)
        self.ids = np.ascontiguousarray(robot_ids, dtype=np.int64)
        rows = body_rows(obstacles)
        self.obstacle_ids = np.ascontiguousarray(rows[:, 0], dtype=np.int64)
        self.obstacles = np.ascontiguousarray(rows[:, 1:])  # x, y, vx, vy, radius
        self.detection_range_m = float(detection_range_m)
        self.shapes = list(shapes)

    def rows(self, i: int, positions: np.ndarray, velocities: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """(robots, obstacles) seen by the robot at row ``i`` of ``positions`` (n, 2+):
        discs, then the nearest points of the walls and polygons in range."""
        robots, seen = sense_discs(i, _floats(positions), _floats(velocities), self.radii,
                                   self.ids, self.obstacles, self.obstacle_ids,
                                   self.detection_range_m)
        if self.shapes:
            walls = body_rows(shape_bodies(float(positions[i, 0]), float(positions[i, 1]),
                                           self.shapes, self.detection_range_m))
            seen = np.concatenate([seen, walls]) if len(walls) else seen
        return robots, seen


    def fleet_rows(self, positions: np.ndarray, velocities: np.ndarray
                   ) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`rows` for every robot, in one call of the kernel."""
        pos = _floats(positions)
        out = sense_fleet(pos, _floats(velocities), self.radii, self.ids, self.obstacles,
                          self.obstacle_ids, self.detection_range_m)
        if not self.shapes:
            return out
        for i, (robots, seen) in enumerate(out):
            walls = body_rows(shape_bodies(float(pos[i, 0]), float(pos[i, 1]), self.shapes,
                                           self.detection_range_m))
            if len(walls):
                out[i] = (robots, np.concatenate([seen, walls]))
        return out


def _floats(rows: np.ndarray) -> np.ndarray:
    """``rows`` as the kernel reads them, C-ordered float64: a plant's state as it is (its
    (n, 3) arrays are; the kernel reads the first two columns), a copy otherwise."""
    if type(rows) is np.ndarray and rows.dtype == np.float64 and rows.flags.c_contiguous:
        return rows
    return np.ascontiguousarray(rows, dtype=float)


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
    """(robots, obstacles) seen by the robot at row ``i`` of ``positions``, as bodies:
    :meth:`Perception.rows` for one call."""
    robots, seen = Perception(robot_radii, robot_ids, obstacles, detection_range_m,
                              shapes).rows(i, positions, velocities)
    return bodies_of(robots), bodies_of(seen)


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
