"""Robots, obstacles and contacts in a pybullet world: the rigid-body plant.

Same interface as :class:`plant.model_plant.ModelPlant` (``q``, ``q_dot``,
``step``), plus what only a simulated world has: real collisions between robots
and obstacles (:attr:`PybulletPlant.contacts`) and sensing by geometric queries
(:meth:`PybulletPlant.perceive`).

Traction model: computed wheel forces on the chassis (docs/pybullet.md)
-----------------------------------------------------------------------
Of the three options in docs/pybullet.md (explicit rollers, anisotropic
friction, computed wheel forces) this plant computes the wheel forces. Explicit
rollers need tiny time steps and are fragile at the paper's 50 m/s;
anisotropic friction cannot represent a driven wheel torque exactly. The wheels
are therefore not bodies: their effect on the chassis is computed from the
no-slip roller kinematics every physics sub-step and applied as generalised
forces, and Bullet integrates the chassis and resolves its contacts.

Bodies. The robots are Featherstone multibodies with a fixed base at the world
origin, up to ``robots_per_body`` robots (default ROBOTS_PER_BODY) in each. A
robot is a planar chain from that base: its link 3j prismatic along world x,
3j + 1 prismatic along world y, 3j + 2 revolute about z (j = its place in its
body). The joint positions are exactly q = [x, y, phi] and the joint velocities
q_dot. Its x and y links are massless and have no collision shape; its yaw link
carries the chassis: a vertical cylinder of the robot's radius and the inertia
of M_q (plant/mecanum.py ``generalised_inertia``, the wheel inertia reflected
through the no-slip rollers)

    m_t = m + 4 I_w / R^2,   I_t = I_z + 4 I_w (l + w)^2 / R^2.          (P1)

With massless sliders the articulated inertia seen by the x and the y joints is
m_t and the one seen by the yaw joint is I_t, and the chassis centre of mass is
on the yaw axis, so Bullet's joint-space equation of motion is exactly

    M_q q_ddot = F + F_contact,   M_q = diag(m_t, m_t, I_t)              (P2)

with no Coriolis term (checked in tests/integration/test_pybullet_plant.py). The
robots of one body do not act on each other through it: its base is fixed, so
a force on one robot's chain accelerates that chain's joints only (the
articulated-body pass carries nothing across a base that cannot move; checked
against one body per robot). Gravity is 0 (the joints are planar anyway); joint
damping, link damping, the default velocity motors and the joint velocity cap
are all disabled, so F (ours) and F_contact (Bullet's contact solver) are the
only forces.

Robots share bodies because a pybullet call costs a fixed ~1-3 µs besides its
work, and forces go in and states come out by the body: two calls per body and
sub-step, not two per robot. The groups stay small because Bullet's contact
solver works on every joint of the bodies a contact involves, so a contact costs
in proportion to its bodies' size (figures in docs/pybullet.md). pybullet's state
of one body holds 128 coordinates (7 of the base, 3 per robot), hence at most
MAX_ROBOTS_PER_BODY.

Wheel forces. From the current joint velocities, every sub-step:

    theta_dot = P T(phi)^T q_dot / R                   (inverse of eq. 1)  (P3)
    tau_w = u + h_d(t) - tau_c(theta_dot) - C_theta R^2 theta_dot          (P4)
    tau_c = (C_f m g R / 4) tanh(theta_dot / omega_s)   (as in ModelPlant)
    F = T(phi) P^T tau_w / R          (world frame [F_x, F_y, M_z])        (P5)

F is applied as joint forces (TORQUE_CONTROL) on the three joints. Since
P^T P = diag(4, 4, 4 (l + w)^2) commutes with T(phi), M_q^-1 F is term by term
eq. (4) of the paper, q_ddot = -A0 q_dot - A1 + B (u + h_d): the continuous-time
dynamics of the two plants are identical away from contacts, and they differ
only in the integrator (Bullet's semi-implicit Euler with the force held over a
sub-step, v += h M_q^-1 F, q += h v, against RK4 in ModelPlant). The pure force
law (P3)-(P5) is :class:`ForceLaw` / :func:`generalised_force`, with no
pybullet in it.

Stepping. ``step(t, dt, ...)`` advances ``substeps`` sub-steps of h = dt / substeps;
before each the forces are recomputed from the state after the previous sub-step
(TORQUE_CONTROL forces last one stepSimulation), with h_d evaluated at the sub-step's
start time. **Bullet is stepped only where a contact can happen.** Bullet looks for
contact points at the positions a sub-step starts from and keeps none farther apart than
its 0.02 m breaking threshold, so a sub-step that starts with every robot more than
``CONTACT_QUERY_GAP_M`` (0.1 m) from every other body, surface to surface, has no
contact and no constraint acts on the joints: it is Bullet's free step of (P2),
v += h M_q^-1 F, q += h v, and the kernel computes it without calling Bullet
(:attr:`ForceLaw.free_substep`). Bullet's joints are set to the plant's state
(resetJointStatesMultiDof, one call per body) before the next sub-step that needs
Bullet (a body within the gap), before its closest-point queries (:meth:`perceive`),
and after every step with the GUI. A sub-step near a body is one
setJointMotorControlArray per body, one stepSimulation and one getContactPoints, and
then the state: read back from Bullet (getJointStates, one per body) when Bullet found
a contact point, and after the step's last sub-step; otherwise the free step again.
Bullet's articulated-body pass rounds M_q^-1 F its own way, so a computed free step
agrees with Bullet's own to ~1e-13 relative, not bit for bit; through collisions the
states stay within ~1e-10 of a plant that steps Bullet at every sub-step and the
contact events are the same (tests/integration/test_pybullet_plant.py). A world with
walls or polygons (prisms, not discs) steps Bullet at every sub-step. The sub-steps'
loop and the arithmetic between the calls (the states Bullet returned into q, q_dot,
then h_d and (P3)-(P5) into the next forces) run in the plant kernel
(:attr:`ForceLaw.step_in_bullet`, :attr:`ForceLaw.substep`). Deterministic settings:
deterministicOverlappingPairs=1, numSubSteps=1, sleeping disabled, one physics
client per plant (several plants coexist in one process).

Walls and convex polygons (plant/shapes.py) are static convex hulls of their
prism (the polygon at z = +-height/2), with Bullet's collision margin set to 0:
with the default margin (1 mm for a hull) contact came 1 mm early; with 0 a
cylinder's distance to the hull is exact to ~1e-15 m (measured). Perception sees
a wall or polygon as its point nearest the robot's centre (plant/perception.py
``shape_bodies``), computed from the same vertices.

Obstacles are static cylinders (mass 0) at their positions with their radii;
a point obstacle (radius 0) gets MIN_COLLISION_RADIUS_M. Every column is
``HEIGHT_PER_RADIUS`` times the largest radius tall, centred on z = 0: the
contact normal of two columns is then always horizontal (a penetration through
the caps would cost more than any sideways one; with short columns Bullet's EPA
resolved deep overlaps vertically), and Bullet's distances between two columns
are exact to ~2e-11 m when apart and ~1e-8 m in penetration (measured). Robots
collide with robots and obstacles: robots of one body through Bullet's
self-collision of a body's links (URDF_USE_SELF_COLLISION; a link never collides
with its parent), robots of two bodies as any two bodies do. A body's base and a
robot's sliders have no shape, so nothing of a robot collides with itself.
Contact friction and restitution are Bullet's defaults (lateral friction 0.5,
restitution 0); Bullet's contacts are speculative (a pair within its contact
threshold is kept from closing the gap), so even a 50 m/s impact stops at the
surface, and a resting contact settles ~1e-5 m deep (measured).

Contacts. After each sub-step the contact points of robot-robot and
robot-obstacle pairs are read (getContactPoints). Bullet's narrowphase runs at
the start of stepSimulation, so those points describe the configuration at the
sub-step's start time, and that is the time they are labelled with (so the state
at the end of a ``step`` is checked during the next one). A pair
touches when one of its points has distance <= 0. A :class:`ContactEvent`
starts when a pair goes from not touching to touching; its max_depth_m (the
largest penetration, metres, >= 0) grows while it lasts and t_end is the time of
the first sample at which the pair no longer touches. Robots are named by their
robot id, obstacles by their Body ident (-(k+1) for the scenario's k-th); Bullet
names a point's two sides by (body, link), which the plant maps to those.
"""

