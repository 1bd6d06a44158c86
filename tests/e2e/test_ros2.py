"""ROS 2 sees the fleet (docs/ros2.md), checked with code that is not ours: zenoh-ros2-sdk,
a pure-Python implementation of rmw_zenoh's protocol, discovers the run through its
liveliness tokens, computes the RIHS01 hashes itself from ROS 2's .msg definitions
(tests/ros2_msgs, nothing fetched) and subscribes with them; its CDR decoder is
rosbags'. The values it decodes are the run's timeseries.npz at the same stamps.

Each test starts a Zenoh router of its own (``omnifleet router`` on a free loopback
port, ended by pid) and a run of ``lab`` with ``--ros2`` to it."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from procs import finish, kill_run, start

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

REPO = Path(__file__).resolve().parents[2]
MSGS = REPO / "tests" / "ros2_msgs"
ROBOTS = (1, 2, 3)  # lab's
TOPICS = {  # lab on the model plant: every topic and its type
    **{f"/robot_{r}/odom": "nav_msgs/msg/Odometry" for r in ROBOTS},
    **{f"/robot_{r}/cmd_vel": "geometry_msgs/msg/TwistStamped" for r in ROBOTS},
    **{f"/robot_{r}/joint_states": "sensor_msgs/msg/JointState" for r in ROBOTS},
    "/leader/pose": "geometry_msgs/msg/PoseStamped", "/tf": "tf2_msgs/msg/TFMessage",
    "/obstacles": "visualization_msgs/msg/MarkerArray",
    "/fleet/status": "diagnostic_msgs/msg/DiagnosticArray",
}
NODES = {"plant", "leader", "launcher", *(f"agent_{r}" for r in ROBOTS)}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture(scope="module")
def router() -> Iterator[int]:
    """A Zenoh router on a free loopback port (the SDK's session binds to the first one
    it is given: one router for the module)."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", "router", "--listen",
                             f"tcp/127.0.0.1:{port}"], cwd=REPO, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30
        while not _listening(port):
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "the router did not listen within 30 s"
            time.sleep(0.05)  # polling a condition (the port), not standing in for one
        from zenoh_ros2_sdk.message_registry import get_registry

        get_registry(str(MSGS))  # ROS 2's definitions from the repository, never fetched
        yield port
    finally:
        kill_run(proc)


class Heard:
    """Messages an SDK subscriber decoded, with the attachment rmw_zenoh sends."""

    def __init__(self) -> None:
        self.msgs: list = []
        self.lock = threading.Lock()

    def __call__(self, msg) -> None:
        with self.lock:
            self.msgs.append(msg)


def _subscribe(port: int, topic: str, ros_type: str, heard: Heard, **kw):
    from zenoh_ros2_sdk.subscriber import ROS2Subscriber

    return ROS2Subscriber(topic, ros_type, heard, router_port=port, **kw)


