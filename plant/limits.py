"""Velocity saturation shared by whoever applies a velocity limit: the agent's command
(agents/core.py) and what a plant applies of a command (plant/command.py)."""

from __future__ import annotations

from plant.fleet_kernel import saturate_velocity_of

Vec3 = tuple[float, float, float]


def saturate_velocity_vec(v: Vec3, max_speed: float, max_yaw_rate: float) -> Vec3:
    """(vx, vy) scaled into ``max_speed`` (direction kept), w clipped to ``max_yaw_rate``
    (plant/fleet_kernel.pyx, the agent's kernel uses the same): agents.fusion
    saturate_velocity on floats."""
    return saturate_velocity_of(v, max_speed, max_yaw_rate)
