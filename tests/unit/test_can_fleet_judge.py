"""The fault-free CAN fleet run is run once more when it was not the undisturbed run its
claims are about (tests/can_fleet_runs.py ``disturbed``): a robot settled late, or a node
stalled for more than two periods."""

from tests.can_fleet_runs import STALL_PERIODS, disturbed, stalled

SETTLED = {"settled": True, "reasons": []}


def _m(stall_s: float, verdict=SETTLED, rate_hz: float = 100.0) -> dict:
    return {"control_rate_hz": rate_hz, "verdict": verdict, "deadline_misses": 0,
            "longest_stall": {"node": "bridge-1", "duration_s": stall_s, "t_s": 2.4}}


def test_a_stall_beyond_two_periods_is_a_disturbed_run():
    assert STALL_PERIODS == 2.0
    assert stalled(_m(0.002)) is None and disturbed(_m(0.002)) is None  # a quiet run
    assert stalled(_m(0.020)) is None  # two periods at 100 Hz: still undisturbed
    why = disturbed(_m(0.0378))
    assert why == "the bridge-1 stalled 37.8 ms from t = 2.40 s (more than 2 periods)"
    assert stalled(_m(0.0378, rate_hz=10.0)) is None  # under one period at 10 Hz
    assert stalled({"control_rate_hz": 100.0}) is None  # no stall reported


def test_a_late_robot_and_a_stall_are_both_named():
    late = {"settled": False, "reasons": ["robot #3 settled at 6.760 s >= 5.657 s"]}
    why = disturbed(_m(0.05, verdict=late))
    assert "robot #3 settled at 6.760 s" in why and "stalled 50.0 ms" in why
