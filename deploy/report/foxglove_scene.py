"""A run's step k as Foxglove messages: the scene and the frames.

Pure: (Scenario, TimeSeries, k) in, messages out, no I/O. The recorder writes
them into the run's MCAP, the live view serves them over Foxglove's WebSocket
protocol (topic names: ``deploy/report/foxglove_topics.py``; the plot signals:
``deploy/report/foxglove_plots.py``). Built only from the time series and the
scenario, so it does not depend on the shape of the wire.

Scene (``foxglove.SceneUpdate``, frame ``world``, z up, the plane z = 0):

- ``/scene/obstacles``: each obstacle as a cylinder of its radius (at least
  ``MIN_DRAWN_RADIUS_M``: the paper's obstacles are points), its R_a ring
  (radius + ``obstacle_safe_distance_m``, as in Fig. 4); each wall and polygon as
  its prism (triangles, 1 m tall) and outline, with its R_a band (the curve at R_a
  from its surface);
- ``/scene/robots``: each robot as a disc of its body radius with an arrow for
  its heading, and the virtual leader;
- ``/scene/formation``: each robot's desired formation position x_fd of
  eq. (16) (as its agent estimates it) as a ghost disc, joined to the robot;
- ``/scene/behaviors``: around each robot, the R_a ring while its FOCB is
  active and the R_c ring while its FRCB is active (replaced every update);
- ``/scene/traces``: the paths travelled so far (robots and leader).

Frames: ``/tf`` (``FrameTransforms``: world -> ``robot-<id>``, world ->
``leader``), ``/robots/poses`` (``PosesInFrame``), ``/leader/pose``
(``PoseInFrame``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CylinderPrimitive,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    TextPrimitive,
    Timestamp,
    TriangleListPrimitive,
    Vector3,
)

from deploy.contract.scenario import Scenario
from deploy.report.foxglove_topics import (
    LEADER_FRAME,
    LEADER_POSE_TOPIC,
    POSES_TOPIC,
    SCENE_BEHAVIORS,
    SCENE_FORMATION,
    SCENE_OBSTACLES,
    SCENE_ROBOTS,
    SCENE_TRACES,
    TF_TOPIC,
    WORLD_FRAME,
    robot_frame,
    stride,
)
from deploy.report.palette import COLORS
from deploy.report.timeseries import BEHAVIOR_BITS, TimeSeries
from plant.shapes import Polygon, offset_outline

TRACE_STEP_S = 0.05  # one trace point per 50 ms of the run (the recent part, live)
TRACE_RECENT_S = 2.0  # live: the last 2 s at TRACE_STEP_S, older history coarser
MIN_DRAWN_RADIUS_M = 0.15  # a point obstacle is drawn this big (as in figures.py)
ROBOT_HEIGHT_M = 0.25
LEADER_COLOR = "#1f3fbf"


@dataclass(frozen=True)
class _Static:
    ids: list[int]
    radius: float
    obstacles: np.ndarray  # (m, 2)
    obstacle_radii: np.ndarray  # (m,)
    r_a: float
    r_c: float
    shapes: tuple[Polygon, ...] = ()  # walls and polygons


class FleetScene:
    """Turns rows of a run's time series into scene and frame messages."""

    def __init__(self, sc: Scenario, trace_history_step_s: float = TRACE_STEP_S,
                 stamp_offset_ns: int = 0) -> None:
        """``trace_history_step_s``: spacing of trace points older than
        ``TRACE_RECENT_S`` (a live view keeps its scenes small with a coarser one);
        ``stamp_offset_ns``: added to t in the messages' own stamps (the wall clock
        at t = 0 when the file's log time is the wall clock)."""
        s = sc.spec
        self.sc = sc
        self.st = _Static(
            ids=list(sc.robot_ids), radius=s.robot.body_radius_m,
            obstacles=np.array([o.position for o in s.obstacles], float).reshape(-1, 2),
            obstacle_radii=np.array([o.radius_m for o in s.obstacles], float),
            r_a=s.behaviors.obstacle_safe_distance_m, r_c=s.behaviors.robot_safe_distance_m,
            shapes=tuple(sc.obstacle_shapes()))
        self.stamp_offset_ns = stamp_offset_ns
        self.trace_stride = stride(sc, 1.0 / TRACE_STEP_S)
        self.history_stride = stride(sc, 1.0 / trace_history_step_s)
        self.recent_steps = int(round(TRACE_RECENT_S / sc.dt))
        self._obstacle_entities = self._obstacles()
        # per path (robot frame or the leader's): its points by row, built once for the
        # series they come from (each scene's trace re-sends the path so far: built anew
        # every scene, the points cost O(k) each time, ~1 s for paper's 720 scenes)
        self._points: dict[str, tuple[TimeSeries, list[Point3 | None]]] = {}

    def time(self, k: int) -> float:
        return k * self.sc.dt

    # -- scene ------------------------------------------------------------------------
    def scene_messages(self, ts: TimeSeries, k: int) -> dict[str, object]:
        """Every scene and frame topic at step k (rows 0..k must be filled)."""
        stamp = _stamp(self.time(k), self.stamp_offset_ns)
        q = ts.q[k]
        ok = np.isfinite(q).all(axis=1)
        out: dict[str, object] = {
            SCENE_OBSTACLES: SceneUpdate(entities=self._obstacle_entities),
            SCENE_ROBOTS: SceneUpdate(entities=[
                *(self._robot(rid, i, q[i], stamp) for i, rid in enumerate(self.st.ids) if ok[i]),
                *self._leader(ts.leader_q[k], stamp)]),
            SCENE_FORMATION: SceneUpdate(entities=[
                self._desired(rid, i, q[i], ts.q_fd[k, i], stamp)
                for i, rid in enumerate(self.st.ids)
                if ok[i] and np.isfinite(ts.q_fd[k, i]).all()]),
            SCENE_BEHAVIORS: SceneUpdate(
                deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)],
                entities=[e for i, rid in enumerate(self.st.ids) if ok[i]
                          for e in self._behaviors(rid, i, q[i], int(ts.active[k, i]), stamp)]),
            SCENE_TRACES: SceneUpdate(entities=self._traces(ts, k, stamp)),
        }
        poses = [_pose(q[i]) for i in range(len(self.st.ids)) if ok[i]]
        transforms = [FrameTransform(timestamp=stamp, parent_frame_id=WORLD_FRAME,
                                     child_frame_id=robot_frame(rid), translation=_vec(q[i]),
                                     rotation=_yaw(q[i][2]))
                      for i, rid in enumerate(self.st.ids) if ok[i]]
        lq = ts.leader_q[k]
        if np.isfinite(lq).all():
            transforms.append(FrameTransform(
                timestamp=stamp, parent_frame_id=WORLD_FRAME, child_frame_id=LEADER_FRAME,
                translation=_vec(lq), rotation=_yaw(lq[2])))
            out[LEADER_POSE_TOPIC] = PoseInFrame(timestamp=stamp, frame_id=WORLD_FRAME,
                                                 pose=_pose(lq))
        out[TF_TOPIC] = FrameTransforms(transforms=transforms)
        out[POSES_TOPIC] = PosesInFrame(timestamp=stamp, frame_id=WORLD_FRAME, poses=poses)
        return out

    def _obstacles(self) -> list[SceneEntity]:
        st, grey, ring = self.st, _color("#4d4d4d"), _color("#4d4d4d", 0.6)
        out = []
        for j, (p, r) in enumerate(zip(st.obstacles, st.obstacle_radii, strict=True)):
            drawn = max(float(r), MIN_DRAWN_RADIUS_M)
            out.append(SceneEntity(
                frame_id=WORLD_FRAME, id=f"obstacle-{j + 1}",
                cylinders=[CylinderPrimitive(
                    pose=_pose((p[0], p[1], 0.0), z=0.5), size=Vector3(x=2 * drawn, y=2 * drawn, z=1.0),
                    bottom_scale=1.0, top_scale=1.0, color=grey)],
                lines=[_ring(p, float(r) + st.r_a, ring, dashed=True)],
                texts=[_label((p[0], p[1]), f"o{j + 1}", grey)]))
        for poly in st.shapes:
            out.append(SceneEntity(
                frame_id=WORLD_FRAME, id=f"obstacle-{-poly.ident}",
                triangles=[_prism(poly, 1.0, grey)],
                lines=[_outline(poly.array, ring, z=1.0),
                       _outline(offset_outline(poly, st.r_a), ring, z=0.02, dashed=True)],
                texts=[_label(poly.centroid, poly.name, grey)]))
        return out

    def _robot(self, rid: int, i: int, q: np.ndarray, stamp: Timestamp) -> SceneEntity:
        r, c = self.st.radius, _color(COLORS[i % len(COLORS)])
        return SceneEntity(
            timestamp=stamp, frame_id=WORLD_FRAME, id=robot_frame(rid),
            cylinders=[CylinderPrimitive(pose=_pose(q, z=ROBOT_HEIGHT_M / 2),
                                         size=Vector3(x=2 * r, y=2 * r, z=ROBOT_HEIGHT_M),
                                         bottom_scale=1.0, top_scale=1.0, color=c)],
            arrows=[ArrowPrimitive(pose=_pose(q, z=ROBOT_HEIGHT_M + 0.05), shaft_length=1.2 * r,
                                   shaft_diameter=0.15 * r, head_length=0.5 * r,
                                   head_diameter=0.4 * r, color=_color("#222222"))],
            texts=[_label(q, str(rid), c, dz=ROBOT_HEIGHT_M + 0.6)])

    def _leader(self, lq: np.ndarray, stamp: Timestamp) -> list[SceneEntity]:
        if not np.isfinite(lq).all():
            return []
        r, c = 0.6 * self.st.radius, _color(LEADER_COLOR)
        return [SceneEntity(
            timestamp=stamp, frame_id=WORLD_FRAME, id="leader",
            cylinders=[CylinderPrimitive(pose=_pose(lq, z=0.05), size=Vector3(x=2 * r, y=2 * r, z=0.1),
                                         bottom_scale=1.0, top_scale=1.0, color=c)],
            arrows=[ArrowPrimitive(pose=_pose(lq, z=0.15), shaft_length=2 * r, shaft_diameter=0.2 * r,
                                   head_length=0.8 * r, head_diameter=0.6 * r, color=c)],
            texts=[_label(lq, "leader", c, dz=0.8)])]

    def _desired(self, rid: int, i: int, q: np.ndarray, q_fd: np.ndarray,
                 stamp: Timestamp) -> SceneEntity:
        r, col = self.st.radius, COLORS[i % len(COLORS)]
        return SceneEntity(
            timestamp=stamp, frame_id=WORLD_FRAME, id=f"desired-{rid}",
            cylinders=[CylinderPrimitive(pose=_pose(q_fd, z=0.01), size=Vector3(x=2 * r, y=2 * r, z=0.02),
                                         bottom_scale=1.0, top_scale=1.0, color=_color(col, 0.3))],
            lines=[LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=2.0,
                                 scale_invariant=True, color=_color(col, 0.6),
                                 points=[_point(q, 0.02), _point(q_fd, 0.02)])])

    def _behaviors(self, rid: int, i: int, q: np.ndarray, active: int,
                   stamp: Timestamp) -> list[SceneEntity]:
        col, out = COLORS[i % len(COLORS)], []
        if active & BEHAVIOR_BITS["FOCB"]:
            out.append(SceneEntity(timestamp=stamp, frame_id=WORLD_FRAME, id=f"focb-{rid}",
                                   lines=[_ring(q, self.st.r_a, _color(col, 0.9))],
                                   texts=[_label((q[0] + self.st.r_a, q[1]), "FOCB R_a", _color(col))]))
        if active & BEHAVIOR_BITS["FRCB"]:
            out.append(SceneEntity(timestamp=stamp, frame_id=WORLD_FRAME, id=f"frcb-{rid}",
                                   lines=[_ring(q, self.st.r_c, _color(col, 0.9), dashed=True)],
                                   texts=[_label((q[0] - self.st.r_c, q[1]), "FRCB R_c", _color(col))]))
        return out

    def _trace_rows(self, k: int) -> np.ndarray:
        """Rows of the trace up to k: fine for the last TRACE_RECENT_S, the
        history at its own spacing (the same as the recent part by default)."""
        split = max(0, k - self.recent_steps)
        split -= split % self.history_stride
        return np.r_[np.arange(0, split, self.history_stride),
                     np.arange(split, k, self.trace_stride), k]

    def _traces(self, ts: TimeSeries, k: int, stamp: Timestamp) -> list[SceneEntity]:
        rows = self._trace_rows(k)
        out = []
        paths = [(robot_frame(rid), ts.q[:, i], COLORS[i % len(COLORS)])
                 for i, rid in enumerate(self.st.ids)]
        paths.append((LEADER_FRAME, ts.leader_q, LEADER_COLOR))
        for name, path, col in paths:
            every = self._points_of(name, ts, path, k)
            pts = [p for p in map(every.__getitem__, rows.tolist()) if p is not None]
            out.append(SceneEntity(
                timestamp=stamp, frame_id=WORLD_FRAME, id=f"trace-{name}",
                lines=[LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=2.0,
                                     scale_invariant=True, points=pts, color=_color(col, 0.8))]))
        return out

    def _points_of(self, name: str, ts: TimeSeries, path: np.ndarray, k: int
                   ) -> list[Point3 | None]:
        """Rows 0..k of ``path`` as points (None where not finite), kept for ``ts``: a row
        is final once a scene of it is asked for (a live view's series fills as it goes,
        so nothing past k is read)."""
        held = self._points.get(name)
        if held is None or held[0] is not ts:
            held = self._points[name] = (ts, [])
        pts = held[1]
        if len(pts) <= k:
            pts += [Point3(x=x, y=y, z=0.0) if math.isfinite(x) and math.isfinite(y) else None
                    for x, y in path[len(pts):k + 1, :2].tolist()]
        return pts


