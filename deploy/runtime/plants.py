"""A scenario's world in a plant: the plants by name (pybullet, model, kinematic, and
can-emulated), what each lets a robot sense, and its contact events. The one place that
turns a scenario into a plant; the in-process runner and the plant node both build theirs
here, so they stay equal. ``can-emulated`` is registered here too, by the same name
``--plant`` takes, but no process holds it: the launcher starts a drive emulator and a
CAN bridge per robot for it (deploy/run/plan.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

from deploy.contract.scenario import PLANT_KINDS, Scenario
from plant.disturbance import make_disturbance
from plant.interface import Plant, Touching
from plant.model_plant import KinematicPlant, ModelPlant
from plant.perception import Perception, Sensor

__all__ = ["CAN_EMULATED", "PLANTS", "PLANT_KINDS", "contact_log", "make_plant", "sensor_for"]

CAN_EMULATED = "can-emulated"  # every robot through a CAN bridge and a drive emulator


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


@dataclass(frozen=True)
class PlantEntry:
    """A plant by name: what it is (``--plant`` help), and how one process builds it
    from a scenario (None: the plant is processes of its own, started by the launcher)."""

    about: str
    build: Callable[..., Plant] | None
    realtime_only: bool = False  # hardware, or its emulation: the wall clock only


# The plants by name (the scenario's [plant] kind, --plant).
PLANTS: dict[str, PlantEntry] = {
    "pybullet": PlantEntry("rigid bodies, real contacts", _pybullet),
    "model": PlantEntry("eq. 4, RK4", _model),
    "kinematic": PlantEntry("q_dot = the commanded velocity", _kinematic),
    CAN_EMULATED: PlantEntry("every robot through a CAN bridge and a drive emulator, one "
                             "process each (--driver picks the drives' protocol)", None,
                             realtime_only=True),
}
IN_PROCESS = tuple(name for name, e in PLANTS.items() if e.build is not None)
if IN_PROCESS != PLANT_KINDS:  # the schema's names and these are the same
    raise RuntimeError(f"plant builders {IN_PROCESS} != the scenario's plant kinds {PLANT_KINDS}")


def make_plant(sc: Scenario, kind: str, gui: bool = False) -> Plant:
    """The scenario's robots (and, for pybullet, obstacles) in a plant of ``kind``.

    Call its ``close()`` when done (a pybullet plant holds a physics client).
    """
    entry = PLANTS.get(kind)
    if entry is None or entry.build is None:
        raise ValueError(f"no plant {kind!r} that one process holds; choose one of "
                         f"{', '.join(IN_PROCESS)}")
    build = entry.build
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
