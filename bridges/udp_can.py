"""A CAN bus over UDP multicast for emulated drives (python-can interface ``omnifleet_udp``).

What python-can's ``udp_multicast`` does (a group and a port make a bus: any number of
processes, on one host or a LAN, hear every frame), for the CAN fleet's emulated drives,
at a fraction of its cost per frame. Measured on the 2-core development VM, warm, a frame
at a time: ``udp_multicast`` sent a frame in 14.9 µs (a dict of its fields packed by
msgpack) and received one in 10.5 µs (a ``select`` first, msgpack, a checked
``can.Message``), and every member heard its own frames back (5.7 µs each to skip:
``deploy/nodes/can_options.py``). At lab's 200 Hz a bridge moves ~9 frames a period and the
emulator ~30: their CAN frames alone were ~400 µs of a bridge's 1 ms step (docs/bench-history.md,
"The realtime budget"). Here:

- a datagram carries one or more frames in a fixed binary layout (:data:`HEADER`, then
  :data:`FRAME` and the data of each): the frames a node sends at once (a bridge's four
  torques, a robot's four encoder estimates) travel as one datagram
  (:func:`send_frames`);
- a bus knows its own datagrams by the random id in their header and skips them before
  unpacking anything (a CAN controller does not hand a node its own frames back);
- reading never waits unless asked to (``recv(timeout=0)`` is one ``recvmsg``), and each
  frame carries the kernel's time of arrival (``SO_TIMESTAMPNS``, the wall clock), as on
  socketcan;
- a datagram that is not one of ours, or is cut short, is dropped and counted
  (``malformed``), never raised.

Real hardware keeps its own interface (socketcan, pcan, ...): the bridge and the emulator
see a python-can bus either way.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import time
from collections import deque
from collections.abc import Iterable, Sequence
from typing import Any

import can

INTERFACE = "omnifleet_udp"  # its name for python-can (pyproject.toml's entry point)
DEFAULT_GROUP = "239.74.163.2"
DEFAULT_PORT = 43114
MAGIC = b"OFC1"
HEADER = struct.Struct("<4sQB")  # magic, the sending bus's id, frames in the datagram
FRAME = struct.Struct("<IBB")  # arbitration id, flags, data length; then the data
EXTENDED, REMOTE, ERROR, FD, BRS, ESI = 1, 2, 4, 8, 16, 32
MAX_FRAMES = 64  # frames a datagram carries at most
MAX_DATAGRAM = HEADER.size + MAX_FRAMES * (FRAME.size + 64)
RECEIVE_BUFFER_BYTES = 4 << 20  # a host off the CPU for tens of ms must not drop frames
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux's; the module lacks the name
_STAMP_SPACE = socket.CMSG_SPACE(16)
_TIMESPEC = struct.Struct("qq")


def pack(frames: Sequence[can.Message], sender: int) -> bytes:
    """One datagram holding ``frames`` (at most :data:`MAX_FRAMES`)."""
    parts = [HEADER.pack(MAGIC, sender, len(frames))]
    for m in frames:
        data = bytes(m.data or b"")
        flags = ((EXTENDED if m.is_extended_id else 0) | (REMOTE if m.is_remote_frame else 0)
                 | (ERROR if m.is_error_frame else 0) | (FD if m.is_fd else 0)
                 | (BRS if m.bitrate_switch else 0) | (ESI if m.error_state_indicator else 0))
        # a remote frame carries no data but asks for dlc bytes: its length says so
        parts.append(FRAME.pack(m.arbitration_id, flags, m.dlc if m.is_remote_frame else len(data)))
        if not m.is_remote_frame:
            parts.append(data)
    return b"".join(parts)


def unpack(datagram: bytes, timestamp: float, channel: Any) -> tuple[int, list[can.Message]] | None:
    """(sender id, frames) of a datagram; None when it is not a whole one of ours."""
    if len(datagram) < HEADER.size:
        return None
    magic, sender, n = HEADER.unpack_from(datagram)
    if magic != MAGIC or not 1 <= n <= MAX_FRAMES:
        return None
    out: list[can.Message] = []
    at, size = HEADER.size, len(datagram)
    for _ in range(n):
        if at + FRAME.size > size:
            return None
        arb, flags, length = FRAME.unpack_from(datagram, at)
        at += FRAME.size
        remote = bool(flags & REMOTE)
        fd = bool(flags & FD)
        if length > (64 if fd else 8):
            return None
        if remote:
            data, dlc = b"", length
        else:
            if at + length > size:
                return None
            data, dlc = datagram[at:at + length], length
            at += length
        out.append(can.Message(timestamp=timestamp, arbitration_id=arb,
                               is_extended_id=bool(flags & EXTENDED), is_remote_frame=remote,
                               is_error_frame=bool(flags & ERROR), is_fd=fd,
                               bitrate_switch=bool(flags & BRS),
                               error_state_indicator=bool(flags & ESI),
                               dlc=dlc, data=data, channel=channel, is_rx=True, check=False))
    return (sender, out) if at == size else None


class UdpCanBus(can.BusABC):
    """CAN over UDP multicast: ``channel`` the group's address, ``port`` its port (every
    group on one port is heard by every bus on that port; one port per bus keeps them
    apart, as ``udp_multicast``)."""

    def __init__(self, channel: str = DEFAULT_GROUP, port: int = DEFAULT_PORT,
                 hop_limit: int = 1, receive_own_messages: bool = False, **kwargs: Any) -> None:
        if receive_own_messages:
            raise can.CanInterfaceNotImplementedError(
                f"{INTERFACE} does not hand a bus its own frames back")
        super().__init__(channel, **kwargs)
        self.channel = channel
        self.channel_info = f"{INTERFACE} {channel}:{port}"
        try:
            group = socket.inet_pton(socket.AF_INET, channel)
        except OSError as exc:
            raise can.CanInitializationError(
                f"{INTERFACE}: channel {channel!r} is not an IPv4 multicast group address") from exc
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, hop_limit)
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
                if opt is not None:
                    try:  # root may exceed net.core.rmem_max; others get what it allows
                        sock.setsockopt(socket.SOL_SOCKET, opt, RECEIVE_BUFFER_BYTES)
                        break
                    except OSError:
                        continue
            sock.bind(("", int(port)))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                            group + struct.pack("@I", socket.INADDR_ANY))
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise can.CanInitializationError(f"{INTERFACE} {channel}:{port}: {exc}") from exc
        self._sock = sock
        self._dest = (channel, int(port))
        self._id = int.from_bytes(os.urandom(8), "little")
        self._rx: deque[can.Message] = deque()
        self.malformed = 0  # datagrams on the group that were not whole frames of ours
        self.sent_datagrams = 0

    # -- sending ------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._put(pack((msg,), self._id))

    def send_batch(self, msgs: Sequence[can.Message]) -> None:
        """Several frames at once: one datagram (a CAN bus would carry them back to back)."""
        for i in range(0, len(msgs), MAX_FRAMES):
            self._put(pack(msgs[i:i + MAX_FRAMES], self._id))

    def _put(self, datagram: bytes) -> None:
        try:
            self._sock.sendto(datagram, self._dest)
        except BlockingIOError as exc:  # the socket's send buffer full: a CAN bus off
            raise can.CanOperationError(f"{self.channel_info}: send buffer full") from exc
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: {exc}") from exc
        self.sent_datagrams += 1

    # -- receiving ----------------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._rx:
            return self._rx.popleft(), False
        end = None if timeout is None else time.monotonic() + timeout
        sock = self._sock
        while True:
            try:
                datagram, anc, _, _ = sock.recvmsg(MAX_DATAGRAM, _STAMP_SPACE)
            except BlockingIOError:
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return None, False
                select.select((sock,), (), (), left)
                continue
            except InterruptedError:
                continue
            stamp = time.time()
            for level, kind, data in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= 16:
                    sec, nsec = _TIMESPEC.unpack_from(data)
                    stamp = sec + nsec * 1e-9
            if len(datagram) >= HEADER.size and HEADER.unpack_from(datagram)[1] == self._id:
                continue  # our own, looped back by the group
            got = unpack(datagram, stamp, self.channel)
            if got is None:
                self.malformed += 1
                continue
            self._rx.extend(got[1])
            return self._rx.popleft(), False

    def fileno(self) -> int:
        return self._sock.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()


def send_frames(bus: can.BusABC, frames: Iterable[can.Message]) -> None:
    """``frames`` on ``bus``, sent together where the bus can (:class:`UdpCanBus`), else one
    at a time (socketcan and the rest send each as it comes: python-can has no batch)."""
    if isinstance(bus, UdpCanBus):
        batch = list(frames)
        if batch:
            bus.send_batch(batch)
        return
    for frame in frames:
        bus.send(frame)