def _stamp_s(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _yaw(q) -> float:
    return 2.0 * math.atan2(q.z, q.w)


def test_decoded_topics_equal_the_run_series_at_their_stamps(router, tmp_path: Path):
    """Lockstep, under a namespace: every header is stamped in simulated time, /clock
    (global) moves forward, and robot_1/odom, cmd_vel and joint_states decode to the
    series' values at that step (the twist in the robot's frame, REP 105)."""
    heard = {t: Heard() for t in ("odom", "cmd", "joints", "clock")}
    ns = "/lab_1"  # every topic under it, but /clock
    subs = [_subscribe(router, f"{ns}/robot_1/odom", "nav_msgs/msg/Odometry", heard["odom"]),
            _subscribe(router, f"{ns}/robot_1/cmd_vel", "geometry_msgs/msg/TwistStamped",
                       heard["cmd"]),
            _subscribe(router, f"{ns}/robot_1/joint_states", "sensor_msgs/msg/JointState",
                       heard["joints"]),
            _subscribe(router, "/clock", "rosgraph_msgs/msg/Clock", heard["clock"])]
    out = tmp_path / "run"
    try:
        # 12 s of lab: ~3 s of wall time, ~60 turns of the launcher's loop that publish
        rc, _, err = finish(start("run", "lab", "--plant", "model", "--duration", "12",
                                  "--ros2", f"tcp/127.0.0.1:{router}", "--ros2-rate", "100",
                                  "--ros2-namespace", ns,
                                  "--out", str(out), "--no-figures", "--no-record"))
    finally:
        for s in subs:
            s.close()
    assert rc == 0, err
    assert "ros2: " in err and " 0 errors" in err, err
    series = np.load(out / "timeseries.npz")
    dt = float(series["t"][1] - series["t"][0])
    odom = heard["odom"].msgs
    assert len(odom) >= 5, f"only {len(odom)} odometry messages arrived"
    worst_pose = worst_twist = 0.0
    for m in odom:
        k = round(_stamp_s(m) / dt)
        assert abs(series["t"][k] - _stamp_s(m)) < 1e-9
        q, v = series["q"][k, 0], series["q_dot"][k, 0]
        p = m.pose.pose
        worst_pose = max(worst_pose, abs(p.position.x - q[0]), abs(p.position.y - q[1]),
                         abs(math.remainder(_yaw(p.orientation) - q[2], 2 * math.pi)))
        c, s = math.cos(q[2]), math.sin(q[2])
        body = (c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2])
        tw = m.twist.twist
        worst_twist = max(worst_twist, *(abs(a - b) for a, b in zip(
            (tw.linear.x, tw.linear.y, tw.angular.z), body, strict=True)))
        assert m.header.frame_id == "world" and m.child_frame_id == "robot_1/base_link"
    assert worst_pose < 1e-12 and worst_twist < 1e-12, (worst_pose, worst_twist)
    for m in heard["cmd"].msgs:
        k = round(_stamp_s(m) / dt)
        q, v = series["q"][k, 0], series["v_cmd"][k, 0]
        c, s = math.cos(q[2]), math.sin(q[2])
        assert abs(m.twist.linear.x - (c * v[0] + s * v[1])) < 1e-12
        assert abs(m.twist.angular.z - v[2]) < 1e-12
    joints = heard["joints"].msgs
    assert joints and all(list(m.name) == [f"robot_1/wheel_{w}" for w in range(1, 5)]
                          for m in joints)
    for m in joints:
        k = round(_stamp_s(m) / dt)
        assert np.array_equal(np.asarray(m.effort), series["torque"][k, 0])
    clock = [c.clock.sec + c.clock.nanosec * 1e-9 for c in heard["clock"].msgs]
    assert len(clock) >= 5 and all(b > a for a, b in zip(clock, clock[1:], strict=False))
    assert clock[-1] == pytest.approx(series["t"][-1], abs=1e-9)  # the last row is published


def _tokens(port: int, kind: str) -> list[str]:
    from zenoh_ros2_sdk.session import ZenohSession

    session = ZenohSession.get_instance("127.0.0.1", port)
    return [str(r.ok.key_expr) for r in session.liveliness.get(f"@ros2_lv/0/**/{kind}/**",
                                                                timeout=1.0)
            if r.ok is not None]


def _shapes(markers) -> list[tuple]:
    return [(m.id, m.type, m.pose.position.x, m.pose.position.y, m.scale.x)
            for m in markers.markers]


def _while_running(proc: subprocess.Popen, ask):
    """``ask()`` until it answers (a liveliness query may come back before the router
    has answered for every token, as ``ros2 topic list`` within its spin time), as long
    as the run goes."""
    while proc.poll() is None:
        answer = ask()
        if answer:
            return answer
    pytest.fail(f"the run ended (exit {proc.returncode}) before discovery answered")


