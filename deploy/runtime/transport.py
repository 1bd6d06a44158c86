"""Zenoh I/O for every node: session from flags or a config file, typed
publishers and subscribers over the wire contract, liveliness, counters.

This is the only module (with the launcher) that imports zenoh; the math in
``agents/`` and ``plant/`` never sees it.

Receive where you work (docs/distributed.md): every subscription is a *direct* zenoh
callback (``indirect=False``: it runs on zenoh's own receive thread, no extra
Python thread) that only copies the payload into the node's :class:`Mailbox`, a
``queue.SimpleQueue``. The node's working thread decodes, validates and handles
each message when it waits (:meth:`Mailbox.wait_until`), so handlers run on the
thread that computes: no Condition hand-off, no lock contention. Measured on the
2-core machine (ping-pong / 2, 300 B, zenoh 1.10): indirect callback +
Condition p50 85-89 µs, direct callback + SimpleQueue 85-87 µs, ``FifoChannel.recv``
78-80 µs; with zenoh's runtime cut to one worker per pool 80 and 60 µs; with
the ``lowlatency`` transport 58-68 and 56-58 µs (docs/distributed.md). The queue
is chosen over one FifoChannel per subscription because a node waits on several
keys at once with a deadline, which ``recv()`` (no timeout, one channel) cannot.
"""

from __future__ import annotations

import json
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from deploy.contract.keyring import WRONG_SENDER, Keyring
from deploy.contract.wire import (
    LAUNCHER_ROLE,
    MAX_REPORT_KEYS,
    WIRE_VERSION,
    Codec,
    Control,
    Keys,
    LeaderState,
    Message,
    NodeReport,
    Reply,
    Sample,
    StateLog,
    Telemetry,
    encode,
)
from deploy.runtime.datagrams import DATA_KINDS, DatagramPath, Dispatch
from deploy.runtime.step_costs import DECODE, HANDLE, MAC, RECEIVE, SEND, StepCosts, now_ns
from deploy.runtime.step_costs import ENCODE as ENCODE_PART
from deploy.runtime.wire_spool import SpoolWriter

MAX_PEER_EVENTS = 10_000
# distinct keys counted in Node.received: a wildcard subscription (ctl/*) hears any key a
# peer makes up, and a report with more than MAX_REPORT_KEYS entries does not decode
MAX_RECEIVED_KEYS = MAX_REPORT_KEYS // 2
# what a refused message was, in its reason ("reply: MAC does not check")
WHAT = {Sample: "sample", Reply: "reply", LeaderState: "leader", Control: "control",
        NodeReport: "report", Telemetry: "telemetry", StateLog: "state log"}


# zenoh's connect retry: period_init_ms 1000 by default (then x2, up to 4 s)
CONNECT_RETRY = {"period_init_ms": 50, "period_max_ms": 2000, "period_increase_factor": 2}


class TransportError(RuntimeError):
    """Bad endpoint or zenoh configuration (exit code 2 at the CLI)."""


def zenoh_config(
    config_file: str | Path | None = None,
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    gossip: bool = True,
    lowlatency: bool = False,
) -> Any:
    """A peer configuration: explicit endpoints, multicast scouting off.

    With a config file, the file decides everything and ``listen``/``connect``
    are added to it. ``gossip`` on (zenoh's default): peers that connect to one
    common endpoint learn of each other and link directly (every pair: a full
    mesh). Off: a peer links only to the endpoints it is given, so the launcher
    hands each node the endpoints of the nodes it talks to (links as the graph).
    ``lowlatency``: zenoh's low-latency unicast transport (a put is written by the
    publishing thread, no transmit task to wake; QoS off, so no priorities): both
    ends of a link must ask for it, else zenoh falls back to the default transport.
    """
    import zenoh

    try:
        if config_file is not None:
            cfg = zenoh.Config.from_file(str(config_file))
        else:
            cfg = zenoh.Config()
            cfg.insert_json5("mode", '"peer"')
            cfg.insert_json5("scouting/multicast/enabled", "false")
            # a peer dialled before it listens (the nodes of a run start at once) is
            # dialled again after 50 ms, not zenoh's default 1 s (a run's start-up)
            cfg.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
            if not gossip:
                cfg.insert_json5("scouting/gossip/enabled", "false")
            if lowlatency:
                cfg.insert_json5("transport/unicast/lowlatency", "true")
                cfg.insert_json5("transport/unicast/qos/enabled", "false")
        listen, connect = list(listen), list(connect)
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps(listen))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(connect))
    except Exception as exc:  # zenoh raises its own ZError for bad JSON5/keys
        raise TransportError(f"zenoh configuration: {exc}") from exc
    return cfg


