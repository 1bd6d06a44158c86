"""Stand-ins for zenoh and a CAN bus, so the fuzz tests can drive the real plant
node and bridge with bytes: :class:`FakeNode` decodes and dispatches exactly as
``deploy.runtime.transport.Node.subscribe`` does (the real :class:`Codec`, invalid ones
counted), :class:`RecordingBus` keeps what is sent and hands out queued frames."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import can

from deploy.contract.wire import Codec, Keys, Message
from deploy.runtime.transport import WHAT, Counters, Mailbox


class FakeNode:
    def __init__(self, robot_ids: list[int], role: str = "fuzz", keyring: Any = None) -> None:
        """``keyring``: the node's keys (deploy/contract/keyring.py, fleet ``fuzz``): what
        is delivered is opened as Node.subscribe opens it, before decoding."""
        self.role = role
        self.keyring = keyring
        self.keys = Keys("fuzz")
        self.codec = Codec(robot_ids)
        self.counters = Counters()
        self.mailbox = Mailbox()
        self.costs = self.mailbox.costs  # as Node.costs
        self.datagrams = None  # no local data path
        self.received: dict[str, int] = {}
        self.refused: dict[str, int] = {}
        self.peers_alive: set[str] = set()
        self.published: list[tuple[str, Message]] = []
        self._subs: list[tuple[str, type[Message], Callable[[Message], None], int | None]] = []

    def subscribe(self, key: str, kind: type[Message], on_message: Callable[[Message], None],
                  robot: int | None = None) -> None:
        self._subs.append((key, kind, on_message, robot))

    def deliver(self, key: str, payload: bytes) -> Message | None:
        """``payload`` arrives on ``key``: what Node.subscribe's callback does (a
        subscription with a ``*`` chunk hears every key that chunk matches)."""
        subs = [s for s in self._subs if _matches(s[0], key)]
        assert subs, f"nobody subscribed to {key}"
        out = None
        for _, kind, on_message, robot in subs:
            data = payload
            if self.keyring is not None:
                data, why = self.keyring.open(payload, key)
                if data is None:
                    self.refuse(f"{WHAT[kind]}: {why}")
                    continue
            msg = self.codec.decode(kind, data, robot)
            if msg is None:
                self.counters.invalid += 1
                continue
            self.received[key] = self.received.get(key, 0) + 1
            on_message(msg)
            out = msg
        return out

    def wait_filed(self, timeout_s: float) -> bool:  # as Node.wait_filed without a launcher
        return True

    def refuse(self, why: str, dropped: bool = True) -> None:  # as Node.refuse
        self.refused[why] = self.refused.get(why, 0) + 1
        if dropped:
            self.counters.dropped += 1

    def publish(self, key: str, factory: Callable[[int, int], Message],
                checked: bool = False) -> Message | None:
        try:
            msg = factory(len(self.published), 0)
        except Exception:  # as Node.publish: a message failing validation is not sent
            self.counters.dropped += 1
            return None
        self.published.append((key, msg))
        return msg

    def declare_alive(self) -> None:
        pass

    def wake_on(self, keys: Any) -> None:  # as Node.wake_on without a datagram path
        pass

    def stamp_arrivals(self) -> None:  # likewise
        pass

    def arrival_ns(self) -> int | None:  # nothing here is stamped by a kernel
        return None

    def declare_ready(self) -> None:
        pass


def _matches(pattern: str, key: str) -> bool:
    """A key expression with ``*`` chunks (one chunk each) against a concrete key."""
    a, b = pattern.split("/"), key.split("/")
    return len(a) == len(b) and all(x in ("*", y) for x, y in zip(a, b, strict=True))


class RecordingBus(can.BusABC):
    """A python-can bus that records sends and hands out frames queued with :meth:`feed`.

    ``recv`` with a timeout waits on an event (for a bridge's reader thread), so an
    idle reader does not spin."""

    def __init__(self) -> None:
        self.sent: list[can.Message] = []
        self.incoming: deque[can.Message] = deque()
        self._closed = threading.Event()
        super().__init__(channel="fuzz")

    def feed(self, frames: list[can.Message]) -> None:
        self.incoming.extend(frames)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[Any, bool]:
        if self.incoming:
            return self.incoming.popleft(), False
        if timeout:
            self._closed.wait(timeout)
        return None, False

    def shutdown(self) -> None:
        self._closed.set()
        super().shutdown()
