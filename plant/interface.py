"""What every plant is, and what some can do besides (typed, not probed with hasattr).

A plant integrates every robot's dynamics: ``q``, ``q_dot`` (n x 3: x, y, phi),
``step(t, dt, torques, v_cmd)`` and ``close()`` (release what it holds: a physics
client; nothing for the plants that integrate in numpy). A plant that simulates bodies also answers what each
robot perceives (:class:`Perceiving`) and logs its contacts (:class:`Touching`); for the
others, perception and contacts come from the scenario's geometry.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from plant.bodies import Body

# integration substeps per control step, for the plants that integrate (model, pybullet)
# and the scenario's [plant] table: RK4 / stepSimulation at dt / 4
DEFAULT_SUBSTEPS = 4


@runtime_checkable
class Plant(Protocol):
    q: np.ndarray
    q_dot: np.ndarray

    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class Perceiving(Protocol):
    def perceive(self, i: int, detection_range_m: float) -> tuple[list[Body], list[Body]]: ...


@runtime_checkable
class Touching(Protocol):
    contacts: list[Any]  # contact events (plant.pybullet_plant.ContactEvent)