from __future__ import annotations

import ctypes
import math
import os
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from plant.bodies import Body
from plant.disturbance import Disturbance
from plant.fleet_kernel import FleetDynamics
from plant.interface import DEFAULT_SUBSTEPS
from plant.mecanum import MecanumModel, generalised_inertia
from plant.perception import shape_bodies
from plant.shapes import Polygon


def _import_pybullet_quietly():
    """pybullet prints its build time on stderr (C stdio) when imported, in the
    middle of a command's own messages: send that line to /dev/null."""
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            import pybullet

            ctypes.CDLL(None).fflush(None)  # C buffers, while fd 2 is still /dev/null
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    return pybullet


pb = _import_pybullet_quietly()

DisturbanceFn = Callable[[float], np.ndarray]

MIN_COLLISION_RADIUS_M = 0.01  # collision radius of a point obstacle (scenario radius 0)
HEIGHT_PER_RADIUS = 4.0  # column height / largest radius: contact normals stay horizontal
MAX_JOINT_VELOCITY = 1e9  # Bullet clamps joint speeds at 100 by default; effectively no cap
LINKS_PER_ROBOT = 3  # x slider, y slider, yaw (the chassis): robot j of a body has links 3j .. 3j + 2
CHASSIS_LINK = 2  # of a robot's three links, the one carrying the chassis shape and M_q's mass / yaw inertia
# Robots per multibody: fewer pybullet calls per sub-step against a contact solve that
# grows with the body (measured, docs/pybullet.md).
ROBOTS_PER_BODY = 6
MAX_ROBOTS_PER_BODY = 40  # pybullet's state of a body: 128 coordinates, 7 of the base and 3 per robot