@dataclass
class Counters:
    sent: int = 0
    dropped: int = 0  # could not be sent (transport error) or discarded on arrival
    late: int = 0  # arrived after its step's deadline, or a step ran without it
    invalid: int = 0  # failed validation at decode
    nonfinite: int = 0  # values this node computed that were NaN or Inf (note_nonfinite)


BEHIND_RETRY_S = 0.002  # a waiting node with frames held for a slow receiver retries this often
# Mailbox.sleep_until looks at the stop flag at least this often, a backstop only: every
# stop of a node wakes its wait (a signal's handler and a lost peer's timer post to the
# mailbox; a stop message arrives on it). At 0.05 s the leader, whose waits are 100 ms
# batches at 200 Hz, woke twice a batch: 36.9-41.1 -> 32.0-32.5 µs a step (the CAN fleet)
MAX_WAIT_S = 1.0


class Mailbox:
    """Everything that arrives for a node, handled on the node's working thread.

    zenoh's receive threads (and the node's own helper threads: fault delays,
    timers, signal handlers) only ``post`` an item; :meth:`wait_until` takes the
    items and runs their handlers on the waiting thread until ``ready()`` holds or
    the timeout passes. ``lock`` is held while a handler runs: a helper thread that
    reads what handlers write takes it too (the node's own thread never waits for it).

    With a datagram path (deploy/runtime/datagrams.py) the waiting thread blocks on the
    node's socket instead: datagrams are handled as they are read (``on_datagram``),
    and a ``post`` from another thread wakes it with an empty datagram.
    """

    def __init__(self, datagrams: DatagramPath | None = None) -> None:
        self.lock = threading.RLock()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._dgram = datagrams
        self.on_datagram: Callable[[bytes], None] = lambda frame: None
        # the node's step costs: a frame's reading and handling is ``receive`` (its
        # handler moves its own parts out: Node.subscribe)
        self.costs = StepCosts()

    def post(self, handler: Callable[[Any], None], item: Any = None) -> None:
        """From any thread (a signal handler too): run ``handler(item)`` on the
        node's thread at its next wait."""
        self._queue.put((handler, item))
        if self._dgram is not None:
            self._dgram.wake()

    def wake(self) -> None:
        """Make a waiter re-check its condition (the stop flag)."""
        self.post(_nothing, None)

    def _run(self, entry: tuple[Callable[[Any], None], Any]) -> None:
        handler, item = entry
        if self._dgram is not None:  # not a frame of the datagram path: no kernel stamp,
            self._dgram.arrived_unix_ns = None  # no authenticated connection
            self._dgram.frame_from = None
        t0 = now_ns()
        with self.lock:
            handler(item)
        self.costs.ns[RECEIVE] += now_ns() - t0

    def drain(self, until: float | None = None) -> None:
        """Handle everything already arrived, without waiting; with ``until`` (a
        time.monotonic()), stop there even if more keeps arriving."""
        q, dgram = self._queue, self._dgram
        n = 0
        while True:
            while not q.empty():
                self._run(q.get_nowait())  # one consumer: what empty() saw is still there
                n += 1
                if until is not None and n % 32 == 0 and time.monotonic() >= until:
                    return
            if dgram is None:
                return
            t0 = now_ns()
            with self.lock:
                woke = dgram.read_ready(self.on_datagram, until)
            self.costs.ns[RECEIVE] += now_ns() - t0
            if not woke or q.empty() or (until is not None and time.monotonic() >= until):
                return

    def _ready_at_deadline(self, ready: Callable[[], bool]) -> bool:
        """``ready()`` once what had already arrived is handled (at most a batch, as
        ``drain(until=now)`` takes): a wait's deadline can pass while this process waits
        for a core with its inputs in the socket, and a frame handled just before it (a
        neighbour's share) left the sample behind it unread. 30 agents at 100 Hz on 2
        cores counted such samples as deadline misses."""
        if ready():
            return True
        self.drain(time.monotonic())
        return ready()

    def wait_until(self, ready: Callable[[], bool], timeout_s: float, bounded: bool = False,
                   ready_first: bool = False, coalesce_s: float = 0.0) -> bool:
        """Handle arrivals until ``ready()`` holds (True) or ``timeout_s`` passes
        (False). Everything already arrived is handled before the first check,
        unless ``bounded``: then the wait returns by its timeout even when messages
        arrive faster than their handlers run (the launcher, recording a loaded fleet:
        its kill schedule waited for the traffic to stop, and an agent planned to be
        killed at 4 s was killed after the run had ended). ``ready_first``: return at
        once if ``ready()`` already holds (a lockstep step's inputs: what arrived for
        later steps can wait; saves a system call). ``coalesce_s`` (a listener off the
        fleet's path, on the datagram path): while frames keep coming, look for them
        once every ``coalesce_s`` and handle all that came meanwhile, instead of being
        woken by each; a look that finds nothing waits for the next frame as usual.

        Why: recording ``paper``, the launcher hears ~11,000 frames a second and was
        woken ~5,900 times a second, each wake-up a context switch here and in the
        sender that woke it, and on 2 cores often a run process of the chain put off
        the CPU. Looking every 2 ms (3 alternating pairs of ``run paper --no-figures``):
        the launcher's CPU 9.6-9.9 -> 7.6-8.2 s, every process's 25.9-27.2 -> 23.4-24.4
        s, the run 13.9-14.6 -> 13.2-13.7 s; 5 ms did no better (docs/bench-history.md)."""
        if ready_first and ready():
            return True
        deadline = time.monotonic() + timeout_s
        self.drain(deadline if bounded else None)
        if ready():
            return True
        if self._dgram is not None:
            dgram = self._dgram
            recv_wait, on, q = dgram.recv_wait, self.on_datagram, self._queue
            came = False  # coalescing: something came since the last look
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    return self._ready_at_deadline(ready)
                if dgram.behind:  # frames held for a slow receiver: send them first,
                    dgram.flush()  # and look again soon if it is still behind
                    if dgram.behind:
                        left = min(left, BEHIND_RETRY_S)
                if coalesce_s > 0.0:
                    frame = recv_wait(0.0)
                    if frame is None and came:  # still coming: look again in a while
                        came = False
                        time.sleep(min(coalesce_s, left))
                        continue
                    if frame is None:  # quiet: wake at the next frame
                        frame = recv_wait(left)
                    came = frame is not None
                else:
                    frame = recv_wait(left)
                if frame:
                    t0 = now_ns()
                    with self.lock:
                        on(frame)
                    self.costs.ns[RECEIVE] += now_ns() - t0
                while not q.empty():  # posted by another thread (its wake-up: b"")
                    self._run(q.get_nowait())
                if ready():
                    return True
        get = self._queue.get
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return self._ready_at_deadline(ready)
            try:
                entry = get(timeout=left)
            except queue.Empty:
                return self._ready_at_deadline(ready)
            self._run(entry)
            self.drain(deadline if bounded else None)
            if ready():
                return True


    def sleep_until(self, until: float, stop: Callable[[], bool]) -> None:
        """Wait until ``until`` (time.monotonic()) or ``stop()``, handling what wakes the
        node meanwhile (what another thread posts; on the datagram path the frames that
        wake it, :meth:`Node.wake_on`, and any found readable), one at a time: a flood
        never holds the wait past ``until``. A realtime loop's wait for its next period:
        one blocking wait when nothing comes, where :meth:`wait_until` looks again
        before and after it (a period of ``Periodic`` took 4 looks and a wait)."""
        q, dgram = self._queue, self._dgram
        if dgram is None:
            while not stop():
                left = until - time.monotonic()
                if left <= 0:
                    return
                try:
                    entry = q.get(timeout=min(left, MAX_WAIT_S))
                except queue.Empty:
                    continue
                self._run(entry)
            return
        on, recv_wait = self.on_datagram, dgram.recv_wait
        while not stop():
            left = until - time.monotonic()
            if left <= 0:
                return
            if dgram.behind:  # frames held for a slow receiver: send them first
                dgram.flush()
                if dgram.behind:
                    left = min(left, BEHIND_RETRY_S)
            frame = recv_wait(min(left, MAX_WAIT_S))
            if frame:
                t0 = now_ns()
                with self.lock:
                    on(frame)
                self.costs.ns[RECEIVE] += now_ns() - t0
            while not q.empty():  # posted by another thread (its wake-up: b"")
                self._run(q.get_nowait())


