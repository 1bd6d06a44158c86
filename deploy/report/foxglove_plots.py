"""A run's plot signals as Foxglove messages: rows of its time series (and the
scenario) in, one JSON message per robot and one for the fleet per row out.

Pure, no I/O. ``/plot/robot/<id>`` (:class:`RobotSignals`: the tracking and
formation errors of Fig. 5, the estimator error, the wheel torques of Fig. 6,
the active behaviors, limit and safety activity, gaps between surfaces) and ``/plot/fleet``
(:class:`FleetSignals`). Foxglove's Plot panel reads any numeric field by path
(``/plot/robot/2.tracking_error``, ``/plot/robot/1.torque[3]``); the JSON Schema
comes from ``deploy/report/foxglove_json.py`` (Foxglove has no well-known message for
a row of scalars).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np

from deploy.contract.scenario import Scenario
from deploy.report.foxglove_topics import PLOT_FLEET, plot_topic
from deploy.report.targets import FormationTargets
from deploy.report.timeseries import BEHAVIOR_BITS, TimeSeries


class RobotSignals(msgspec.Struct, kw_only=True):
    """One robot at step k, for Foxglove's Plot panel (``/plot/robot/<id>.field``)."""

    t: float  # s
    robot: int
    tracking_error: float  # |e|, e = q - q_d, behavioral tracking error (Fig. 5)
    e: tuple[float, float, float]  # its components x, y, psi
    formation_error: float  # |x - (x_0 + rho_i)| with the true leader, m
    fdb_error: float | None  # |x - x_fd| (FDB's task error), m; absent while FDB is inactive
    estimator_error: float  # |p0_hat_i - p0|: eq. (14)'s position estimate against the leader, m
    estimator_heading_error: float  # |psi0_hat_i - psi0|, rad
    sliding: float  # |s|
    torque: tuple[float, float, float, float]  # wheel torques, N m (Fig. 6)
    torque_peak: float  # max |tau_j|, N m
    speed: float  # |(x_dot, y_dot)|, m/s
    command_speed: float  # |v_d| fused velocity command (translation), m/s
    active: int  # active behaviors bitmask FDB=1 FOCB=2 FRCB=4
    fdb: int  # 1 while active
    focb: int
    frcb: int
    order: str  # active behaviors, highest priority first
    nonfinite: int  # 1: the law gave NaN/Inf and the torques were zeroed
    speed_limited: int  # 1: the velocity command sits at the scenario's max_speed_mps
    torque_limited: int  # 1: a wheel torque sits at max_wheel_torque_nm
    speed_factor: float  # degradation: 1 full speed
    safety_active: int  # 1: the safety filter changed the command (agents/safety_filter.py)
    safety_dv: float  # by how much, m/s
    input_age_s: float  # age of the freshest leader information
    obstacle_gap: float | None  # surface to surface, to the nearest obstacle, m
    robot_gap: float | None  # surface to surface, to the nearest robot, m


class FleetSignals(msgspec.Struct, kw_only=True):
    t: float
    leader_speed: float  # m/s
    max_tracking_error: float
    settle_threshold: float  # the band of the settling criterion
    settled: int  # 1: every robot's |e| is inside the band now
    settling_bound_s: float  # sqrt(2) T_p
    min_obstacle_gap: float | None  # surface to surface, m (metrics.json's min_obstacle_gap_m)
    min_robot_gap: float | None  # surface to surface, m (metrics.json's min_robot_gap_m)
    nonfinite: int  # robots whose law gave NaN/Inf at this step


@dataclass(frozen=True)
class _Limits:
    ids: list[int]
    radius: float
    max_speed: float
    max_torque: float
    threshold: float
    bound: float


