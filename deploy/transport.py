"""Zenoh I/O for every node: session from flags or a config file, typed
publishers and subscribers over the wire contract, liveliness, counters.

This is the only module (with the launcher) that imports zenoh; the math in
``agents/`` and ``plant/`` never sees it. Subscriber callbacks run on zenoh's
threads: they decode, validate and hand the message to the node through
:class:`Mailbox` (one lock, one condition), so node loops are plain Python.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from deploy.wire import Codec, Keys, Message, encode

MAX_PEER_EVENTS = 10_000


class TransportError(RuntimeError):
    """Bad endpoint or zenoh configuration (exit code 2 at the CLI)."""


def zenoh_config(
    config_file: str | Path | None = None,
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
) -> Any:
    """A peer configuration: explicit endpoints, multicast scouting off.

    With a config file, the file decides everything and ``listen``/``connect``
    are added to it. Gossip scouting stays on (zenoh's default): peers that
    connect to one common endpoint learn of each other and link directly.
    """
    import zenoh

    try:
        if config_file is not None:
            cfg = zenoh.Config.from_file(str(config_file))
        else:
            cfg = zenoh.Config()
            cfg.insert_json5("mode", '"peer"')
            cfg.insert_json5("scouting/multicast/enabled", "false")
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


@dataclass
class Mailbox:
    """Messages handed over from zenoh threads; the node waits on ``changed``."""

    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        self.changed = threading.Condition(self.lock)

    def wait_until(self, ready: Callable[[], bool], timeout_s: float) -> bool:
        """Wait until ``ready()`` (checked under the lock) or the timeout."""
        with self.changed:
            return self.changed.wait_for(ready, timeout_s)


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
    ) -> None:
        import zenoh

        self._zenoh = zenoh
        self.role = role
        self.keys = keys
        self.codec = codec
        self.sender = sender
        self.counters = Counters()
        self.received: dict[str, int] = {}  # valid messages per key (what we really heard)
        self.mailbox = Mailbox()
        self.lossless = lossless
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

        def on_token(sample: Any, bag: set[str]) -> None:
            role = keys.role_of(str(sample.key_expr))
            with self.mailbox.changed:
                alive = sample.kind == self._zenoh.SampleKind.PUT
                if bag is self.peers_alive and len(self.peer_events) < MAX_PEER_EVENTS:
                    self.peer_events.append((time.time_ns(), role, alive))
                if alive:
                    bag.add(role)
                else:
                    bag.discard(role)
                    if bag is self.peers_alive and role in self.required:
                        self.on_lost(role)
                self.mailbox.changed.notify_all()

        lv = self.session.liveliness()
        self._subs.append(lv.declare_subscriber(
            keys.alive_all, lambda s: on_token(s, self.peers_alive), history=True))
        self._subs.append(lv.declare_subscriber(
            keys.ready_all, lambda s: on_token(s, self.peers_ready), history=True))

    def declare_alive(self) -> None:
        """Declare after every subscriber: a peer that sees the token has them."""
        self._tokens.append(self.session.liveliness().declare_token(self.keys.alive(self.role)))

    def declare_ready(self) -> None:
        self._tokens.append(self.session.liveliness().declare_token(self.keys.ready(self.role)))

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
        with self.mailbox.lock:
            return wanted - seen

    # -- data -------------------------------------------------------------------------
    def publish(self, key: str, msg_factory: Callable[[int, int], Message]) -> Message | None:
        """Build the message with (seq, stamp_ns) and put it on ``key``. A message
        that fails its own validation (a NaN) is not sent: counted as dropped."""
        pub = self._pubs.get(key)
        if pub is None:
            cc = self._zenoh.CongestionControl
            # data in realtime may be dropped under congestion (newest wins);
            # control and reports never are
            must_arrive = self.lossless or "/ctl/" in key or "/report/" in key
            pub = self.session.declare_publisher(
                key, express=True,
                congestion_control=cc.BLOCK if must_arrive else cc.DROP,
            )
            self._pubs[key] = pub
            self._seq[key] = 0
        seq = self._seq[key]
        self._seq[key] = seq + 1
        try:
            msg = msg_factory(seq, time.monotonic_ns())  # validates: NaN never leaves
            pub.put(encode(msg))
            self.counters.sent += 1
        except Exception as exc:
            self.counters.dropped += 1
            if self.counters.dropped <= 5:
                print(f"{self.role}: not sent on {key}: {exc}", file=sys.stderr)
            return None
        return msg

    def subscribe(
        self,
        key: str,
        kind: type[Message],
        on_message: Callable[[Message], None],
        robot: int | None = None,
    ) -> None:
        """Decode and validate on arrival; ``on_message`` runs under the mailbox
        lock (keep it short: store and return), and waiters are woken."""
        codec, box, counters, received = self.codec, self.mailbox, self.counters, self.received

        def callback(sample: Any) -> None:
            msg = codec.decode(kind, sample.payload.to_bytes(), robot)
            with box.changed:
                if msg is None:
                    counters.invalid += 1
                    return
                k = str(sample.key_expr)
                received[k] = received.get(k, 0) + 1
                on_message(msg)
                box.changed.notify_all()

        self._subs.append(self.session.declare_subscriber(key, callback))

    def subscribe_raw(self, key: str, callback: Callable[[str, bytes], None]) -> None:
        """Bytes and key as they arrive (the recorder)."""
        self._subs.append(self.session.declare_subscriber(
            key, lambda s: callback(str(s.key_expr), s.payload.to_bytes())))

    def close(self) -> None:
        for t in self._tokens:
            t.undeclare()
        self._tokens.clear()
        try:
            self.session.close()
        except Exception:
            pass
