"""Robots, obstacles and contacts in a pybullet world: the rigid-body plant.

Same interface as :class:`plant.model_plant.ModelPlant` (``q``, ``q_dot``,
``step``), plus what only a simulated world has: real collisions between robots
and obstacles (:attr:`PybulletPlant.contacts`) and sensing by geometric queries
(:meth:`PybulletPlant.perceive`).

Traction model: computed wheel forces on the chassis (DESIGN section 7)
-----------------------------------------------------------------------
Of the three options in DESIGN section 7 (explicit rollers, anisotropic
friction, computed wheel forces) this plant computes the wheel forces. Explicit
rollers need tiny time steps and are fragile at the paper's 50 m/s;
anisotropic friction cannot represent a driven wheel torque exactly. The wheels
are therefore not bodies: their effect on the chassis is computed from the
no-slip roller kinematics every physics sub-step and applied as generalised
forces, and Bullet integrates the chassis and resolves its contacts.

Bodies. Each robot is a Featherstone multibody with a fixed base at the world
origin and a planar chain: link 0 prismatic along world x, link 1 prismatic
along world y, link 2 revolute about z. The joint positions are exactly
q = [x, y, phi] and the joint velocities q_dot. Links 0 and 1 are massless and
have no collision shape; link 2 carries the chassis: a vertical cylinder of the
robot's radius and the inertia of M_q (plant/mecanum.py ``generalised_inertia``,
the wheel inertia reflected through the no-slip rollers)

    m_t = m + 4 I_w / R^2,   I_t = I_z + 4 I_w (l + w)^2 / R^2.          (P1)

With massless sliders the articulated inertia seen by the x and the y joints is
m_t and the one seen by the yaw joint is I_t, and the chassis centre of mass is
on the yaw axis, so Bullet's joint-space equation of motion is exactly

    M_q q_ddot = F + F_contact,   M_q = diag(m_t, m_t, I_t)              (P2)

with no Coriolis term (checked in tests/integration/test_pybullet_plant.py). Gravity is 0
(the joints are planar anyway); joint damping, link damping, the default
velocity motors and the joint velocity cap are all disabled, so F (ours) and
F_contact (Bullet's contact solver) are the only forces.

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

Stepping. ``step(t, dt, ...)`` calls stepSimulation ``substeps`` times with
fixedTimeStep h = dt / substeps; before each call the forces are recomputed from
the state Bullet returned (TORQUE_CONTROL forces last one stepSimulation), with
h_d evaluated at the sub-step's start time. Deterministic settings:
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
collide with robots and obstacles; a robot's base and sliders have no shape, so
nothing of a robot collides with itself. Contact friction and restitution are
Bullet's defaults (lateral friction 0.5, restitution 0); Bullet's contacts are
speculative (a pair within its contact threshold is kept from closing the gap),
so even a 50 m/s impact stops at the surface, and a resting contact settles
~1e-5 m deep (measured).

Contacts. After each sub-step the contact points of robot-robot and
robot-obstacle pairs are read (getContactPoints). Bullet's narrowphase runs at
the start of stepSimulation, so those points describe the configuration at the
sub-step's start time, and that is the time they are labelled with (so the state
at the end of a ``step`` is checked during the next one). A pair
touches when one of its points has distance <= 0. A :class:`ContactEvent`
starts when a pair goes from not touching to touching; its max_depth_m (the
largest penetration, metres, >= 0) grows while it lasts and t_end is the time of
the first sample at which the pair no longer touches. Robots are named by their
robot id, obstacles by their Body ident (-(k+1) for the scenario's k-th).
"""

from __future__ import annotations

import ctypes
import os
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from plant.bodies import Body
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

Disturbance = Callable[[float], np.ndarray]

