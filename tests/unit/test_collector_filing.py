"""The launcher's filing of the fleet's batched logs (deploy/run/collector.py): every
cell written once, by the first row for it; rows outside the run, ahead of it, or for a
cell already filled counted and dropped; the leader's overlapping batches kept first."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.contract.scenario import load_scenario
from deploy.contract.wire import (
    WIRE_VERSION,
    LeaderState,
    StateLog,
    StateRow,
    Telemetry,
    TelemetryRow,
)
from deploy.run.collector import Collector

STEPS = 20


@pytest.fixture()
def collector() -> Collector:
    return Collector(load_scenario("paper"), STEPS)


def _row(k: int, robots: int = 3, x: float | None = None) -> StateRow:
    x = float(k) if x is None else x
    return StateRow(k, k * 0.001, [(x, 10.0 * j, -x) for j in range(robots)],
                    [(x + 0.5, j + 0.25, 0.0) for j in range(robots)], [j == 1 for j in range(robots)])


def _log(rows: list[StateRow], robots: list[int] | None = None) -> StateLog:
    return StateLog(WIRE_VERSION, 0, 0, 0, robots=robots or [1, 2, 3], rows=rows)


def test_a_state_log_fills_its_steps_cells_and_flags(collector):
    collector.add(_log([_row(k) for k in range(4, 15)]))
    ts = collector.ts
    assert collector.have_state[4:15].all() and not collector.have_state[:4].any()
    assert not collector.have_state[15:].any()
    assert ts.q[7, 2].tolist() == [7.0, 20.0, -7.0]
    assert ts.q_dot[14, 0].tolist() == [14.5, 0.25, 0.0]
    assert collector.faulted[4:15, 1].all() and not collector.faulted[4:15, [0, 2]].any()
    assert collector.newest_k == 14 and collector.refused == {} and collector.out_of_range == 0


def test_rows_outside_the_run_ahead_of_it_or_for_filled_cells_are_counted_and_dropped(collector):
    collector.add(_log([_row(k) for k in range(0, 5)]))
    collector.horizon = lambda: 10
    collector.add(_log([_row(k, x=99.0) for k in (-2, 3, 4, 5, 6, 11, 12, STEPS, STEPS + 5)]))
    assert collector.out_of_range == 3  # -2, STEPS, STEPS + 5
    assert collector.refused == {"second state row for a step": 2,  # 3, 4
                                 "state row ahead of the run": 2}  # 11, 12
    q = collector.ts.q[:, 0, 0]
    assert q[3] == 3.0 and q[4] == 4.0  # the first row stays
    assert q[5] == q[6] == 99.0 and collector.have_state[5:7].all()
    assert not collector.have_state[7:].any() and collector.newest_k == 6


def test_a_step_twice_in_one_log_keeps_the_first_row(collector):
    collector.add(_log([_row(2, x=1.0), _row(3), _row(2, x=2.0), _row(1)]))
    assert collector.ts.q[2, 0, 0] == 1.0 and collector.have_state[1:4].all()
    assert collector.refused == {"second state row for a step": 1}


def test_a_bridges_log_fills_its_own_robots_column_only(collector):
    collector.add(_log([_row(k, robots=1, x=5.0) for k in range(3)], robots=[3]))
    assert collector.have_state[:3, 2].all() and not collector.have_state[:, :2].any()
    assert collector.ts.q[1, 2].tolist() == [5.0, 0.0, -5.0]
    collector.add(_log([_row(1, robots=3, x=7.0)]))  # robot 3 of step 1 is filled already
    assert collector.refused == {"second state row for a step": 1}
    assert not collector.have_state[1, :2].any()


def test_leader_batches_overlap_and_the_first_state_of_a_step_stays(collector):
    def batch(k: int, n: int, x: float) -> LeaderState:
        return LeaderState(WIRE_VERSION, 0, 0, 0, k=k, t=k * 0.001,
                           q=[(x + i, 0.0, 0.0) for i in range(n)],
                           q_dot=[(0.0, x + i, 0.0) for i in range(n)])

    collector.add(batch(0, 8, 100.0))
    collector.add(batch(4, 8, 200.0))  # steps 4..7 heard already
    collector.add(batch(STEPS - 2, 5, 300.0))  # 3 past the run's end
    collector.add(batch(-3, 2, 400.0))  # before it
    ts = collector.ts
    assert ts.leader_q[:8, 0].tolist() == [100.0 + i for i in range(8)]
    assert ts.leader_q[8:12, 0].tolist() == [204.0, 205.0, 206.0, 207.0]
    assert ts.leader_v[11, 1] == 207.0
    assert ts.leader_q[STEPS - 2:, 0].tolist() == [300.0, 301.0]
    assert collector.have_leader[:12].all() and collector.have_leader[STEPS - 2:].all()
    assert not collector.have_leader[12:STEPS - 2].any()
    assert collector.out_of_range == 3 + 2
    assert not ts.leader_q[12:STEPS - 2].any()  # never written (zeros, as allocated)


def test_a_realtime_series_fills_each_gap_forward_from_the_step_before_and_counts_it(collector):
    """Realtime: a step whose state, telemetry or leader never came repeats the step
    before it (the first step: NaN), and every robot-step filled is counted."""
    collector.add(_log([_row(k) for k in range(8) if k != 5]))  # step 5's states lost
    collector.add(LeaderState(WIRE_VERSION, 0, 0, 0, k=0, t=0.0,
                              q=[(float(k), 0.0, 0.0) for k in range(8)],
                              q_dot=[(1.0, 0.0, 0.0)] * 8))
    collector.have_leader[3] = False  # the leader's step 3 lost
    collector.ts.leader_q[3] = 99.0
    collector.have_telemetry[:8] = True
    collector.have_telemetry[6, 1] = False  # robot 2's telemetry of step 6 lost
    collector.ts.e[6, 1] = 42.0
    ts = collector.series(realtime=True)
    assert ts.steps == 8
    assert ts.q[5].tolist() == ts.q[4].tolist() and ts.q[5, 0, 0] == 4.0
    assert ts.q[6, 0, 0] == 6.0  # a step heard is its own
    assert ts.leader_q[3].tolist() == [2.0, 0.0, 0.0]
    assert ts.e[6, 1].tolist() == ts.e[5, 1].tolist() != [42.0] * len(ts.e[6, 1])
    assert collector.filled == 3 + 1  # step 5: three robots' states; step 6: one telemetry


def _telemetry(robot: int, ks: list[int], misses: list[int]) -> Telemetry:
    z3, z4 = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)
    return Telemetry(WIRE_VERSION, robot, 0, 0, robot=robot, rows=[
        TelemetryRow(k, k * 0.001, z3, z3, z3, z3, z4, z3, z3, None, "FM", False,
                     deadline_misses=n) for k, n in zip(ks, misses, strict=True)])


def test_each_agents_deadline_misses_are_its_newest_telemetry_count(collector):
    """What /fleet/status says live (deploy/ros2/fleet_messages.py): per agent, the most its
    telemetry has counted; a batch that arrives late cannot take the count back."""
    collector.add(_telemetry(2, [0, 1, 2], [0, 1, 3]))
    collector.add(_telemetry(3, [5], [7]))
    collector.add(_telemetry(2, [3], [2]))  # an older count, later: the count stays
    assert collector.agent_misses.tolist() == [0, 3, 7]
    from deploy.ros2.fleet_messages import robot_status

    status = robot_status(collector.ts, 2, 0.002, [1, 2, 3], "omnifleet", collector.agent_misses)
    assert [dict(v)["deadline_misses"] for _, _, _, v in status] == ["0", "3", "7"]
    assert all("deadline_misses" not in v for _, _, _, v in
               robot_status(collector.ts, 2, 0.002, [1, 2, 3], "omnifleet"))


def _filed_row_by_row(c: Collector, msg: StateLog, horizon: int | None) -> None:
    """The rule, one row at a time (as the launcher filed them before)."""
    cols = [c.row[r] for r in msg.robots]
    for row in msg.rows:
        k = row.k
        if not 0 <= k < c.steps:
            c.out_of_range += 1
        elif horizon is not None and k > horizon:
            c.refused["state row ahead of the run"] = c.refused.get("state row ahead of the run", 0) + 1
        elif c.have_state[k, cols].any():
            c.refused["second state row for a step"] = c.refused.get("second state row for a step", 0) + 1
        else:
            c.ts.q[k, cols], c.ts.q_dot[k, cols] = row.q, row.q_dot
            c.have_state[k, cols] = True
            c.faulted[k, cols] = row.faulted
            c.newest_k = max(c.newest_k, k)


@pytest.mark.parametrize(("defer_rows", "one_robot_a_log"), [
    (0, False), (7, False), (10_000, False), (7, True), (10_000, True)])
def test_a_log_filed_at_once_equals_its_rows_filed_one_by_one(defer_rows, one_robot_a_log):
    """At once, and held then filed together (Collector.defer_rows): the logs of each
    robot set together (a CAN fleet's bridges: one robot each), one by one where the
    sets overlap."""
    rng = np.random.default_rng(7)
    sc = load_scenario("paper")
    fast, slow = Collector(sc, STEPS), Collector(sc, STEPS)
    fast.defer_rows = defer_rows
    for n in range(200):
        robots = [int(r) for r in rng.choice([1, 2, 3], size=1 if one_robot_a_log else
                                             rng.integers(1, 4), replace=False)]
        rows = [StateRow(int(k), 0.001 * int(k), [tuple(rng.normal(size=3)) for _ in robots],
                         [tuple(rng.normal(size=3)) for _ in robots],
                         [bool(b) for b in rng.integers(0, 2, len(robots))])
                for k in rng.integers(-3, STEPS + 3, size=rng.integers(1, 7))]
        horizon = None if n % 3 else int(rng.integers(0, STEPS))
        fast.horizon = lambda h=horizon: h
        fast.add(_log(rows, robots))
        _filed_row_by_row(slow, _log(rows, robots), horizon)
    if defer_rows > 1000:
        assert not fast.have_state.any()  # held: nothing filed yet
    fast.flush()
    for name in ("q", "q_dot"):
        assert np.array_equal(getattr(fast.ts, name), getattr(slow.ts, name), equal_nan=True)
    assert np.array_equal(fast.have_state, slow.have_state)
    assert np.array_equal(fast.faulted, slow.faulted)
    assert (fast.refused, fast.out_of_range, fast.newest_k) == (
        slow.refused, slow.out_of_range, slow.newest_k)
    assert fast.refused["second state row for a step"] > 0 and fast.out_of_range > 0


def test_held_logs_are_filed_for_whoever_reads_the_cells(collector):
    from deploy.report.live_view import collector_rows

    collector.defer_rows = 10_000
    collector.add(_log([_row(k) for k in range(0, 6)]))
    assert collector.newest_k == -1  # held
    assert collector_rows(collector, realtime=True)() == 5  # a live view's look files them
    collector.add(_log([_row(k) for k in range(6, 9)]))
    assert collector.series(realtime=True).q.shape[0] == 9  # and the run's series
