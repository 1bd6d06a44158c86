"""A disturbance that starts per robot (the drive emulators': from each robot's first
arming) is evaluated in the model plant's kernel, and moves the robots exactly as the same
function of t staged in Python at the RK4 stages' times does (the general path)."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.contract.scenario import load_scenario
from plant.disturbance import StartedDisturbance, make_disturbance
from plant.model_plant import ModelPlant


@pytest.mark.parametrize("kind", ["paper", "constant", "none"])
def test_the_kernel_gives_what_the_staged_function_gives_bit_for_bit(kind):
    sc = load_scenario("lab")
    q, qd = sc.initial_state()
    d = make_disturbance(kind, 1.5, (0.2, -0.1, 0.05, 0.3))
    models = [sc.model()] * sc.n
    in_kernel, staged = StartedDisturbance(d, sc.n), StartedDisturbance(d, sc.n)
    a = ModelPlant(models, q, qd, in_kernel, substeps=1)
    b = ModelPlant(models, q, qd, lambda t: staged(t), substeps=1)  # any function of t
    rng = np.random.default_rng(7)
    starts = {40: (0, 0.0403), 250: (2, 0.2507), 251: (0, 9.0)}  # robot 0's second: ignored
    for k in range(600):
        if k in starts:
            for dist in (in_kernel, staged):
                dist.begin(*starts[k])
        u = rng.normal(scale=0.5, size=(sc.n, 4))
        a.step(k * 0.005, 0.005, u, None)
        b.step(k * 0.005, 0.005, u, None)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.q_dot, b.q_dot)
    assert in_kernel.start[0] == pytest.approx(0.0403) and np.isnan(in_kernel.start[1])


def test_a_robot_that_never_started_feels_nothing():
    sc = load_scenario("lab")
    q, qd = sc.initial_state()
    d = make_disturbance("constant", 1.0, (2.0, 2.0, 2.0, 2.0))  # far beyond friction
    started = StartedDisturbance(d, sc.n)
    started.begin(0, 0.0)
    plant = ModelPlant([sc.model()] * sc.n, q, qd, started, substeps=1)
    for k in range(200):
        plant.step(k * 0.005, 0.005, np.zeros((sc.n, 4)), None)
    assert np.abs(plant.q[0] - q[0]).max() > 1e-3  # pushed
    assert np.array_equal(plant.q[1:], q[1:])  # untouched: no torque, no disturbance
