"""Turn what a distributed run put on the wire into the run's time series.

The launcher hears every key of the fleet. Robot states and the leader state
give the world columns, agent telemetry the agent columns, both indexed by the
step k the plant stamped. Lockstep runs fill every (k, robot) exactly once; a
realtime run may miss some, which are filled forward from the previous step
(and counted).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from deploy.runner import FormationTargets
from deploy.scenario import Scenario
from deploy.timeseries import BEHAVIOR_BITS, TimeSeries
from deploy.wire import LeaderState, NodeReport, RobotState, Telemetry


@dataclass
class Collected:
    states: dict[tuple[int, int], RobotState] = field(default_factory=dict)
    leaders: dict[int, LeaderState] = field(default_factory=dict)
    telemetry: dict[tuple[int, int], Telemetry] = field(default_factory=dict)
    reports: dict[str, NodeReport] = field(default_factory=dict)
    newest_k: int = -1


class Collector:
    def __init__(self, sc: Scenario) -> None:
        self.sc = sc
        self.data = Collected()
        self.lock = threading.Lock()
        self.filled = 0  # (k, robot) cells filled forward

    def add(self, msg: object) -> None:
        d = self.data
        with self.lock:
            if isinstance(msg, RobotState):
                d.states[(msg.k, msg.robot)] = msg
                if msg.k > d.newest_k:
                    d.newest_k = msg.k
            elif isinstance(msg, Telemetry):
                d.telemetry[(msg.k, msg.robot)] = msg
            elif isinstance(msg, LeaderState):
                d.leaders[msg.k] = msg
            elif isinstance(msg, NodeReport):
                d.reports[msg.role] = msg

    def series(self, realtime: bool = False) -> TimeSeries:
        """Lockstep: steps 0..K-1 where K is the first step some robot's state is
        missing (a lockstep run has them all). Realtime: every step up to the
        newest state, gaps filled forward from the previous step (and counted)."""
        sc, d = self.sc, self.data
        ids = sc.robot_ids
        with self.lock:
            if realtime:
                steps = d.newest_k + 1
            else:
                steps = 0
                while all((steps, r) in d.states for r in ids):
                    steps += 1
            ts = TimeSeries.allocate(steps, sc.n)
            targets = FormationTargets(sc)
            leader = None
            tel: list[Telemetry | None] = [None] * sc.n
            state: list[RobotState | None] = [None] * sc.n
            q0, v0 = np.full(3, np.nan), np.full(3, np.nan)
            for k in range(steps):
                t = k * sc.dt
                leader = d.leaders.get(k, leader)
                if leader is not None:
                    q0, v0 = np.array(leader.q), np.array(leader.q_dot)
                for i, r in enumerate(ids):
                    m = d.states.get((k, r))
                    if m is None:
                        self.filled += 1
                    state[i] = m or state[i]
                    m = d.telemetry.get((k, r))
                    if m is None:
                        self.filled += 1
                    tel[i] = m or tel[i]
                q = np.array([s.q if s else (np.nan,) * 3 for s in state])
                qd = np.array([s.q_dot if s else (np.nan,) * 3 for s in state])
                ts.record_world(k, t, q0, v0, q, qd, targets.at(t, q0, v0))
                for i in range(sc.n):
                    if tel[i] is not None:
                        record_telemetry(ts, k, i, tel[i])
        return ts


def record_telemetry(ts: TimeSeries, k: int, i: int, m: Telemetry) -> None:
    """The same columns as TimeSeries.record_agent, from the wire."""
    ts.q_d[k, i] = m.q_d
    ts.e[k, i] = m.e
    ts.s[k, i] = m.s
    ts.v_cmd[k, i] = m.v_cmd
    ts.torque[k, i] = m.torques
    ts.q0_hat[k, i] = m.q0_hat
    ts.q_fd[k, i] = m.q_fd
    ts.fdb_error[k, i] = np.nan if m.fdb_error is None else m.fdb_error
    names = m.order.split(">") if m.order else []
    ts.active[k, i] = sum(BEHAVIOR_BITS.get(b, 0) for b in names)
    ts.order[k, i] = m.order
    ts.nonfinite[k, i] = int(m.nonfinite)
