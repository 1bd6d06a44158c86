"""The run's state at one step as ROS 2 messages (pure: from the run's time series to
``rosbags`` message objects; deploy/ros2/gateway.py puts them on the wire).

Frames: ``world`` (the scenario's plane, z up), ``robot_N/base_link`` (robot N: x forward,
as psi measures), ``leader``. Conventions are REP 103/105's, which nav2 and RViz assume:
an Odometry's pose is in ``world`` and its twist in the robot's own ``base_link`` (the
world-frame velocity q_dot rotated by -psi); a ``cmd_vel`` is body-frame too (the fused
velocity command v_d of eq. (26), the series' v_cmd, rotated the same way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from deploy.ros2.types import make

WORLD_FRAME = "world"
LEADER_FRAME = "leader"
WHEELS = 4
ODOM, CMD_VEL, JOINTS = "nav_msgs/msg/Odometry", "geometry_msgs/msg/TwistStamped", \
    "sensor_msgs/msg/JointState"
POSE, TF, MARKERS = "geometry_msgs/msg/PoseStamped", "tf2_msgs/msg/TFMessage", \
    "visualization_msgs/msg/MarkerArray"
STATUS, CLOCK, TWIST = "diagnostic_msgs/msg/DiagnosticArray", "rosgraph_msgs/msg/Clock", \
    "geometry_msgs/msg/Twist"
OBSTACLE_HEIGHT_M = 1.0
MIN_DRAWN_RADIUS_M = 0.15  # a point obstacle is drawn this big (as in the figures)


def base_link(rid: int) -> str:
    return f"robot_{rid}/base_link"


def wheel_names(rid: int) -> list[str]:
    """Wheels in the order of the rows of P, eq. (2) (the recording's torque order)."""
    return [f"robot_{rid}/wheel_{w + 1}" for w in range(WHEELS)]


def stamp(ns: int) -> Any:
    return make("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000,
                nanosec=ns % 1_000_000_000)


def header(ns: int, frame: str) -> Any:
    return make("std_msgs/msg/Header", stamp=stamp(ns), frame_id=frame)


def _quaternion(psi: float) -> Any:
    return make("geometry_msgs/msg/Quaternion", z=math.sin(psi / 2), w=math.cos(psi / 2))


def _pose(x: float, y: float, psi: float) -> Any:
    return make("geometry_msgs/msg/Pose", position=make("geometry_msgs/msg/Point", x=x, y=y),
                orientation=_quaternion(psi))


def _twist(vx: float, vy: float, wz: float) -> Any:
    return make(TWIST, linear=make("geometry_msgs/msg/Vector3", x=vx, y=vy),
                angular=make("geometry_msgs/msg/Vector3", z=wz))


def body_frame(psi: float, v_world: np.ndarray) -> tuple[float, float, float]:
    """T(psi)^T v, eq. (3): a world-frame [x_dot, y_dot, psi_dot] in the body frame."""
    c, s = math.cos(psi), math.sin(psi)
    return (c * v_world[0] + s * v_world[1], -s * v_world[0] + c * v_world[1], float(v_world[2]))


def odometry(rid: int, ns: int, q: np.ndarray, q_dot: np.ndarray) -> Any:
    psi = float(q[2])
    return make(ODOM, header=header(ns, WORLD_FRAME), child_frame_id=base_link(rid),
                pose=make("geometry_msgs/msg/PoseWithCovariance",
                          pose=_pose(float(q[0]), float(q[1]), psi)),
                twist=make("geometry_msgs/msg/TwistWithCovariance",
                           twist=_twist(*body_frame(psi, q_dot))))


def cmd_vel(rid: int, ns: int, psi: float, v_cmd: np.ndarray) -> Any:
    return make(CMD_VEL, header=header(ns, base_link(rid)),
                twist=_twist(*body_frame(psi, v_cmd)))


def joint_states(rid: int, ns: int, angle: np.ndarray, speed: np.ndarray,
                 torque: np.ndarray) -> Any:
    return make(JOINTS, header=header(ns, base_link(rid)), name=wheel_names(rid),
                position=np.array(angle, np.float64), velocity=np.array(speed, np.float64),
                effort=np.array(torque, np.float64))  # copies: never the caller's arrays


def leader_pose(ns: int, q0: np.ndarray) -> Any:
    return make(POSE, header=header(ns, WORLD_FRAME),
                pose=_pose(float(q0[0]), float(q0[1]), float(q0[2])))


def _transform(ns: int, child: str, q: np.ndarray) -> Any:
    return make("geometry_msgs/msg/TransformStamped", header=header(ns, WORLD_FRAME),
                child_frame_id=child, transform=make(
                    "geometry_msgs/msg/Transform",
                    translation=make("geometry_msgs/msg/Vector3", x=float(q[0]), y=float(q[1])),
                    rotation=_quaternion(float(q[2]))))


def transforms(ns: int, robot_ids: list[int], q: np.ndarray, q0: np.ndarray) -> Any:
    """world -> each robot_N/base_link, and world -> leader."""
    return make(TF, transforms=[_transform(ns, base_link(r), q[i]) for i, r in
                                enumerate(robot_ids)] + [_transform(ns, LEADER_FRAME, q0)])


def clock(ns: int) -> Any:
    return make(CLOCK, clock=stamp(ns))


@dataclass(frozen=True)
class ObstacleShapes:
    discs: list[tuple[float, float, float]]  # x, y, radius
    polygons: list[list[tuple[float, float]]]  # walls and polygons, their vertices


def obstacle_markers(ns: int, shapes: ObstacleShapes) -> Any:
    """Discs as cylinders, walls and polygons as closed outlines (LINE_STRIP), in world."""
    grey = make("std_msgs/msg/ColorRGBA", r=0.3, g=0.3, b=0.3, a=1.0)
    markers = []
    for j, (x, y, r) in enumerate(shapes.discs):
        d = 2 * max(r, MIN_DRAWN_RADIUS_M)
        markers.append(make(
            "visualization_msgs/msg/Marker", header=header(ns, WORLD_FRAME), ns="obstacles",
            id=j + 1, type=3, action=0, color=grey,
            pose=make("geometry_msgs/msg/Pose",
                      position=make("geometry_msgs/msg/Point", x=x, y=y, z=OBSTACLE_HEIGHT_M / 2),
                      orientation=_quaternion(0.0)),
            scale=make("geometry_msgs/msg/Vector3", x=d, y=d, z=OBSTACLE_HEIGHT_M)))
    for j, vertices in enumerate(shapes.polygons):
        ring = [*vertices, vertices[0]]
        markers.append(make(
            "visualization_msgs/msg/Marker", header=header(ns, WORLD_FRAME), ns="obstacles",
            id=len(shapes.discs) + j + 1, type=4, action=0, color=grey,
            pose=make("geometry_msgs/msg/Pose", orientation=_quaternion(0.0)),
            scale=make("geometry_msgs/msg/Vector3", x=0.05),
            points=[make("geometry_msgs/msg/Point", x=float(px), y=float(py)) for px, py in ring]))
    return make(MARKERS, markers=markers)


LEVELS = {"ok": 0, "warn": 1, "error": 2, "stale": 3}


def status(ns: int, entries: list[tuple[str, str, str, dict[str, str]]]) -> Any:
    """``entries``: (name, level in LEVELS, message, values)."""
    return make(STATUS, header=header(ns, ""), status=[
        make("diagnostic_msgs/msg/DiagnosticStatus", level=LEVELS[level], name=name,
             message=message, hardware_id=name,
             values=[make("diagnostic_msgs/msg/KeyValue", key=k, value=v)
                     for k, v in values.items()])
        for name, level, message, values in entries])


class FleetFrames:
    """The run's rows as ROS 2 messages, newest row by newest row: the wheel angles are
    summed over every row since the last sum (the series holds them all), and only when a
    row's joint states are built, so a row's joint positions do not depend on which rows
    were published before it, and nobody watching the wheels costs no sum.

    ``robot_ids``, ``dt``: the run's; ``wheels_of_twist``: (1/R) P of eq. (1), 4 x 3."""

    def __init__(self, robot_ids: list[int], dt: float, wheels_of_twist: np.ndarray) -> None:
        self.robot_ids, self.dt = list(robot_ids), dt
        self.wheels_of_twist = wheels_of_twist
        self.wheel_angle = np.zeros((len(self.robot_ids), WHEELS))
        self.wheel_speed = np.zeros((len(self.robot_ids), WHEELS))
        self.last = -1  # the newest row summed

    def advance(self, ts: Any, k: int) -> None:
        """Sum the wheels' turns over rows last+1..k: theta_dot = (1/R) P T(psi)^T q_dot,
        eq. (1), the rectangle rule at the run's dt."""
        rows = slice(self.last + 1, k + 1)
        q, q_dot = ts.q[rows], ts.q_dot[rows]
        c, s = np.cos(q[..., 2]), np.sin(q[..., 2])
        body = np.stack([c * q_dot[..., 0] + s * q_dot[..., 1],
                         -s * q_dot[..., 0] + c * q_dot[..., 1], q_dot[..., 2]], axis=-1)
        speeds = body @ self.wheels_of_twist.T  # (rows, n, 4)
        if len(speeds):
            self.wheel_angle += speeds.sum(axis=0) * self.dt
            self.wheel_speed = speeds[-1]
        self.last = max(self.last, k)

    def messages(self, ts: Any, k: int, ns: int,
                 wanted: Any = lambda _topic: True) -> list[tuple[str, Any]]:
        """(topic relative to the namespace, message) of row ``k``, stamped ``ns``; only
        the topics ``wanted`` says yes to are built. /clock, /obstacles and /fleet/status
        are the caller's."""
        out: list[tuple[str, Any]] = []
        q, q_dot, q0 = ts.q[k], ts.q_dot[k], ts.leader_q[k]
        for i, rid in enumerate(self.robot_ids):
            if wanted(f"robot_{rid}/odom"):
                out.append((f"robot_{rid}/odom", odometry(rid, ns, q[i], q_dot[i])))
            if wanted(f"robot_{rid}/cmd_vel"):
                out.append((f"robot_{rid}/cmd_vel", cmd_vel(rid, ns, float(q[i, 2]),
                                                            ts.v_cmd[k, i])))
            if wanted(f"robot_{rid}/joint_states"):
                if self.last < k:
                    self.advance(ts, k)
                out.append((f"robot_{rid}/joint_states", joint_states(
                    rid, ns, self.wheel_angle[i], self.wheel_speed[i], ts.torque[k, i])))
        if wanted("leader/pose"):
            out.append(("leader/pose", leader_pose(ns, q0)))
        if wanted("tf"):
            out.append(("tf", transforms(ns, self.robot_ids, q, q0)))
        return out


_STAMP = ["header.stamp.sec", "header.stamp.nanosec"]
_XY_YAW = ["position.x", "position.y", "orientation.z", "orientation.w"]
_TWIST = ["linear.x", "linear.y", "angular.z"]


def _sec_ns(ns: int) -> tuple[int, int]:
    return ns // 1_000_000_000, ns % 1_000_000_000


class EncodedFrames(FleetFrames):
    """:class:`FleetFrames` whose messages come as CDR bytes, packed into layouts rosbags
    made (deploy/ros2/fixed_layout.py): equal, byte for byte, to ``encode`` of
    :meth:`FleetFrames.messages` (tests/unit/test_ros2_graph.py), ~3 µs a message
    instead of ~40."""

    def __init__(self, robot_ids: list[int], dt: float, wheels_of_twist: np.ndarray) -> None:
        super().__init__(robot_ids, dt, wheels_of_twist)
        from deploy.ros2.fixed_layout import FixedLayout

        z3, z4 = np.zeros(3), np.zeros(WHEELS)
        n = len(self.robot_ids)
        self.odom = {r: FixedLayout(odometry(r, 0, z3, z3), _STAMP + [
            f"pose.pose.{f}" for f in _XY_YAW] + [f"twist.twist.{f}" for f in _TWIST],
            "iIddddddd") for r in self.robot_ids}
        self.cmd = {r: FixedLayout(cmd_vel(r, 0, 0.0, z3), _STAMP + [
            f"twist.{f}" for f in _TWIST], "iIddd") for r in self.robot_ids}
        self.joints = {r: FixedLayout(joint_states(r, 0, z4, z4, z4), _STAMP + [
            f"{c}[{w}]" for c in ("position", "velocity", "effort") for w in range(WHEELS)],
            "iI" + "d" * 3 * WHEELS) for r in self.robot_ids}
        self.pose = FixedLayout(leader_pose(0, z3), _STAMP + [f"pose.{f}" for f in _XY_YAW],
                                "iIdddd")
        self.tf = FixedLayout(transforms(0, self.robot_ids, np.zeros((n, 3)), z3), [
            f"transforms[{i}].{f}" for i in range(n + 1) for f in _STAMP + [
                "transform.translation.x", "transform.translation.y",
                "transform.rotation.z", "transform.rotation.w"]], "iIdddd" * (n + 1))
        self.clock_layout = FixedLayout(clock(0), ["clock.sec", "clock.nanosec"], "iI")

    def clock_bytes(self, ns: int) -> bytes:
        return self.clock_layout.pack(*_sec_ns(ns))

    def encoded(self, ts: Any, k: int, ns: int,
                wanted: Any = lambda _topic: True) -> list[tuple[str, str, bytes]]:
        """(topic relative to the namespace, type, CDR bytes) of row ``k``: what
        :meth:`FleetFrames.messages` gives, encoded. The row is read as Python floats
        once (``tolist``) and the body frame of eq. (3) computed on them, the same
        operations in the same order as :func:`body_frame`: numpy's per-element indexing
        and scalar arithmetic cost ~30 µs a message after the launcher's 50 ms sleep."""
        out: list[tuple[str, str, bytes]] = []
        sec, nsec = _sec_ns(ns)
        q, q_dot, v_cmd = ts.q[k].tolist(), ts.q_dot[k].tolist(), ts.v_cmd[k].tolist()
        wheels: tuple[list, list, list] | None = None
        sin, cos = math.sin, math.cos
        for i, rid in enumerate(self.robot_ids):
            x, y, psi = q[i]
            c, s = cos(psi), sin(psi)
            if wanted(f"robot_{rid}/odom"):
                vx, vy, w = q_dot[i]
                out.append((f"robot_{rid}/odom", ODOM, self.odom[rid].pack(
                    sec, nsec, x, y, sin(psi / 2), cos(psi / 2),
                    c * vx + s * vy, -s * vx + c * vy, w)))
            if wanted(f"robot_{rid}/cmd_vel"):
                vx, vy, w = v_cmd[i]
                out.append((f"robot_{rid}/cmd_vel", CMD_VEL, self.cmd[rid].pack(
                    sec, nsec, c * vx + s * vy, -s * vx + c * vy, w)))
            if wanted(f"robot_{rid}/joint_states"):
                if wheels is None:
                    if self.last < k:
                        self.advance(ts, k)
                    wheels = (self.wheel_angle.tolist(), self.wheel_speed.tolist(),
                              ts.torque[k].tolist())
                angle, speed, torque = wheels
                out.append((f"robot_{rid}/joint_states", JOINTS, self.joints[rid].pack(
                    sec, nsec, *angle[i], *speed[i], *torque[i])))
        x0, y0, psi0 = ts.leader_q[k].tolist()
        if wanted("leader/pose"):
            out.append(("leader/pose", POSE, self.pose.pack(
                sec, nsec, x0, y0, sin(psi0 / 2), cos(psi0 / 2))))
        if wanted("tf"):
            values: list[float] = []
            for x, y, psi in (*q, (x0, y0, psi0)):
                values += [sec, nsec, x, y, sin(psi / 2), cos(psi / 2)]
            out.append(("tf", TF, self.tf.pack(*values)))
        return out


def robot_status(ts: Any, k: int, t_s: float, robot_ids: list[int], prefix: str,
                 misses: Any = None) -> list[tuple[str, str, str, dict[str, str]]]:
    """Each agent's health at row ``k`` (time ``t_s``), as :func:`status` takes it;
    ``misses``: each agent's deadline misses so far (None: not known, in process)."""
    out = []
    for i, rid in enumerate(robot_ids):
        nonfinite, infeasible = bool(ts.nonfinite[k, i]), bool(ts.safety_infeasible[k, i])
        level = "error" if nonfinite else "warn" if infeasible else "ok"
        message = ("the law gave a non-finite value: torques zeroed" if nonfinite else
                   "no command met every barrier" if infeasible else "running")
        out.append((f"{prefix}/agent_{rid}", level, message, {
            "t_s": f"{t_s:.3f}", "speed_factor": f"{ts.speed_factor[k, i]:.3f}",
            "input_age_s": f"{ts.input_age[k, i]:.4f}",
            "safety_filter_dv_mps": f"{ts.safety_dv[k, i]:.4f}",
            "active_behaviours": str(ts.order[k, i]),
            **({} if misses is None else {"deadline_misses": str(int(misses[i]))})}))
    return out


def obstacle_shapes_of(sc: Any) -> ObstacleShapes:
    """A scenario's discs, walls and polygons."""
    return ObstacleShapes(
        discs=[(float(o.position[0]), float(o.position[1]), float(o.radius_m))
               for o in sc.spec.obstacles],
        polygons=[[tuple(map(float, v)) for v in p.vertices] for p in sc.obstacle_shapes()])


def frames_for(sc: Any) -> EncodedFrames:
    model = sc.model()
    return EncodedFrames(list(sc.robot_ids), sc.dt, model.P / model.params.wheel_radius_m)
