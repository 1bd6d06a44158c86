"""Leader paths through waypoints (agents/waypoint_path.py) and per-robot scale: the
leader's velocity, acceleration and heading rate are the derivatives of its position
(checked by finite differences, the estimator and the ESO use them), the speed profile
is the one asked for, the path passes through every waypoint, and the loader refuses
what cannot be driven, naming the key."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scenario_edits import WALL_GAP, refused

from agents.leader import LeaderGenerator
from agents.waypoint_path import SpeedProfile, waypoint_path
from deploy.contract.scenario import SCENARIO_DIR, ScenarioError, load_scenario, parse_scenario
from deploy.report.targets import FormationTargets

POINTS = [[-3.0, 0.0], [0.0, 0.5], [3.0, 0.0], [6.0, 1.0], [6.5, 3.0]]


def test_velocity_acceleration_and_heading_rate_are_the_derivatives_of_the_position():
    path = waypoint_path(POINTS, speed=0.8, accel=0.5)
    h = 1e-5
    for t in np.linspace(0.05, path.profile.duration - 0.05, 200):
        p, v, a, psi, w = path.state(t)
        (pm, vm, _, psim, _), (pp, vp, _, psip, _) = path.state(t - h), path.state(t + h)
        # central differences: error ~ h^2 |p'''| plus the arc-length table's ~1e-7
        assert np.allclose((pp - pm) / (2 * h), v, atol=5e-7), t
        assert np.allclose((vp - vm) / (2 * h), a, atol=5e-6), t
        dpsi = math.remainder(psip - psim, 2 * math.pi)
        assert dpsi / (2 * h) == pytest.approx(w, abs=5e-6), t
        assert psi == pytest.approx(math.atan2(v[1], v[0]), abs=1e-9) or np.hypot(*v) < 1e-9


def test_speed_profile_from_rest_to_rest_through_every_waypoint():
    path = waypoint_path(POINTS, speed=0.8, accel=0.5)
    ts = np.linspace(0.0, path.profile.duration + 1.0, 4001)
    states = [path.state(t) for t in ts]
    speed = np.array([np.hypot(*s[1]) for s in states])
    assert speed[0] == 0.0 and speed[-1] == 0.0
    assert speed.max() == pytest.approx(0.8)  # cruises at speed_mps
    along = np.diff(speed) / np.diff(ts)
    assert np.abs(along).max() <= 0.5 + 1e-9  # ramps at accel_mps2
    assert np.allclose(states[0][0], POINTS[0]) and np.allclose(states[-1][0], POINTS[-1])
    # the spline interpolates: every waypoint is on the path the leader drives
    pos = np.array([s[0] for s in states])
    for w in POINTS:
        assert np.hypot(*(pos - w).T).min() < 0.8 * (ts[1] - ts[0]) + 1e-9
    # travelled = path length
    assert np.sum(np.hypot(*np.diff(pos, axis=0).T)) == pytest.approx(path.length, rel=1e-5)


def test_a_short_path_is_a_triangle_that_never_reaches_cruise_speed():
    prof = SpeedProfile(length=1.0, speed=5.0, accel=1.0)
    assert prof.duration == pytest.approx(2.0)
    assert prof.at(0.5) == pytest.approx((0.125, 0.5, 1.0))
    assert prof.at(1.0)[:2] == pytest.approx((0.5, 1.0))  # the peak speed, half-way
    assert prof.at(1.5) == pytest.approx((0.875, 0.5, -1.0))
    assert prof.at(2.0)[:2] == pytest.approx((1.0, 0.0))


def test_the_leader_generator_follows_the_waypoint_path():
    sc = load_scenario("wall-gap")
    gen = LeaderGenerator(sc.leader_spec(), sc.dt)
    path = sc.leader_spec().waypoints
    for _ in range(250):
        q0, v0 = gen.state()
        p, v, _, psi, w = path.state(gen.t)
        assert np.allclose(q0[:2], p) and np.allclose(v0[:2], v)
        assert q0[2] == pytest.approx(psi) and v0[2] == pytest.approx(w)
        gen.advance()
    assert sc.initial_estimates(0)[0][:2] == pytest.approx(POINTS_WALL_GAP_START)


POINTS_WALL_GAP_START = [1.4, 0.0]


@pytest.mark.parametrize("old, new, key, words", [
    ('path = "waypoints"', 'path = "spline"', "leader.path", "expected one of: harmonic, waypoints"),
    ('path = "waypoints"\n', "", "leader.waypoints", 'only with path = "waypoints"'),
    ("speed_mps = 1.0\n", "", "leader.speed_mps", 'required with path = "waypoints"'),
    ("accel_mps2 = 1.0", "accel_mps2 = 0.0", "leader.accel_mps2", "must be > 0"),
    ("speed_mps = 1.0", "speed_mps = -1.0", "leader.speed_mps", "must be > 0"),
    ("waypoints = [[1.4, 0.0], [2.5, 0.0],", "waypoints = [[1.4, 0.0], [1.4, 0.0],",
     "leader.waypoints[1]", "repeats the point before it"),
    ("[6.0, 2.0]]", "[6.0, 2.0, 1.0]]", "leader.waypoints[4]", "expected 2 numbers"),
    ("waypoints = [[1.4, 0.0], [2.5, 0.0], [3.6, 0.0], [5.0, 0.6], [6.0, 2.0]]",
     "waypoints = [[1.4, 0.0]]", "leader.waypoints", "at least 2 points"),
    ('heading = "tangent"', 'heading = "tangent"\nx = { fn = "sin", amp = 1.0, freq = 1.0 }',
     "leader.x", 'only with path = "harmonic"'),
    ("speed_mps = 1.0", "sped_mps = 1.0", "leader", "did you mean `speed_mps`"),
])
def test_a_bad_waypoint_leader_is_refused_naming_the_key(old, new, key, words):
    msg = refused(old, new)
    assert "mine.toml" in msg and f"`{key}`" in msg and words in msg, msg


def test_a_harmonic_leader_needs_x_and_y():
    lab = (SCENARIO_DIR / "lab.toml").read_text()
    line = next(ln for ln in lab.splitlines() if ln.startswith("y = "))
    with pytest.raises(ScenarioError, match=r"`leader.y`: required with path = \"harmonic\""):
        parse_scenario(lab.replace(line + "\n", ""), "mine.toml")


def test_per_robot_scale_overrides_the_formation_for_that_robot_only():
    text = WALL_GAP.replace("offset = [-1.6, 0.0]", "offset = [-1.6, 0.0]\ninitial_scale = [0.5, 1.0]\n"
                            "scale_changes = [{ start_s = 1.0, end_s = 2.0, to = [1.0, 1.0] }]")
    sc = parse_scenario(text, "mine.toml")
    assert sc.agent_config(2).initial_scale == (0.5, 1.0)
    assert [c.to for c in sc.agent_config(2).scale_changes] == [(1.0, 1.0)]
    assert sc.agent_config(1).initial_scale == (1.0, 1.0) and sc.agent_config(1).scale_changes == ()
    q0, v0 = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    targets = FormationTargets(sc)
    assert np.allclose(targets.at(0.0, q0, v0)[1:], [[-0.8, 0.0], [-0.8, 0.0]])  # 0.5 x 1.6
    assert np.allclose(targets.at(2.5, q0, v0)[2], [-1.6, 0.0])  # back to its own offset
    bad = text.replace("start_s = 1.0, end_s = 2.0", "start_s = 2.0, end_s = 1.0")
    with pytest.raises(ScenarioError, match=r"`robots\[2\].scale_changes\[0\]`: windows"):
        parse_scenario(bad, "mine.toml")
    with pytest.raises(ScenarioError, match=r"`robots\[2\].initial_scale`: expected 2"):
        parse_scenario(text.replace("initial_scale = [0.5, 1.0]", "initial_scale = [0.5]"), "m")
