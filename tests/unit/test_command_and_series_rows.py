"""What a plant applies of a command (plant/command.py, ``CommandBounds``) and how a step's
agent columns are written (deploy/report/timeseries.py, ``record_agent_row``): the bounds
read once give what the scenario's limits say, a NaN is never turned into a number, and a
row written into an allocated series (one block) equals the same row written column by
column into a series built from its columns."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from deploy.report.timeseries import AGENT_FLOAT_COLUMNS, AGENT_ROW_WIDTH, COLUMNS, TimeSeries
from plant.command import PLAUSIBLE_SPEED_MPS, PLAUSIBLE_TORQUE_NM, CommandBounds, exceeds


def test_bounds_follow_the_limits_and_the_plausibility_bounds():
    lab = CommandBounds.of(SimpleNamespace(max_wheel_torque_nm=2.0, max_speed_mps=1.5,
                                           max_yaw_rate_radps=2.0))
    assert (lab.torque, lab.speed, lab.yaw_rate) == (2.0, 1.5, 2.0)
    torques, v = lab.applied((3.0, -5.0, 1.0, float("nan")), (3.0, 4.0, -9.0))
    assert torques[:3] == (2.0, -2.0, 1.0) and math.isnan(torques[3])  # NaN kept: refused later
    assert np.hypot(v[0], v[1]) == 1.5 and v[0] / v[1] == 3.0 / 4.0 and v[2] == -2.0
    assert lab.plan([(9.0,) * 4, (-0.5,) * 4]) == [(2.0,) * 4, (-0.5,) * 4]
    none = CommandBounds.of(SimpleNamespace(max_wheel_torque_nm=math.inf, max_speed_mps=math.inf,
                                            max_yaw_rate_radps=math.inf))
    assert none.torque == PLAUSIBLE_TORQUE_NM and none.speed == PLAUSIBLE_SPEED_MPS
    assert none.applied((1e30,) * 4, (0.0, 0.0, 0.0))[0] == (PLAUSIBLE_TORQUE_NM,) * 4


def test_exceeds_looks_at_the_torques_and_the_plan():
    assert not exceeds((1.0, -2.0), [(2.0, -2.0)], 2.0)
    assert exceeds((1.0, -2.5), [], 2.0) and exceeds((0.0,), [(0.0,), (0.0, 3.0)], 2.0)
    assert not exceeds((float("nan"),), [], 2.0)  # as abs(nan) > bound: the plant refuses it


def test_a_row_written_as_one_block_equals_the_same_row_column_by_column():
    rng = np.random.default_rng(1)
    block = TimeSeries.allocate(3, 2)
    columns = TimeSeries(**{c: getattr(TimeSeries.allocate(3, 2), c).copy() for c in COLUMNS})
    assert not hasattr(columns, "_agent_rows")
    for k in range(3):
        for i in range(2):
            floats = tuple(rng.normal(size=AGENT_ROW_WIDTH))
            args = (k, i, floats, ("FOCB", "FDB") if i else (), bool(k % 2), i == 1, k == 2)
            block.record_agent_row(*args)
            columns.record_agent_row(*args)
    for c in COLUMNS:
        assert np.array_equal(getattr(block, c), getattr(columns, c)), c
    j = 0
    for name, width in AGENT_FLOAT_COLUMNS:  # the block's views are the named columns
        assert getattr(block, name).shape == ((3, 2) if width == 1 else (3, 2, width))
        j += width
    assert j == AGENT_ROW_WIDTH
    assert block.order[0, 1] == "FOCB>FDB" and block.active[0, 1] == 3
    assert block.speed_factor.dtype == float and block.nonfinite[1, 0] == 1
    # the row is packed into the block's bytes: a row outside it is refused, never wrapped
    # around (numpy's k = -1) or written past its end
    for k, i in ((-1, 0), (3, 0), (0, 2), (0, -1)):
        with pytest.raises(IndexError):
            block.record_agent_row(k, i, (0.0,) * AGENT_ROW_WIDTH, (), False, False, False)
    assert np.array_equal(block.q_d, columns.q_d)