def _stamp(t: float, offset_ns: int = 0) -> Timestamp:
    ns = max(0, int(round(t * 1e9)) + offset_ns)
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _color(hex_rgb: str, alpha: float = 1.0) -> Color:
    h = hex_rgb.lstrip("#")
    return Color(r=int(h[0:2], 16) / 255, g=int(h[2:4], 16) / 255, b=int(h[4:6], 16) / 255, a=alpha)


def _vec(q) -> Vector3:
    return Vector3(x=float(q[0]), y=float(q[1]), z=0.0)


def _point(q, z: float = 0.0) -> Point3:
    return Point3(x=float(q[0]), y=float(q[1]), z=z)


def _yaw(psi: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(psi / 2), w=math.cos(psi / 2))


def _pose(q, z: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=float(q[0]), y=float(q[1]), z=z), orientation=_yaw(float(q[2])))


def _label(p, text: str, color: Color, dz: float = 1.2) -> TextPrimitive:
    return TextPrimitive(pose=Pose(position=Vector3(x=float(p[0]), y=float(p[1]), z=dz),
                                   orientation=Quaternion(w=1.0)),
                         billboard=True, font_size=14.0, scale_invariant=True, color=color, text=text)


RING_SEGMENTS = 48


def _outline(points: np.ndarray, color: Color, z: float, dashed: bool = False) -> LinePrimitive:
    kind = LinePrimitiveLineType.LineList if dashed else LinePrimitiveLineType.LineLoop
    pts = [Point3(x=float(x), y=float(y), z=z) for x, y in points]
    if dashed and len(pts) % 2:
        pts = pts[:-1]
    return LinePrimitive(type=kind, thickness=1.5 if dashed else 2.0, scale_invariant=True,
                         points=pts, color=color)


