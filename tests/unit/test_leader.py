"""The virtual leader: analytic path, tangent heading unwrapped (erratum 6)."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from agents.leader import Harmonic, LeaderGenerator, LeaderSpec, leader_generator
from deploy.contract.scenario import bundled_names, load_scenario


def _run(spec: LeaderSpec, dt: float, steps: int):
    gen = LeaderGenerator(spec, dt)
    qs, vs = [], []
    for _ in range(steps):
        q, v = gen.state()
        qs.append(q)
        vs.append(v)
        gen.advance()
    return np.array(qs), np.array(vs)


def test_paper_leader_is_the_printed_path_with_tangent_heading():
    """q0 = [-40 cos(t + 0.5), 16 sin(2t + 1)], heading = atan2(y0', x0') (mod 2 pi)."""
    sc = load_scenario("paper")
    dt = 1e-3
    q, v = _run(sc.leader_spec(), dt, 3000)
    t = np.arange(3000) * dt
    assert np.allclose(q[:, 0], -40 * np.cos(t + 0.5))
    assert np.allclose(q[:, 1], 16 * np.sin(2 * t + 1))
    tangent = np.arctan2(32 * np.cos(2 * t + 1), 40 * np.sin(t + 0.5))
    assert np.allclose(np.angle(np.exp(1j * (q[:, 2] - tangent))), 0.0, atol=1e-12)


def test_heading_is_unwrapped_and_its_rate_is_its_derivative():
    sc = load_scenario("paper")
    dt = 1e-3
    q, v = _run(sc.leader_spec(), dt, 24000)
    assert np.max(np.abs(np.diff(q[:, 2]))) < 0.5  # continuous: no 2 pi jumps
    fd = np.diff(q, axis=0) / dt
    mid = 0.5 * (v[1:] + v[:-1])
    assert np.allclose(fd, mid, atol=0.05 * np.abs(mid).max())


def test_polar_heading_option_is_the_printed_formula():
    spec = LeaderSpec(Harmonic("cos", -40.0, 1.0, 0.5), Harmonic("sin", 16.0, 2.0, 1.0),
                      heading="polar")
    q, _ = _run(spec, 0.01, 200)
    polar = np.arctan2(q[:, 1], q[:, 0])
    assert np.allclose(np.angle(np.exp(1j * (q[:, 2] - polar))), 0.0, atol=1e-12)


def test_path_follower_starts_at_rest_on_the_path_and_converges():
    """The authors' virtual leader: starts at the path's first point at rest, follows it."""
    spec = load_scenario("reference-code").leader_spec()
    dt = 0.012
    q, v = _run(spec, dt, 2000)
    assert np.allclose(v[0, :2], 0.0)
    th0 = spec.theta0
    assert math.isclose(q[0, 0], 16 * math.sin(2 * th0 + 1))
    t = np.arange(2000) * dt
    th = th0 + spec.theta_rate * t
    path = np.stack([16 * np.sin(2 * th + 1), -40 * np.cos(th + 0.5)], axis=1)
    assert np.linalg.norm(q[-500:, :2] - path[-500:], axis=1).max() < 1.0


@pytest.mark.parametrize("name", [n for n in bundled_names()
                                  if load_scenario(n).leader_spec().steered is None])
def test_a_batch_is_the_states_step_by_step_bit_for_bit(name):
    """The leader node's batches (one loop for a harmonic path) are what state_floats and
    advance give one step at a time, and leave the generator where those leave it."""
    sc = load_scenario(name)
    batched, stepped = (leader_generator(sc.leader_spec(), sc.dt) for _ in range(2))
    rng = random.Random(5)
    for _ in range(60):
        count = rng.randint(1, 40)
        got = batched.batch(count)
        want = ([], [])
        for _ in range(count):
            q, v = stepped.state_floats()
            want[0].append(q)
            want[1].append(v)
            stepped.advance()
        assert got == want and batched.k == stepped.k
        assert batched.state_floats() == stepped.state_floats()  # and from there on, one step
        batched.advance()
        stepped.advance()



@pytest.mark.parametrize("spec", [
    LeaderSpec(Harmonic("cos", -40.0, 1.0, 0.5), Harmonic("sin", 16.0, 2.0, 1.0),
               heading="polar"),
    LeaderSpec(Harmonic("cos", 2.0, 0.5), Harmonic("cos", 1.0, 1.0, 0.3, 0.5),
               kind="path_follower"),
])
def test_a_batch_of_the_other_paths_is_their_steps_too(spec):
    batched, stepped = LeaderGenerator(spec, 0.01), LeaderGenerator(spec, 0.01)
    got = batched.batch(300)
    want = []
    for _ in range(300):
        want.append(stepped.state_floats())
        stepped.advance()
    assert list(zip(*got, strict=True)) == want and batched.k == stepped.k == 300