class FleetPlots:
    """Turns rows of a run's time series into plot messages."""

    def __init__(self, sc: Scenario) -> None:
        s = sc.spec
        self.sc = sc
        self.st = _Limits(
            ids=list(sc.robot_ids), radius=s.robot.body_radius_m,
            max_speed=s.limits.max_speed_mps, max_torque=s.limits.max_wheel_torque_nm,
            threshold=s.metrics.settle_threshold, bound=math.sqrt(2.0) * s.controller.T_p)
        self.targets = FormationTargets(sc)

    def time(self, k: int) -> float:
        return k * self.sc.dt

    def messages(self, ts: TimeSeries, k: int) -> dict[str, msgspec.Struct]:
        """Every plot topic at step k (the formation target computed here)."""
        return next(iter(self.rows(ts, [k], series_target=False)))[1]

    def rows(self, ts: TimeSeries, rows, series_target: bool = True):
        """(k, {topic: message}) for each k of ``rows``, computed column-wise.
        ``series_target``: take x_0 + rho_i from the series' ``target`` column
        (a finished run's series has it; a live distributed one does not yet)."""
        st = self.st
        rows = np.asarray(list(rows), dtype=int)
        if not len(rows):
            return
        q, lq, lv = ts.q[rows], ts.leader_q[rows], ts.leader_v[rows]
        if series_target:
            target = ts.target[rows]
        else:
            target = np.array([self.targets.at(self.time(k), lq[j], lv[j]) if np.isfinite(lq[j]).all()
                               else np.full((len(st.ids), 2), np.nan) for j, k in enumerate(rows)])
        e = ts.e[rows]
        err = np.linalg.norm(e, axis=2)
        tau = ts.torque[rows]
        peak = np.max(np.abs(tau), axis=2)
        vcmd = np.hypot(ts.v_cmd[rows, :, 0], ts.v_cmd[rows, :, 1])
        d_h = ts.q0_hat[rows, :, 2] - lq[:, None, 2]
        obst, rob = _clearances(q[:, :, :2], st.radius, self.sc.obstacle_gaps(q[:, :, :2]))
        cols = {
            "tracking_error": err, "formation_error": np.linalg.norm(q[:, :, :2] - target, axis=2),
            "fdb_error": ts.fdb_error[rows],
            "estimator_error": np.linalg.norm(ts.q0_hat[rows, :, :2] - lq[:, None, :2], axis=2),
            "estimator_heading_error": np.abs(np.arctan2(np.sin(d_h), np.cos(d_h))),
            "sliding": np.linalg.norm(ts.s[rows], axis=2), "torque_peak": peak,
            "speed": np.hypot(ts.q_dot[rows, :, 0], ts.q_dot[rows, :, 1]), "command_speed": vcmd,
            "speed_factor": ts.speed_factor[rows], "input_age_s": ts.input_age[rows],
            "safety_dv": ts.safety_dv[rows],
            "obstacle_gap": obst, "robot_gap": rob,
        }
        nullable = ("fdb_error", "obstacle_gap", "robot_gap")
        lists = {name: c.tolist() for name, c in cols.items()}
        e_l, tau_l = e.tolist(), tau.tolist()
        active = ts.active[rows].astype(int).tolist()
        nonfinite = ts.nonfinite[rows].astype(int).tolist()
        safety = ts.safety_active[rows].astype(int).tolist()
        order = ts.order[rows].tolist()
        speed_lim = (vcmd >= st.max_speed * (1 - 1e-9)).astype(int).tolist()
        torque_lim = (peak >= st.max_torque * (1 - 1e-9)).astype(int).tolist()
        settled = np.all(err < st.threshold, axis=1).astype(int).tolist()
        max_err = np.max(err, axis=1).tolist()
        leader_speed = np.hypot(lv[:, 0], lv[:, 1]).tolist()
        min_obst, min_rob = np.min(obst, axis=1).tolist(), np.min(rob, axis=1).tolist()
        fdb_bit, focb_bit, frcb_bit = (BEHAVIOR_BITS[b] for b in ("FDB", "FOCB", "FRCB"))
        for j, k in enumerate(rows.tolist()):
            t = self.time(k)
            out: dict[str, msgspec.Struct] = {}
            for i, rid in enumerate(st.ids):
                v = {name: lists[name][j][i] for name in lists}
                for name in nullable:
                    v[name] = _finite(v[name])
                a = active[j][i]
                out[plot_topic(rid)] = RobotSignals(
                    t=t, robot=rid, e=tuple(e_l[j][i]), torque=tuple(tau_l[j][i]), active=a,
                    fdb=int(bool(a & fdb_bit)), focb=int(bool(a & focb_bit)),
                    frcb=int(bool(a & frcb_bit)), order=order[j][i], nonfinite=nonfinite[j][i],
                    speed_limited=speed_lim[j][i], torque_limited=torque_lim[j][i],
                    safety_active=safety[j][i], **v)
            out[PLOT_FLEET] = FleetSignals(
                t=t, leader_speed=leader_speed[j], max_tracking_error=max_err[j],
                settle_threshold=st.threshold, settled=settled[j], settling_bound_s=st.bound,
                min_obstacle_gap=_finite(min_obst[j]), min_robot_gap=_finite(min_rob[j]),
                nonfinite=sum(nonfinite[j]))
            yield k, out


def _clearances(p: np.ndarray, radius: float,
                obstacle_gaps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, n, 2) positions and (rows, n, m) obstacle gaps -> per row and robot: gap
    to the nearest obstacle's surface, to the nearest other robot's surface (inf: none)."""
    rows, n = p.shape[:2]
    obst = obstacle_gaps.min(axis=2) if obstacle_gaps.shape[2] else np.full((rows, n), np.inf)
    dr = np.linalg.norm(p[:, :, None, :] - p[:, None, :, :], axis=3) - 2 * radius
    dr[:, np.arange(n), np.arange(n)] = np.inf
    return obst, dr.min(axis=2)


def _finite(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None
