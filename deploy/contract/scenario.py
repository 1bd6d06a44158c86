"""The scenario schema: one place, validated on load.

A scenario is a TOML file (see ``deploy/scenarios/*.toml`` and
``docs/scenarios.md``). Decoding uses msgspec with unknown fields forbidden, so
a typo is an error naming the key; the semantic checks after it (shapes, the
graph's directed spanning tree, positive gains) name the key too. Every error
is a :class:`ScenarioError` carrying the file name; the CLI exits with code 2.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, fields, replace
from functools import cached_property
from pathlib import Path
from typing import Literal, get_type_hints

import msgspec
import numpy as np

from agents.controller import ControllerGains
from agents.core import AgentConfig
from agents.degradation import MAX_COMMAND_HORIZON, DegradationConfig
from agents.eso import EsoGains
from agents.estimator import EstimatorGains
from agents.formation import ScaleChange
from agents.leader import Harmonic, LeaderSpec, leader_generator
from agents.steered_leader import SteeredSpec
from agents.waypoint_path import waypoint_path
from deploy.contract.options import MAX_RATE_HZ
from deploy.contract.plant_registry import find_plant, in_process_plants
from deploy.contract.schema_hints import readable
from plant.bodies import Body
from plant.interface import DEFAULT_SUBSTEPS
from plant.mecanum import MecanumModel, RobotParams
from plant.shapes import Polygon, convex_ccw, signed_distances, wall_vertices

SCENARIO_DIR = Path(__file__).resolve().parents[1] / "scenarios"


def bundled_names() -> list[str]:
    """The bundled scenarios' names (the files in SCENARIO_DIR), sorted."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
BEHAVIOR_NAMES = ("FDB", "FOCB", "FRCB")


class ScenarioError(ValueError):
    """A scenario that cannot be run, with the file and key named."""


class _S(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    pass


def _section(name: str, domain: type, only: tuple[str, ...] | None = None) -> type[_S]:
    """A scenario table with the fields, types and defaults of the domain dataclass it
    decodes into (all of them, or ``only`` these): every default is declared once, with
    the math, and the table cannot drift from it."""
    hints = get_type_hints(domain)
    return msgspec.defstruct(name, [(f.name, hints[f.name], f.default) for f in fields(domain)
                                    if only is None or f.name in only], bases=(_S,), kw_only=True,
                             module=__name__)


def _default(domain: type, name: str):
    """The default of field ``name`` of a domain dataclass (a table whose keys are named
    otherwise takes its defaults from there)."""
    f = next(f for f in fields(domain) if f.name == name)
    return f.default if f.default_factory is MISSING else f.default_factory()


RobotPhysics = _section("RobotPhysics", RobotParams)


class ScaleStep(_S, kw_only=True):
    start_s: float
    end_s: float
    to: list[float]


class RobotEntry(_S, kw_only=True):
    id: int
    position: list[float]
    heading_rad: float = 0.0
    velocity: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0])
    offset: list[float]
    heading_offset_rad: float = 0.0
    # this robot's own S(t) (its offset scaled on its own schedule); default: [formation]'s
    initial_scale: list[float] | None = None
    scale_changes: list[ScaleStep] | None = None
    estimate_position: list[float] | None = None  # q0_hat(0) [x, y, phi]; default: own pose
    estimate_velocity: list[float] | None = None  # v0_hat(0); default: own velocity


class Graph(_S, kw_only=True):
    adjacency: list[list[float]]
    leader: list[float]


class PathComponent(_S, kw_only=True):
    fn: Literal["sin", "cos"]
    amp: float
    freq: float
    phase: float = 0.0
    offset: float = 0.0


STEERED_YAW_RATE_RADPS = 0.5  # path = "ros2": the default bound on the yaw rate
# path = "ros2": the default command timeout. Longer than a robot's (0.1 s): a command
# reaches the leader through the launcher's 50 ms loop and the leader's 50 ms batches
STEERED_TIMEOUT_S = 0.5


class Leader(_S, kw_only=True):
    kind: Literal["analytic", "path_follower"] = "analytic"
    # "harmonic": x, y as one sin/cos term each; "waypoints": a C2 spline through
    # ``waypoints`` driven at ``speed_mps`` with ramps of ``accel_mps2`` (agents/waypoint_path.py)
    # "ros2": no path; the leader follows a twist on the ROS 2 topic /leader/cmd_vel (realtime
    # runs with --ros2; agents/steered_leader.py), from ``start``, bounded by ``speed_mps`` and
    # ``yaw_rate_radps``, stopping when none came for ``command_timeout_s``
    path: Literal["harmonic", "waypoints", "ros2"] = "harmonic"
    x: PathComponent | None = None
    y: PathComponent | None = None
    waypoints: list[list[float]] | None = None
    speed_mps: float | None = None
    accel_mps2: float | None = None
    # the harmonic path's parameter theta = theta0 + theta_rate t (None: 0 and 1; only with
    # path = "harmonic": a waypoint path has its own speed)
    theta0: float | None = None
    theta_rate: float | None = None
    follow_gain: float = 3.5
    heading: Literal["tangent", "polar"] = "tangent"
    start: list[float] | None = None  # path = "ros2": [x, y, psi] at t = 0 (default 0, 0, 0)
    yaw_rate_radps: float | None = None  # path = "ros2": the bound on the yaw rate (default 0.5)
    command_timeout_s: float | None = None  # path = "ros2": stop after this long without one


class Formation(_S, kw_only=True):
    initial_scale: list[float] = msgspec.field(
        default_factory=lambda: list(_default(AgentConfig, "initial_scale")))
    scale_changes: list[ScaleStep] = msgspec.field(default_factory=list)
    kappa1: float = _default(AgentConfig, "kappa1")
    kappa2: float = _default(AgentConfig, "kappa2")


class Obstacle(_S, kw_only=True):
    position: list[float]
    radius_m: float = 0.0


class Wall(_S, kw_only=True):
    """A straight wall: the rectangle of ``thickness_m`` around start-end (plant/shapes.py)."""

    start: list[float]
    end: list[float]
    thickness_m: float = 0.1


