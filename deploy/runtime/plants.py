"""A scenario's world in a plant: the builders of the plants the registry names
(deploy/contract/plant_registry.py: pybullet, model, kinematic; ``can-emulated`` is no
process's plant: the launcher starts a drive emulator and a CAN bridge per robot for it,
deploy/run/plan.py), what each lets a robot sense, and its contact events. The one place
that turns a scenario into a plant; the in-process runner and the plant node both build
theirs here, so they stay equal.
"""

from __future__ import annotations

from dataclasses import asdict
from importlib import import_module

from deploy.contract.plant_registry import CAN_EMULATED, PLANTS, find_plant, in_process_plants
from deploy.contract.scenario import Scenario
from plant.disturbance import make_disturbance
from plant.interface import Plant, Touching
from plant.model_plant import KinematicPlant, ModelPlant
from plant.perception import Perception, Sensor

__all__ = ["CAN_EMULATED", "PLANTS", "contact_log", "make_plant", "sensor_for"]


def pybullet_plant(sc: Scenario, q, qd, disturbance, gui: bool) -> Plant:
    from plant.pybullet_plant import PybulletPlant  # pybullet loads only when asked for

    return PybulletPlant(
        [sc.model()] * sc.n, q, qd, disturbance, [sc.spec.robot.body_radius_m] * sc.n,
        sc.robot_ids, sc.obstacle_bodies(), sc.spec.plant.substeps, gui=gui,
        shapes=sc.obstacle_shapes(),
    )


def model_plant(sc: Scenario, q, qd, disturbance, gui: bool) -> Plant:
    return ModelPlant([sc.model()] * sc.n, q, qd, disturbance, sc.spec.plant.substeps)


def kinematic_plant(sc: Scenario, q, qd, disturbance, gui: bool) -> Plant:
    return KinematicPlant(q, qd)


def make_plant(sc: Scenario, kind: str, gui: bool = False) -> Plant:
    """The scenario's robots (and, for pybullet, obstacles) in a plant of ``kind``.

    Call its ``close()`` when done (a pybullet plant holds a physics client).
    """
    entry = find_plant(kind)
    if entry is None or entry.build is None:
        raise ValueError(f"no plant {kind!r} that one process holds; choose one of "
                         f"{', '.join(in_process_plants())}")
    build = entry.build
    if isinstance(build, str):  # "module:function"
        module, _, name = build.partition(":")
        build = getattr(import_module(module), name)
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
