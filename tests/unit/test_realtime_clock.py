"""The judge of realtime runs (tests/realtime_clock.py): a run that kept its clock is
judged; one that missed it is retried once, then skipped only when other programs
measurably took the CPU, failed when they did not; a missing report always fails."""

from __future__ import annotations

import warnings
from contextlib import contextmanager

import pytest
from realtime_clock import (
    OTHERS_SHARE,
    MachineLoad,
    RanOnceMore,
    clock_missed,
    judged,
    late_with_misses,
    loop_missed,
    measured,
    once_more,
)

# the judge warns of each second run (RanOnceMore): here the second runs are the subject
pytestmark = pytest.mark.filterwarnings("ignore::realtime_clock.RanOnceMore")

LOADED = MachineLoad(cores=2, wall_s=10.0, busy_cores=2.0, ours_cores=0.8)
QUIET = MachineLoad(cores=2, wall_s=10.0, busy_cores=0.9, ours_cores=0.8)


def _metrics(jitter_p99_ms: float | None, rate_hz: float = 200.0, **kw) -> dict:
    return {"control_rate_hz": rate_hz, "deadline_misses": 7, "reports_missing": [],
            "jitter_ms": None if jitter_p99_ms is None else {"p99": jitter_p99_ms}} | kw


def _runs(*jitters):
    calls = []

    def run():
        calls.append(1)
        return _metrics(jitters[len(calls) - 1])
    return run, calls


def _machine(load: MachineLoad):
    @contextmanager
    def measure():
        yield load
    return measure


def test_a_run_that_kept_its_period_is_judged_at_once():
    run, calls = _runs(4.9)
    assert judged(run, lambda m: m, "x", _machine(QUIET))["jitter_ms"]["p99"] == 4.9
    assert len(calls) == 1


def test_a_run_starved_by_others_is_retried_once_and_the_retry_judged():
    run, calls = _runs(9.0, 3.0)
    assert judged(run, lambda m: m, "x", _machine(LOADED))["jitter_ms"]["p99"] == 3.0
    assert len(calls) == 2


@pytest.mark.filterwarnings("default::realtime_clock.RanOnceMore")
def test_a_second_run_is_said_in_the_warnings_with_its_reason_and_the_load():
    run, _ = _runs(9.0, 3.0)
    with pytest.warns(RanOnceMore, match=r"x: run once more: .*9\.0 ms.*other programs took "
                      r"1\.20 of 2 cores"):
        judged(run, lambda m: m, "x", _machine(LOADED))
    run, _ = _runs(3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RanOnceMore)
        judged(run, lambda m: m, "x", _machine(LOADED))  # kept its clock: no second run


def test_starved_by_others_twice_is_skipped_naming_both_measurements():
    run, calls = _runs(9.0, 8.0)
    with pytest.raises(pytest.skip.Exception,
                       match=r"9\.0 ms.*other programs took 1\.20 of 2 cores.*then.*8\.0 ms"):
        judged(run, lambda m: m, "x", _machine(LOADED))
    assert len(calls) == 2


def test_starved_far_beyond_the_period_is_skipped_without_a_retry():
    run, calls = _runs(63.0, 1.0)
    with pytest.raises(pytest.skip.Exception, match=r"63\.0 ms.*12\.6 periods"):
        judged(run, lambda m: m, "x", _machine(LOADED))
    assert len(calls) == 1


def test_a_run_late_once_on_a_quiet_machine_is_judged_by_its_retry():
    """A late stretch of a shared host (one bridge's p99 5.4 ms against 5 ms, others at
    0.21 of 2 cores): once more, and the retry that kept its clock is judged."""
    run, calls = _runs(9.0, 1.0)
    assert judged(run, lambda m: m, "x", _machine(QUIET))["jitter_ms"]["p99"] == 1.0
    assert len(calls) == 2


def test_a_run_that_missed_its_clock_twice_on_a_quiet_machine_fails():
    run, calls = _runs(9.0, 8.0)
    with pytest.raises(pytest.fail.Exception, match=r"left alone.*9\.0 ms.*then.*8\.0 ms"):
        judged(run, lambda m: m, "x", _machine(QUIET))
    assert len(calls) == 2


def test_far_beyond_the_period_on_a_quiet_machine_fails_without_a_retry():
    run, calls = _runs(63.0, 1.0)
    with pytest.raises(pytest.fail.Exception, match=r"left alone.*63\.0 ms.*12\.6 periods"):
        judged(run, lambda m: m, "x", _machine(QUIET))
    assert len(calls) == 1


def test_a_test_measuring_its_own_run_gets_the_same_second_chance():
    """once_more: for the CAN bridge tests, which start and measure their processes."""
    tries = iter([({"try": 1}, QUIET, "p99 5.4 ms > 5.0 ms"), ({"try": 2}, QUIET, None)])
    assert once_more(lambda: next(tries), "x") == {"try": 2}
    tries = iter([({"try": 1}, QUIET, "p99 5.4 ms"), ({"try": 2}, QUIET, "p99 6.1 ms")])
    with pytest.raises(pytest.fail.Exception, match=r"5\.4 ms.*then p99 6\.1 ms"):
        once_more(lambda: next(tries), "x")
    tries = iter([({"try": 1}, LOADED, "p99 9 ms"), ({"try": 2}, LOADED, "p99 8 ms")])
    with pytest.raises(pytest.skip.Exception, match="starved"):
        once_more(lambda: next(tries), "x")
    tries = iter([({"try": 1}, QUIET, None)])
    assert once_more(lambda: next(tries), "x") == {"try": 1}  # kept its clock: run once


