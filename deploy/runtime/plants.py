"""A scenario's world in a plant: the plant of a kind (pybullet, model, kinematic), what it
lets each robot sense, and its contact events. The one place that turns a scenario into a
plant; the in-process runner and the plant node both build theirs here, so they stay equal.
"""

from __future__ import annotations

from dataclasses import asdict

from deploy.contract.scenario import PLANT_KINDS, Scenario
from plant.disturbance import make_disturbance
from plant.model_plant import KinematicPlant, ModelPlant
from plant.perception import Sensor, sense

__all__ = ["PLANT_KINDS", "contact_log", "make_plant", "sensor_for"]


def make_plant(sc: Scenario, kind: str, gui: bool = False):
    """The scenario's robots (and, for pybullet, obstacles) in a plant of ``kind``.

    A pybullet plant holds a physics client: call its ``close()`` when done.
    """
    q, qd = sc.initial_state()
    d = sc.spec.disturbance
    disturbance = make_disturbance(d.kind, d.scale, tuple(d.constant_nm))
    if kind == "pybullet":
        from plant.pybullet_plant import PybulletPlant

        return PybulletPlant(
            [sc.model()] * sc.n, q, qd, disturbance, [sc.spec.robot.body_radius_m] * sc.n,
            sc.robot_ids, sc.obstacle_bodies(), sc.spec.plant.substeps, gui=gui,
            shapes=sc.obstacle_shapes(),
        )
    if kind == "model":
        return ModelPlant([sc.model()] * sc.n, q, qd, disturbance, sc.spec.plant.substeps)
    if kind == "kinematic":
        return KinematicPlant(q, qd)
    raise ValueError(f"unknown plant {kind!r}; choose one of {', '.join(PLANT_KINDS)}")


def contact_log(plant) -> list[dict] | None:
    """The plant's contact events as plain records, or None when the plant has no
    bodies that can touch (model and kinematic plants: contacts come from geometry)."""
    events = getattr(plant, "contacts", None)
    if events is None:
        return None
    return [asdict(e) for e in events]


def sensor_for(plant, sc: Scenario) -> Sensor:
    """i -> (robots, obstacles) robot i senses now: the plant's own world query when
    it has one (pybullet), else :func:`sense` on the plant's positions."""
    det = sc.spec.behaviors.detection_range_m
    if hasattr(plant, "perceive"):
        return lambda i: plant.perceive(i, det)
    radii = [sc.spec.robot.body_radius_m] * sc.n
    ids, obstacles, shapes = sc.robot_ids, sc.obstacle_bodies(), sc.obstacle_shapes()
    return lambda i: sense(i, plant.q[:, :2], plant.q_dot[:, :2], radii, ids, obstacles, det,
                           shapes)
