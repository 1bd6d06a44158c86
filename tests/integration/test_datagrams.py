"""The local data path (deploy/runtime/datagrams.py): who gets a key, in order, whole;
what a receiver that reads behind, restarts or is gone costs its sender; and, on real
nodes, that a frame on it is opened, decoded and counted as one from zenoh is."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from deploy.contract.keyring import Keyring, keyring_text, new_master
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import (
    WIRE_VERSION,
    Codec,
    Control,
    Keys,
    Reply,
    Share,
    encode,
    run_roles,
)
from deploy.runtime.datagrams import DatagramPath, Dispatch, key_matches

KEY = "omr/t/robot/1/cmd"


@pytest.fixture()
def run_dir(tmp_path_factory) -> Path:
    # a short path: a unix socket's path is at most 107 bytes
    import tempfile

    return Path(tempfile.mkdtemp(prefix="omf-"))


def _pair(run_dir: Path, lossless: bool = True, **kw) -> tuple[DatagramPath, DatagramPath]:
    rx = DatagramPath(run_dir, "rx", lossless)
    rx.hear(["omr/t/robot/*/cmd"])
    tx = DatagramPath(run_dir, "tx", lossless, **kw)
    tx.refresh()
    return tx, rx


def _frames(rx: DatagramPath, n: int, timeout_s: float = 5.0,
            tx: DatagramPath | None = None) -> list[bytes]:
    """Up to ``n`` frames ``rx`` receives; ``tx``: a sender that sends what it holds as
    the receiver catches up (a node does so before it waits)."""
    out: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        if tx is not None:
            tx.flush()
        f = rx.recv_wait(0.1)
        if f:
            out.append(f)
    return out


def test_key_expressions_match_as_zenoh_matches_them():
    assert key_matches("a/b/c", "a/b/c") and not key_matches("a/b/c", "a/b/d")
    assert key_matches("a/*/c", "a/x/c") and not key_matches("a/*/c", "a/x/y/c")
    assert key_matches("a/**", "a/x/y/c") and key_matches("a/**/c", "a/c")
    assert not key_matches("a/*", "a")


def test_a_key_reaches_whoever_hears_it_whole_and_in_order(run_dir):
    tx, rx = _pair(run_dir)
    other = DatagramPath(run_dir, "other", True)
    other.hear(["omr/t/robot/2/cmd"])
    tx.refresh()
    assert tx.receivers(KEY) == ["rx"]
    payloads = [bytes([i % 251]) * (100 + i) for i in range(300)]
    for p in payloads:
        assert tx.send(KEY, p) == 0
    got = _frames(rx, len(payloads), tx=tx)
    head = bytes((len(KEY),)) + KEY.encode()
    assert got == [head + p for p in payloads]
    assert other.recv() is None  # robot 1's key is not robot 2's
    for d in (tx, rx, other):
        d.close()
    assert not list(run_dir.glob("*.dgram")) and not list(run_dir.glob("*.hears"))


def test_a_receiver_that_reads_behind_holds_its_sender_only_past_the_backlog(run_dir):
    tx, rx = _pair(run_dir, max_backlog=100_000)
    n = 3000  # far more than a connection holds (~170 frames of 400 bytes)
    for i in range(n):
        assert tx.send(KEY, i.to_bytes(4, "big") * 100) == 0
    assert tx.behind and tx.deferred > 0  # held, not lost, and the sender went on
    got: list[bytes] = []
    deadline = time.monotonic() + 10
    while len(got) < n and time.monotonic() < deadline:
        tx.flush()
        f = rx.recv_wait(0.01)
        if f:
            got.append(f)
    assert [int.from_bytes(f[-4:], "big") for f in got] == list(range(n))  # all, in order
    assert not tx.behind and not tx.dropped


def test_a_lossy_sender_drops_its_oldest_held_frame_and_counts_it(run_dir):
    tx, rx = _pair(run_dir, lossless=False, max_backlog=10)
    for i in range(2000):
        tx.send(KEY, i.to_bytes(4, "big") * 100)
    assert tx.dropped["rx"] > 0
    got = _frames(rx, 10_000, timeout_s=1.0, tx=tx)
    # whatever was kept is in order, and the newest frame made it
    ks = [int.from_bytes(f[-4:], "big") for f in got]
    assert ks == sorted(ks) and ks[-1] == 1999


def test_a_lossless_sender_gives_up_on_a_stalled_receiver_after_its_wait(run_dir):
    tx, _rx = _pair(run_dir, max_backlog=5, lossless_wait_s=0.2)
    t0 = time.monotonic()
    lost = sum(tx.send(KEY, b"x" * 4000) for _ in range(400))
    assert lost > 0 and tx.dropped["rx"] == lost
    assert time.monotonic() - t0 < 0.2 * (lost + 2) + 5


def test_a_restarted_receiver_is_dialled_again_and_a_gone_one_costs_a_count(run_dir):
    tx, rx = _pair(run_dir)
    assert tx.send(KEY, b"first") == 0 and _frames(rx, 1)
    rx.close()
    assert tx.send(KEY, b"to nobody") == 1  # gone: counted, never raised
    again = DatagramPath(run_dir, "rx", True)
    again.hear(["omr/t/robot/*/cmd"])
    tx.refresh()
    assert tx.send(KEY, b"second") == 0
    assert _frames(again, 1)[0].endswith(b"second")


def test_connections_opened_ahead_carry_the_first_frame_and_a_missing_receiver_waits(run_dir):
    """``connect_ahead`` opens what the first send would dial (a realtime node does so
    before its first period): the receiver has accepted it before any frame, and the
    first frame goes on it; a receiver not there yet is dialled at the send, as before."""
    tx, rx = _pair(run_dir)
    assert tx.connect_ahead([KEY, "omr/t/robot/1/sample"]) == 1  # nobody hears the sample
    assert rx.recv_wait(0.2) is None  # the accept and the hello: no frame to deliver
    assert len(rx._conns) == 1 and tx.connect_ahead([KEY]) == 0  # opened once
    assert tx.send(KEY, b"first") == 0
    assert _frames(rx, 1)[0].endswith(b"first") and len(rx._conns) == 1
    rx.close()
    late = DatagramPath(run_dir, "late", True)
    late.hear(["omr/t/robot/2/cmd"])
    key2 = "omr/t/robot/2/cmd"
    late.close()  # gone before the node connects ahead: nothing opened, nothing raised
    tx.refresh()
    assert tx.connect_ahead([key2]) == 0
    again = DatagramPath(run_dir, "late", True)
    again.hear([key2])
    tx.refresh()
    assert tx.send(key2, b"dialled at the send") == 0
    assert _frames(again, 1)[0].endswith(b"dialled at the send")


def test_another_thread_wakes_the_waiting_one(run_dir):
    rx = DatagramPath(run_dir, "rx", True)
    threading.Timer(0.05, rx.wake).start()
    t0 = time.monotonic()
    assert rx.recv_wait(5.0) == b""
    assert time.monotonic() - t0 < 2.0


def test_a_short_wait_keeps_its_time_below_a_scheduler_tick(run_dir):
    """A realtime loop's wait of a fraction of a millisecond: a kernel receive timeout
    would round it up to a scheduler tick (4 ms at 250 Hz). The shortest of 20 waits
    (a loaded machine can only make one longer, never shorter), against what a sleep of
    the same length overshot on this machine meanwhile: this test runs beside others at a
    tenth of a process's CPU weight (tests/suite.py), where a fixed bound judged the
    scheduler, not the wait; a timeout in ticks overshoots by milliseconds either way."""
    rx = DatagramPath(run_dir, "rx", True)
    for want in (0.0003, 0.002):
        took, slept = [], []
        for _ in range(20):
            t0 = time.perf_counter()
            assert rx.recv_wait(want) is None
            t1 = time.perf_counter()
            time.sleep(want)
            took.append(t1 - t0)
            slept.append(time.perf_counter() - t1)
        assert want <= min(took) < min(slept) + 0.0015, (want, sorted(took)[:3], min(slept))


def test_dispatch_by_exact_key_and_wildcard_and_counts_what_nobody_hears():
    d = Dispatch()
    heard: list[tuple[str, bytes, str]] = []
    d.add(KEY, lambda p, k: heard.append(("exact", p, k)))
    d.add("omr/t/**", lambda p, k: heard.append(("all", p, k)))
    head = bytes((len(KEY),)) + KEY.encode()
    d(head + b"abc")
    assert heard == [("exact", b"abc", KEY), ("all", b"abc", KEY)]
    d(bytes((5,)) + b"other" + b"x")
    d(b"\x03\xff\xfe\xfdx")  # a key that is not text
    assert d.unheard == 2


def _reply(robot: int) -> bytes:
    z = (0.0, 0.0, 0.0)
    return encode(Reply(WIRE_VERSION, robot, 1, 0, robot=robot, k=0, t=0.0,
                        torques=(1.0,) * 4, v_cmd=z, state_seq=0, state_stamp_ns=0,
                        share=Share(z, z, z, z, z, z)))


def test_a_node_sends_data_on_the_path_and_refuses_a_forgery_there_as_on_zenoh(run_dir):
    """Real nodes, each with its keyring: agent 1's reply reaches the plant on the local
    path (not zenoh), control goes on zenoh, and a reply forged on the path (plain, or
    under another run's keys) is refused before decoding and counted by reason."""
    from deploy.runtime.transport import Node, zenoh_config

    sc = load_scenario("paper")
    keys, master = Keys("t"), new_master()
    roles = [*run_roles(sc.robot_ids), "launcher"]
    ring = {r: Keyring.from_text(keyring_text(master, "t", r, roles), "test", r, sc, keys)
            for r in roles}
    other = Keyring.from_text(keyring_text(new_master(), "t", "agent-1", roles), "x",
                              "agent-1", sc, keys)
    plant = Node("plant", keys, Codec(sc.robot_ids), zenoh_config(gossip=False),
                 keyring=ring["plant"], datagrams=DatagramPath(run_dir, "plant", True))
    agent = Node("agent-1", keys, Codec(sc.robot_ids), zenoh_config(gossip=False), 1,
                 keyring=ring["agent-1"], datagrams=DatagramPath(run_dir, "agent-1", True))
    got: list[Reply] = []
    ctl: list[Control] = []
    try:
        plant.subscribe(keys.cmd(1), Reply, got.append, robot=1)
        plant.subscribe(keys.ctl_all, Control, ctl.append)
        assert list((run_dir / "plant.hears").read_text().split(keys.cmd(1)))[1:]  # heard here
        agent.datagrams.refresh()
        msg = agent.publish(keys.cmd(1), lambda seq, stamp: Reply(
            WIRE_VERSION, 1, seq, stamp, robot=1, k=0, t=0.0, torques=(1.0,) * 4,
            v_cmd=(0.0,) * 3, state_seq=0, state_stamp_ns=0,
            share=Share(*([(0.0,) * 3] * 6))))
        assert msg is not None and keys.cmd(1) not in agent._pubs  # not a zenoh publisher
        forger = DatagramPath(run_dir, "forger", True)
        forger.refresh()
        forger.send(keys.cmd(1), _reply(1))  # plain
        forger.send(keys.cmd(1), other.seal(_reply(1), keys.cmd(1)))  # another run's keys
        plant.mailbox.wait_until(lambda: len(got) >= 1 and sum(plant.refused.values()) >= 2,
                                 5.0)
        assert [m.seq for m in got] == [0]  # the real one, once
        assert plant.refused == {"reply: unsigned": 1, "reply: MAC does not check": 1}
        assert plant.received == {keys.cmd(1): 1}
        forger.close()
    finally:
        agent.close()
        plant.close()


def test_a_connection_is_bound_to_the_role_its_hello_proves_and_to_nothing_else(run_dir):
    """Authenticated connections (docs/hardening.md): agent 1's connection says a hello
    under its key with the plant, and its replies then go untagged and are taken; a hello
    made under another run's keys binds nothing (counted, and what follows on it must
    carry tags that check: it is refused as unsigned); a node of the run bound as itself
    (agent 2, its own keys) is still refused what only agent 1 may send."""
    from deploy.runtime.transport import Node, zenoh_config

    sc = load_scenario("paper")
    keys, master = Keys("t"), new_master()
    roles = [*run_roles(sc.robot_ids), "launcher"]
    ring = {r: Keyring.from_text(keyring_text(master, "t", r, roles), "test", r, sc, keys)
            for r in roles}
    other = Keyring.from_text(keyring_text(new_master(), "t", "agent-1", roles), "x",
                              "agent-1", sc, keys)
    plant = Node("plant", keys, Codec(sc.robot_ids), zenoh_config(gossip=False),
                 keyring=ring["plant"], datagrams=DatagramPath(run_dir, "plant", True))
    got: list[Reply] = []
    sent: list[bytes] = []
    forgers = []
    try:
        plant.subscribe(keys.cmd(1), Reply, got.append, robot=1)
        real = DatagramPath(run_dir, "agent-1", True)
        real.authenticate(ring["agent-1"].hello, ring["agent-1"].hello_from)
        forged = DatagramPath(run_dir, "agent-1x", True)  # another run's agent 1
        forged.authenticate(other.hello, other.hello_from)
        rogue = DatagramPath(run_dir, "agent-2", True)  # agent 2, bound as itself
        rogue.authenticate(ring["agent-2"].hello, ring["agent-2"].hello_from)
        forgers += [real, forged, rogue]
        for path in forgers:
            path.refresh()
        sent.append(_reply(1))
        real.send(keys.cmd(1), sent[0])  # untagged: the connection says who sends it
        forged.send(keys.cmd(1), _reply(1))
        rogue.send(keys.cmd(1), _reply(1))
        plant.mailbox.wait_until(lambda: len(got) >= 1 and sum(plant.refused.values()) >= 2,
                                 5.0)
        assert [encode(m) for m in got] == sent  # the real one, once, as it was sent
        assert plant.datagrams.hellos_refused == 1
        assert plant.refused == {"reply: unsigned": 1,
                                 "reply: not signed by a sender of this key": 1}
    finally:
        for path in forgers:
            path.close()
        plant.close()


class _Looks:
    """Counts how a coalescing listener looks for frames: blocking waits and pauses."""

    def __init__(self, rx: DatagramPath, monkeypatch) -> None:
        self.blocking = self.pauses = 0
        real_wait = rx.recv_wait

        def recv_wait(timeout_s: float):
            self.blocking += timeout_s > 0.0
            return real_wait(timeout_s)
        rx.recv_wait = recv_wait  # the mailbox reads it when it waits
        real_sleep = time.sleep

        def sleep(s: float) -> None:
            self.pauses += 1
            real_sleep(s)
        monkeypatch.setattr("deploy.runtime.transport.time.sleep", sleep)


def test_a_coalescing_listener_hears_every_frame_in_order_and_looks_once_a_pause(
        run_dir, monkeypatch):
    """The launcher's way of hearing a busy fleet (``Mailbox.wait_until(coalesce_s=...)``):
    every frame handled, in order; it pauses at most once per ``coalesce_s`` of the wait,
    and waits to be woken only after a pause that found nothing (or first), however the
    frames are spread (a loaded machine only spreads them more). Without coalescing it
    was woken by nearly every frame."""
    from deploy.runtime.transport import Mailbox

    tx, rx = _pair(run_dir)
    box = Mailbox(rx)
    got: list[bytes] = []
    box.on_datagram = got.append
    pace = time.sleep  # the sender's own, not the listener's counted one
    looks = _Looks(rx, monkeypatch)
    payloads = [i.to_bytes(2, "big") for i in range(200)]

    def send() -> None:
        for p in payloads:
            assert tx.send(KEY, p) == 0
            pace(0.0002)  # a frame every ~0.2 ms, for ~40 ms or more
    sender = threading.Thread(target=send)
    t0 = time.monotonic()
    sender.start()
    assert box.wait_until(lambda: len(got) == len(payloads), 10.0, coalesce_s=0.002)
    took = time.monotonic() - t0
    sender.join()
    head = bytes((len(KEY),)) + KEY.encode()
    assert got == [head + p for p in payloads]
    assert looks.pauses <= took / 0.002 + 1, (looks.pauses, took)
    assert looks.blocking <= looks.pauses + 1, (looks.blocking, looks.pauses)
    tx.close()
    rx.close()


def test_a_quiet_coalescing_listener_waits_for_the_next_frame_without_polling(
        run_dir, monkeypatch):
    """Nothing coming: one blocking wait for the whole timeout, no pauses (coalescing costs
    a quiet listener nothing), and the first frame after the quiet is handled by it."""
    from deploy.runtime.transport import Mailbox

    tx, rx = _pair(run_dir)
    box = Mailbox(rx)
    got: list[bytes] = []
    box.on_datagram = got.append
    tx.send(KEY, b"0")  # connected and accepted before the quiet part
    assert box.wait_until(lambda: bool(got), 10.0)
    got.clear()
    looks = _Looks(rx, monkeypatch)
    assert not box.wait_until(lambda: bool(got), 0.1, coalesce_s=0.002)
    assert looks.pauses == 0 and looks.blocking == 1
    threading.Timer(0.05, lambda: tx.send(KEY, b"x")).start()
    assert box.wait_until(lambda: bool(got), 10.0, coalesce_s=0.002)
    assert looks.pauses == 0 and looks.blocking == 2
    tx.close()
    rx.close()


def test_a_frame_goes_to_the_agents_first_and_to_the_launcher_last(run_dir):
    """Whatever the directory's order: the plant acts on an agent's reply (it steps, or
    ends the run), so every agent that hears the same reply must have it first (an agent
    that ended with the run once reported its neighbour's last share missing)."""
    nodes = []
    for role in ("launcher", "plant", "agent-3", "leader", "agent-2"):
        d = DatagramPath(run_dir, role, True)
        d.hear(["omr/t/robot/*/cmd"])
        nodes.append(d)
    tx = DatagramPath(run_dir, "agent-1", True)
    tx.refresh()
    assert tx.receivers(KEY) == ["agent-2", "agent-3", "leader", "plant", "launcher"]
    for d in (tx, *nodes):
        d.close()


def test_a_frame_that_came_before_the_deadline_counts_though_the_wait_looked_too_late(run_dir):
    """A realtime agent handles a neighbour's share and waits for a core past its deadline,
    while its sample arrives (30 agents at 100 Hz on 2 cores): the sample in the socket
    is handled before the wait says it did not come, not counted as a deadline miss."""
    from deploy.runtime.transport import Mailbox

    rx = DatagramPath(run_dir, "agent", True)
    rx.hear(["omr/t/**"])
    neighbour, plant = DatagramPath(run_dir, "neighbour", True), DatagramPath(run_dir, "plant", True)
    neighbour.refresh()
    plant.refresh()
    box = Mailbox(rx)
    handled: list[str] = []

    def on(frame: bytes) -> None:
        key = frame[1:1 + frame[0]].decode()
        handled.append(key)
        if key.endswith("share") and len(handled) > 2:  # the sample comes meanwhile, and
            assert plant.send("omr/t/robot/1/sample", b"x") == 0  # the deadline passes
            time.sleep(0.6)

    box.on_datagram = on
    for sender, key in ((plant, "omr/t/robot/1/sample"), (neighbour, "omr/t/robot/2/share")):
        assert sender.send(key, b"x") == 0  # both linked, as in a run
    assert box.wait_until(lambda: len(handled) == 2, 5.0)
    share = threading.Timer(0.002, neighbour.send, ("omr/t/robot/2/share", b"x"))
    share.start()  # during the wait
    try:
        assert box.wait_until(lambda: handled[2:][-1:] == ["omr/t/robot/1/sample"], 0.5)
    finally:
        share.join()
    assert handled[2:] == ["omr/t/robot/2/share", "omr/t/robot/1/sample"]
