"""Turn what a distributed run put on the wire into the run's time series.

The launcher hears the fleet's batched logs, off the control path: the plant's
(or bridges') :class:`StateLog` and the leader's states give the world columns,
the agents' :class:`Telemetry` rows the agent columns, all indexed by the step k
the plant stamped. Lockstep runs fill every (k, robot) exactly once; a
realtime run may miss some, which are filled forward from the previous step
(and counted).

Every cell is written once: the first row for a (step, robot) stays, a second one
(forged or replayed) is refused and counted; and, without keys, a row for a step the
run cannot have reached yet on the launcher's clock (``horizon``) is refused and
counted, so a forged message costs at most its own cells (with keys only each row's own
node can have sent it: deploy/run/observer.py).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from deploy.contract.scenario import Scenario
from deploy.contract.wire import LeaderState, NodeReport, StateLog, Telemetry, TelemetryRow
from deploy.report.targets import FormationTargets
from deploy.report.timeseries import COLUMNS, TimeSeries


class Collector:
    """Writes each message straight into preallocated columns (memory does not
    grow with the number of messages), remembering which cells were filled."""

    def __init__(self, sc: Scenario, steps: int) -> None:
        self.sc, self.steps = sc, steps
        self.row = {r: i for i, r in enumerate(sc.robot_ids)}
        self.ts = TimeSeries.allocate(steps, sc.n)
        self.have_state = np.zeros((steps, sc.n), bool)
        self.have_telemetry = np.zeros((steps, sc.n), bool)
        self.have_leader = np.zeros(steps, bool)
        self.faulted = np.zeros((steps, sc.n), bool)  # a bridge's state said faulted (CAN)
        # each agent's deadline misses so far, as its newest telemetry says (for the live
        # views; the run's figure is its final report's)
        self.agent_misses = np.zeros(sc.n, np.int64)
        self.reports: dict[str, NodeReport] = {}
        self.newest_k = -1
        self.out_of_range = 0  # messages stamped with a step outside the run
        self.filled = 0  # cells filled forward (realtime)
        self.lock = threading.Lock()
        # the newest step the run can have reached now (None: no bound known), set by the
        # launcher from its own clock; rows past it and second rows for a cell: refused
        self.horizon: Callable[[], int | None] = lambda: None
        self.refused: dict[str, int] = {}
        # state logs held to be filed together (0: each as it comes): with its numpy calls
        # cold after the launcher's sleep, one log cost ~330 µs to file (a CAN fleet's
        # bridges send 30 a second) and a thousand rows at once little more. Whoever reads
        # the cells during the run files them first (:meth:`flush`; the live views'
        # ``collector_rows``), and so does :meth:`series`
        self.defer_rows = 0
        self._pending: list[tuple[StateLog, int | None]] = []  # with the horizon they met
        self._pending_rows = 0

    def _refuse(self, why: str, times: int = 1) -> None:
        if times:
            self.refused[why] = self.refused.get(why, 0) + times

    def _file_states(self, msg: StateLog, horizon: int | None) -> None:
        """A state log's rows, all at once (a row cost ~21 µs filed alone: numpy's
        overhead a call, ~10 calls a row; a CAN fleet's three bridges send 600 rows a
        second). As filed row by row: a row outside the run is counted, one ahead of
        the horizon or for a cell already filled (before this log, or by an earlier row
        of it) refused and counted, the first row for a step kept."""
        self._file_rows(msg.robots, msg.rows, horizon)

    def _file_rows(self, robots: list[int], rows: list, horizon: int | None | np.ndarray
                   ) -> None:
        """Rows of the same robots, in the order they came; ``horizon``: each row's (an
        array), or one for all (None: no bound known)."""
        if not rows:
            return
        cols = [self.row[r] for r in robots]
        ks = np.fromiter((row.k for row in rows), np.int64, len(rows))
        inside = (ks >= 0) & (ks < self.steps)
        self.out_of_range += int(np.count_nonzero(~inside))
        ahead = inside & (ks > horizon) if horizon is not None else np.zeros_like(inside)
        self._refuse("state row ahead of the run", int(np.count_nonzero(ahead)))
        candidate = np.flatnonzero(inside & ~ahead)
        filled = self.have_state[np.ix_(ks[candidate], cols)].any(axis=1)
        fresh = candidate[~filled]
        _, first = np.unique(ks[fresh], return_index=True)  # a step twice: the first row
        keep = fresh[np.sort(first)]
        self._refuse("second state row for a step", len(candidate) - len(keep))
        if not len(keep):
            return
        k_kept = ks[keep]
        at = np.ix_(k_kept, cols)
        ts = self.ts
        ts.q[at] = np.array([rows[i].q for i in keep], float)
        ts.q_dot[at] = np.array([rows[i].q_dot for i in keep], float)
        self.have_state[at] = True
        self.faulted[at] = np.array([rows[i].faulted for i in keep], bool)
        self.newest_k = max(self.newest_k, int(k_kept.max()))

    def flush(self) -> None:
        """File the state logs held so far (see ``defer_rows``)."""
        with self.lock:
            self._file_pending()

    def _file_pending(self) -> None:
        """The held logs, as filed one by one in the order they came: the logs of one
        robot set together (a log's cells are its robots'; sets that do not overlap
        cannot take each other's cells), one by one when sets overlap."""
        pending, self._pending, self._pending_rows = self._pending, [], 0
        if not pending:
            return
        by_robots: dict[tuple[int, ...], list[tuple[StateLog, int | None]]] = {}
        for msg, horizon in pending:
            by_robots.setdefault(tuple(msg.robots), []).append((msg, horizon))
        robots = [r for key in by_robots for r in key]
        if len(robots) != len(set(robots)):
            for msg, horizon in pending:
                self._file_states(msg, horizon)
            return
        no_bound = np.iinfo(np.int64).max
        for key, logs in by_robots.items():
            rows = [row for msg, _ in logs for row in msg.rows]
            if all(h is None for _, h in logs):
                self._file_rows(list(key), rows, None)
                continue
            horizons = np.fromiter((no_bound if h is None else h for msg, h in logs
                                    for _ in msg.rows), np.int64, len(rows))
            self._file_rows(list(key), rows, horizons)

    def add(self, msg: object) -> None:
        ts = self.ts
        with self.lock:
            if isinstance(msg, NodeReport):
                self.reports[msg.role] = msg
                return
            horizon = self.horizon()
            if isinstance(msg, StateLog):
                if not self.defer_rows:
                    self._file_states(msg, horizon)
                    return
                self._pending.append((msg, horizon))
                self._pending_rows += len(msg.rows)
                if self._pending_rows >= self.defer_rows:
                    self._file_pending()
            elif isinstance(msg, Telemetry):
                i = self.row[msg.robot]
                for row in msg.rows:
                    if not 0 <= row.k < self.steps:
                        self.out_of_range += 1
                        continue
                    if horizon is not None and row.k > horizon:
                        self._refuse("telemetry row ahead of the run")
                        continue
                    if self.have_telemetry[row.k, i]:
                        self._refuse("second telemetry row for a step")
                        continue
                    record_telemetry(ts, row.k, i, row)
                    self.have_telemetry[row.k, i] = True
                    self.agent_misses[i] = max(self.agent_misses[i], row.deadline_misses)
            elif isinstance(msg, LeaderState):
                for n, (q, qd) in enumerate(zip(msg.q, msg.q_dot, strict=True)):
                    k = msg.k + n
                    if not 0 <= k < self.steps:
                        self.out_of_range += 1
                        continue
                    if self.have_leader[k]:
                        continue  # lockstep batches overlap: the first stays
                    ts.leader_q[k], ts.leader_v[k] = q, qd
                    self.have_leader[k] = True
            # samples, replies, control: recorded, not part of the series

    def series(self, realtime: bool = False) -> TimeSeries:
        """Lockstep: steps 0..K-1 where K is the first step some robot's state is
        missing (a lockstep run has them all). Realtime: every step up to the
        newest state, gaps filled forward from the previous step (and counted)."""
        sc = self.sc
        with self.lock:
            self._file_pending()
            if realtime:
                steps = self.newest_k + 1
            else:
                complete = self.have_state.all(axis=1)
                steps = self.steps if complete.all() else int(np.argmin(complete))
            ts = TimeSeries(**{c: getattr(self.ts, c)[:steps].copy() for c in COLUMNS})
            self._fill_forward(ts, steps)
            if realtime:  # the rows filled forward (or left NaN) are no robot's state
                ts.state_heard = self.have_state[:steps].copy()
        ts.t[:] = np.arange(steps) * sc.dt
        ts.target[:] = FormationTargets(sc).along(ts.t, ts.leader_q)
        return ts

    def _fill_forward(self, ts: TimeSeries, steps: int) -> None:
        world = ("q", "q_dot")
        agent = [c for c in COLUMNS if c not in (*world, "t", "leader_q", "leader_v", "target")]
        # only the steps with something missing (a whole lockstep run has none: walking
        # every step and robot in Python took ~0.1 s of paper's end)
        gaps = ~self.have_leader[:steps] | ~self.have_state[:steps].all(axis=1) | \
            ~self.have_telemetry[:steps].all(axis=1)
        for k in np.flatnonzero(gaps).tolist():
            if not self.have_leader[k]:
                prev = (ts.leader_q[k - 1], ts.leader_v[k - 1]) if k else (np.nan, np.nan)
                ts.leader_q[k], ts.leader_v[k] = prev
            for i in range(self.sc.n):
                for have, cols in ((self.have_state, world), (self.have_telemetry, agent)):
                    if not have[k, i]:
                        self.filled += 1
                        for c in cols:
                            col = getattr(ts, c)
                            col[k, i] = col[k - 1, i] if k else (
                                np.nan if col.dtype.kind == "f" else col[k, i])


def record_telemetry(ts: TimeSeries, k: int, i: int, m: TelemetryRow) -> None:
    """The same columns as TimeSeries.record_agent, from the wire."""
    ts.record_agent_row(
        k, i, (*m.q_d, *m.e, *m.s, *m.v_cmd, *m.torques, *m.q0_hat, *m.q_fd,
               np.nan if m.fdb_error is None else m.fdb_error, m.input_age_s, m.speed_factor,
               m.safety_dv),
        m.order.split(">") if m.order else (), m.nonfinite,
        m.safety_dv > 0.0 or m.safety_infeasible, m.safety_infeasible)