class GuiUnavailable(RuntimeError):
    """The window was asked for on a machine without a display."""


@dataclass(frozen=True)
class ContactEvent:
    """One contact of two bodies, from first touch (t_start) to release (t_end)."""

    t_start: float
    body_a: int  # robot id (the smaller one for two robots)
    body_b: int  # robot id, or obstacle ident -(k+1)
    max_depth_m: float  # largest penetration while it lasted, >= 0
    t_end: float | None = None  # None while it lasts


class ForceLaw:
    """The wheels' generalised force on the chassis, (P3)-(P5), rows = robots: the plant
    kernel's (plant/fleet_kernel.pyx ``FleetDynamics.wheel_forces``), one pass over the
    fleet. ``law(q, q_dot, wheel_torques)`` with (n,3), (n,3), (n,4) arrays
    (``wheel_torques`` = u + h_d) gives the (n,3) world-frame forces [F_x, F_y, M_z].

    :attr:`substep` is the same law as a plant's sub-step uses it (``FleetDynamics.
    bullet_substep``): from the joint states Bullet returned to the next forces in one
    call, h_d added inside when ``disturbance`` is the scenario's (:class:`Disturbance`);
    :attr:`step_in_bullet` runs a whole step's sub-steps with the same arithmetic.
    """

    def __init__(self, models: Sequence[MecanumModel], disturbance: Disturbance | None = None) -> None:
        known = disturbance or Disturbance("none")
        self._fleet = FleetDynamics(list(models), known.kind, known.scale, known.constant, 1)
        self._out = np.empty((len(models), 3))

    @classmethod
    def from_models(cls, models: Sequence[MecanumModel]) -> ForceLaw:
        return cls(models)

    def __call__(self, q: np.ndarray, q_dot: np.ndarray, wheel_torques: np.ndarray) -> np.ndarray:
        out = np.empty_like(self._out)
        self._fleet.wheel_forces(np.ascontiguousarray(q, dtype=float),
                                 np.ascontiguousarray(q_dot, dtype=float),
                                 np.ascontiguousarray(wheel_torques, dtype=float), out)
        return out

    @property
    def substep(self) -> Callable[..., list[float] | None]:
        """``substep(states, torques, t, q, q_dot)``: ``states`` (getJointStates' tuples of
        every robot's x, y, yaw in turn, or None) into q, q_dot, then the forces from
        torques + h_d(t) as one flat list [F_x, F_y, M_z, ...] (``torques`` None: none)."""
        return self._fleet.bullet_substep

    @property
    def step_in_bullet(self) -> Callable[..., list[tuple]]:
        """``step_in_bullet(bullet, bodies, torques, other, wheel_torques, t, h, substeps, q,
        q_dot)``: a pybullet plant's whole step, its sub-steps' loop compiled
        (``FleetDynamics.bullet_step``); each sub-step's contact points."""
        return self._fleet.bullet_step

    @property
    def catch_up_bullet(self) -> Callable[[tuple, list, np.ndarray, np.ndarray], None]:
        """``catch_up_bullet(bullet, bodies, q, q_dot)``: Bullet's joints set to q, q_dot
        when the last sub-steps ran without Bullet (``FleetDynamics.catch_up_bullet``)."""
        return self._fleet.catch_up_bullet

    @property
    def free_substep(self) -> Callable[[list[float], float, np.ndarray, np.ndarray], None]:
        """``free_substep(forces, h, q, q_dot)``: a sub-step without contact as Bullet
        integrates it, v += h M_q^-1 F, q += h v, in place (``FleetDynamics.
        bullet_free_substep``)."""
        return self._fleet.bullet_free_substep


