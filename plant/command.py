"""What a plant applies of a wheel command, whoever sent it: each wheel torque
clamped to ``limits.max_wheel_torque_nm`` (as a drive clamps its setpoint, and as
the CAN bridge and the drive emulator do), the velocity command (the kinematic
plant moves at it) saturated to ``max_speed_mps`` / ``max_yaw_rate_radps``.

The agents already respect the limits, so this changes nothing for them (the
in-process runner and the plant node apply it alike, so they stay equal); it
holds for any bytes that decode as a command.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from agents.fusion import saturate_velocity_vec


def applied_command(torques: Sequence[float], v_cmd: Sequence[float],
                    limits: Any) -> tuple[tuple[float, ...], tuple[float, float, float]]:
    """(torques, v_cmd) to step the plant with; ``limits`` is the scenario's [limits]."""
    lim = limits.max_wheel_torque_nm
    # written with comparisons so a NaN stays NaN (the plant refuses it; never on the wire)
    clamped = tuple(lim if x > lim else -lim if x < -lim else float(x) for x in torques)
    vx, vy, w = (float(x) for x in v_cmd)
    return clamped, saturate_velocity_vec((vx, vy, w), limits.max_speed_mps,
                                          limits.max_yaw_rate_radps)
