"""The vector types of the law's inputs and outputs: planar, pose-sized and wheel-sized
float tuples (the compiled law's and the wire's form)."""

from __future__ import annotations

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Vec4 = tuple[float, float, float, float]
