"""The bridge's pure parts: wheel odometry (eq. 1 and the pose integration) and
the command gate that decides what torque may reach the bus."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridges.odometry import Odometry
from bridges.safety import ZERO, CommandGate
from deploy.scenario import load_scenario


@pytest.fixture(scope="module")
def model():
    return load_scenario("lab").model()


def wheel_speeds_of(model, body_twist) -> np.ndarray:
    """theta_dot = P v_r / R: the inverse of eq. (1) in the body frame."""
    return model.P @ np.asarray(body_twist, float) / model.params.wheel_radius_m


def test_body_twist_inverts_the_wheel_kinematics(model):
    odo = Odometry(model, np.zeros(3))
    for twist in ([1.0, 0.0, 0.0], [0.0, -0.7, 0.0], [0.0, 0.0, 2.0], [0.3, 0.4, -1.1]):
        assert np.allclose(odo.body_twist(wheel_speeds_of(model, twist)), twist, atol=1e-12)


def test_constant_twist_follows_the_exact_arc(model):
    v, w, dt, T = 1.0, 0.5, 0.005, 2.0
    odo = Odometry(model, np.zeros(3))
    speeds = wheel_speeds_of(model, [v, 0.0, w])
    for _ in range(int(round(T / dt))):
        odo.update(speeds, dt)
    exact = np.array([v / w * math.sin(w * T), v / w * (1 - math.cos(w * T)), w * T])
    assert np.abs(odo.q - exact).max() < 1e-6  # mid-heading integration: exact on arcs up to rounding
    assert np.allclose(odo.q_dot, [v * math.cos(w * T), v * math.sin(w * T), w], atol=1e-12)


def test_strafe_moves_sideways_in_the_world_frame(model):
    odo = Odometry(model, np.array([1.0, 2.0, math.pi / 2]))
    for _ in range(100):
        odo.update(wheel_speeds_of(model, [0.0, 0.5, 0.0]), 0.01)
    # heading +90 deg: body +y is world -x
    assert np.allclose(odo.q, [1.0 - 0.5, 2.0, math.pi / 2], atol=1e-12)


def test_gate_passes_fresh_commands_clamped_to_the_limit():
    gate = CommandGate(0.1, 2.0)
    gate.command((1.0, -3.0, 2.5, 0.0), now_s=10.0)
    d = gate.decide(10.05, faulted=False)
    assert d.armed and d.torques == (1.0, -2.0, 2.0, 0.0) and d.reason == "command"


@pytest.mark.parametrize("case", ["none", "stale", "faulted", "estop", "nan"])
def test_gate_gives_zero_torque_and_disarms(case):
    gate = CommandGate(0.1, 2.0)
    now = 5.0
    if case != "none":
        gate.command((math.nan, 0.0, 0.0, 0.0) if case == "nan" else (1.0, 1.0, 1.0, 1.0), now)
    if case == "stale":
        now += 0.1 + 1e-9
    if case == "estop":
        gate.estop()
        gate.command((1.0, 1.0, 1.0, 1.0), now)  # a later command does not undo an e-stop
    d = gate.decide(now, faulted=case == "faulted")
    assert d.torques == ZERO and not d.armed


def test_gate_timeout_must_be_positive():
    with pytest.raises(ValueError):
        CommandGate(0.0, 1.0)