def _prism(poly: Polygon, height: float, color: Color) -> TriangleListPrimitive:
    """A convex polygon extruded to ``height``: top fan and the side walls, as triangles."""
    v = poly.array
    n = len(v)
    tris: list[tuple[float, float, float]] = []
    for k in range(1, n - 1):  # top: a fan from vertex 0 (convex)
        tris += [(*v[0], height), (*v[k], height), (*v[k + 1], height)]
    for k in range(n):
        a, b = v[k], v[(k + 1) % n]
        tris += [(*a, 0.0), (*b, 0.0), (*b, height), (*a, 0.0), (*b, height), (*a, height)]
    return TriangleListPrimitive(pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0),
                                           orientation=Quaternion(w=1.0)),
                                 points=[Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in tris],
                                 color=color)


def _ring(center, radius: float, color: Color, dashed: bool = False) -> LinePrimitive:
    a = np.linspace(0.0, 2 * math.pi, RING_SEGMENTS, endpoint=False)
    pts = [Point3(x=float(center[0] + radius * math.cos(x)), y=float(center[1] + radius * math.sin(x)),
                  z=0.02) for x in a]
    if dashed:  # every other segment
        return LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=1.5, scale_invariant=True,
                             points=pts, color=color)
    return LinePrimitive(type=LinePrimitiveLineType.LineLoop, thickness=2.0, scale_invariant=True,
                         points=pts, color=color)

