"""The distributed runtime: one process per node over zenoh on loopback.

Every process a test starts is ended by pid in a ``finally`` (the launcher stops
its own children; the tests check that too)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from outputs_doc import undocumented
from procs import assert_same_series, finish, kill_run, pids_with, start, stat_fields
from realtime_clock import judged

from deploy.report.metrics import control_figures
from deploy.report.timeseries import TimeSeries
from deploy.report.verdict import MAX_MISS_SHARE
from deploy.run.plan import free_tcp_port

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

zenoh = pytest.importorskip("zenoh")

REPO = Path(__file__).resolve().parents[2]
DURATION = "0.3"


@pytest.fixture(scope="module")
def distributed_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    fleet = f"t-equal-{os.getpid()}"
    rc, _, err = finish(start("run", "paper", "--plant", "model", "--duration", DURATION,
                              "--out", str(out), "--no-figures", "--fleet", fleet))
    assert rc == 0, err
    assert not pids_with(fleet), "a node of the run outlived it"
    return out


@pytest.mark.load_safe
def test_lockstep_run_equals_the_in_process_reference(distributed_run, tmp_path):
    rc, _, err = finish(start("run", "paper", "--plant", "model", "--in-process", "--duration",
                              DURATION, "--out", str(tmp_path), "--no-figures"))
    assert rc == 0, err
    a = TimeSeries.load(distributed_run / "timeseries.npz")
    b = TimeSeries.load(tmp_path / "timeseries.npz")
    assert a.steps == b.steps == 300
    assert_same_series(a, b)
    ma = json.loads((distributed_run / "metrics.json").read_text())
    mb = json.loads((tmp_path / "metrics.json").read_text())
    assert control_figures(ma) == control_figures(mb)


@pytest.mark.load_safe
def test_run_reports_processes_messages_and_a_recording(distributed_run):
    from mcap.reader import make_reader

    m = json.loads((distributed_run / "metrics.json").read_text())
    assert undocumented(m) == []  # docs/outputs.md lists every key a fleet's run writes
    assert m["files"] == ["metrics.json", "timeseries.npz", "recording.mcap", "logs/"]
    roles = sorted(p["role"] for p in m["processes"])
    assert roles == ["agent-1", "agent-2", "agent-3", "launcher", "leader", "plant"]
    assert all(p["peak_rss_mb"] and p["peak_rss_mb"] > 0 for p in m["processes"])
    msg = m["messages"]
    assert msg["sent"] > 0 and msg["invalid"] == 0 and msg["late"] == 0 and msg["dropped"] == 0
    from foxglove_decode import decode

    from deploy.report.foxglove_topics import SCENE_ROBOTS

    robots = set()
    with open(distributed_run / "recording.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == m["recording"]["messages"] > 0
        for schema, channel, message in reader.iter_messages():  # as Foxglove decodes them
            value = decode(schema.name, schema.encoding, schema.data, channel.message_encoding,
                           message.data)
            assert message.log_time <= float(DURATION) * 1e9  # lockstep: simulation time
            if channel.topic == SCENE_ROBOTS:
                robots |= {e.id for e in value.entities}
    topics = {c.topic for c in summary.channels.values()}
    assert "/robot/3/cmd" in topics and SCENE_ROBOTS in topics  # no omr/<fleet>/ prefix
    assert robots >= {"robot-1", "robot-2", "robot-3"}


def _robot_messages(path: Path) -> dict[str, list[tuple[int, int, str]]]:
    """Each sample and reply topic's messages: (sequence, log time, the message but the
    monotonic clock stamps of its sender and of the state it answers) in order."""
    from mcap.reader import make_reader

    out: dict[str, list[tuple[int, int, str]]] = {}
    with open(path, "rb") as f:
        for _s, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if channel.topic.startswith("/robot/"):
                value = json.loads(message.data)
                for stamp in ("stamp_ns", "state_stamp_ns"):  # each run's clock its own
                    value.pop(stamp, None)
                out.setdefault(channel.topic, []).append(
                    (message.sequence, message.log_time, json.dumps(value, sort_keys=True)))
    return {topic: sorted(msgs) for topic, msgs in out.items()}


@pytest.mark.load_safe
def test_the_plants_record_of_samples_and_replies_is_what_the_launcher_heard(
        distributed_run, tmp_path):
    """The recording's samples and replies come from the plant's record of them
    (deploy/runtime/wire_spool.py): the same messages, field for field, as a launcher
    that hears them on the wire records, in the same lockstep run."""
    from deploy.contract.scenario import load_scenario
    from deploy.report.recorder import McapRecorder
    from deploy.run.launcher import Launcher, LaunchOptions

    sc = load_scenario("paper")
    recorder = McapRecorder(tmp_path / "recording.mcap", sim_dt=sc.dt)  # as `omnifleet run`'s
    opts = LaunchOptions("paper", "model", "lockstep", tmp_path, duration_s=float(DURATION),
                         fleet=f"t-heard-{os.getpid()}", spool=False, recorder=recorder)
    try:
        Launcher(sc, opts).run()
    finally:
        recorder.close()
    heard = _robot_messages(tmp_path / "recording.mcap")
    spooled = _robot_messages(distributed_run / "recording.mcap")
    assert sorted(heard) == [f"/robot/{r}/{kind}" for r in (1, 2, 3) for kind in ("cmd", "sample")]
    for r in (1, 2, 3):  # every step's sample; every step's reply and the initial share
        assert len(spooled[f"/robot/{r}/sample"]) == 300
        assert len(spooled[f"/robot/{r}/cmd"]) == 301
    assert spooled == heard


@pytest.mark.load_safe
def test_each_agent_hears_only_its_graph_neighbours(distributed_run):
    """paper.toml: a = [[0,0,0],[1,0,0],[1,1,0]], b = [1,0,0] (self loop dropped)."""
    m = json.loads((distributed_run / "metrics.json").read_text())
    heard = {p["role"]: set(p["received"]) for p in m["processes"] if p["role"] != "launcher"}

    def tails(role):
        return {k.split("/", 2)[2] for k in heard[role]}

    # one sample a step from the plant, the neighbours' replies (their shares)
    assert tails("agent-3") == {"robot/3/sample", "robot/1/cmd", "robot/2/cmd", "ctl/tick",
                                "ctl/end"}
    assert tails("agent-2") == {"robot/2/sample", "robot/1/cmd", "ctl/tick", "ctl/end"}
    assert tails("agent-1") == {"robot/1/sample", "leader/state", "ctl/tick", "ctl/end"}
    for key in heard["agent-2"] | heard["agent-3"]:
        assert "leader" not in key
    # and what each heard, it heard every step (300 steps + the initial share)
    received = {p["role"]: p["received"] for p in m["processes"] if p["role"] != "launcher"}
    shares_of_2 = [n for k, n in received["agent-3"].items() if k.endswith("/robot/2/cmd")]
    assert shares_of_2 == [301]
    samples = [n for k, n in received["agent-3"].items() if k.endswith("/robot/3/sample")]
    assert samples == [300]


def _wait_ready(session, fleet: str, roles: set[str], timeout: float, proc=None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise TimeoutError(f"fleet {fleet} ended (exit {proc.returncode}) before a probe "
                               "saw every node ready")
        replies = session.liveliness().get(f"omr/{fleet}/ready/*", timeout=1.0)
        seen = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}
        if roles <= seen:
            return
        time.sleep(0.05)
    raise TimeoutError(f"fleet {fleet} not ready")


NODES = {"plant", "leader", "agent-1", "agent-2", "agent-3"}
# paper runs probed from outside while they go: long enough that the probe's session
# links, sees every node ready and sends before the run ends (1 s of paper, ~1 s of wall
# time on the datagram path, ended before a probe had seen every node once)
PROBED_S = "4.0"


@contextlib.contextmanager
def running_fleet(name: str, *args: str):
    """``omnifleet run paper ARGS`` (ARGS hold --out) with a known endpoint and fleet;
    yields (launcher process, fleet, a zenoh session linked to every node of the run,
    from the run's logs/endpoints.json) once every node is ready. Everything is ended
    by pid on the way out, whatever happened."""
    from deploy.runtime.transport import zenoh_config

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    fleet = f"t-{name}-{os.getpid()}"
    out = Path(args[args.index("--out") + 1])
    proc = start("run", "paper", "--no-figures", "--fleet", fleet, "--endpoint", endpoint,
                 *args)
    session = None
    try:
        where = out / "logs" / "endpoints.json"
        deadline = time.monotonic() + 60
        while not where.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)  # polling for a file another process writes
        endpoints = list(json.loads(where.read_text()).values())
        session = zenoh.open(zenoh_config(connect=endpoints, gossip=False))
        _wait_ready(session, fleet, NODES, 60, proc)
        yield proc, fleet, session
    finally:
        if session is not None:
            session.close()
        kill_run(proc, fleet)


def assert_no_process_left(fleet: str) -> None:
    deadline = time.monotonic() + 5
    while pids_with(fleet) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not pids_with(fleet), "orphans left behind"


def test_garbage_on_every_key_is_refused_counted_and_changes_no_torque(tmp_path):
    from deploy.contract.wire import Keys

    out = tmp_path / "garbage"
    with running_fleet("garbage", "--duration", PROBED_S, "--out", str(out)) as (
            proc, fleet, session):
        keys = Keys(fleet)
        targets = [keys.leader_state, keys.ctl("stop"), keys.ctl("tick"), keys.report("plant"),
                   keys.state_log("plant")]
        for r in (1, 2, 3):
            targets += [keys.sample(r), keys.cmd(r), keys.telemetry(r)]
        wrong_type = json.dumps(None).encode()
        for key in targets:
            for payload in (b"\xc1garbage", b"", wrong_type, b"\x93\x01\x02"):
                session.put(key, payload)
        rc, _, err = finish(proc)
    assert rc == 0, err
    m = json.loads((out / "metrics.json").read_text())
    # every node counts what reached its subscriptions; the launcher hears all keys. None of
    # it is in an envelope of the run's keys: refused before decoding (docs/hardening.md)
    unsigned = sum(n for why, n in m["messages"].get("refused", {}).items()
                   if why.endswith(": unsigned"))
    assert unsigned >= 4 * len(targets) and m["messages"]["invalid"] == 0
    rc, _, err = finish(start("run", "paper", "--in-process", "--duration", PROBED_S,
                              "--out", str(tmp_path / "ref"), "--no-figures"))
    assert rc == 0, err
    a = TimeSeries.load(out / "timeseries.npz")
    b = TimeSeries.load(tmp_path / "ref" / "timeseries.npz")
    assert np.array_equal(a.torque, b.torque), m["messages"]


@pytest.mark.load_safe
def test_sigint_stops_every_process_of_the_run(tmp_path):
    from mcap.reader import make_reader

    with running_fleet("sigint", "--out", str(tmp_path)) as (proc, fleet, _session):
        assert len(pids_with(fleet) - {proc.pid}) >= 5
        os.kill(proc.pid, signal.SIGINT)
        rc, _, err = finish(proc, timeout=30)
        assert_no_process_left(fleet)  # before the fixture's clean-up kills what is left
    assert rc == 130, err
    assert "interrupted" in err
    with open(tmp_path / "recording.mcap", "rb") as f:  # flushed, with its summary
        assert make_reader(f).get_summary() is not None


def _fork_servers_of(launcher: int) -> set[int]:
    return {p for p in pids_with("deploy.nodes.forks")
            if (f := stat_fields(p)) is not None and int(f[1]) == launcher}


@pytest.mark.load_safe
def test_a_launcher_killed_outright_leaves_no_process_behind(tmp_path):
    """SIGKILL gives the launcher no chance to stop anyone: every node, forked and handed
    to it, still ends (the kernel's SIGTERM as its parent dies), and so does the fork
    server. Judged before the fixture's own clean-up kills what is left."""
    with running_fleet("sigkill", "--out", str(tmp_path), "--no-record") as (proc, fleet, _s):
        nodes = pids_with(fleet) - {proc.pid}
        assert len(nodes) >= 5
        assert all(int(stat_fields(p)[1]) == proc.pid for p in nodes)  # the launcher's own
        servers = _fork_servers_of(proc.pid)
        assert len(servers) == 1  # the nodes came from it

        def left() -> set[int]:
            return pids_with(fleet) | {p for p in servers
                                       if (f := stat_fields(p)) is not None and f[0] != "Z"}

        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        deadline = time.monotonic() + 30  # a bound for a loaded machine, not a wait
        while left() and time.monotonic() < deadline:
            time.sleep(0.05)  # polling for the processes to have ended
        assert not left(), "left behind by a launcher killed outright"


@pytest.mark.load_safe
def test_an_agent_for_an_unknown_robot_fails_fast():
    t0 = time.monotonic()
    rc, _, err = finish(start("agent", "--scenario", "paper", "--robot", "7"), timeout=60)
    assert rc == 2
    assert "no robot 7" in err and "1, 2, 3" in err
    assert time.monotonic() - t0 < 30


@pytest.mark.load_safe
def test_a_bad_zenoh_config_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.json5"
    bad.write_text("{ this is not json5")
    rc, _, err = finish(start("agent", "--scenario", "paper", "--robot", "1",
                              "--zenoh-config", str(bad)), timeout=60)
    assert rc == 2 and "zenoh configuration" in err


@pytest.mark.load_safe
def test_a_node_that_dies_fails_the_run_and_is_named(tmp_path):
    with running_fleet("death", "--out", str(tmp_path), "--no-record") as (proc, fleet, _s):
        victim = [p for p in pids_with(fleet) if "--robot 2" in
                  (Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ").decode())]
        assert len(victim) == 1
        os.kill(victim[0], signal.SIGKILL)
        rc, _, err = finish(proc, timeout=60)
        assert_no_process_left(fleet)  # before the fixture's clean-up kills what is left
    assert rc == 1
    assert "agent-2" in err and "FAILED" in err


@pytest.mark.realtime
def test_realtime_run_reports_latency_jitter_and_misses(tmp_path):
    """lab.toml at 200 Hz on the wall clock: every process on its own clock."""
    def run():
        out = tmp_path / f"run-{len(list(tmp_path.iterdir()))}"
        rc, _, err = finish(start("run", "lab", "--clock", "realtime", "--duration", "2.0",
                                  "--out", str(out), "--no-figures", "--no-record"))
        assert rc == 0, err
        return out, json.loads((out / "metrics.json").read_text())
    out, m = judged(run, lambda r: r[1], "lab realtime")
    assert m["clock"] == "realtime"
    assert undocumented(m) == []  # docs/outputs.md lists every key a realtime run writes
    lat, jit = m["latency_ms"], m["jitter_ms"]
    assert 0 < lat["p50"] <= lat["p99"] and jit["p50"] <= jit["p99"] <= 5.0  # one period
    # every node reported its misses, within the verdict's share of the 400 steps
    by_node = m["deadline_misses_by_node"]
    assert set(by_node) == {"leader", "plant", "agent-1", "agent-2", "agent-3"}
    assert sum(by_node.values()) == m["deadline_misses"]
    assert max(by_node.values()) <= MAX_MISS_SHARE * 400 and m["verdict"]["on_time"]
    # whose loop woke late: each node's own p99 (pooled, they make jitter_ms)
    late = m["jitter_p99_ms_by_node"]
    assert {"plant", "agent-1", "agent-2", "agent-3"} <= set(late) <= set(by_node)
    assert all(np.isfinite(v) and v >= 0.0 for v in late.values())
    assert abs(m["steps"] - 400) <= 4  # the plant kept the wall clock
    ts = TimeSeries.load(out / "timeseries.npz")
    assert np.isfinite(ts.torque).all() and np.abs(ts.torque).max() <= 2.0  # lab's limit
    assert m["contacts"] == 0


@pytest.mark.realtime
def test_a_realtime_fleet_holds_the_formation_lockstep_holds(tmp_path):
    """The wall clock behaves like lockstep: each realtime step is built from inputs of one
    step (the leader's and the neighbours' shares of the same k, deploy/nodes/agent.py), so
    lab's formation on the wall clock is the in-process run's (lockstep's, bit for bit):
    its RMS within 10 % per robot, whole run and after settling, over 12 s in which the
    robots cross the room at up to 1.7 m/s. On a quiet machine the two series' poses agree
    to ~1e-14 m; late steps move them apart, which the 10 % allows."""
    def run():
        out = tmp_path / f"rt-{len(list(tmp_path.iterdir()))}"
        rc, _, err = finish(start("run", "lab", "--clock", "realtime", "--plant", "model",
                                  "--duration", "12", "--out", str(out), "--no-figures",
                                  "--no-record"))
        assert rc == 0, err
        return json.loads((out / "metrics.json").read_text())
    rt = judged(run, lambda m: m, "lab realtime, 12 s")
    ref_out = tmp_path / "in-process"
    rc, _, err = finish(start("run", "lab", "--in-process", "--plant", "model", "--duration",
                              "12", "--out", str(ref_out), "--no-figures", "--no-record"))
    assert rc == 0, err
    ref = json.loads((ref_out / "metrics.json").read_text())
    for key in ("formation_rms_whole_run_m", "formation_rms_after_settling_m"):
        for got, want in zip(rt[key], ref[key], strict=True):
            assert got is not None and want is not None and want > 0.1, (key, got, want)
            assert abs(got - want) <= 0.1 * want, (key, rt[key], ref[key])
    assert rt["contacts"] == 0


@pytest.mark.load_safe
def test_a_bad_fleet_name_is_refused_before_anything_starts(tmp_path):
    out = tmp_path / "run"
    rc, _, err = finish(start("run", "paper", "--fleet", "a/b", "--duration", "0.1",
                              "--out", str(out)), timeout=60)
    assert rc == 2 and "fleet name 'a/b'" in err
    assert not out.exists()  # refused before anything was written (an empty recording was)


@pytest.mark.load_safe
@pytest.mark.parametrize("robots", [3, 7])
def test_each_node_links_only_to_the_nodes_it_talks_to(tmp_path, robots):
    """Links as the graph (docs/distributed.md), read from every node's own zenoh session: an
    agent has a link with its plant, the leader iff b_i != 0, its graph neighbours
    in either direction, and the launcher; no other pair of nodes is linked (3:
    paper, whose agents all talk; 7: a binary tree, where most pairs do not)."""
    from deploy.contract.scaled_scenarios import scale_scenario
    from deploy.contract.scenario import load_scenario

    if robots == 3:
        scenario = "paper"
    else:
        scenario = str(tmp_path / "tree.toml")
        Path(scenario).write_text(scale_scenario(robots))
    out = tmp_path / "links"
    rc, _, err = finish(start("run", scenario, "--duration", "0.2", "--out", str(out),
                              "--no-figures", "--no-record"))
    assert rc == 0, err
    m = json.loads((out / "metrics.json").read_text())
    links = {p["role"]: set(p["links"]) for p in m["processes"] if p.get("links") is not None}
    sc = load_scenario(scenario)
    talks = {"plant": {"launcher", "leader"}, "leader": {"launcher", "plant"}}
    talks |= {f"agent-{r}": {"launcher", "plant"} for r in sc.robot_ids}
    for i, r in enumerate(sc.robot_ids):
        me = f"agent-{r}"
        talks["plant"].add(me)
        if sc.leader_weights[i] != 0.0:
            talks[me].add("leader")
            talks["leader"].add(me)
        for j, _w in sc.agent_config(i).neighbours:
            talks[me].add(f"agent-{j}")
            talks[f"agent-{j}"].add(me)
    assert links == talks
    agent_pairs = sum(len(v - {"launcher", "plant", "leader"}) for k, v in links.items()
                      if k.startswith("agent")) // 2
    assert agent_pairs == (3 if robots == 3 else robots - 1)  # a tree: N - 1 edges


def test_a_forged_stop_from_a_peer_on_the_fleet_neither_stops_nor_steers_the_run(tmp_path):
    """Found by probing (docs/hardening.md): a well-formed ``ctl/stop`` or ``ctl/estop`` from any
    process that reached the fleet ended the run early with exit 0, and ``--check``
    passed it. Control is now taken only from the plant or the launcher, authenticated
    with the per-node keys (docs/hardening.md): the forged ones are refused and counted,
    the run goes to its end, equal to the reference."""
    from deploy.contract.wire import WIRE_VERSION, Control, Keys, encode

    out = tmp_path / "forged-stop"
    with running_fleet("forged", "--duration", PROBED_S, "--out", str(out)) as (
            proc, fleet, session):
        keys = Keys(fleet)
        for seq, command in enumerate(("stop", "estop", "end", "stop")):
            forged = Control(WIRE_VERSION, 0, seq, 0, command=command, k=10**9, t=1.0)
            session.put(keys.ctl(command), encode(forged))
        rc, _, err = finish(proc)
    assert rc == 0, err
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == 4000 and m["verdict"]["pass"], m["verdict"]
    refused = m["messages"].get("refused", {})
    assert sum(n for why, n in refused.items() if why.endswith("control: unsigned")) >= 4, refused
    rc, _, err = finish(start("run", "paper", "--in-process", "--duration", PROBED_S,
                              "--out", str(tmp_path / "ref"), "--no-figures"))
    assert rc == 0, err
    assert_same_series(TimeSeries.load(out / "timeseries.npz"),
                       TimeSeries.load(tmp_path / "ref" / "timeseries.npz"))
