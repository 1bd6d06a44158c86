"""When the fleet tests run their fault-free CAN run once more (tests/can_fleet_runs.py)."""

from tests.can_fleet_runs import late_settling

LATE = {"settled": False, "reasons": ["robot #3 settled at 6.740 s >= 5.657 s"]}


def test_a_robot_that_settled_late_is_run_once_more_naming_the_clock_beside_it():
    why = late_settling({"verdict": LATE, "deadline_misses": 0,
                         "emulator_lag_ms": {"p50": 1.0, "p99": 2.0, "max": 143.25},
                         "odometry_drift": {"robot": [1, 2, 3], "max_m": [0.01, None, 0.34]}})
    assert why == ("robot #3 settled at 6.740 s >= 5.657 s (deadline misses 0, the emulator's "
                   "largest lag 143.2 ms, odometry drift up to 0.340 m)")
    never = {"settled": False, "reasons": ["robot #1 never settled"]}
    assert "robot #1 never settled" in late_settling({"verdict": never})


def test_a_run_whose_robots_settled_in_time_is_not_run_again():
    assert late_settling({"verdict": {"settled": True, "reasons": []}}) is None
    assert late_settling({"verdict": {"settled": True, "reasons": ["a gap between surfaces "
                                                                   "reached 0"]}}) is None
