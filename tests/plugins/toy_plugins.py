"""A package of a lab's own, as docs/extending.md builds it: one plant and one drive
protocol, registered by entry points (tests/e2e/test_plugins.py installs it in a
folder of its own and runs omnifleet with it).

- ``weak-motors``: the model plant (eq. 4) whose motors give 80 % of the torque asked;
- ``toy-odrive``: ODrive CANSimple on node ids 8-11 (a second robot's drives on a bus
  where 0-3 are taken).
"""

from __future__ import annotations

import numpy as np

from bridges.drivers import DRIVERS, DriverEntry
from deploy.contract.plant_registry import PlantEntry
from plant.model_plant import ModelPlant

STRENGTH = 0.8  # of the torque asked, at every wheel


class WeakMotorsPlant(ModelPlant):
    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None:
        super().step(t, dt, STRENGTH * np.asarray(torques, dtype=float), v_cmd)


def weak_motors(sc, q, q_dot, disturbance, gui: bool) -> WeakMotorsPlant:
    """The builder a PlantEntry names: the scenario, the robots' initial states, the
    scenario's disturbance, --gui."""
    return WeakMotorsPlant([sc.model()] * sc.n, q, q_dot, disturbance, sc.spec.plant.substeps)


WEAK_MOTORS = PlantEntry("the model plant whose motors give 80 % of the torque asked",
                         weak_motors)

_odrive = DRIVERS["odrive-cansimple"]
TOY_ODRIVE = DriverEntry("ODrive CANSimple on node ids 8-11", _odrive.node_id_range,
                         (8, 9, 10, 11), _odrive.make, _odrive.emulator)