def test_a_ros2_graph_discovers_every_node_and_topic_and_the_latched_obstacles(
        router, tmp_path: Path):
    """Realtime: while the run goes, discovery through liveliness tokens (what
    ``ros2 topic list -t`` and ``ros2 topic info -v`` do) finds every topic with its type,
    its publisher's node under /omnifleet, the hash the SDK computes from ROS 2's .msg
    files and the QoS; a subscriber that joins late still gets /obstacles (transient
    local); after the run every token is gone."""
    from zenoh_ros2_sdk.discovery import get_topic_info, get_topic_names_and_types
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability

    ns = ""  # the lockstep test's run is under /lab_1: nothing of it is taken for this one's
    topics_here = {f"{ns}{t}": ty for t, ty in TOPICS.items()}
    proc = start("run", "lab", "--plant", "model", "--clock", "realtime", "--duration", "8",
                 "--ros2", f"tcp/127.0.0.1:{router}", "--ros2-namespace", ns,
                 "--out", str(tmp_path / "run"), "--no-figures", "--no-record")
    try:
        def every_topic():
            found = dict(get_topic_names_and_types(router_port=router, timeout=1.0))
            return found if set(topics_here) <= set(found) else None

        topics = _while_running(proc, every_topic)
        assert {t: topics[t] for t in topics_here} == {t: [ty] for t, ty in topics_here.items()}
        clock = get_topic_info("/clock", router_port=router, verbose=True, timeout=1.0)
        # realtime: the wall clock is ROS 2's time (the lockstep test's run, under /lab_1,
        # may still be leaving the graph)
        assert clock is None or all(p.node_namespace != "/omnifleet" for p in clock.publishers)

        def publishers(topic: str):
            info = get_topic_info(topic, router_port=router, verbose=True, timeout=1.0)
            return None if info is None else info.publishers

        (pub,) = _while_running(proc, lambda: publishers(f"{ns}/robot_1/odom"))
        assert (pub.node_name, pub.node_namespace) == ("plant", f"{ns}/omnifleet")
        sdk = _subscribe(router, f"{ns}/robot_2/odom", "nav_msgs/msg/Odometry", Heard())
        assert pub.type_hash == sdk.type_hash  # the SDK's own hash of ROS 2's definition
        sdk.close()
        qos = QosProfile.decode(pub.qos)
        assert (qos.reliability, qos.durability, qos.history_depth) == (
            QosReliability.RELIABLE, QosDurability.VOLATILE, 10)
        statuses = Heard()
        status_sub = _subscribe(router, f"{ns}/fleet/status",
                                "diagnostic_msgs/msg/DiagnosticArray", statuses)
        (latched,) = _while_running(proc, lambda: publishers(f"{ns}/obstacles"))
        assert QosProfile.decode(latched.qos).durability == QosDurability.TRANSIENT_LOCAL
        nodes = _while_running(proc, lambda: NODES <= (
            found := {k.split("/")[8] for k in _tokens(router, "NN")
                      if k.split("/")[7] == f"{ns}/omnifleet".replace("/", "%")}) and found)
        assert NODES <= nodes, nodes

        def latched_sample():
            markers = Heard()
            _subscribe(router, f"{ns}/obstacles", "visualization_msgs/msg/MarkerArray", markers,
                       qos=QosProfile(durability=QosDurability.TRANSIENT_LOCAL,
                                      history_depth=1)).close()
            return markers.msgs  # the cached sample, queried as the subscriber joined

        # the cached sample (zenoh may answer the query on more than one route: the same
        # sample twice, as happened under CI's load)
        arrays = _while_running(proc, latched_sample)
        array = arrays[0]
        assert all(_shapes(a) == _shapes(array) for a in arrays), len(arrays)
        rc, _, err = finish(proc)
        status_sub.close()
    finally:
        kill_run(proc)
    assert rc == 0, err
    sc = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert sc["scenario"] == "lab"
    # /fleet/status: every process of the run while it goes, each agent's health, and the
    # verdict as the run ends
    during = [{st.name: st for st in m.status} for m in statuses.msgs]
    assert any({f"omnifleet/{r}" for r in ("plant", "leader", "agent_1", "agent_2",
                                           "agent_3", "launcher")} <= set(d) for d in during)
    running = next(d for d in during if "omnifleet/plant" in d)
    assert running["omnifleet/plant"].message == "running"
    assert {kv.key for kv in running["omnifleet/agent_1"].values} >= {
        "process", "speed_factor", "input_age_s", "safety_filter_dv_mps", "deadline_misses"}
    # each agent's deadline misses so far, live: never more than its final report says
    for rid in (1, 2, 3):
        live = [int(v.value) for d in during if f"omnifleet/agent_{rid}" in d
                for v in d[f"omnifleet/agent_{rid}"].values if v.key == "deadline_misses"]
        assert live and live == sorted(live), live
        assert live[-1] <= sc["deadline_misses_by_node"][f"agent-{rid}"]
    last = during[-1]["omnifleet/launcher"].message
    assert last.startswith("verdict: ") and (last == "verdict: PASS") == sc["verdict"]["pass"]
    assert len(array.markers) == 3 and all(m.header.frame_id == "world" for m in array.markers)
    assert not [k for k in _tokens(router, "NN") if f"{ns}/omnifleet/" in k.replace("%", "/")]


@pytest.mark.parametrize("bad", [["--ros2", "localhost"], ["--ros2-rate", "nan"],
                                 ["--ros2", "--ros2-namespace", "/2x"]])