class PolygonObstacle(_S, kw_only=True):
    """A convex polygon, its vertices in either winding."""

    vertices: list[list[float]]


class Behaviors(_S, kw_only=True):
    enabled: list[str] = msgspec.field(default_factory=lambda: list(BEHAVIOR_NAMES))
    priority: list[str] = msgspec.field(default_factory=lambda: list(_default(AgentConfig, "priority")))
    avoidance_engage: Literal["inside", "approaching"] = _default(AgentConfig, "avoidance_engage")
    fdb_gains: list[float] = msgspec.field(default_factory=lambda: list(_default(AgentConfig, "fdb_gains")))
    focb_gains: list[float] = msgspec.field(default_factory=lambda: list(_default(AgentConfig, "focb_gains")))
    frcb_gains: list[float] = msgspec.field(default_factory=lambda: list(_default(AgentConfig, "frcb_gains")))
    obstacle_safe_distance_m: float = _default(AgentConfig, "obstacle_safe_m")
    robot_safe_distance_m: float = _default(AgentConfig, "robot_safe_m")
    detection_range_m: float = 8.0
    # which perceived bodies the avoidance behaviors guard: "every" one in range, a task
    # each, nearest first (docs/safety.md), or only the "nearest" (the authors' script)
    guard: Literal["every", "nearest"] = _default(AgentConfig, "guard")


class Safety(_S, kw_only=True):
    """The safety filter, the last layer of every agent (agents/safety_filter.py)."""

    filter: bool = _default(AgentConfig, "safety_filter")
    margin_m: float = _default(AgentConfig, "safety_margin_m")  # kept on top of contact
    exit_time_s: float = _default(AgentConfig, "safety_exit_time_s")  # inside the margin


class Estimator(_S, kw_only=True):
    # q0_hat(0), v0_hat(0): "leader" = the leader's true initial state (our reading of
    # the paper's q0_hat(0) = p(0)); "robot" = the robot's own pose and velocity.
    # A robot's estimate_position/estimate_velocity override either.
    init: Literal["leader", "robot"] = "leader"
    iota: list[float] = msgspec.field(default_factory=lambda: list(EstimatorGains().iota))
    eta: list[float] = msgspec.field(default_factory=lambda: list(EstimatorGains().eta))


Controller = _section("Controller", ControllerGains)


Eso = _section("Eso", EsoGains)


# how fast the fused velocity command may change (max_accel_mps2: a reference the torques
# can follow), how far q_d may run ahead (max_tracking_error): AgentConfig's fields
Limits = _section("Limits", AgentConfig, only=(
    "max_speed_mps", "max_yaw_rate_radps", "max_wheel_torque_nm", "max_accel_mps2",
    "max_yaw_accel_radps2", "max_tracking_error"))


class Disturbance(_S, kw_only=True):
    kind: Literal["paper", "none", "constant"] = "paper"
    scale: float = 1.0
    constant_nm: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])


class PlantSection(_S, kw_only=True):
    kind: str = "pybullet"  # a plant one process holds (plant_registry.py), checked on load
    substeps: int = DEFAULT_SUBSTEPS
    # lockstep, a step whose command was lost (fault injection) or late: "hold"
    # the last command (a driver's input persists), or "zero" the torques for
    # that step (a command is valid for one period only)
    missed_command: Literal["hold", "zero"] = "hold"


_DEGRADATION = DegradationConfig()  # the defaults live with the math


class Degradation(_S, kw_only=True):
    """How an agent degrades when its inputs go stale (agents/degradation.py)."""

    stale_after_s: float = _DEGRADATION.stale_after_s  # older inputs are left out of eq. (14)
    slow_after_s: float = _DEGRADATION.slow_after_s  # older leader information: slow down
    slow_ramp_s: float = _DEGRADATION.slow_ramp_s  # full speed to degraded speed, and back
    degraded_speed_mps: float = _DEGRADATION.degraded_speed_mps
    reacquire_tau_s: float = _DEGRADATION.reacquire_tau_s  # blend toward the source ...
    reacquire_tol_m: float = _DEGRADATION.reacquire_tol_m  # ... until this close
    reacquire_min_s: float = _DEGRADATION.reacquire_min_s  # ... and at least this long
    # torques for the next steps, predicted and sent with each command: the plant
    # plays them when a command is lost (agents/look_ahead.py); 0 = off
    command_horizon: int = _DEGRADATION.command_horizon


class Metrics(_S, kw_only=True):
    settle_threshold: float = 0.05
    # a robot within this of its formation position (x_0 + rho_i, the true leader's) has
    # reached it (deploy/report/formation_reach.py); the verdict wants every robot there
    # at the end, except those the scenario expects never to get there, and why
    formation_threshold_m: float = 0.1
    expect_unreached: list[int] = msgspec.field(default_factory=list)
    expect_unreached_why: str = ""


class LawSection(_S, kw_only=True):
    """The control law every agent runs (agents/laws/__init__.py, docs/laws.md)."""

    # paper (the paper's law, compiled), a bundled law's name, module:Class, or
    # path/to/file.py:Class (a path relative to this scenario's folder, or absolute)
    use: str = "paper"
    params: dict[str, float | int | bool | str] = msgspec.field(default_factory=dict)


class ScenarioFile(_S, kw_only=True):
    name: str
    description: str = ""
    duration_s: float
    control_rate_hz: float
    robot: RobotPhysics = msgspec.field(default_factory=RobotPhysics)
    robots: list[RobotEntry]
    graph: Graph
    leader: Leader
    formation: Formation = msgspec.field(default_factory=Formation)
    obstacles: list[Obstacle] = msgspec.field(default_factory=list)
    walls: list[Wall] = msgspec.field(default_factory=list)
    polygons: list[PolygonObstacle] = msgspec.field(default_factory=list)
    behaviors: Behaviors = msgspec.field(default_factory=Behaviors)
    safety: Safety = msgspec.field(default_factory=Safety)
    estimator: Estimator = msgspec.field(default_factory=Estimator)
    controller: Controller = msgspec.field(default_factory=Controller)
    eso: Eso = msgspec.field(default_factory=Eso)
    limits: Limits = msgspec.field(default_factory=Limits)
    disturbance: Disturbance = msgspec.field(default_factory=Disturbance)
    plant: PlantSection = msgspec.field(default_factory=PlantSection)
    degradation: Degradation = msgspec.field(default_factory=Degradation)
    metrics: Metrics = msgspec.field(default_factory=Metrics)
    law: LawSection = msgspec.field(default_factory=LawSection)


