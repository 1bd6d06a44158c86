"""rmw_zenoh's names, tokens, QoS strings and attachments as deploy/ros2/graph.py writes
them, read back by code that is not ours: zenoh-ros2-sdk's token parser and QoS decoder,
zenoh's own serializer for the attachment, and the SDK's own RIHS01 hashes from ROS 2's
.msg files (tests/ros2_msgs) against rosbags' store; the messages, decoded by rosbags,
say what the series said."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from deploy.ros2 import fleet_messages as fm
from deploy.ros2.graph import (
    TRANSIENT_LOCAL,
    Qos,
    Ros2NameError,
    Ros2Node,
    attachment,
    check_namespace,
    data_key,
    gid,
    parse_attachment,
)
from deploy.ros2.options import Ros2OptionError, ros2_options
from deploy.ros2.types import decode, encode, type_hash

sdk = pytest.importorskip("zenoh_ros2_sdk")
MSGS = Path(__file__).resolve().parents[1] / "ros2_msgs"
PUBLISHED = (fm.ODOM, fm.CMD_VEL, fm.JOINTS, fm.POSE, fm.TF, fm.MARKERS, fm.STATUS, fm.CLOCK,
             fm.TWIST)


def test_data_keys_are_domain_topic_dds_type_and_hash():
    h = type_hash(fm.ODOM)
    assert data_key(3, "/lab/robot_1/odom", fm.ODOM, h) == \
        f"3/lab/robot_1/odom/nav_msgs::msg::dds_::Odometry_/{h}"


def test_the_sdk_parses_our_tokens_into_what_we_declared():
    from zenoh_ros2_sdk.discovery import _parse_liveliness_keyexpr
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability

    node = Ros2Node(7, "ab12", 4, "/lab/omnifleet", "agent_2")
    assert node.token() == "@ros2_lv/7/ab12/4/4/NN/%/%lab%omnifleet/agent_2"
    token = node.endpoint_token(9, "MP", "/lab/obstacles", fm.MARKERS, type_hash(fm.MARKERS),
                                Qos(durability=TRANSIENT_LOCAL, depth=1))
    parsed = _parse_liveliness_keyexpr(token)
    assert {k: parsed[k] for k in ("domain_id", "session_id", "node_id", "entity_id", "kind",
                                   "namespace", "node_name", "qualified_name", "dds_type")} == {
        "domain_id": 7, "session_id": "ab12", "node_id": 4, "entity_id": 9, "kind": "MP",
        "namespace": "/lab/omnifleet", "node_name": "agent_2", "qualified_name": "/lab/obstacles",
        "dds_type": "visualization_msgs::msg::dds_::MarkerArray_"}
    qos = QosProfile.decode(parsed["qos"])
    assert (qos.reliability, qos.durability, qos.history_depth) == (
        QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, 1)
    assert QosProfile.decode(Qos().token()).history_depth == 10


def test_the_attachment_is_what_zenohs_serializer_writes():
    from zenoh.ext import Int64, z_serialize

    g = gid("ab12", 1, 2)
    raw = attachment(41, 1_700_000_000_123_456_789, g)
    assert raw == z_serialize((Int64(41), Int64(1_700_000_000_123_456_789), g)).to_bytes()
    assert parse_attachment(raw) == (41, 1_700_000_000_123_456_789, g)
    assert len(g) == 16 and g != gid("ab12", 1, 3)
    with pytest.raises(ValueError):
        parse_attachment(raw[:-1])


@pytest.mark.parametrize("ros_type", PUBLISHED)
def test_type_hashes_agree_with_the_sdk_hash_of_ros2_definitions(ros_type):
    from zenoh_ros2_sdk.message_registry import MessageRegistry
    from zenoh_ros2_sdk.utils import get_type_hash, load_dependencies_recursive

    registry = MessageRegistry(str(MSGS))
    path = registry.get_msg_file_path(ros_type)
    assert path is not None and path.is_relative_to(MSGS), "kept in the repository"
    text = path.read_text()
    deps = load_dependencies_recursive(ros_type, text, registry)
    assert get_type_hash(ros_type, msg_definition=text, dependencies=deps) == type_hash(ros_type)


def test_odometry_twist_is_in_the_robot_frame_and_decodes_to_the_state():
    q, q_dot = np.array([1.0, -2.0, 0.7]), np.array([0.3, 0.4, -0.1])
    msg = decode(encode(fm.odometry(2, 5_250_000_000, q, q_dot)), fm.ODOM)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (5, 250_000_000)
    assert (msg.header.frame_id, msg.child_frame_id) == ("world", "robot_2/base_link")
    p, tw = msg.pose.pose, msg.twist.twist
    assert (p.position.x, p.position.y) == (1.0, -2.0)
    assert 2 * math.atan2(p.orientation.z, p.orientation.w) == pytest.approx(0.7, abs=1e-15)
    # rotated back into the world, the twist is q_dot again (eq. 3)
    c, s = math.cos(0.7), math.sin(0.7)
    world = (c * tw.linear.x - s * tw.linear.y, s * tw.linear.x + c * tw.linear.y)
    assert world == pytest.approx((0.3, 0.4), abs=1e-15) and tw.angular.z == -0.1


def test_status_and_markers_carry_what_they_are_given():
    msg = decode(encode(fm.status(0, [("omnifleet/agent_1", "warn", "no command met every "
                                       "barrier", {"t_s": "1.000"})])), fm.STATUS)
    (st,) = msg.status
    assert (st.level, st.name, st.values[0].key, st.values[0].value) == (
        1, "omnifleet/agent_1", "t_s", "1.000")
    shapes = fm.ObstacleShapes(discs=[(1.0, 2.0, 0.0)], polygons=[[(0, 0), (1, 0), (0, 1)]])
    markers = decode(encode(fm.obstacle_markers(0, shapes)), fm.MARKERS).markers
    assert [m.type for m in markers] == [3, 4]  # a cylinder, a closed outline
    assert markers[0].scale.x == 2 * fm.MIN_DRAWN_RADIUS_M  # a point obstacle, drawn
    assert len(markers[1].points) == 4 and markers[1].points[0].x == markers[1].points[-1].x


def test_namespaces_are_checked_as_ros2_does():
    assert check_namespace("") == "" and check_namespace("/") == ""
    assert check_namespace("lab/run_2/") == "/lab/run_2"
    for bad in ("/2lab", "/la-b", "/a//b"):
        with pytest.raises(Ros2NameError):
            check_namespace(bad)


class _Args:
    def __init__(self, ros2="tcp/127.0.0.1:7447", ns="", rate=50.0):
        self.ros2, self.ros2_namespace, self.ros2_rate = ros2, ns, rate


def test_options_refuse_a_bad_endpoint_domain_or_namespace(monkeypatch):
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    opts = ros2_options(_Args())
    assert (opts.endpoint, opts.domain, opts.namespace) == ("tcp/127.0.0.1:7447", 0, "")
    assert ros2_options(_Args(ros2=None)) is None
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert ros2_options(_Args()).domain == 42
    for bad in ("x", "-1", "233", "4.5"):
        monkeypatch.setenv("ROS_DOMAIN_ID", bad)
        with pytest.raises(Ros2OptionError, match="ROS_DOMAIN_ID"):
            ros2_options(_Args())
    monkeypatch.delenv("ROS_DOMAIN_ID")
    with pytest.raises(Ros2OptionError, match="endpoint"):
        ros2_options(_Args(ros2="localhost"))
    with pytest.raises(Ros2OptionError, match="namespace"):
        ros2_options(_Args(ns="/a b"))


def test_the_packed_bytes_are_rosbags_bytes_for_any_row():
    """The gateway's CDR (layouts rosbags made, numbers packed in) equals rosbags' own
    encoding of the same messages, for random rows of a three-robot run."""
    from deploy.contract.scenario import load_scenario
    from deploy.report.timeseries import TimeSeries

    sc = load_scenario("lab")
    ts = TimeSeries.allocate(50, sc.n)
    rng = np.random.default_rng(7)
    for name in ("q", "q_dot", "v_cmd", "torque", "leader_q"):
        getattr(ts, name)[:] = rng.normal(0.0, 3.0, getattr(ts, name).shape)
    fast, slow = fm.frames_for(sc), fm.frames_for(sc)
    for k in (0, 7, 31, 49):
        ns = 1_700_000_000_123_456_789 + k * 5_000_000
        packed = fast.encoded(ts, k, ns)
        built = slow.messages(ts, k, ns)
        assert [(t, ty) for t, ty, _ in packed] == [(t, m.__msgtype__) for t, m in built]
        assert [b for _, _, b in packed] == [encode(m) for _, m in built]
        assert fast.clock_bytes(ns) == encode(fm.clock(ns))


def test_joint_positions_integrate_the_models_wheel_speeds_however_rows_are_batched():
    """/robot_N/joint_states: each wheel's angle is the sum of the plant model's own wheel
    speeds (eq. 1, MecanumModel.wheel_speeds) over every row times dt, its velocity the
    newest row's, whether the gateway reads the rows one at a time or ten at once."""
    from deploy.contract.scenario import load_scenario
    from deploy.report.timeseries import TimeSeries

    sc = load_scenario("lab")
    model, steps = sc.model(), 40
    ts = TimeSeries.allocate(steps, sc.n)
    rng = np.random.default_rng(3)
    ts.q[:] = rng.normal(0.0, 2.0, ts.q.shape)
    ts.q_dot[:] = rng.normal(0.0, 1.0, ts.q_dot.shape)
    expected = np.zeros((sc.n, 4))
    for k in range(steps):
        expected += sc.dt * np.array([model.wheel_speeds(ts.q[k, i, 2], ts.q_dot[k, i])
                                      for i in range(sc.n)])
    one, ten = fm.frames_for(sc), fm.frames_for(sc)
    for k in range(steps):
        one.advance(ts, k)
    for k in range(9, steps, 10):
        ten.advance(ts, k)
    for frames in (one, ten):
        np.testing.assert_allclose(frames.wheel_angle, expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(frames.wheel_speed, [
            model.wheel_speeds(ts.q[-1, i, 2], ts.q_dot[-1, i]) for i in range(sc.n)],
            rtol=1e-12, atol=1e-12)