def test_a_bad_ros2_option_exits_2_before_anything_starts(bad, tmp_path: Path):
    out = tmp_path / "run"
    rc, _, err = finish(start("run", "lab", "--duration", "1", "--out", str(out), *bad))
    assert rc == 2, err
    assert "ros2" in err and not out.exists(), err


def test_a_ros2_node_drives_the_leader_and_bad_commands_are_refused(router, tmp_path: Path):
    """teleop (leader.path = "ros2"), realtime: a ROS 2 publisher on /leader/cmd_vel drives
    the leader, bounded by the scenario (0.6 m/s) and stopped by its timeout; malformed
    CDR, NaN twists and a flood are refused and counted, and no robot touches."""
    from zenoh_ros2_sdk.discovery import get_topic_info
    from zenoh_ros2_sdk.publisher import ROS2Publisher

    out = tmp_path / "run"
    proc = start("run", "teleop", "--plant", "model", "--clock", "realtime", "--duration", "9",
                 "--ros2", f"tcp/127.0.0.1:{router}", "--ros2-namespace", "/teleop",
                 "--out", str(out), "--no-figures", "--no-record")
    pub = ROS2Publisher("/teleop/leader/cmd_vel", "geometry_msgs/msg/Twist",
                        router_port=router)
    poses = Heard()
    sub = _subscribe(router, "/teleop/leader/pose", "geometry_msgs/msg/PoseStamped", poses)
    vec = pub.session_mgr.store.types["geometry_msgs/msg/Vector3"]
    try:
        def subscribed():
            info = get_topic_info("/teleop/leader/cmd_vel", router_port=router, verbose=True,
                                  timeout=1.0)
            return info is not None and [s for s in info.subscribers if s.node_name == "leader"]

        _while_running(proc, subscribed)  # the leader's subscription, as ROS 2 sees it
        _while_running(proc, lambda: poses.msgs)  # the run has started
        for _ in range(3):
            pub.pub.put(b"\x00\x01\x00\x00garbage")  # not CDR of a Twist
        for _ in range(4):
            pub.publish(linear=vec(x=math.nan, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
        for _ in range(2000):  # a flood, as fast as this loop goes
            pub.publish(linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
        time.sleep(0.2)  # the next commands come at a teleop's rate: 20 Hz
        lasted = []  # each phase's wall time, as this process kept it
        for vx, seconds in ((3.0, 1.0), (0.3, 2.0)):  # 3 m/s: five times the bound
            began = time.monotonic()
            for _ in range(round(seconds * 20)):
                pub.publish(linear=vec(x=vx, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0))
                time.sleep(0.05)
            lasted.append(time.monotonic() - began)
        rc, _, err = finish(proc)
    finally:
        pub.close()
        sub.close()
        kill_run(proc)
    assert rc == 0, err
    m = json.loads((out / "metrics.json").read_text())
    steer = m["ros2"]["leader_cmd_vel"]
    refused = steer["refused"]
    assert refused.get("not a Twist (11 bytes)") == 3, refused
    assert refused.get("non-finite") == 4, refused
    assert refused.get("over 100 a second", 0) > 1000, refused
    assert steer["taken"] >= 60, steer
    assert m["contacts"] == 0 and m["verdict"]["no_contact"], m["verdict"]["reasons"]
    series = np.load(out / "timeseries.npz")
    q0, v0 = series["leader_q"], series["leader_v"]
    assert np.isfinite(q0).all() and np.isfinite(v0).all()
    speed = np.hypot(v0[:, 0], v0[:, 1])
    assert speed.max() <= 0.6 + 1e-9, speed.max()  # the scenario's bound, never more
    travelled = q0[-1, 0] - q0[0, 0]
    # the first phase at the bound, the second at 0.3 m/s, as long as this process sent
    # them; then at most the 0.5 s timeout at 0.3 m/s more. Each command reaches the leader
    # later by the launcher's loop and the leader's batches (~0.1 s), and the run's
    # processes may lag this one: a few tenths of a metre either way
    sent = 0.6 * lasted[0] + 0.3 * lasted[1]
    assert sent - 0.3 <= travelled <= sent + 0.15 + 0.2, (travelled, lasted)
    assert abs(q0[-1, 1] - q0[0, 1]) < 1e-9 and speed[-1] == 0.0


def test_a_ros2_run_folder_opens_as_a_rosbag2_bag_of_the_run(router, tmp_path: Path):
    """--ros2 with a recording: ros2.mcap and metadata.yaml make the run folder a rosbag2
    bag that rosbags' reader (not ours) opens; every topic at --ros2-rate per simulated
    second, its odometry the series' at its stamps, its types and hashes ROS 2's."""
    from rosbags.rosbag2 import Reader

    from deploy.ros2.types import decode

    out = tmp_path / "run"
    rc, _, err = finish(start("run", "lab", "--plant", "model", "--in-process", "--duration",
                              "3", "--ros2", f"tcp/127.0.0.1:{router}", "--ros2-rate", "20",
                              "--out", str(out), "--no-figures"))
    assert rc == 0, err
    m = json.loads((out / "metrics.json").read_text())
    assert {"recording.mcap", "ros2.mcap", "metadata.yaml"} <= set(m["files"])
    series = np.load(out / "timeseries.npz")
    meta = json.loads((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    hashes = {t["topic_metadata"]["name"]: t["topic_metadata"]["type_description_hash"]
              for t in meta["topics_with_message_count"]}
    with Reader(out) as bag:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in bag.connections}
        assert {t: ty for t, (ty, _) in topics.items()} == {**TOPICS, "/clock":
                                                           "rosgraph_msgs/msg/Clock"}
        rows = len(range(0, 600, 10)) + 1  # 3 s at 200 Hz, every 10th row and the last
        assert topics["/robot_2/odom"][1] == rows and topics["/obstacles"][1] == 1
        worst = 0.0
        for conn, t_ns, raw in bag.messages(connections=[c for c in bag.connections
                                                          if c.topic == "/robot_2/odom"]):
            msg = decode(raw, conn.msgtype)
            k = round(t_ns * 1e-9 / 0.005)
            assert _stamp_s(msg) == pytest.approx(t_ns * 1e-9, abs=1e-9)
            p = msg.pose.pose.position
            worst = max(worst, abs(p.x - series["q"][k, 1, 0]), abs(p.y - series["q"][k, 1, 1]))
        assert worst == 0.0
    from deploy.ros2.types import type_hash

    assert all(h == type_hash(topics[t][0]) for t, h in hashes.items())


def test_a_fleet_started_by_hand_is_seen_through_record(router, tmp_path: Path):
    """Nodes started by hand (as on several machines) and `omnifleet record --ros2`: the
    recorder's gateway publishes what it hears; odometry decodes to its series."""
    port = _free_port()
    heard = Heard()
    sub = _subscribe(router, "/by_hand/robot_1/odom", "nav_msgs/msg/Odometry", heard)
    common = ("--scenario", "lab", "--duration", "3")
    procs = [start("record", *common, "--listen", f"tcp/127.0.0.1:{port}", "--out",
                   str(tmp_path / "rec"), "--no-figures", "--ros2", f"tcp/127.0.0.1:{router}",
                   "--ros2-namespace", "/by_hand")]
    try:
        node = ("--connect", f"tcp/127.0.0.1:{port}", "--wait-recorder")
        procs += [start("plant", *common, *node, "--plant", "model"),
                  start("leader", *common, *node)]
        procs += [start("agent", *common, *node, "--robot", str(r)) for r in ROBOTS]
        results = [finish(p) for p in procs]
    finally:
        sub.close()
        for p in procs:
            kill_run(p)
    assert [rc for rc, _, _ in results] == [0] * len(procs), [e for _, _, e in results]
    assert "ros2: " in results[0][2] and " 0 errors" in results[0][2], results[0][2]
    series = np.load(tmp_path / "rec" / "timeseries.npz")
    assert len(heard.msgs) >= 3
    for m in heard.msgs:
        k = round(_stamp_s(m) / 0.005)
        assert (m.pose.pose.position.x, m.pose.pose.position.y) == tuple(series["q"][k, 0, :2])


@pytest.mark.parametrize("how", [["--clock", "realtime"], ["--ros2"], ["--in-process"]])
def test_a_steered_leader_runs_only_realtime_with_ros2(how, tmp_path: Path):
    """teleop's leader follows ROS 2: without --ros2, or on the lockstep clock (in process
    too), nothing could steer it, and the run says so before anything starts (exit 2)."""
    out = tmp_path / "run"
    rc, _, err = finish(start("run", "teleop", "--duration", "1", "--out", str(out), *how))
    assert rc == 2, err
    assert 'leader.path = "ros2"' in err and "--clock realtime --ros2" in err, err
    assert not (out / "metrics.json").exists()