MIN_COLLISION_RADIUS_M = 0.01  # collision radius of a point obstacle (scenario radius 0)
HEIGHT_PER_RADIUS = 4.0  # column height / largest radius: contact normals stay horizontal
MAX_JOINT_VELOCITY = 1e9  # Bullet clamps joint speeds at 100 by default; effectively no cap
CHASSIS_LINK = 2  # the link carrying the chassis shape and M_q's mass / yaw inertia
_JOINTS = [0, 1, 2]  # x slider, y slider, yaw


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
    (``wheel_torques`` = u + h_d) gives the (n,3) world-frame forces [F_x, F_y, M_z]."""

    def __init__(self, models: Sequence[MecanumModel]) -> None:
        self._fleet = FleetDynamics(list(models), "none", 0.0, (0.0,) * 4, 1)
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
    (n,3) world [x, y, phi] and their rates, read back from Bullet after every
    step; ``contacts`` lists every contact event so far.
    """

    kind = "pybullet"

    def __init__(
        self,
        models: Sequence[MecanumModel],
        q: np.ndarray,
        q_dot: np.ndarray,
        disturbance: Disturbance,
        robot_radii: Sequence[float],
        robot_ids: Sequence[int],
        obstacles: Sequence[Body],
        substeps: int = DEFAULT_SUBSTEPS,
        gui: bool = False,
        shapes: Sequence[Polygon] = (),
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
        self.contacts: list[ContactEvent] = []
        self._law = ForceLaw.from_models(self.models)
        self._h: float | None = None

        if gui and not os.environ.get("DISPLAY"):
            # pybullet's GUI would end the whole process on a failed X connection
            raise GuiUnavailable("--gui needs a display, and DISPLAY is not set")
        self._cid = pb.connect(pb.GUI if gui else pb.DIRECT)
        if self._cid < 0:
            raise RuntimeError("could not connect to a pybullet physics server")
        self._finalizer = weakref.finalize(self, _disconnect, self._cid)
        cid = self._cid
        pb.setGravity(0.0, 0.0, 0.0, physicsClientId=cid)
        pb.setPhysicsEngineParameter(numSubSteps=1, deterministicOverlappingPairs=1,
                                     physicsClientId=cid)

        radii = self.robot_radii + [o.radius for o in self.obstacles]
        self._height = HEIGHT_PER_RADIUS * max([MIN_COLLISION_RADIUS_M, *radii])
        shapes: dict[float, int] = {}

        def shape(radius: float) -> int:
            if radius not in shapes:
                shapes[radius] = pb.createCollisionShape(
                    pb.GEOM_CYLINDER, radius=radius, height=self._height, physicsClientId=cid)
            return shapes[radius]

        def visual(radius: float, rgba: list[float]) -> int:
            if not gui:
                return -1
            return pb.createVisualShape(pb.GEOM_CYLINDER, radius=radius, length=self._height,
                                        rgbaColor=rgba, physicsClientId=cid)

        self._robots: list[int] = []
        for k, model in enumerate(self.models):
            m_t, _, i_t = np.diag(generalised_inertia(model.params))  # (P1)
            r = self.robot_radii[k]
            body = pb.createMultiBody(
                baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=-1,
                basePosition=[0.0, 0.0, 0.0],
                linkMasses=[0.0, 0.0, float(m_t)],
                linkCollisionShapeIndices=[-1, -1, shape(r)],
                linkVisualShapeIndices=[-1, -1, visual(r, [0.2, 0.4, 0.9, 1.0])],
                linkPositions=[[0.0, 0.0, 0.0]] * 3,
                linkOrientations=[[0.0, 0.0, 0.0, 1.0]] * 3,
                linkInertialFramePositions=[[0.0, 0.0, 0.0]] * 3,
                linkInertialFrameOrientations=[[0.0, 0.0, 0.0, 1.0]] * 3,
                linkParentIndices=[0, 1, 2],
                linkJointTypes=[pb.JOINT_PRISMATIC, pb.JOINT_PRISMATIC, pb.JOINT_REVOLUTE],
                linkJointAxis=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                physicsClientId=cid,
            )
            for link in (-1, *_JOINTS):
                pb.changeDynamics(body, link, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                                  maxJointVelocity=MAX_JOINT_VELOCITY,
                                  activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING,
                                  physicsClientId=cid)
            # x, y inertia of the chassis are irrelevant (planar joints); I_t about z
            pb.changeDynamics(body, CHASSIS_LINK, localInertiaDiagonal=[i_t, i_t, i_t],
                              physicsClientId=cid)
            pb.setJointMotorControlArray(body, _JOINTS, pb.VELOCITY_CONTROL, forces=[0.0] * 3,
                                         physicsClientId=cid)
            for j in _JOINTS:
                pb.resetJointState(body, j, self.q[k, j], self.q_dot[k, j], physicsClientId=cid)
            self._robots.append(body)

        self._obstacle_ids: list[int] = []
        self._collision_radius: list[float] = []
        for o in self.obstacles:
            r = max(float(o.radius), MIN_COLLISION_RADIUS_M)
            x, y = (float(v) for v in o.position)
            self._obstacle_ids.append(pb.createMultiBody(
                baseMass=0.0, baseCollisionShapeIndex=shape(r),
                baseVisualShapeIndex=visual(r, [0.8, 0.3, 0.2, 1.0]),
                basePosition=[x, y, 0.0], physicsClientId=cid,
            ))
            self._collision_radius.append(r)
        self._shape_ids = [self._prism(poly, gui) for poly in self.shapes]

        # pybullet body id -> scenario ident (robot id, or obstacle ident)
        self._ident = {b: rid for b, rid in zip(self._robots, self.robot_ids, strict=True)}
        self._ident.update({b: o.ident for b, o in zip(self._obstacle_ids, self.obstacles, strict=True)})
        self._ident.update({b: p.ident for b, p in zip(self._shape_ids, self.shapes, strict=True)})
        self._ongoing: dict[tuple[int, int], int] = {}  # pair -> index in self.contacts

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
        """Advance by dt with wheel torques u held; ``v_cmd`` is ignored."""
        u = np.asarray(torques, dtype=float)
        if u.shape != (len(self._robots), 4):
            raise ValueError(f"torques must be ({len(self._robots)}, 4), got {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError("torques must be finite")
        if not (dt > 0.0 and np.isfinite(dt)):
            raise ValueError(f"dt must be positive and finite, got {dt}")
        cid = self._cid
        h = dt / self.substeps
        if h != self._h:
            pb.setPhysicsEngineParameter(fixedTimeStep=h, numSubSteps=1, physicsClientId=cid)
            self._h = h
        q, qd = self.q, self.q_dot
        for k in range(self.substeps):
            ts = t + k * h
            forces = self._law(q, qd, u + self.disturbance(ts))  # (P3)-(P5)
            for body, f in zip(self._robots, forces.tolist(), strict=True):
                pb.setJointMotorControlArray(body, _JOINTS, pb.TORQUE_CONTROL, forces=f,
                                             physicsClientId=cid)
            pb.stepSimulation(physicsClientId=cid)
            q, qd = self._read_state()
            self._record_contacts(ts)
        self.q, self.q_dot = q, qd

    def _read_state(self) -> tuple[np.ndarray, np.ndarray]:
        cid = self._cid
        q, qd = [], []
        for body in self._robots:
            (x, vx, *_), (y, vy, *_), (phi, w, *_) = pb.getJointStates(body, _JOINTS,
                                                                      physicsClientId=cid)
            q.append((x, y, phi))
            qd.append((vx, vy, w))
        return np.array(q), np.array(qd)

    def _record_contacts(self, ts: float) -> None:
        """Update the contact events from the points Bullet found at sub-step time ``ts``."""
        depth: dict[tuple[int, int], float] = {}
        for point in pb.getContactPoints(physicsClientId=self._cid):
            a, b, dist = self._ident.get(point[1]), self._ident.get(point[2]), point[8]
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
        cid, me = self._cid, self._robots[i]
        reach = float(detection_range_m) - self.robot_radii[i]
        robots: list[Body] = []
        for j, body in enumerate(self._robots):
            if j != i and pb.getClosestPoints(me, body, reach, linkIndexA=CHASSIS_LINK,
                                              linkIndexB=CHASSIS_LINK, physicsClientId=cid):
                robots.append(Body(self.robot_ids[j], self.q[j, :2].copy(), self.q_dot[j, :2].copy(),
                                   self.robot_radii[j]))
        seen = [
            o for o, body, rc in zip(self.obstacles, self._obstacle_ids, self._collision_radius,
                                     strict=True)
            if pb.getClosestPoints(me, body, reach + float(o.radius) - rc, linkIndexA=CHASSIS_LINK,
                                   physicsClientId=cid)
        ]
        x, y = self.q[i, :2].tolist()
        return robots, seen + shape_bodies(x, y, self.shapes, float(detection_range_m))


def _disconnect(cid: int) -> None:
    try:
        pb.disconnect(physicsClientId=cid)
    except pb.error:  # already gone
        pass
