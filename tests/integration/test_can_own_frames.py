"""A udp_multicast bus as the CAN commands open it (deploy/nodes/can_options.py) hears
what the others on its group send, never its own frames back, as a CAN controller:
the group's loopback reaches the sending socket too, and a bridge's reader used to wake
for each of its own torque frames."""

from __future__ import annotations

import random
from types import SimpleNamespace

import can
import pytest

from deploy.nodes.can_options import _drop_own_frames, _open


@pytest.fixture
def two_buses():
    group = f"239.74.{random.randrange(1, 250)}.{random.randrange(1, 250)}"
    port = random.randrange(20000, 60000)
    a = _open("udp_multicast", group, {"port": port}, None)
    b = _open("udp_multicast", group, {"port": port}, None)
    try:
        yield a, b
    finally:
        a.shutdown()
        b.shutdown()


def _frame(data: list[int]) -> can.Message:
    return can.Message(arbitration_id=0x0E, data=data, is_extended_id=False)


def _heard(bus, wait_s: float = 0.3) -> list[bytes]:
    """Every frame's data the bus receives until it has heard nothing for ``wait_s``."""
    out = []
    while (msg := bus.recv(wait_s)) is not None:
        out.append(bytes(msg.data))
    return out


def test_a_bus_hears_the_others_frames_and_not_its_own(two_buses):
    a, b = two_buses
    a.send(_frame([1, 2, 3]))
    b.send(_frame([4, 5, 6]))
    assert _heard(a) == [bytes([4, 5, 6])]
    assert _heard(b) == [bytes([1, 2, 3])]


def test_identical_frames_of_two_senders_each_reach_the_other_as_often_as_sent(two_buses):
    """What a bus drops is counted by copy: of identical bytes it sent twice and the
    other sent once, it hears the other's one copy; the other hears both of its."""
    a, b = two_buses
    same = _frame([7, 7, 7, 7])
    a.send(same)
    a.send(same)
    b.send(same)
    assert _heard(a) == [bytes([7, 7, 7, 7])]
    assert _heard(b) == [bytes([7, 7, 7, 7])] * 2


class _Loopback:
    """A multicast group's socket as python-can's udp_multicast bus holds it: what it
    sends comes back to it (the loopback), after whatever was queued before."""

    def __init__(self) -> None:
        self.queue: list[bytes] = []

    def send(self, data: bytes, timeout: float | None = None) -> None:
        self.queue.append(data)

    def recv(self, timeout: float | None = None):
        return (self.queue.pop(0), ("127.0.0.1", 0), 0.0) if self.queue else None


def test_a_poll_reads_past_its_own_frames_to_the_others():
    """``recv(timeout=0)`` (the emulator polls its bus so once a tick) returns the other's
    datagram queued behind two of its own, and None once only its own were there."""
    bus = SimpleNamespace(_multicast=_Loopback())
    _drop_own_frames(bus)
    group = bus._multicast
    group.send(b"own-1")
    group.send(b"own-2")
    group.queue.append(b"theirs")
    assert group.recv(0.0) == (b"theirs", ("127.0.0.1", 0), 0.0)
    group.send(b"own-3")
    assert group.recv(0.0) is None
    assert group.queue == []