def test_others_taking_a_quarter_of_an_unsaturated_machine_starve_it_too():
    """Busy 1.7 of 2 cores, 0.5 of them others': eight CAN fleet processes late by 20 ms."""
    assert MachineLoad(cores=2, wall_s=10.0, busy_cores=1.7, ours_cores=1.2).loaded
    assert not MachineLoad(cores=2, wall_s=10.0, busy_cores=1.5, ours_cores=1.2).loaded


def test_a_run_that_saturates_the_machine_by_itself_fails():
    """Busy 1.95 of 2 cores, 1.90 of them the run's: too big for this machine, not starved."""
    alone = MachineLoad(cores=2, wall_s=10.0, busy_cores=1.95, ours_cores=1.9)
    assert not alone.loaded and LOADED.loaded and not QUIET.loaded
    with pytest.raises(pytest.fail.Exception, match="left alone"):
        judged(_runs(9.0, 9.5)[0], lambda m: m, "x", _machine(alone))


def test_a_missing_report_fails_and_is_never_skipped():
    for load in (QUIET, LOADED):
        with pytest.raises(pytest.fail.Exception, match="did not arrive"):
            judged(lambda: _metrics(None), lambda m: m, "x", _machine(load))
        with pytest.raises(pytest.fail.Exception, match="no report from agent-2"):
            judged(lambda: _metrics(1.0, reports_missing=["agent-2"]), lambda m: m, "x",
                   _machine(load))


def test_the_verdicts_misses_and_stall_count_as_a_missed_clock():
    m = _metrics(1.0, verdict={"on_time": False, "reasons": [
        "robot #1 never settled", "deadline misses beyond 5% of the 400 steps: plant 90 (22%)"]})
    assert clock_missed(m).startswith("deadline misses beyond 5%")
    assert clock_missed(_metrics(1.0, verdict={"on_time": True, "reasons": []})) is None
    late = _metrics(1.0, verdict={"on_time": True, "reasons": [
        "agent-2 restarted by the fault plan but still starting when the run ended"]})
    assert "still starting" in clock_missed(late)  # a start-up the machine starved


def test_the_machine_measurement_sees_a_busy_child_as_ours():
    import subprocess
    import sys

    with measured() as load:
        subprocess.run([sys.executable, "-c", "import time\nt=time.process_time()\n"
                        "while time.process_time() - t < 0.5: pass"], check=True)
    assert load.ours_cores * load.wall_s >= 0.45  # the child's CPU time, once reaped
    assert load.busy_cores is not None and load.busy_cores * load.wall_s >= 0.45
    assert 0 < OTHERS_SHARE < 1


def test_a_nodes_own_report_says_whether_its_loop_kept_its_period():
    import types

    def report(*ms):
        return [types.SimpleNamespace(jitter_ns=[int(x * 1e6) for x in ms])]

    assert loop_missed(report(*[0.2] * 99, 4.9), 0.005, "bridge") is None
    assert "bridge loop jitter p99 5.4 ms > one period 5.0 ms" == loop_missed(
        report(*[5.4] * 100), 0.005, "bridge")
    for missing in ([], [types.SimpleNamespace(jitter_ns=[])]):
        with pytest.raises(pytest.fail.Exception, match="report .* did not arrive"):
            loop_missed(missing, 0.005, "bridge")


def test_the_suites_background_phase_is_not_counted_as_another_program():
    """The suite's first phase, run beside the realtime tests in a group of low CPU weight
    (tests/background_cpu.py), takes only what the run leaves: a run that missed its clock
    beside it fails, and the reason names what the phase took."""
    beside = MachineLoad(cores=2, wall_s=10.0, busy_cores=1.9, ours_cores=0.9,
                         background_cores=0.95)
    assert not beside.loaded and beside.others_cores == pytest.approx(0.05)
    assert "the suite's background phase 0.95" in beside.text()
    with pytest.raises(pytest.fail.Exception, match="left alone"):
        judged(_runs(9.0, 9.5)[0], lambda m: m, "x", _machine(beside))
    # what the group cannot account for is still others'
    assert MachineLoad(cores=2, wall_s=10.0, busy_cores=1.9, ours_cores=0.9,
                       background_cores=0.3).loaded


def test_a_test_own_sign_of_a_missed_clock_retries_and_skips_a_starved_run():
    late = {"settled": False, "reasons": ["robot #1 settled at 6.620 s >= 5.657 s"]}
    calls = []

    def run():
        calls.append(1)
        return _metrics(1.0, verdict=late)  # jitter within the period: the clock looks kept
    assert clock_missed(run()) is None
    calls.clear()
    with pytest.raises(pytest.skip.Exception, match="settled at 6.620 s.*7 deadline misses"):
        judged(run, lambda m: m, "x", _machine(LOADED), missed_also=late_with_misses)
    assert len(calls) == 2
    with pytest.raises(pytest.fail.Exception, match="left alone"):
        judged(run, lambda m: m, "x", _machine(QUIET), missed_also=late_with_misses)


def test_late_settling_without_a_missed_deadline_is_the_code_not_the_clock():
    late = {"settled": False, "reasons": ["robot #1 settled at 6.620 s >= 5.657 s"]}
    assert late_with_misses(_metrics(1.0, verdict=late, deadline_misses=0)) is None
    assert late_with_misses(_metrics(1.0, verdict={"settled": True, "reasons": []})) is None
    assert "robot #1 settled at 6.620 s" in late_with_misses(_metrics(1.0, verdict=late))