@dataclass(frozen=True)
class Scenario:
    """A validated scenario, with the derived objects the runtime needs."""

    path: str
    spec: ScenarioFile
    adjacency: np.ndarray  # n x n, diagonal zeroed (erratum 7)
    leader_weights: np.ndarray  # b_i
    notes: tuple[str, ...]  # what the loader changed, said out loud

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def n(self) -> int:
        return len(self.spec.robots)

    @property
    def dt(self) -> float:
        return 1.0 / self.spec.control_rate_hz

    @property
    def steps(self) -> int:
        return int(round(self.spec.duration_s * self.spec.control_rate_hz))

    @property
    def robot_ids(self) -> list[int]:
        return [r.id for r in self.spec.robots]

    def index_of(self, robot_id: int) -> int:
        """Row of robot ``robot_id``; a clear error when the scenario has no such robot."""
        ids = self.robot_ids
        if robot_id not in ids:
            raise ScenarioError(
                f"{self.path}: no robot {robot_id} in scenario {self.name!r} "
                f"(its robots are {', '.join(map(str, ids))})"
            )
        return ids.index(robot_id)

    def bridge_phase_s(self, robot_id: int) -> float:
        """When robot ``robot_id``'s CAN bridge runs each period, after the period's start
        t_k: the bridges' periods are staggered by dt / n in the robots' order (as
        bridges on separate hosts would be; aligned, every bridge of one host woke at
        once with the same work, and on 2 cores the last waited for the others:
        docs/bench-history.md). Its state at step k is measured then."""
        return self.dt * self.index_of(robot_id) / self.n

    def listeners(self, index: int) -> list[int]:
        """Ids of the robots whose agents use robot ``index``'s share (a_ji != 0)."""
        return [self.robot_ids[j] for j in range(self.n)
                if j != index and self.adjacency[j, index] != 0.0]

    def with_control_rate(self, hz: float) -> Scenario:
        """The same scenario stepped at another control rate."""
        return replace(self, spec=msgspec.structs.replace(self.spec, control_rate_hz=hz))

    def with_law(self, spec: str, where: str = "--law") -> Scenario:
        """The same scenario with every agent on law ``spec`` (``--law``; a file's path
        relative to the working directory). Its ``[law] params`` stay when ``spec`` names
        the scenario's own law, else the new law's defaults apply. ScenarioError naming
        ``where`` when the law cannot be used."""
        spec = _absolute_law(spec, Path.cwd())
        params = self.spec.law.params if spec == self.spec.law.use else {}
        law = LawSection(use=spec, params=dict(params))
        _load_law(where, law)
        return replace(self, spec=msgspec.structs.replace(self.spec, law=law))

    @property
    def law_name(self) -> str:
        """The name the run's law goes by in reports (paper, consensus, a class's name)."""
        cls, _ = self.law()
        return "paper" if cls is None else cls.law_name()

    def law(self) -> tuple[type | None, object]:
        """(the law's class, its parameters): (None, None) for the paper's compiled law."""
        return _load_law(self.path, self.spec.law)

    def scale_changes(self, index: int | None = None) -> tuple[ScaleChange, ...]:
        """The S(t) schedule as the agents use it: the formation's, or robot ``index``'s
        own when it has one."""
        own = None if index is None else self.spec.robots[index].scale_changes
        changes = self.spec.formation.scale_changes if own is None else own
        return tuple(ScaleChange(c.start_s, c.end_s, (c.to[0], c.to[1])) for c in changes)

    def initial_scale(self, index: int | None = None) -> tuple[float, float]:
        """S(0): the formation's, or robot ``index``'s own when it has one."""
        own = None if index is None else self.spec.robots[index].initial_scale
        s0 = self.spec.formation.initial_scale if own is None else own
        return s0[0], s0[1]

    def robot_params(self) -> RobotParams:
        return RobotParams(**msgspec.structs.asdict(self.spec.robot))

    def model(self) -> MecanumModel:
        return MecanumModel.from_params(self.robot_params())

    def leader_spec(self) -> LeaderSpec:
        return self._leader_spec

    @cached_property
    def _leader_spec(self) -> LeaderSpec:  # a waypoint spline is built once (~10 ms)
        ld = self.spec.leader

        def harm(c: PathComponent | None) -> Harmonic | None:
            return None if c is None else Harmonic(c.fn, c.amp, c.freq, c.phase, c.offset)

        wp = steered = None
        if ld.path == "waypoints":
            wp = waypoint_path(ld.waypoints, ld.speed_mps, ld.accel_mps2)
        if ld.path == "ros2":
            steered = SteeredSpec(
                tuple(ld.start or (0.0, 0.0, 0.0)), ld.speed_mps,
                STEERED_YAW_RATE_RADPS if ld.yaw_rate_radps is None else ld.yaw_rate_radps,
                STEERED_TIMEOUT_S if ld.command_timeout_s is None else ld.command_timeout_s)
        return LeaderSpec(harm(ld.x), harm(ld.y), 0.0 if ld.theta0 is None else ld.theta0,
                          1.0 if ld.theta_rate is None else ld.theta_rate, ld.kind,
                          ld.follow_gain, ld.heading, wp, steered)

    def obstacle_bodies(self) -> list[Body]:
        return [
            Body(-(k + 1), np.array(o.position, float), np.zeros(2), o.radius_m)
            for k, o in enumerate(self.spec.obstacles)
        ]

    def obstacle_shapes(self) -> list[Polygon]:
        """Walls, then polygons, as convex polygons; their idents follow the discs'
        (-(k + 1) over discs, walls, polygons in that order)."""
        return list(self._shapes)

    @cached_property
    def _shapes(self) -> tuple[Polygon, ...]:
        return tuple(obstacle_shapes(self.spec))

    def obstacle_names(self) -> dict[int, str]:
        """ident -> the scenario key of every obstacle (``obstacles[0]``, ``walls[1]``, ...)."""
        names = {-(k + 1): f"obstacles[{k}]" for k in range(len(self.spec.obstacles))}
        names.update({p.ident: p.name for p in self.obstacle_shapes()})
        return names

    def obstacle_gaps(self, positions: np.ndarray) -> np.ndarray:
        """Surface-to-surface gaps of robots at ``positions`` (..., n, 2) to every
        obstacle (discs, walls, polygons in ident order): (..., n, m); 0 is contact
        (plant/shapes.py, G2)."""
        p = np.asarray(positions, dtype=float)
        r = self.spec.robot.body_radius_m
        cols = [np.linalg.norm(p - np.array(o.position, float), axis=-1) - o.radius_m - r
                for o in self.spec.obstacles]
        cols += [signed_distances(p, poly) - r for poly in self._shapes]
        if not cols:
            return np.zeros((*p.shape[:-1], 0))
        return np.stack(cols, axis=-1)

    def initial_state(self) -> tuple[np.ndarray, np.ndarray]:
        q = np.array([[*r.position, r.heading_rad] for r in self.spec.robots], float)
        qd = np.array([[*r.velocity, 0.0] for r in self.spec.robots], float)
        return q, qd

    def initial_estimates(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        r = self.spec.robots[index]
        if self.spec.estimator.init == "leader":
            q, qd = leader_generator(self.leader_spec(), self.dt).state()
        else:
            qs, qds = self.initial_state()
            q, qd = qs[index], qds[index]
        q0 = np.array(r.estimate_position, float) if r.estimate_position else q.copy()
        v0 = np.array(r.estimate_velocity, float) if r.estimate_velocity else qd.copy()
        return q0, v0

    def agent_config(self, index: int, model: MecanumModel | None = None) -> AgentConfig:
        s, r = self.spec, self.spec.robots[index]
        b, ctl, lim = s.behaviors, s.controller, s.limits
        ids = self.robot_ids
        neighbours = tuple(
            (ids[j], float(self.adjacency[index, j]))
            for j in range(self.n)
            if self.adjacency[index, j] != 0.0
        )
        return AgentConfig(
            robot_id=r.id,
            dt=self.dt,
            model=model or self.model(),
            neighbours=neighbours,
            leader_weight=float(self.leader_weights[index]),
            offset=(r.offset[0], r.offset[1]),
            heading_offset=r.heading_offset_rad,
            initial_scale=self.initial_scale(index),
            scale_changes=self.scale_changes(index),
            kappa1=s.formation.kappa1,
            kappa2=s.formation.kappa2,
            enabled=frozenset(b.enabled),
            priority=tuple(b.priority),
            avoidance_engage=b.avoidance_engage,
            fdb_gains=(b.fdb_gains[0], b.fdb_gains[1]),
            focb_gains=(b.focb_gains[0], b.focb_gains[1]),
            frcb_gains=(b.frcb_gains[0], b.frcb_gains[1]),
            obstacle_safe_m=b.obstacle_safe_distance_m,
            robot_safe_m=b.robot_safe_distance_m,
            robot_radius_m=s.robot.body_radius_m,
            estimator=EstimatorGains(
                (s.estimator.iota[0], s.estimator.iota[1], s.estimator.iota[2], s.estimator.iota[3]),
                (s.estimator.eta[0], s.estimator.eta[1]),
            ),
            eso=EsoGains(**msgspec.structs.asdict(s.eso)),
            controller=ControllerGains(**msgspec.structs.asdict(ctl)),
            **msgspec.structs.asdict(lim),
            degradation=DegradationConfig(**msgspec.structs.asdict(s.degradation)),
            guard=b.guard,
            safety_filter=s.safety.filter,
            safety_margin_m=s.safety.margin_m,
            safety_exit_time_s=s.safety.exit_time_s,
        )


def obstacle_shapes(s: ScenarioFile) -> list[Polygon]:
    """The walls and polygons of a (shape-checked) scenario file, idents after the discs."""
    first = len(s.obstacles)
    out = [Polygon(-(first + k + 1), wall_vertices(w.start, w.end, w.thickness_m), f"walls[{k}]")
           for k, w in enumerate(s.walls)]
    first += len(s.walls)
    for k, pg in enumerate(s.polygons):
        ccw = convex_ccw(pg.vertices)
        assert ccw is not None, "validated on load"
        out.append(Polygon(-(first + k + 1), ccw, f"polygons[{k}]"))
    return out


def _fail(path: str, key: str, msg: str) -> ScenarioError:
    return ScenarioError(f"{path}: `{key}`: {msg}")


def _check_plant(path: str, kind: str) -> None:
    try:
        entry = find_plant(kind)
    except ValueError as exc:  # a plug-in of that name that cannot be used
        raise _fail(path, "plant.kind", str(exc)) from None
    if entry is None or entry.build is None:
        raise _fail(path, "plant.kind", f"{kind!r} is not a plant one process holds; "
                    f"expected one of: {', '.join(in_process_plants())}")


def _check_len(path: str, key: str, values: list, n: int) -> None:
    if len(values) != n:
        raise _fail(path, key, f"expected {n} numbers, got {len(values)}")


def _check_finite(path: str, key: str, values) -> None:
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise _fail(path, key, "must be finite numbers")


def has_spanning_tree(adjacency: np.ndarray, leader: np.ndarray) -> bool:
    """True iff every robot is reachable from the leader (a_ij: j -> i, b_i: 0 -> i)."""
    return not unreached_robots(adjacency, leader)


def unreached_robots(adjacency: np.ndarray, leader: np.ndarray) -> list[int]:
    """Rows (in [[robots]] order) of the robots the leader reaches through no path."""
    n = len(leader)
    reached = {i for i in range(n) if leader[i] != 0.0}
    frontier = list(reached)
    while frontier:
        j = frontier.pop()
        for i in range(n):
            if adjacency[i, j] != 0.0 and i not in reached:
                reached.add(i)
                frontier.append(i)
    return [i for i in range(n) if i not in reached]


def start_overlaps(positions: np.ndarray, ids: list[int], radius: float,
                   obstacles: list[tuple[str, np.ndarray, float]],
                   shapes: list[Polygon] = ()) -> list[str]:
    """Every pair that touches or overlaps at t = 0 (gap = centre distance minus the
    radii, <= 0), as a sentence naming both and the gap: robot-robot, then robot-obstacle
    (``obstacles``: (name, centre, radius) of each disc), then robot-wall/polygon
    (gap = signed distance to the polygon minus the radius, G2 of plant/shapes.py)."""
    out = []
    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            d = float(np.hypot(*(positions[a] - positions[b])))
            if d - 2 * radius <= 0:
                out.append(f"robots {ids[a]} and {ids[b]} overlap at the start: centres "
                           f"{d:.3f} m apart, gap {d - 2 * radius:.3f} m (robot.body_radius_m "
                           f"= {radius:g})")
    for a, rid in enumerate(ids):
        for name, centre, r in obstacles:
            d = float(np.hypot(*(positions[a] - centre)))
            if d - radius - r <= 0:
                out.append(f"robot {rid} starts on {name}: centres {d:.3f} m apart, gap "
                           f"{d - radius - r:.3f} m (radii {radius:g} and {r:g})")
        for poly in shapes:
            px, py, d = poly.nearest(float(positions[a][0]), float(positions[a][1]))
            if d - radius <= 0:
                out.append(f"robot {rid} starts on {poly.name}: its centre is {d:.3f} m from "
                           f"the nearest point ({px:.3f}, {py:.3f}){' (inside)' if d < 0 else ''}, "
                           f"gap {d - radius:.3f} m (robot.body_radius_m = {radius:g})")
    return out


def _check_scales(path: str, key: str, initial: list[float] | None,
                  changes: list[ScaleStep] | None) -> None:
    """S(0) two numbers; the windows of S(t) ordered and non-empty."""
    if initial is not None:
        _check_len(path, f"{key}.initial_scale", initial, 2)
    last_end = -math.inf
    for k, c in enumerate(changes or []):
        _check_len(path, f"{key}.scale_changes[{k}].to", c.to, 2)
        if not (c.end_s > c.start_s >= last_end):
            raise _fail(path, f"{key}.scale_changes[{k}]", "windows must be ordered and non-empty")
        last_end = c.end_s


def _check_steered_leader(path: str, ld: Leader) -> None:
    """``path = "ros2"``: no path of its own, a positive speed bound, a start pose."""
    for key in ("x", "y", "theta0", "theta_rate", "waypoints", "accel_mps2"):
        if getattr(ld, key) is not None:
            raise _fail(path, f"leader.{key}", 'not with path = "ros2" (the leader follows '
                        "/leader/cmd_vel; its bounds are speed_mps and yaw_rate_radps)")
    if ld.kind != "analytic":
        raise _fail(path, "leader.kind", 'path = "ros2" follows its commands: leave kind out')
    if ld.speed_mps is None:
        raise _fail(path, "leader.speed_mps", 'required with path = "ros2": the bound on the '
                    "leader's speed, m/s")
    if ld.start is not None:
        _check_len(path, "leader.start", ld.start, 3)
        _check_coordinates(path, "leader.start", ld.start[:2])
        _check_finite(path, "leader.start", ld.start)
    for key, value in (("speed_mps", ld.speed_mps), ("yaw_rate_radps", ld.yaw_rate_radps),
                       ("command_timeout_s", ld.command_timeout_s)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise _fail(path, f"leader.{key}", f"must be a positive number, got {value}")


def _check_leader_path(path: str, ld: Leader, notes: list[str]) -> None:
    """``path = "harmonic"`` needs x and y and nothing of the waypoints; ``"waypoints"``
    needs at least two distinct consecutive points and a positive speed and acceleration;
    ``"ros2"``: see :func:`_check_steered_leader`."""
    if ld.path == "ros2":
        _check_steered_leader(path, ld)
        return
    steered = {"start": ld.start, "yaw_rate_radps": ld.yaw_rate_radps,
               "command_timeout_s": ld.command_timeout_s}
    for key, value in steered.items():
        if value is not None:
            raise _fail(path, f"leader.{key}", 'only with path = "ros2"')
    wp_keys = {"waypoints": ld.waypoints, "speed_mps": ld.speed_mps, "accel_mps2": ld.accel_mps2}
    if ld.path == "harmonic":
        extra = [k for k, v in wp_keys.items() if v is not None]
        if extra:
            raise _fail(path, f"leader.{extra[0]}", 'only with path = "waypoints" (path is '
                        '"harmonic", the default)')
        for key, value in (("x", ld.x), ("y", ld.y)):
            if value is None:
                raise _fail(path, f"leader.{key}", 'required with path = "harmonic" (the default); '
                            'or set path = "waypoints" with waypoints, speed_mps, accel_mps2')
        return
    for key, value in (("x", ld.x), ("y", ld.y), ("theta0", ld.theta0),
                       ("theta_rate", ld.theta_rate)):
        if value is not None:
            raise _fail(path, f"leader.{key}", 'only with path = "harmonic"; with path = '
                        '"waypoints" the path is the waypoints, driven at speed_mps: remove '
                        'x, y, theta0 and theta_rate')
    for key, value in wp_keys.items():
        if value is None:
            raise _fail(path, f"leader.{key}", 'required with path = "waypoints"')
    pts = ld.waypoints
    if len(pts) < 2:
        raise _fail(path, "leader.waypoints", f"at least 2 points are needed, got {len(pts)}")
    for j, p in enumerate(pts):
        _check_len(path, f"leader.waypoints[{j}]", p, 2)
        _check_coordinates(path, f"leader.waypoints[{j}]", p)
    for j in range(1, len(pts)):
        if math.hypot(pts[j][0] - pts[j - 1][0], pts[j][1] - pts[j - 1][1]) <= 1e-9:
            raise _fail(path, f"leader.waypoints[{j}]", f"repeats the point before it {pts[j]}")
    for key in ("speed_mps", "accel_mps2"):
        if wp_keys[key] <= 0:
            raise _fail(path, f"leader.{key}", f"must be > 0, got {wp_keys[key]:g}")
    try:
        wp = waypoint_path(pts, ld.speed_mps, ld.accel_mps2)
    except (ValueError, ArithmeticError) as exc:  # scipy on coordinates near overflow
        raise _fail(path, "leader.waypoints", f"no spline through these points: {exc}") from exc
    if not (math.isfinite(wp.length) and math.isfinite(wp.profile.duration)):
        raise _fail(path, "leader.waypoints", "the path's length is not a finite number "
                    "(coordinates too large)")
    notes.append(f"leader: {wp.length:.4g} m of waypoint path, at rest at the last waypoint "
                 f"from t = {wp.profile.duration:.4g} s")


def _check_metrics(path: str, m: Metrics, ids: list[int]) -> None:
    if m.settle_threshold <= 0:
        raise _fail(path, "metrics.settle_threshold", "must be positive")
    if m.formation_threshold_m <= 0:
        raise _fail(path, "metrics.formation_threshold_m", "must be positive")
    stray = [r for r in m.expect_unreached if r not in ids]
    if stray:
        raise _fail(path, "metrics.expect_unreached", f"no robot {stray[0]} in this scenario "
                    f"(its robots: {', '.join(map(str, ids))})")
    if len(set(m.expect_unreached)) != len(m.expect_unreached):
        raise _fail(path, "metrics.expect_unreached", "names a robot twice")
    if m.expect_unreached and not m.expect_unreached_why.strip():
        raise _fail(path, "metrics.expect_unreached_why", "say why those robots never reach "
                    "their formation position (it goes into the summary and metrics.json)")
    if m.expect_unreached_why and not m.expect_unreached:
        raise _fail(path, "metrics.expect_unreached_why", "given without expect_unreached")


MAX_COORDINATE_M = 1e6  # walls, polygons, waypoints: a world of +-1000 km (no overflow)
MIN_FEATURE_M = 1e-3  # a wall's length and thickness, a polygon's edge: at least 1 mm


def _check_coordinates(path: str, key: str, values: list[float]) -> None:
    if any(abs(v) > MAX_COORDINATE_M for v in values):
        raise _fail(path, key, f"must be within +-{MAX_COORDINATE_M:g} m, got {values}")


def _check_shapes(path: str, s: ScenarioFile) -> None:
    """Walls: two 2-D points apart and a positive thickness; polygons: at least three
    2-D vertices forming a strictly convex polygon of positive area."""
    for k, w in enumerate(s.walls):
        _check_len(path, f"walls[{k}].start", w.start, 2)
        _check_len(path, f"walls[{k}].end", w.end, 2)
        _check_coordinates(path, f"walls[{k}].start", w.start)
        _check_coordinates(path, f"walls[{k}].end", w.end)
        _check_coordinates(path, f"walls[{k}].thickness_m", [w.thickness_m])
        if math.hypot(w.end[0] - w.start[0], w.end[1] - w.start[1]) < MIN_FEATURE_M:
            raise _fail(path, f"walls[{k}]", f"start and end are the same point {w.start}: "
                        f"a wall needs a length of at least {MIN_FEATURE_M:g} m (for a post, "
                        "use [[obstacles]])")
        if w.thickness_m < MIN_FEATURE_M:
            raise _fail(path, f"walls[{k}].thickness_m", f"must be at least {MIN_FEATURE_M:g} m "
                        f"(> 0), got {w.thickness_m:g}")
    for k, pg in enumerate(s.polygons):
        key = f"polygons[{k}].vertices"
        if len(pg.vertices) < 3:
            raise _fail(path, key, f"a polygon needs at least 3 vertices, got {len(pg.vertices)}")
        for j, v in enumerate(pg.vertices):
            _check_len(path, f"{key}[{j}]", v, 2)
            _check_coordinates(path, f"{key}[{j}]", v)
        for j, (a, b) in enumerate(zip(pg.vertices, pg.vertices[1:] + pg.vertices[:1], strict=True)):
            if math.hypot(b[0] - a[0], b[1] - a[1]) < MIN_FEATURE_M:
                raise _fail(path, key, f"vertices {j} and {(j + 1) % len(pg.vertices)} are closer "
                            f"than {MIN_FEATURE_M:g} m: {a}, {b}")
        if convex_ccw(pg.vertices) is None:
            raise _fail(path, key, "must be a convex polygon of positive area, vertices in "
                        "order around it (either way), no three on a line; split a concave "
                        "obstacle into convex polygons")


def _check_all_finite(path: str, node, key: str = "") -> None:
    """Every number in the file is finite; only ``limits.*`` may be inf (no limit). NaN never."""
    if isinstance(node, dict):
        for k, v in node.items():
            _check_all_finite(path, v, f"{key}.{k}" if key else k)
    elif isinstance(node, list):
        for i, v in enumerate(node):
            _check_all_finite(path, v, f"{key}[{i}]")
    elif isinstance(node, float):
        if math.isnan(node) or (math.isinf(node) and not key.startswith("limits.")):
            raise _fail(path, key, f"must be a finite number, got {node}")


def _absolute_law(spec: str, folder: Path) -> str:
    """A law named by a file's path, that path made absolute from ``folder`` (the nodes of
    a run read the scenario from elsewhere, or start elsewhere)."""
    where, sep, cls = spec.rpartition(":")
    if sep and where.endswith(".py") and not Path(where).expanduser().is_absolute():
        return f"{(folder / Path(where).expanduser()).resolve()}:{cls}"
    return spec


def _load_law(path: str, law: LawSection) -> tuple[type | None, object]:
    """The law's class and parameters (agents/laws), or ScenarioError naming ``path``."""
    from agents.laws import LawError, load, params_of

    try:
        cls = load(law.use)
        return cls, params_of(cls, law.params, law.use)
    except LawError as exc:
        raise ScenarioError(f"{path}: law.use: {exc}") from exc


def _validate(path: str, s: ScenarioFile) -> Scenario:
    """The scenario as the runtime takes it, or ScenarioError naming the first key that is
    wrong (checked in the order of the file: rates, robots, graph, formation, leader,
    bodies, behaviours, gains)."""
    notes: list[str] = []
    _check_all_finite(path, msgspec.to_builtins(s))
    if s.law.use != "paper":  # a law of a file: its path from the scenario's folder
        folder = Path(path).parent if Path(path).exists() else Path.cwd()
        s = msgspec.structs.replace(s, law=msgspec.structs.replace(
            s.law, use=_absolute_law(s.law.use, folder)))
        _load_law(path, s.law)  # a law that cannot be used: said now, before anything runs
    _check_plant(path, s.plant.kind)
    if not (0 < s.control_rate_hz <= MAX_RATE_HZ):
        raise _fail(path, "control_rate_hz", f"must be in (0, {MAX_RATE_HZ:g}]")
    if s.duration_s * s.control_rate_hz < 1.0:
        raise _fail(path, "duration_s", f"must be at least one control period "
                    f"({1.0 / s.control_rate_hz:g} s at control_rate_hz = {s.control_rate_hz:g})")
    ids = _checked_robot_ids(path, s)
    A, b = _checked_graph(path, s, ids, notes)
    _check_formation(path, s, A, ids)
    _check_leader_path(path, s.leader, notes)
    _check_bodies(path, s, ids)
    _check_behaviors(path, s)
    _check_gains(path, s, ids)
    return Scenario(path, s, A, b, tuple(notes))


def _checked_robot_ids(path: str, s: ScenarioFile) -> list[int]:
    n = len(s.robots)
    if n == 0:
        raise _fail(path, "robots", "at least one robot is needed")
    ids = [r.id for r in s.robots]
    if len(set(ids)) != n:
        raise _fail(path, "robots.id", f"ids must be unique, got {ids}")
    if any(i < 1 for i in ids):
        raise _fail(path, "robots.id", "ids start at 1 (0 is the leader)")
    for k, r in enumerate(s.robots):
        _check_len(path, f"robots[{k}].position", r.position, 2)
        _check_len(path, f"robots[{k}].velocity", r.velocity, 2)
        _check_len(path, f"robots[{k}].offset", r.offset, 2)
        _check_finite(path, f"robots[{k}]", [*r.position, *r.velocity, *r.offset, r.heading_rad])
        if r.estimate_position is not None:
            _check_len(path, f"robots[{k}].estimate_position", r.estimate_position, 3)
        if r.estimate_velocity is not None:
            _check_len(path, f"robots[{k}].estimate_velocity", r.estimate_velocity, 3)
    return ids


def _checked_graph(path: str, s: ScenarioFile, ids: list[int], notes: list[str]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The adjacency matrix A (self loops zeroed, said in ``notes``) and the leader
    weights b, with a spanning tree rooted at the leader."""
    n = len(ids)
    rows = s.graph.adjacency
    if len(rows) != n or any(len(row) != n for row in rows):  # ragged rows: numpy would raise
        got = f"{len(rows)} rows of {sorted({len(row) for row in rows})} numbers"
        raise _fail(path, "graph.adjacency", f"must be {n}x{n} for {n} robots, got {got}")
    A = np.array(rows, dtype=float).reshape(n, n)
    _check_len(path, "graph.leader", s.graph.leader, n)
    b = np.array(s.graph.leader, dtype=float)
    _check_finite(path, "graph.adjacency", A)
    _check_finite(path, "graph.leader", b)
    if np.any(A < 0) or np.any(b < 0):
        raise _fail(path, "graph", "weights must be non-negative")
    if np.any(np.diag(A) != 0):
        notes.append(
            "graph.adjacency: diagonal (self loops) set to zero (erratum 7: it cancels in "
            "eq. 14 but not in eq. 16)"
        )
        A = A.copy()
        np.fill_diagonal(A, 0.0)
    deaf = unreached_robots(A, b)
    if deaf:
        raise _fail(
            path, "graph", "the graph has no directed spanning tree rooted at the leader: "
            f"{'robots' if len(deaf) > 1 else 'robot'} {', '.join(str(ids[i]) for i in deaf)} "
            f"{'hear' if len(deaf) > 1 else 'hears'} the leader through no path (graph.leader "
            "and the rows and columns of "
            "graph.adjacency follow the order of [[robots]], not their ids)"
        )
    return A, b


def _check_formation(path: str, s: ScenarioFile, A: np.ndarray, ids: list[int]) -> None:
    n = len(ids)
    f = s.formation
    if f.kappa1 < 0 or f.kappa2 < 0:
        raise _fail(path, "formation.kappa1/kappa2", "must be non-negative")
    for i in range(n):
        if f.kappa1 + f.kappa2 * A[i].sum() <= 0:
            raise _fail(path, "formation.kappa1", f"robot {ids[i]}: kappa1 + kappa2 sum_j a_ij is 0")
    _check_scales(path, "formation", f.initial_scale, f.scale_changes)
    for k, r in enumerate(s.robots):
        _check_scales(path, f"robots[{k}]", r.initial_scale, r.scale_changes)


def _check_bodies(path: str, s: ScenarioFile, ids: list[int]) -> None:
    """Obstacles, walls and polygons, and robots that start clear of every body."""
    for k, o in enumerate(s.obstacles):
        _check_len(path, f"obstacles[{k}].position", o.position, 2)
        if o.radius_m < 0:
            raise _fail(path, f"obstacles[{k}].radius_m", "must be >= 0")
    _check_shapes(path, s)
    overlaps = start_overlaps(
        np.array([r.position for r in s.robots], float), ids, s.robot.body_radius_m,
        [(f"obstacles[{k}] at ({o.position[0]:g}, {o.position[1]:g})",
          np.array(o.position, float), o.radius_m) for k, o in enumerate(s.obstacles)],
        obstacle_shapes(s))
    if overlaps:
        raise _fail(path, "robots.position", "; ".join(overlaps))


def _check_behaviors(path: str, s: ScenarioFile) -> None:
    bh = s.behaviors
    for key, names in (("behaviors.enabled", bh.enabled), ("behaviors.priority", bh.priority)):
        bad = [x for x in names if x not in BEHAVIOR_NAMES]
        if bad:
            raise _fail(path, key, f"unknown behavior {bad[0]!r}; known: {', '.join(BEHAVIOR_NAMES)}")
    if sorted(bh.priority) != sorted(BEHAVIOR_NAMES):
        raise _fail(path, "behaviors.priority", f"must order all of {', '.join(BEHAVIOR_NAMES)} once")
    for key in ("fdb_gains", "focb_gains", "frcb_gains"):
        g = getattr(bh, key)
        _check_len(path, f"behaviors.{key}", g, 2)
        if any(x < 0 for x in g) or g[0] <= 0:
            raise _fail(path, f"behaviors.{key}", "gains must be positive")
    rr = s.robot.body_radius_m
    if bh.obstacle_safe_distance_m <= rr:
        raise _fail(path, "behaviors.obstacle_safe_distance_m", "must exceed the robot radius")
    if bh.robot_safe_distance_m <= 2 * rr:
        raise _fail(path, "behaviors.robot_safe_distance_m", "must exceed twice the robot radius")
    if s.safety.margin_m < 0:
        raise _fail(path, "safety.margin_m", "must be >= 0")
    if s.safety.exit_time_s <= 0:
        raise _fail(path, "safety.exit_time_s", "must be positive")


def _check_gains(path: str, s: ScenarioFile, ids: list[int]) -> None:
    """Estimator, controller, observer, limits, disturbance, degradation, plant, metrics
    and the robot's parameters."""
    _check_len(path, "estimator.iota", s.estimator.iota, 4)
    _check_len(path, "estimator.eta", s.estimator.eta, 2)
    c = s.controller
    if not (0 < c.alpha < 1) or c.mu <= 0 or c.T_p <= 0 or c.upsilon <= 0 or c.psi_epsilon <= 0:
        raise _fail(path, "controller", "need 0 < alpha < 1 and mu, T_p, upsilon, psi_epsilon > 0")
    if not (0.5 < s.eso.r1 < 1) or s.eso.mu1 <= 0 or s.eso.mu2 <= 0:
        raise _fail(path, "eso", "need 0.5 < r1 < 1 and mu1, mu2 > 0")
    for key in ("max_speed_mps", "max_yaw_rate_radps", "max_wheel_torque_nm", "max_accel_mps2",
                "max_yaw_accel_radps2", "max_tracking_error"):
        if getattr(s.limits, key) <= 0:
            raise _fail(path, f"limits.{key}", "must be positive (inf for none)")
    _check_len(path, "disturbance.constant_nm", s.disturbance.constant_nm, 4)
    d = s.degradation
    if d.stale_after_s <= 0 or d.slow_after_s <= 0 or d.slow_ramp_s < 0 \
            or d.degraded_speed_mps < 0 or d.reacquire_tau_s < 0 or d.reacquire_tol_m <= 0 \
            or d.reacquire_min_s < 0:
        raise _fail(path, "degradation", "need stale_after_s, slow_after_s > 0 and "
                    "slow_ramp_s, degraded_speed_mps, reacquire_tau_s >= 0, reacquire_tol_m > 0")
    if not 0 <= d.command_horizon <= MAX_COMMAND_HORIZON:
        raise _fail(path, "degradation.command_horizon",
                    f"must be between 0 (off) and {MAX_COMMAND_HORIZON} steps")
    if s.plant.substeps < 1:
        raise _fail(path, "plant.substeps", "must be >= 1")
    _check_metrics(path, s.metrics, ids)
    p = s.robot
    for key in ("wheel_radius_m", "mass_kg", "inertia_z_kgm2", "inertia_wheel_kgm2",
                "half_wheelbase_m", "half_track_m", "body_radius_m", "coulomb_smoothing_radps"):
        if getattr(p, key) <= 0:
            raise _fail(path, f"robot.{key}", "must be positive")


def resolve_path(name_or_path: str | Path) -> Path:
    """A file path, or the name of a bundled scenario (``paper``, ``lab``, ...)."""
    p = Path(name_or_path)
    if p.exists():
        return p
    bundled = SCENARIO_DIR / f"{p.name.removesuffix('.toml')}.toml"
    if bundled.exists():
        return bundled
    known = ", ".join(sorted(x.stem for x in SCENARIO_DIR.glob("*.toml")))
    raise ScenarioError(f"{name_or_path}: no such file, and no bundled scenario by that name ({known})")


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a scenario; raises :class:`ScenarioError` naming file and key."""
    path = resolve_path(name_or_path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ScenarioError(f"{path}: cannot read: {exc}") from exc
    return parse_scenario(raw, str(path))


def parse_scenario(raw: bytes | str, path: str = "<scenario>") -> Scenario:
    """Decode and validate a scenario's TOML text; ``path`` names it in errors."""
    if isinstance(raw, bytes):
        # TOML is UTF-8 text: said as such here, whatever msgspec's version makes of it
        # (0.22 let the UnicodeDecodeError out, 0.23 wraps it in a DecodeError)
        try:
            raw = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ScenarioError(f"{path}: not valid TOML (not UTF-8 text): {exc}") from exc
    try:
        spec = msgspec.toml.decode(raw, type=ScenarioFile)
    except msgspec.ValidationError as exc:
        raise ScenarioError(f"{path}: {_readable(str(exc))}") from exc
    except msgspec.DecodeError as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from exc
    return _validate(path, spec)


def _readable(msg: str) -> str:
    """msgspec's message, readable, with the nearest known key or the allowed values."""
    return readable(msg, ScenarioFile)
