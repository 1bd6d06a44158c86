"""A leader steered from outside (agents/steered_leader.py; leader.path = "ros2"): the pose
integrated from the body twist through T(psi) of eq. (3), within the scenario's bounds,
stopped by the command timeout; the scenario loader and the ROS 2 decoder refuse what
cannot be used."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from agents.steered_leader import SteeredLeader, SteeredSpec, bounded
from deploy.contract.scenario import ScenarioError, load_scenario
from deploy.ros2 import fleet_messages as fm
from deploy.ros2.steering import twist_of
from deploy.ros2.types import encode, make

SPEC = SteeredSpec(start=(1.0, 2.0, math.pi / 2), max_speed_mps=0.6, max_yaw_rate_radps=0.5,
                   timeout_s=0.5)


def test_a_body_twist_moves_the_leader_through_its_heading():
    lead = SteeredLeader(SPEC, 0.01)
    lead.steer((0.4, 0.0, 0.0), t_received=0.0)  # forward, facing +y
    for _ in range(50):
        lead.advance()
    (x, y, psi), (vx, vy, wz) = lead.state_floats()
    assert (x, y, psi) == pytest.approx((1.0, 2.2, math.pi / 2), abs=1e-12)
    assert (vx, vy, wz) == pytest.approx((0.0, 0.4, 0.0), abs=1e-12)


def test_commands_are_bounded_in_speed_and_yaw_rate_keeping_their_direction():
    vx, vy, wz = bounded(SPEC, (3.0, 4.0, -2.0))
    assert math.hypot(vx, vy) == pytest.approx(0.6) and vx / vy == pytest.approx(0.75)
    assert wz == -0.5
    assert bounded(SPEC, (0.1, 0.2, 0.3)) == (0.1, 0.2, 0.3)


def test_the_leader_stops_when_no_command_came_for_the_timeout():
    lead = SteeredLeader(SPEC, 0.01)
    assert lead.state_floats()[1] == (0.0, 0.0, 0.0)  # no command yet: at rest
    lead.steer((0.2, 0.0, 0.1), t_received=0.0)
    for _ in range(50):  # 0.5 s: the command is exactly as old as the timeout
        lead.advance()
    assert lead.state_floats()[1] != (0.0, 0.0, 0.0)
    lead.advance()
    assert lead.state_floats()[1] == (0.0, 0.0, 0.0)
    moved = lead.state_floats()[0]
    lead.advance()
    assert lead.state_floats()[0] == moved


def _steered_lab(tmp_path: Path, leader: str) -> Path:
    text = (Path(__file__).resolve().parents[2] / "deploy/scenarios/teleop.toml").read_text()
    start, end = text.index("[leader]"), text.index("[formation]")
    path = tmp_path / "s.toml"
    path.write_text(text[:start] + "[leader]\n" + leader + "\n" + text[end:])
    return path


@pytest.mark.parametrize(("leader", "key"), [
    ('path = "ros2"', "leader.speed_mps"),
    ('path = "ros2"\nspeed_mps = 0.5\nx = { fn = "cos", amp = 1.0, freq = 1.0 }', "leader.x"),
    ('path = "ros2"\nspeed_mps = -1.0', "leader.speed_mps"),
    ('path = "ros2"\nspeed_mps = 0.5\nstart = [0.0, 0.0]', "leader.start"),
    ('path = "ros2"\nspeed_mps = 0.5\nkind = "path_follower"', "leader.kind"),
    ('path = "ros2"\nspeed_mps = 0.5\ncommand_timeout_s = 0.0', "leader.command_timeout_s"),
    ('x = { fn = "cos", amp = 1.0, freq = 1.0 }\ny = { fn = "sin", amp = 1.0, freq = 1.0 }\n'
     'start = [0.0, 0.0, 0.0]', "leader.start"),
])
def test_the_loader_names_what_a_steered_leader_cannot_take(tmp_path, leader, key):
    with pytest.raises(ScenarioError, match=f"`{key}`"):
        load_scenario(str(_steered_lab(tmp_path, leader)))


def test_the_bundled_teleop_leader_starts_on_its_start_pose():
    spec = load_scenario("teleop").leader_spec().steered
    assert spec == SteeredSpec((-3.8, -2.2, 0.0), 0.6, 0.5, 0.5)


def test_only_a_finite_twist_is_taken_from_ros2():
    twist = make(fm.TWIST, linear=make("geometry_msgs/msg/Vector3", x=0.3, y=-0.1),
                 angular=make("geometry_msgs/msg/Vector3", z=0.2))
    assert twist_of(encode(twist)) == (0.3, -0.1, 0.2)
    nan = make(fm.TWIST, linear=make("geometry_msgs/msg/Vector3", x=math.nan))
    with pytest.raises(ValueError, match="non-finite"):
        twist_of(encode(nan))
    with pytest.raises(ValueError, match="not a Twist"):
        twist_of(b"\x00\x01\x00\x00" + bytes(10))
    with pytest.raises(ValueError, match="malformed CDR"):
        twist_of(b"\xff\xff\x00\x00" + bytes(48))  # an encapsulation CDR does not have


def test_only_the_launcher_may_steer_the_leader_and_only_the_leader_hears_it():
    """Nothing from ROS 2 reaches a robot but through its agent: the gateway's command
    goes launcher -> leader, authenticated (deploy/contract/audience.py)."""
    from deploy.contract.audience import fleet_roles, publishes, receives
    from deploy.contract.wire import Keys

    sc, keys = load_scenario("teleop"), Keys("t")
    roles = fleet_roles(sc)
    steer = keys.leader_steer
    assert {r for r in roles if r != "router" and steer in publishes(r, sc, keys, roles)} == {
        "launcher"}
    assert {r for r in roles if steer in receives(r, sc, keys, roles)} == {
        "leader", "launcher", "router"}
