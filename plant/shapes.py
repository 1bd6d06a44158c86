"""Obstacles that are not discs: wall segments and convex polygons, as one geometry.

A wall is the rectangle of its thickness around the segment ``start``-``end`` (what a
physics engine can collide with, and what a real wall is): four vertices, so every
non-disc obstacle is a convex polygon here. The one query everybody needs is the
point of the polygon nearest a robot's centre and its signed distance (negative
inside), the same in every plant, in perception, in the start check and in the metrics:

    d(c) = min_e |c - proj_e(c)|,  proj_e(c) = a + clip(((c - a).(b - a)) / |b - a|^2, 0, 1) (b - a)
    sign: - when c is inside (left of every CCW edge), + otherwise            (G1)

The surface-to-surface gap of a robot of radius r is d(c) - r (G2); 0 is contact.
Pure numpy and math; imports nothing of the project.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from math import hypot

import numpy as np


@dataclass(frozen=True)
class Polygon:
    """A convex polygon obstacle; ``vertices`` counter-clockwise (see :func:`convex_ccw`)."""

    ident: int  # -(obstacle index + 1), as a disc obstacle's Body
    vertices: tuple[tuple[float, float], ...]
    name: str = ""  # the scenario key it came from, for messages (walls[0], polygons[1])

    def nearest(self, x: float, y: float) -> tuple[float, float, float]:
        """(px, py, signed distance) of the boundary point nearest (x, y), (G1)."""
        best = (0.0, 0.0, float("inf"))
        inside = True
        v = self.vertices
        for k in range(len(v)):
            ax, ay = v[k]
            bx, by = v[(k + 1) % len(v)]
            ex, ey = bx - ax, by - ay
            if ex * (y - ay) - ey * (x - ax) < 0.0:  # right of a CCW edge: outside
                inside = False
            s = ((x - ax) * ex + (y - ay) * ey) / (ex * ex + ey * ey)
            s = 0.0 if s < 0.0 else 1.0 if s > 1.0 else s
            px, py = ax + s * ex, ay + s * ey
            d = hypot(x - px, y - py)
            if d < best[2]:
                best = (px, py, d)
        return best[0], best[1], -best[2] if inside else best[2]

    @property
    def array(self) -> np.ndarray:
        return np.array(self.vertices, dtype=float)

    @property
    def centroid(self) -> tuple[float, float]:
        c = self.array.mean(axis=0)
        return float(c[0]), float(c[1])


def wall_vertices(start: Sequence[float], end: Sequence[float],
                  thickness: float) -> tuple[tuple[float, float], ...]:
    """The rectangle of ``thickness`` around segment start-end, counter-clockwise."""
    (ax, ay), (bx, by) = start, end
    length = hypot(bx - ax, by - ay)
    nx, ny = -(by - ay) / length * thickness / 2, (bx - ax) / length * thickness / 2
    return ((ax - nx, ay - ny), (bx - nx, by - ny), (bx + nx, by + ny), (ax + nx, ay + ny))


def signed_area(vertices: Sequence[Sequence[float]]) -> float:
    """Shoelace area, > 0 for counter-clockwise vertices."""
    v = np.asarray(vertices, dtype=float)
    x, y = v[:, 0], v[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def convex_ccw(vertices: Sequence[Sequence[float]]) -> tuple[tuple[float, float], ...] | None:
    """The vertices counter-clockwise if they form a strictly convex polygon of
    positive area (either winding accepted), else None."""
    v = [(float(p[0]), float(p[1])) for p in vertices]
    if len(v) < 3 or abs(signed_area(v)) <= 1e-12:
        return None
    if signed_area(v) < 0:
        v.reverse()
    for k in range(len(v)):
        (ax, ay), (bx, by), (cx, cy) = v[k], v[(k + 1) % len(v)], v[(k + 2) % len(v)]
        if (bx - ax) * (cy - by) - (by - ay) * (cx - bx) <= 0.0:  # right turn, or collinear
            return None
    return tuple(v) if _winds_once(v) else None


def _winds_once(v: list[tuple[float, float]]) -> bool:
    """The exterior angles of a convex polygon add up to exactly 2 pi."""
    total = 0.0
    n = len(v)
    for k in range(n):
        a, b, c = np.array(v[k]), np.array(v[(k + 1) % n]), np.array(v[(k + 2) % n])
        e1, e2 = b - a, c - b
        total += float(np.arctan2(e1[0] * e2[1] - e1[1] * e2[0], e1 @ e2))
    return abs(total - 2 * np.pi) < 1e-6  # left turns only, yet a star winds twice (4 pi)


def signed_distances(points: np.ndarray, polygon: Polygon) -> np.ndarray:
    """(G1) for many points at once: ``points`` (..., 2) -> (...) signed distances."""
    p = np.asarray(points, dtype=float)
    v = polygon.array
    a, e = v, np.roll(v, -1, axis=0) - v  # (m, 2) edge starts and vectors
    rel = p[..., None, :] - a  # (..., m, 2)
    s = np.clip(np.einsum("...mk,mk->...m", rel, e) / np.einsum("mk,mk->m", e, e), 0.0, 1.0)
    d = np.linalg.norm(rel - s[..., None] * e, axis=-1).min(axis=-1)
    inside = np.all(e[:, 0] * rel[..., 1] - e[:, 1] * rel[..., 0] >= 0.0, axis=-1)
    return np.where(inside, -d, d)


def offset_outline(polygon: Polygon, distance: float, per_corner: int = 8) -> np.ndarray:
    """(K, 2) points, counter-clockwise, of the curve at ``distance`` outside the polygon
    (its Minkowski sum with a disc: straight beside each edge, an arc round each vertex),
    e.g. the R_a band drawn round a wall."""
    v = polygon.array
    n = len(v)
    out = []
    for k in range(n):
        e_in, e_out = v[k] - v[k - 1], v[(k + 1) % n] - v[k]
        a0 = np.arctan2(-e_in[0], e_in[1])  # outward normal of the edge into vertex k
        a1 = np.arctan2(-e_out[0], e_out[1])  # ... and of the edge out of it
        if a1 < a0:
            a1 += 2 * np.pi
        for a in np.linspace(a0, a1, per_corner):
            out.append(v[k] + distance * np.array([np.cos(a), np.sin(a)]))
    return np.array(out)