def generalised_force(model: MecanumModel, q: np.ndarray, q_dot: np.ndarray,
                      wheel_torques: np.ndarray) -> np.ndarray:
    """(P3)-(P5) for one robot: world-frame [F_x, F_y, M_z] from u + h_d (``wheel_torques``)."""
    law = ForceLaw.from_models([model])
    return law(np.asarray(q, float)[None], np.asarray(q_dot, float)[None],
               np.asarray(wheel_torques, float)[None])[0]


def _pair(a: int, b: int) -> tuple[int, int]:
    """Canonical (body_a, body_b): robot first; the smaller robot id first for two robots."""
    if b > 0 and (a < 0 or b < a):
        return b, a
    return a, b


class PybulletPlant:
    """Robots as planar Featherstone multibodies driven by computed wheel forces.

    See the module docstring for the model, (P1)-(P5). ``q`` and ``q_dot`` are
    (n,3) world [x, y, phi] and their rates after the last step (Bullet's, or its free
    step computed: see the module docstring); ``contacts`` lists every contact event so
    far.
    """

    kind = "pybullet"

    def __init__(
        self,
        models: Sequence[MecanumModel],
        q: np.ndarray,
        q_dot: np.ndarray,
        disturbance: DisturbanceFn,
        robot_radii: Sequence[float],
        robot_ids: Sequence[int],
        obstacles: Sequence[Body],
        substeps: int = DEFAULT_SUBSTEPS,
        gui: bool = False,
        shapes: Sequence[Polygon] = (),
        robots_per_body: int = ROBOTS_PER_BODY,
    ) -> None:
        self.models = list(models)
        n = len(self.models)
        self.q = np.array(q, dtype=float).reshape(n, 3)
        self.q_dot = np.array(q_dot, dtype=float).reshape(n, 3)
        if len(robot_radii) != n or len(robot_ids) != n:
            raise ValueError(f"{n} models but {len(robot_radii)} radii and {len(robot_ids)} ids")
        if not (np.all(np.isfinite(self.q)) and np.all(np.isfinite(self.q_dot))):
            raise ValueError("initial state must be finite")
        if substeps < 1:
            raise ValueError("substeps must be >= 1")
        self.disturbance = disturbance
        self.robot_radii = [float(r) for r in robot_radii]
        self.robot_ids = [int(i) for i in robot_ids]
        self.obstacles = list(obstacles)
        self.shapes = list(shapes)
        self.substeps = substeps
        if not 1 <= robots_per_body <= MAX_ROBOTS_PER_BODY:
            raise ValueError(f"robots_per_body must be 1 .. {MAX_ROBOTS_PER_BODY}, got {robots_per_body}")
        self.contacts: list[ContactEvent] = []
        # the scenario's h_d is evaluated in the kernel; any other function of t here
        self._law = ForceLaw(self.models, disturbance if isinstance(disturbance, Disturbance) else None)
        self._other = None if isinstance(disturbance, Disturbance) else disturbance
        self._h: float | None = None
        self._wheel_torques = np.empty((n, 4))  # u + h_d of another disturbance than the scenario's

        self._connect(gui)
        radii = self.robot_radii + [o.radius for o in self.obstacles]
        self._height = HEIGHT_PER_RADIUS * max([MIN_COLLISION_RADIUS_M, *radii])
        self._cylinders: dict[float, int] = {}  # radius -> its collision shape
        self._build_robots(robots_per_body)
        self._build_obstacles()
        self._shape_ids = [self._prism(poly, gui) for poly in self.shapes]
        # the world as discs, for the kernel to skip the contact query of a sub-step that
        # starts with every robot clear of every body; a world with prisms: none (it asks)
        self._discs: tuple = () if self.shapes else (
            np.array(self.robot_radii, dtype=float),
            np.array([[*(float(v) for v in o.position), r]
                      for o, r in zip(self.obstacles, self._collision_radius, strict=True)],
                     dtype=float).reshape(-1, 3))

        # Bullet's (body id, link index) -> scenario ident (robot id, or obstacle ident)
        self._ident = dict(zip(self._chassis, self.robot_ids, strict=True))
        for bodies, named in ((self._obstacle_ids, self.obstacles), (self._shape_ids, self.shapes)):
            self._ident.update({(b, -1): o.ident for b, o in zip(bodies, named, strict=True)})
        self._ongoing: dict[tuple[int, int], int] = {}  # pair -> index in self.contacts

    def _connect(self, gui: bool) -> None:
        """A physics server of this plant's own (a window with ``gui``), without gravity
        (the model is planar), and the pybullet calls the kernel's step loop makes."""
        if gui and not os.environ.get("DISPLAY"):
            # pybullet's GUI would end the whole process on a failed X connection
            raise GuiUnavailable("--gui needs a display, and DISPLAY is not set")
        self._gui = gui
        self._cid = pb.connect(pb.GUI if gui else pb.DIRECT)
        if self._cid < 0:
            raise RuntimeError("could not connect to a pybullet physics server")
        self._finalizer = weakref.finalize(self, _disconnect, self._cid)
        cid = self._cid
        # what the kernel's step loop calls (FleetDynamics.bullet_step), with positional
        # arguments: parsing keywords costs ~0.3 µs a call (of 1-3). setJointMotorControlArray
        # wants every sequence before the client id as long as the joints and reads only the
        # forces in TORQUE_CONTROL: the forces stand in for the target positions, velocities
        # and gains; getContactPoints(-1, -1, -2, -2): no body or link filter (its defaults)
        self._bullet = (pb.setJointMotorControlArray, pb.stepSimulation, pb.getContactPoints,
                        pb.getJointStates, pb.TORQUE_CONTROL, cid, pb.resetJointStatesMultiDof)
        pb.setGravity(0.0, 0.0, 0.0, physicsClientId=cid)
        pb.setPhysicsEngineParameter(numSubSteps=1, deterministicOverlappingPairs=1,
                                     physicsClientId=cid)

    def _cylinder(self, radius: float) -> int:
        """The collision shape of a cylinder of ``radius`` (one per radius)."""
        if radius not in self._cylinders:
            self._cylinders[radius] = pb.createCollisionShape(
                pb.GEOM_CYLINDER, radius=radius, height=self._height, physicsClientId=self._cid)
        return self._cylinders[radius]

    def _visual(self, radius: float, rgba: list[float]) -> int:
        """Its look in the window (-1: none without one)."""
        if not self._gui:
            return -1
        return pb.createVisualShape(pb.GEOM_CYLINDER, radius=radius, length=self._height,
                                    rgbaColor=rgba, physicsClientId=self._cid)

    def _build_robots(self, robots_per_body: int) -> None:
        """The robots in bodies of near-equal size, in order: robot k is (body, its chassis
        link) in ``_chassis``; per body, its joints and its slice of the flat force list."""
        n = len(self.models)
        count = -(-n // robots_per_body)
        sizes = [n // count + (g < n % count) for g in range(count)]
        self._chassis: list[tuple[int, int]] = []
        # per body: (body id, its joint indices, its slice of the flat (3n) force list)
        self._bodies: list[tuple[int, list[int], int, int]] = []
        first = 0
        for size in sizes:
            robots = range(first, first + size)
            body = self._robot_body([self._cylinder(self.robot_radii[k]) for k in robots],
                                    [self._visual(self.robot_radii[k], [0.2, 0.4, 0.9, 1.0])
                                     for k in robots], robots)
            self._chassis += [(body, LINKS_PER_ROBOT * j + CHASSIS_LINK) for j in range(size)]
            self._bodies.append((body, list(range(LINKS_PER_ROBOT * size)), LINKS_PER_ROBOT * first,
                                 LINKS_PER_ROBOT * (first + size)))
            first += size

    def _build_obstacles(self) -> None:
        """Each disc obstacle a fixed cylinder (a point obstacle at least
        MIN_COLLISION_RADIUS_M wide)."""
        self._obstacle_ids: list[int] = []
        self._collision_radius: list[float] = []
        for o in self.obstacles:
            r = max(float(o.radius), MIN_COLLISION_RADIUS_M)
            x, y = (float(v) for v in o.position)
            self._obstacle_ids.append(pb.createMultiBody(
                baseMass=0.0, baseCollisionShapeIndex=self._cylinder(r),
                baseVisualShapeIndex=self._visual(r, [0.8, 0.3, 0.2, 1.0]),
                basePosition=[x, y, 0.0], physicsClientId=self._cid,
            ))
            self._collision_radius.append(r)

    def _robot_body(self, shapes: list[int], visuals: list[int], robots: range) -> int:
        """One multibody holding ``robots`` (indices into the fleet), each a planar chain
        x slider, y slider, yaw from the fixed base, at its state; see the module docstring."""
        cid, size = self._cid, len(robots)
        links = LINKS_PER_ROBOT * size
        inertia = [np.diag(generalised_inertia(self.models[k].params)) for k in robots]  # (P1)
        body = pb.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=-1,
            basePosition=[0.0, 0.0, 0.0],
            linkMasses=[m for m_t, _, _ in inertia for m in (0.0, 0.0, float(m_t))],
            linkCollisionShapeIndices=[c for s in shapes for c in (-1, -1, s)],
            linkVisualShapeIndices=[v for s in visuals for v in (-1, -1, s)],
            linkPositions=[[0.0, 0.0, 0.0]] * links,
            linkOrientations=[[0.0, 0.0, 0.0, 1.0]] * links,
            linkInertialFramePositions=[[0.0, 0.0, 0.0]] * links,
            linkInertialFrameOrientations=[[0.0, 0.0, 0.0, 1.0]] * links,
            # pybullet's parent index: 0 the base, i link i - 1; each chain starts at the base
            linkParentIndices=[p for j in range(size) for p in (0, 3 * j + 1, 3 * j + 2)],
            linkJointTypes=[pb.JOINT_PRISMATIC, pb.JOINT_PRISMATIC, pb.JOINT_REVOLUTE] * size,
            linkJointAxis=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] * size,
            flags=pb.URDF_USE_SELF_COLLISION,  # robots of one body collide with each other
            physicsClientId=cid,
        )
        for link in range(-1, links):
            pb.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                              maxJointVelocity=MAX_JOINT_VELOCITY,
                              activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING,
                              physicsClientId=cid)
        for j, (_, _, i_t) in enumerate(inertia):
            # x, y inertia of the chassis are irrelevant (planar joints); I_t about z
            pb.changeDynamics(body, LINKS_PER_ROBOT * j + CHASSIS_LINK,
                              localInertiaDiagonal=[i_t, i_t, i_t], physicsClientId=cid)
        pb.setJointMotorControlArray(body, list(range(links)), pb.VELOCITY_CONTROL,
                                     forces=[0.0] * links, physicsClientId=cid)
        for j, k in enumerate(robots):
            for axis in range(LINKS_PER_ROBOT):
                pb.resetJointState(body, LINKS_PER_ROBOT * j + axis, self.q[k, axis],
                                   self.q_dot[k, axis], physicsClientId=cid)
        return body

    def _prism(self, poly: Polygon, gui: bool) -> int:
        """A static convex hull of ``poly`` extruded to the column height, margin 0."""
        cid, cx, cy = self._cid, *poly.centroid
        half = self._height / 2
        verts = [[x - cx, y - cy, z] for x, y in poly.vertices for z in (-half, half)]
        col = pb.createCollisionShape(pb.GEOM_MESH, vertices=verts, physicsClientId=cid)
        vis = -1
        if gui:
            vis = pb.createVisualShape(pb.GEOM_MESH, vertices=verts, rgbaColor=[0.8, 0.3, 0.2, 1.0],
                                       physicsClientId=cid)
        body = pb.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
                                  basePosition=[cx, cy, 0.0], physicsClientId=cid)
        pb.changeDynamics(body, -1, collisionMargin=0.0, physicsClientId=cid)
        return body

    # -- lifecycle ---------------------------------------------------------------
    def close(self) -> None:
        """Disconnect this plant's physics client (idempotent)."""
        self._finalizer()

    def __enter__(self) -> PybulletPlant:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- stepping ----------------------------------------------------------------
    def step(self, t: float, dt: float, torques: np.ndarray, v_cmd: np.ndarray) -> None:
        """Advance by dt with wheel torques u held; ``v_cmd`` is ignored. Torques of
        another shape, or not all finite, raise ValueError and change nothing (the
        kernel's first sub-step checks their values before Bullet is called); a closed
        plant raises RuntimeError."""
        if not self._finalizer.alive:  # a sub-step without Bullet would not notice
            raise RuntimeError("this plant is closed (its physics client disconnected)")
        u = np.ascontiguousarray(torques, dtype=float)
        if u.shape != self._wheel_torques.shape:
            raise ValueError(f"torques must be ({len(self._chassis)}, 4), got {u.shape}")
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError(f"dt must be positive and finite, got {dt}")
        cid = self._cid
        h = dt / self.substeps
        if h != self._h:
            pb.setPhysicsEngineParameter(fixedTimeStep=h, numSubSteps=1, physicsClientId=cid)
            self._h = h
        # new arrays each step (whoever kept the last state keeps it unchanged), written in
        # place by every sub-step: the kernel runs the sub-steps' loop, Bullet's calls
        # included (FleetDynamics.bullet_step: the forces in; where a body is near, Bullet's
        # joints caught up, its step, its contact points, its state read back after a
        # contact and at the end; elsewhere the free step computed, Bullet not called)
        q, qd = self.q.copy(), self.q_dot.copy()
        seen = self._law.step_in_bullet(self._bullet, self._bodies, u, self._other,
                                        self._wheel_torques, t, h, self.substeps, q, qd,
                                        *self._discs)
        if self._gui:  # the view shows Bullet's bodies
            self._law.catch_up_bullet(self._bullet, self._bodies, q, qd)
        for k, points in enumerate(seen):
            if points or self._ongoing:
                self._record_contacts(t + k * h, points)
        self.q, self.q_dot = q, qd

    def _record_contacts(self, ts: float, points: Sequence[tuple]) -> None:
        """Update the contact events from the points Bullet found at sub-step time ``ts``."""
        depth: dict[tuple[int, int], float] = {}
        ident = self._ident
        for point in points:
            a, b, dist = ident.get((point[1], point[3])), ident.get((point[2], point[4])), point[8]
            if a is None or b is None or dist > 0.0 or (a < 0 and b < 0):
                continue
            pair = _pair(a, b)
            depth[pair] = max(depth.get(pair, 0.0), -dist)
        for pair in [p for p in self._ongoing if p not in depth]:  # released
            k = self._ongoing.pop(pair)
            self.contacts[k] = replace(self.contacts[k], t_end=ts)
        for pair, d in depth.items():
            k = self._ongoing.get(pair)
            if k is None:
                self._ongoing[pair] = len(self.contacts)
                self.contacts.append(ContactEvent(ts, pair[0], pair[1], d))
            elif d > self.contacts[k].max_depth_m:
                self.contacts[k] = replace(self.contacts[k], max_depth_m=d)

    # -- sensing -----------------------------------------------------------------
    def perceive(self, i: int, detection_range_m: float) -> tuple[list[Body], list[Body]]:
        """(robots, obstacles) robot ``i`` senses: surface within r_det of its centre.

        The same rule and ordering as plant/perception.py ``sense``, decided by
        Bullet's closest-point queries between the collision shapes: body j is
        seen when surface-to-surface distance <= r_det - r_i (plus, for a point
        obstacle, the collision radius it was given, since the rule uses the
        scenario's radius 0). Positions, velocities and radii are the plant's
        state and the scenario's radii.
        """
        self._law.catch_up_bullet(self._bullet, self._bodies, self.q, self.q_dot)
        cid, (me, link) = self._cid, self._chassis[i]
        reach = float(detection_range_m) - self.robot_radii[i]
        robots: list[Body] = []
        for j, (body, other) in enumerate(self._chassis):
            if j != i and pb.getClosestPoints(me, body, reach, linkIndexA=link, linkIndexB=other,
                                              physicsClientId=cid):
                robots.append(Body(self.robot_ids[j], self.q[j, :2].copy(), self.q_dot[j, :2].copy(),
                                   self.robot_radii[j]))
        seen = [
            o for o, body, rc in zip(self.obstacles, self._obstacle_ids, self._collision_radius,
                                     strict=True)
            if pb.getClosestPoints(me, body, reach + float(o.radius) - rc, linkIndexA=link,
                                   physicsClientId=cid)
        ]
        x, y = self.q[i, :2].tolist()
        return robots, seen + shape_bodies(x, y, self.shapes, float(detection_range_m))


def _disconnect(cid: int) -> None:
    try:
        pb.disconnect(physicsClientId=cid)
    except pb.error:  # already gone
        pass
