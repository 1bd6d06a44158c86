"""``[limits] max_tracking_error``: anti-windup on the CLIK reference q_d of eq. (11).

q_d is integrated open loop from v_d. A robot held back (by a hand, an obstacle,
or its agent and bridge off the CPU on a loaded host) leaves q_d running ahead,
and with v_d at the speed limit the robot can never catch up: the position term
then drags it along q_d's path. In a loaded can-emulated lab run this ended in 6
contacts. The cap keeps q_d within the bound of the robot; on a healthy run it
never acts (lab's start-up transient peaks at 9-11 cm, the cap is 20 cm).

Oracle: lab's robot 1 (it needs only the leader) on the model plant, eq. (4),
held still for 1 s at t = 3 s while its agent keeps stepping.
"""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from agents.core import AgentCore
from agents.leader import LeaderGenerator
from deploy.contract.scenario import Scenario, load_scenario
from deploy.run.runner import run_in_process
from plant.disturbance import make_disturbance
from plant.model_plant import ModelPlant
from plant.perception import sense

pytestmark = [pytest.mark.slow]

HOLD = (3.0, 4.0)
AFTER_S = 8.0


def lab_with_cap(cap: float) -> Scenario:
    sc = load_scenario("lab")
    spec = msgspec.structs.replace(
        sc.spec, limits=msgspec.structs.replace(sc.spec.limits, max_tracking_error=cap))
    return type(sc)(sc.path, spec, sc.adjacency, sc.leader_weights, sc.notes)


def held_robot_errors(sc: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """||e|| of robot 1 stepping on the model plant, held still during HOLD."""
    spec, dt, model = sc.spec, sc.dt, sc.model()
    q, qd = sc.initial_state()
    q0h, v0h = sc.initial_estimates(0)
    agent = AgentCore(sc.agent_config(0, model), q[0], qd[0], q0h, v0h)
    d = spec.disturbance
    plant = ModelPlant([model], q[0:1], qd[0:1],
                       make_disturbance(d.kind, d.scale, tuple(d.constant_nm)), spec.plant.substeps)
    leader = LeaderGenerator(sc.leader_spec(), dt)
    obstacles_map = sc.obstacle_bodies()
    steps = int(round((HOLD[1] + AFTER_S) / dt))
    t, err = np.arange(steps) * dt, np.empty(steps)
    for k in range(steps):
        robots, obstacles = sense(0, plant.q[:, :2], plant.q_dot[:, :2], [spec.robot.body_radius_m],
                                  [1], obstacles_map, spec.behaviors.detection_range_m)
        out = agent.step(t[k], plant.q[0], plant.q_dot[0], {}, leader.state(), obstacles, robots)
        err[k] = np.linalg.norm(out.tracking_error)
        if HOLD[0] <= t[k] < HOLD[1]:
            plant.q_dot[:] = 0.0  # held still
        else:
            plant.step(t[k], dt, np.array([out.torques]), np.array([out.v_cmd]))
        leader.advance()
    return t, err


def at(t: np.ndarray, err: np.ndarray, after_release_s: float) -> float:
    return float(err[np.searchsorted(t, HOLD[1] + after_release_s)])


def test_without_the_cap_the_reference_winds_up_and_the_error_grows_again():
    t, err = held_robot_errors(lab_with_cap(math.inf))
    print(f"\nno cap: ||e|| at release {at(t, err, 0) * 100:.0f} cm, +0.5 s "
          f"{at(t, err, 0.5) * 100:.0f} cm, +1 s {at(t, err, 1.0) * 100:.0f} cm, "
          f"+8 s {at(t, err, 7.99) * 100:.0f} cm")
    assert err[t >= HOLD[1]].max() > 1.0  # measured 1.42 m
    assert at(t, err, 1.0) > 0.5  # measured 1.27 m: v_d at the speed limit, q_d ahead
    assert at(t, err, 1.0) > at(t, err, 0.5)  # it grows again (measured 42 -> 127 cm)
    assert at(t, err, 7.99) > 0.1  # measured 15.6 cm after 8 s


def test_with_the_cap_the_reference_stays_by_the_robot_and_it_catches_up_at_once():
    sc = load_scenario("lab")
    cap = sc.spec.limits.max_tracking_error
    band = sc.spec.metrics.settle_threshold
    assert band < cap < math.inf  # the cap must not hide a settling failure
    t, err = held_robot_errors(sc)
    print(f"\ncap {cap}: max ||e|| {err.max() * 100:.1f} cm, +0.5 s after release "
          f"{at(t, err, 0.5) * 100:.1f} cm, +8 s {at(t, err, 7.99) * 100:.1f} cm")
    assert err.max() <= cap + 1e-12
    assert at(t, err, 0.5) < band  # measured 2.3 cm
    # what stays (up to 8.6 cm over 8 s) is the paper's slow observer unlearning the
    # "disturbance" that held the robot (mu2 = 0.2; docs/hardware.md)
    assert err[t >= HOLD[1] + 0.5].max() < cap


def test_the_cap_never_acts_on_a_healthy_run():
    """lab in lockstep on the model plant, 8 s: bit-identical with and without the cap."""
    capped = run_in_process(load_scenario("lab"), "model", duration_s=8.0).series
    free = run_in_process(lab_with_cap(math.inf), "model", duration_s=8.0).series
    # the start-up transient peaks at 9.2 cm here (10-11 cm in realtime), below the cap
    assert np.linalg.norm(capped.e, axis=2).max() < 0.75 * load_scenario("lab").spec.limits.max_tracking_error
    for name in ("q", "torque", "q_d", "e"):
        assert np.array_equal(getattr(capped, name), getattr(free, name)), name


def test_the_cap_must_be_positive(tmp_path):
    from deploy.contract.scenario import ScenarioError

    text = Path(load_scenario("lab").path).read_text().replace(
        "max_tracking_error = 0.2", "max_tracking_error = 0.0")
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ScenarioError, match="max_tracking_error"):
        load_scenario(bad)
