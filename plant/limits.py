"""Velocity saturation shared by whoever applies a velocity limit: the agent's command
(agents/core.py) and what a plant applies of a command (plant/command.py)."""

from __future__ import annotations

from math import hypot

Vec3 = tuple[float, float, float]


def saturate_velocity_vec(v: Vec3, max_speed: float, max_yaw_rate: float) -> Vec3:
    """(vx, vy) scaled into ``max_speed`` (direction kept), w clipped to ``max_yaw_rate``:
    agents.fusion.saturate_velocity on floats."""
    vx, vy, w = v
    speed = hypot(vx, vy)
    if speed > max_speed:
        k = max_speed / speed
        vx, vy = vx * k, vy * k
    w = -max_yaw_rate if w < -max_yaw_rate else max_yaw_rate if w > max_yaw_rate else w
    return vx, vy, w