def _nothing(_item: Any) -> None:
    pass


class Node:
    """One zenoh peer: session, liveliness token, typed pub/sub, counters."""

    def __init__(
        self,
        role: str,
        keys: Keys,
        codec: Codec,
        config: Any,
        sender: int = 0,
        lossless: bool = True,
        keyring: Keyring | None = None,
        datagrams: DatagramPath | None = None,
    ) -> None:
        """``keyring``: this node's keys (deploy/contract/keyring.py): every message it
        sends is sealed for its receivers, and every message it hears is refused and
        counted unless a sender of its key tagged it for this node, before it is
        decoded. None (a node started by hand without keys): neither.
        ``datagrams``: the run's datagram path on this host (deploy/runtime/datagrams.py):
        the data keys go there to the nodes of the run's directory, zenoh carries the
        rest (and still hears the data keys, from anyone else)."""
        import zenoh

        self._zenoh = zenoh
        self.role = role
        self.keys = keys
        self.codec = codec
        self.sender = sender
        self.counters = Counters()
        self.received: dict[str, int] = {}  # valid messages per key (what we really heard)
        self.datagrams = datagrams
        self.mailbox = Mailbox(datagrams)
        self.costs = self.mailbox.costs  # where its run loop spends its time (step_costs.py)
        self._dispatch = Dispatch()
        self.mailbox.on_datagram = self._dispatch
        self._by_datagram: dict[str, bool] = {}  # key -> sent on the datagram path
        self.lossless = lossless
        self._version_warned = False
        self.links_noted: list[str] | None = None
        self.refused: dict[str, int] = {}  # messages refused on arrival, by reason
        self.keyring = keyring
        if keyring is not None and datagrams is not None:  # connections that say who we are
            datagrams.authenticate(keyring.hello, keyring.hello_from)
        # this node's own record of what it sends and hears on some keys, for the run's
        # recording on this host (deploy/runtime/wire_spool.py); None: no record
        self.spool: SpoolWriter | None = None
        try:
            self.session = zenoh.open(config)
        except Exception as exc:
            raise TransportError(f"cannot open a zenoh session: {exc}") from exc
        self._subs: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._seq: dict[str, int] = {}
        self._tokens: list[Any] = []
        self.peers_alive: set[str] = set()
        # (unix ns, role, alive): every appearance and loss of a peer's alive token
        self.peer_events: list[tuple[int, str, bool]] = []
        self.peers_ready: set[str] = set()
        self.required: set[str] = set()  # roles whose disappearance ends this node
        self.on_lost: Callable[[str], None] = lambda role: None
        self._watch_liveliness()

    # -- liveliness -----------------------------------------------------------------
    def _watch_liveliness(self) -> None:
        keys = self.keys

        put = self._zenoh.SampleKind.PUT

        def on_token(event: tuple[str, bool, int, set[str]]) -> None:  # node's thread
            role, alive, at_ns, bag = event
            if bag is self.peers_alive and len(self.peer_events) < MAX_PEER_EVENTS:
                self.peer_events.append((at_ns, role, alive))
            if self.datagrams is not None and bag is self.peers_alive:
                self.datagrams.refresh()  # who hears what here: a peer came or went
            if alive:
                bag.add(role)
            else:
                bag.discard(role)
                if bag is self.peers_alive and role in self.required:
                    self.on_lost(role)

        def arrived(sample: Any, bag: set[str]) -> None:  # zenoh's thread
            self.mailbox.post(on_token, (keys.role_of(str(sample.key_expr)),
                                         sample.kind == put, time.time_ns(), bag))

        lv = self.session.liveliness()
        self._subs.append(lv.declare_subscriber(
            keys.alive_all, self._direct(lambda s: arrived(s, self.peers_alive)), history=True))
        self._subs.append(lv.declare_subscriber(
            keys.ready_all, self._direct(lambda s: arrived(s, self.peers_ready)), history=True))

    def _direct(self, fn: Callable[[Any], None]) -> Any:
        """A callback zenoh runs on its receive thread (no extra Python thread)."""
        return self._zenoh.handlers.Callback(fn, indirect=False)

    def declare_alive(self) -> None:
        """Declare after every subscriber: a peer that sees the token has them."""
        self._tokens.append(self.session.liveliness().declare_token(self.keys.alive(self.role)))

    def declare_ready(self) -> None:
        self._tokens.append(self.session.liveliness().declare_token(self.keys.ready(self.role)))

    def declare_filed(self, role: str) -> None:
        """The launcher: ``role``'s report is in hand (its node may close now)."""
        self._tokens.append(self.session.liveliness().declare_token(self.keys.filed(role)))

    def wait_filed(self, timeout_s: float) -> bool:
        """After this node's report: stay until the launcher says it holds it, at most
        ``timeout_s``; at once when no launcher is in the run (a fleet started by hand or
        by ``deploy plan``). zenoh drops what a closing session still has queued for a
        peer: a report queued behind the traffic of a launcher that records (and reads
        seconds behind at 500 Hz) was lost when its node closed right after the put."""
        if LAUNCHER_ROLE not in self.peers_alive:
            return True
        filed: list[bool] = []
        self._subs.append(self.session.liveliness().declare_subscriber(
            self.keys.filed(self.role),
            self._direct(lambda s: self.mailbox.post(filed.append, True)), history=True))
        return self.mailbox.wait_until(
            lambda: bool(filed) or LAUNCHER_ROLE not in self.peers_alive, timeout_s)

    def wait_for_roles(self, roles: Iterable[str], bag: str, timeout_s: float,
                       should_stop: Callable[[], bool] = lambda: False) -> set[str]:
        """Wait until every role's token is seen; return the ones still missing."""
        wanted = set(roles)
        seen = self.peers_alive if bag == "alive" else self.peers_ready
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if self.mailbox.wait_until(lambda: wanted <= seen or should_stop(),
                                       min(max(left, 0.0), 0.2)):
                break
            if left <= 0:
                break
        return wanted - seen

    # -- data -------------------------------------------------------------------------
    def publish(self, key: str, msg_factory: Callable[[int, int], Message],
                checked: bool = False) -> Message | None:
        """Build the message with (seq, stamp_ns) and put it on ``key``. A message
        that fails its own validation (a NaN) is not sent: counted as dropped.
        ``checked``: the caller has checked every float of the message against the
        wire's bound (:data:`deploy.contract.wire.FLOAT_LIMIT`, NaN refused) in bulk
        (a plant, its whole state once a step): the message is not decoded again here."""
        by_datagram = self._by_datagram.get(key)
        if by_datagram is None:
            by_datagram = self._sends_by_datagram(key)
        pub = None if by_datagram else self._publisher(key)
        seq = self._seq.get(key, 0)
        self._seq[key] = seq + 1
        costs = self.costs.ns
        try:
            t0 = now_ns()
            msg = msg_factory(seq, time.monotonic_ns())
            data = encode(msg)
            if not checked:
                self.codec.check(type(msg), data)  # the receivers' schema: NaN never leaves
            plain = data
            t1 = now_ns()
            costs[ENCODE_PART] += t1 - t0
            if self.keyring is not None and not (by_datagram and self.datagrams.authenticated):
                data = self.keyring.seal(data, key)  # (on our connections: no tag needed)
                t2 = now_ns()
                costs[MAC] += t2 - t1
                t1 = t2
            if by_datagram:
                self.counters.dropped += self.datagrams.send(key, data)  # type: ignore[union-attr]
            else:
                pub.put(data)
            costs[SEND] += now_ns() - t1
            self.counters.sent += 1
            spool = self.spool
            if spool is not None and key in spool.keys:
                spool.write(key, plain)
        except Exception as exc:
            self.counters.dropped += 1
            if self.counters.dropped <= 5:
                print(f"{self.role}: not sent on {key}: {exc}", file=sys.stderr)
            return None
        return msg

    def _sends_by_datagram(self, key: str) -> bool:
        """Whether ``key`` goes out on the datagram path (remembered)."""
        by_datagram = self._by_datagram.get(key)
        if by_datagram is None:
            by_datagram = self._by_datagram[key] = self._is_data(key)
        return by_datagram

    def _publisher(self, key: str) -> Any:
        """zenoh's publisher of ``key``, declared at its first use."""
        pub = self._pubs.get(key)
        if pub is None:
            cc = self._zenoh.CongestionControl
            # data in realtime may be dropped under congestion (newest wins);
            # control and reports never are
            must_arrive = self.lossless or "/ctl/" in key or "/report/" in key
            pub = self._pubs[key] = self.session.declare_publisher(
                key, express=True,
                congestion_control=cc.BLOCK if must_arrive else cc.DROP,
            )
        return pub

    def connect_ahead(self, keys: Iterable[str]) -> None:
        """What the first publish on each of ``keys`` would open, opened now: the datagram
        path's connections to its receivers (:meth:`DatagramPath.connect_ahead`), zenoh's
        publisher of a key that goes by zenoh. A realtime node does so before its first
        period, where each of a run's nodes used to open them at t = 0, at once."""
        by_datagram = []
        for key in keys:
            if self._sends_by_datagram(key):
                by_datagram.append(key)
            else:
                self._publisher(key)
        if by_datagram:
            self.datagrams.connect_ahead(by_datagram)  # type: ignore[union-attr]

    def wake_on(self, keys: Iterable[str] | None) -> None:
        """On the datagram path, be woken from a wait only by frames on ``keys`` (None:
        by every frame); the others are handled at the next wake (realtime loops:
        :meth:`deploy.runtime.datagrams.DatagramPath.wake_on`). zenoh's deliveries, and
        whatever another thread posts, still wake the node."""
        if self.datagrams is not None:
            self.datagrams.wake_on(keys)

    def stamp_arrivals(self) -> None:
        """Have the kernel stamp what arrives on the datagram path (:meth:`arrival_ns`)."""
        if self.datagrams is not None:
            self.datagrams.stamp_arrivals()

    def arrival_ns(self) -> int | None:
        """When the message being handled reached this node, on its monotonic clock (ns),
        if the kernel stamped it (:meth:`stamp_arrivals`, the datagram path); else None."""
        d = self.datagrams
        if d is None or d.arrived_unix_ns is None:
            return None
        return d.arrived_unix_ns - time.time_ns() + time.monotonic_ns()

    def _is_data(self, key: str) -> bool:
        """A data key of the run, sent on the datagram path when this node has one."""
        if self.datagrams is None:
            return False
        found = self.keys.kind_of(key)
        return found is not None and found[0] in DATA_KINDS

    def _hear_by_datagram(self, key: str, handler: Callable[[bytes, str], None],
                          kind: type[Message] | None = None) -> None:
        """Also hear ``key`` (a data key, or a wildcard over some) on the datagram path;
        ``kind``: the message type the key carries (None: any)."""
        if self.datagrams is None:
            return
        if kind is not None and kind not in DATA_KINDS:
            return
        if "*" not in key and not self._is_data(key):
            return
        if "/ctl/" in key or "/report/" in key:  # never on the datagram path
            return
        self._dispatch.add(key, handler)
        self.datagrams.hear([key])

    def subscribe(
        self,
        key: str,
        kind: type[Message],
        on_message: Callable[[Message], None],
        robot: int | None = None,
    ) -> None:
        """Decoded and validated on the node's thread as it waits; ``on_message``
        runs there too. Valid messages are counted per key they came on."""
        counters, received, post = self.counters, self.received, self.mailbox.post
        keyring, what = self.keyring, WHAT.get(kind, kind.__name__)
        decode = self.codec.decoder_for(kind, robot)
        open_ = keyring.open if keyring is not None else None
        dgram = self.datagrams
        may_send = keyring.may_send if keyring is not None else None

        costs = self.costs.ns

        def handle(data: bytes, on: str = key) -> None:  # the node's thread
            t0 = now_ns()
            if open_ is not None:  # before anything decodes it or looks at its step
                sender = None if dgram is None else dgram.frame_from
                if sender is not None:  # on a connection bound to its sender (datagrams.py)
                    if not may_send(sender, on):  # type: ignore[misc]
                        self.refuse_unsigned(what, WRONG_SENDER, on)
                        return
                else:
                    payload, why = open_(data, on)
                    if payload is None:
                        self.refuse_unsigned(what, why, on)
                        return
                    data = payload
            t1 = now_ns()
            msg = decode(data)
            t2 = now_ns()
            if msg is None:
                counters.invalid += 1
                self._warn_version()
                return
            if on not in received and len(received) >= MAX_RECEIVED_KEYS:
                on = key  # made-up keys under a wildcard: counted under the wildcard
            received[on] = received.get(on, 0) + 1
            spool = self.spool
            if spool is not None and on in spool.keys:
                spool.write(on, data)
            on_message(msg)
            t3 = now_ns()
            # the parts of this frame, out of the receive span that holds them (Mailbox)
            costs[MAC] += t1 - t0
            costs[DECODE] += t2 - t1
            costs[HANDLE] += t3 - t2
            costs[RECEIVE] -= t3 - t0

        if "*" in key:  # a wildcard: the key each sample came on
            def arrived(s: Any) -> None:
                post(lambda item: handle(*item), (s.payload.to_bytes(), str(s.key_expr)))
        else:
            def arrived(s: Any) -> None:
                post(handle, s.payload.to_bytes())
        self._subs.append(self.session.declare_subscriber(key, self._direct(arrived)))
        self._hear_by_datagram(key, handle, kind)

    def refuse(self, why: str, dropped: bool = True) -> None:
        """Count a message refused on arrival (a forged step, a bad signature), by
        reason; reported in ``NodeReport.refused``. ``dropped``: it was not used at all
        (counted in ``messages.dropped`` too); False: used, but clamped."""
        self.refused[why] = self.refused.get(why, 0) + 1
        if dropped:
            self.counters.dropped += 1

    def refuse_unsigned(self, what: str, why: str, key: str) -> None:
        """Count a message whose authentication failed (deploy/contract/keyring.py); say
        so on stderr the first time for each reason."""
        reason = f"{what}: {why}"
        self.refuse(reason)
        if self.refused[reason] == 1:
            print(f"{self.role}: refused a {what} on {key} ({why}): forged, or from a node "
                  "without this run's keys; every such message is counted in its report",
                  file=sys.stderr, flush=True)

    def note_nonfinite(self, what: str) -> None:
        """Count a value this node computed that is not finite (a diverged law or
        plant); say so on stderr the first time, with ``what`` it was. Reported in
        ``NodeReport.nonfinite``."""
        self.counters.nonfinite += 1
        if self.counters.nonfinite == 1:
            print(f"{self.role}: computed a non-finite {what}; every such value is counted "
                  "(nonfinite in its report) and this is said once", file=sys.stderr, flush=True)

    def _warn_version(self) -> None:
        c = self.codec
        if c.wrong_version and not self._version_warned:
            self._version_warned = True
            print(f"{self.role}: refused messages of wire version "
                  f"{', '.join(map(str, sorted(c.versions_seen)))}; this node speaks "
                  f"{WIRE_VERSION}: every node of a fleet must run the same omnifleet",
                  file=sys.stderr, flush=True)

    def subscribe_raw(self, key: str, callback: Callable[[tuple[str, bytes, str | None]], None]
                      ) -> None:
        """(key, bytes, sender) as they arrive, handled on the node's thread (the recorder):
        ``sender`` is the role of the authenticated connection a frame came on, when that
        role may send on ``key`` (the bytes carry no tag then); None: check their tags."""
        post, dgram, keyring = self.mailbox.post, self.datagrams, self.keyring
        self._subs.append(self.session.declare_subscriber(key, self._direct(
            lambda s: post(callback, (str(s.key_expr), s.payload.to_bytes(), None)))))

        def heard(data: bytes, on: str) -> None:
            sender = None if dgram is None else dgram.frame_from
            if sender is not None and (keyring is None or not keyring.may_send(sender, on)):
                sender = None
            callback((on, data, sender))
        self._hear_by_datagram(key, heard)

    def linked_peers(self) -> list[str]:
        """The zenoh ids of the peers this session had a link with (zenoh's own
        info): now, and when the run started (:meth:`note_links`; at the end of a run
        peers leave one by one, and a link can still be forming at its start)."""
        now = {str(z) for z in self.session.info.peers_zid()}
        return sorted(now | set(self.links_noted or ()))

    def note_links(self) -> None:
        self.links_noted = self.linked_peers()

    @property
    def zid(self) -> str:
        return str(self.session.info.zid())

    def flush_data(self) -> None:
        """Send what the datagram path holds for receivers that read behind, waiting for
        them (up to its lossless wait); what they still do not take is counted dropped."""
        if self.datagrams is None or not self.datagrams.behind:
            return
        self.datagrams.flush(wait_s=self.datagrams.lossless_wait_s)
        left = sum(len(p.backlog) for p in self.datagrams.behind_peers())
        if left:
            self.counters.dropped += left
            print(f"{self.role}: {left} data message(s) not taken by a receiver within "
                  f"{self.datagrams.lossless_wait_s:g} s", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.spool is not None:
            self.spool.close()
        for t in self._tokens:
            t.undeclare()
        self._tokens.clear()
        try:
            self.session.close()
        except Exception:
            pass
        if self.datagrams is not None:
            self.datagrams.close()
