"""A scenario's world in a plant: the plant of a kind (pybullet, model, kinematic), what it
lets each robot sense, and its contact events. The one place that turns a scenario into a
plant; the in-process runner and the plant node both build theirs here, so they stay equal.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict

from deploy.contract.scenario import PLANT_KINDS, Scenario
from plant.disturbance import make_disturbance
from plant.interface import Plant, Touching
from plant.model_plant import KinematicPlant, ModelPlant
from plant.perception import Perception, Sensor

__all__ = ["PLANT_KINDS", "contact_log", "make_plant", "sensor_for"]


def _pybullet(sc: Scenario, q, qd, disturbance, gui: bool) -> Plant:
    from plant.pybullet_plant import PybulletPlant  # pybullet loads only when asked for

    return PybulletPlant(
        [sc.model()] * sc.n, q, qd, disturbance, [sc.spec.robot.body_radius_m] * sc.n,
        sc.robot_ids, sc.obstacle_bodies(), sc.spec.plant.substeps, gui=gui,
        shapes=sc.obstacle_shapes(),
    )


def _model(sc: Scenario, q, qd, disturbance, gui: bool) -> Plant:
    return ModelPlant([sc.model()] * sc.n, q, qd, disturbance, sc.spec.plant.substeps)


def _kinematic(sc: Scenario, q, qd, disturbance, gui: bool) -> Plant:
    return KinematicPlant(q, qd)


# The plants by name (the scenario's [plant] kind, --plant): one builder each.
PLANTS: dict[str, Callable[..., Plant]] = {"pybullet": _pybullet, "model": _model,
                                           "kinematic": _kinematic}
if tuple(PLANTS) != PLANT_KINDS:  # the schema's names and these are the same
    raise RuntimeError(f"plant builders {tuple(PLANTS)} != the scenario's plant kinds {PLANT_KINDS}")


def make_plant(sc: Scenario, kind: str, gui: bool = False) -> Plant:
    """The scenario's robots (and, for pybullet, obstacles) in a plant of ``kind``.

    A pybullet plant holds a physics client: call its ``close()`` when done.
    """
    build = PLANTS.get(kind)
    if build is None:
        raise ValueError(f"unknown plant {kind!r}; choose one of {', '.join(PLANTS)}")
    q, qd = sc.initial_state()
    d = sc.spec.disturbance
    return build(sc, q, qd, make_disturbance(d.kind, d.scale, tuple(d.constant_nm)), gui)


def contact_log(plant: Plant) -> list[dict] | None:
    """The plant's contact events as plain records, or None when the plant has no
    bodies that can touch (model and kinematic plants: contacts come from geometry)."""
    if not isinstance(plant, Touching):
        return None
    return [asdict(e) for e in plant.contacts]


def sensor_for(plant: Plant, sc: Scenario) -> Sensor:
    """() -> per robot, (robots, obstacles) it senses now, as rows (ident, x, y, vx, vy, radius):
    the perception kernel on the plant's positions (plant/perception.py), for every plant.
    Robots and obstacles are discs, so the rule is exact geometry; the pybullet plant's own
    closest-point queries (``PybulletPlant.perceive``) give the same bodies
    (tests/integration/test_pybullet_plant.py) at ~10x the cost (21 queries a step on
    ``paper``)."""
    det = sc.spec.behaviors.detection_range_m
    world = Perception([sc.spec.robot.body_radius_m] * sc.n, sc.robot_ids, sc.obstacle_bodies(),
                       det, sc.obstacle_shapes())
    return lambda: world.fleet_rows(plant.q, plant.q_dot)
