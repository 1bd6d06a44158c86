"""can-check --spin: which way a wheel turned is judged by how its speed changed under the
torque, not by the speed it already had (deploy/nodes/can_check.py spin_verdict)."""

import time
from types import SimpleNamespace

from deploy.nodes.can_check import arrival, spin_verdict, spun_long_enough


def test_a_wheel_already_turning_backwards_that_the_torque_slows_turns_with_it():
    # coasting at -2 rev/s (a robot on the ground, moved by the wheels spun before it)
    line = spin_verdict(11, 0.3, -2.0, [-1.9, -1.5, -1.2])
    assert "positive" in line and "against" not in line
    assert "peak 0.800 rev/s at +0.300 N m" in line


def test_a_wheel_that_speeds_up_against_its_torque_is_flagged():
    line = spin_verdict(9, 0.3, 0.0, [-0.2, -0.9, -1.4])
    assert "negative" in line and "turns against the torque" in line


def test_a_negative_torque_that_turns_the_wheel_backwards_agrees():
    line = spin_verdict(8, -0.3, 0.5, [0.3, -0.4])
    assert "negative" in line and "against" not in line


def test_a_wheel_whose_speed_never_changed_did_not_move():
    assert "did not move" in spin_verdict(10, 0.3, 1.0, [1.0, 1.0])


def test_a_spin_lasts_until_its_readings_span_the_spin_time_by_their_arrival():
    """A can-check held off the CPU reads a burst of readings late: the window is theirs
    (when they reached the host), not the loop's clock (deploy/nodes/can_check.py)."""
    started = 1000.0
    assert not spun_long_enough([], started, 0.3)
    assert not spun_long_enough([1000.01, 1000.02], started, 0.3)  # read after 0.3 s or not
    assert spun_long_enough([1000.01, 1000.2, 1000.3], started, 0.3)


def test_a_reading_is_timed_by_the_bus_stamp_unless_it_is_another_clocks():
    now = time.time()
    assert arrival(SimpleNamespace(timestamp=now - 0.25)) == now - 0.25  # the kernel's stamp
    for other in (0.0, None, 12.5):  # none, or an emulator's own time: read now
        assert abs(arrival(SimpleNamespace(timestamp=other)) - time.time()) < 0.5
