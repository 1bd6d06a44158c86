"""The per-step messages of a run on one host, over unix sockets beside zenoh.

Why (measured on the 2-core machine, docs/bench-history.md "The local data path"): a zenoh
delivery between two Python processes wakes three to four threads (the sender's
transmit task, the receiver's receive task, then the thread that works), about 20
system calls; a lockstep step of ``paper`` (3 samples, 3 replies, 3 shares) cost
~430 µs of wall time and ~700 µs of CPU in messaging alone, with no work at all.
The same pattern over unix sockets, a system call or two each way and the waiting
thread woken directly: ~80-100 µs and ~100 µs.

What travels here: the data keys of a run whose nodes share a directory
(``--datagrams DIR``; ``omnifleet run`` gives every node its private run directory):
samples, replies, leader batches, telemetry and state logs (:data:`DATA_KINDS`).
What stays on zenoh: liveliness, control, reports (large, once), and every message
between hosts. A node with this path still subscribes to its data keys on zenoh
too: a message put there (another host, an outside peer) is heard, checked and
counted as before.

How:

- each node listens on ``DIR/<role>.dgram`` and writes ``DIR/<role>.hears``, the key
  expressions it subscribed to, before it declares itself alive;
- a sender sends a message on key K to every node of DIR whose ``.hears`` matches K
  (read again whenever a peer's liveliness changes), over one connection per
  receiver: ``frame = len(K) (1 byte) | K | payload``, where the payload is the
  message as zenoh would carry it (sealed for its receivers: deploy/contract/mac.py);
- the sockets are ``SOCK_SEQPACKET``: a connection per sender and receiver, each
  frame delivered whole and in order, a receiver waits on all of its connections at
  once (epoll). First built on ``SOCK_DGRAM`` (one socket a node, one system call a
  message), but the kernel queues at most ``net.unix.max_dgram_qlen`` datagrams for a
  receiver (10 by default; only root may raise it): 30 agents answering one plant at
  100 Hz overflowed it every period, their replies waited in the senders and reached
  the plant stale (30,899 refused in 20 s). A connection holds what its socket buffer
  holds (~170 frames) instead;
- when a connection is full the sender holds the frame in a backlog of its own for
  that receiver and sends it, in order, as the receiver catches up (before its next
  frame to it, and before the sender waits); only a backlog of ``MAX_BACKLOG`` frames
  makes a lossless sender (lockstep) wait and a lossy one (realtime) drop its oldest;
- a receiver that is gone (its process ended, or restarted on a new socket): the
  socket is dialled again once, else the message is dropped and counted;
- a realtime node is woken only by what starts its step (:meth:`DatagramPath.wake_on`):
  an agent by its robot's sample, a plant or a leader by nothing but its timer. The
  frames of every other connection wait in their sockets, unheard, and are read at the
  next wake. A connection is told apart by the key of the frames it carries (a sender
  writes one kind of message to a receiver): until its first frame it wakes the
  receiver. Measured: an agent of ``paper`` at 1 kHz woke 1.3-3 times a step, each wake
  ~15 µs of CPU in this VM before any work (docs/bench-history.md, "The realtime budget").
"""

from __future__ import annotations

import errno
import json
import os
import select
import socket
import struct
import time
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path

from deploy.contract.audience import robot_of
from deploy.contract.keyring import HELLO
from deploy.contract.wire import LAUNCHER_ROLE, LeaderState, Reply, Sample, StateLog, Telemetry

# the message kinds of the control path and of its observers' series
DATA_KINDS = (Sample, Reply, LeaderState, Telemetry, StateLog)
SOCKET_SUFFIX = ".dgram"
HEARS_SUFFIX = ".hears"
MAX_DATAGRAM = 1 << 16  # every data message is far smaller (a batch of telemetry ~2 kB)
MAX_KEY_BYTES = 255
CONNECT_TIMEOUT_S = 1.0
LISTEN_BACKLOG = 512  # connections a listener holds before it accepts them
# a receiver gone: its process ended (EPIPE, ECONNRESET), or restarted on a new socket
_GONE = (errno.EPIPE, errno.ECONNRESET, errno.ECONNREFUSED, errno.ENOENT, errno.ENOTCONN)
# how long a lossless sender waits for a receiver that reads behind before it gives up on
# a message (counted): a receiver alive but stalled that long (a lockstep run stalls with
# it anyway); one that is gone refuses at once
LOSSLESS_WAIT_S = 30.0
LONG_WAIT_S = 0.25  # a wait this long or longer is one epoll_wait (see recv_wait)
MAX_MATCHED_KEYS = 1024  # distinct keys whose wildcard match is remembered
# frames held for one receiver whose queue is full (an observer that reads behind): past
# it a lossless sender waits, a lossy one drops the oldest (~2 s of a lockstep paper run)
MAX_BACKLOG = 8192
# unix socket paths are at most 107 bytes (sun_path): long run directories are refused
MAX_SOCKET_PATH = 107
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux's; the module lacks the name
_STAMP_SPACE = socket.CMSG_SPACE(16)  # one struct timespec
_TIMESPEC = struct.Struct("qq")
_HELLO_KEY = HELLO.encode()


class DatagramError(OSError):
    """A local data path that cannot be opened (a directory too deep, not writable)."""


def key_matches(pattern: str, key: str) -> bool:
    """Whether zenoh key expression ``pattern`` (``*`` one chunk, ``**`` any number of
    chunks) matches the concrete ``key``."""
    return _match(pattern.split("/"), key.split("/"))


def _match(p: list[str], k: list[str]) -> bool:
    if not p:
        return not k
    if p[0] == "**":
        return any(_match(p[1:], k[i:]) for i in range(len(k) + 1))
    return bool(k) and (p[0] == "*" or p[0] == k[0]) and _match(p[1:], k[1:])


class _Peer:
    """One receiver: its socket path, what it hears, and our connection to it."""

    def __init__(self, role: str, path: str, hears: list[str]) -> None:
        self.role, self.path, self.hears = role, path, hears
        self.sock: socket.socket | None = None
        self.backlog: deque[bytes] = deque()  # frames its full connection did not take yet
        self.stalled = False  # a lossless wait for it timed out (no more waits until it reads)

    def connect(self) -> socket.socket:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            s.settimeout(CONNECT_TIMEOUT_S)  # a listener accepts at once; never hang on it
            s.connect(self.path)
            s.setblocking(False)
        except OSError:
            s.close()
            raise
        self.sock = s
        return s

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


def _send_order(role: str) -> tuple[int, str]:
    """Agents, then the rest (plant, bridges, leader), then the launcher."""
    agent = robot_of(role, "agent-") is not None
    return (0 if agent else 2 if role == LAUNCHER_ROLE else 1, role)


class DatagramPath:
    """One node's end of the run's local data path: its listening socket and the
    connections of its senders (what it hears), the peers it sends to, and the counts
    of what could not be delivered."""

    def __init__(self, directory: str | Path, role: str, lossless: bool,
                 lossless_wait_s: float = LOSSLESS_WAIT_S, max_backlog: int = MAX_BACKLOG) -> None:
        self.dir, self.role, self.lossless = Path(directory), role, lossless
        self.lossless_wait_s = lossless_wait_s
        path = str(self.dir / f"{role}{SOCKET_SUFFIX}")
        if len(path.encode()) > MAX_SOCKET_PATH:
            raise DatagramError(f"--datagrams {directory}: the socket path {path} is longer "
                                f"than the {MAX_SOCKET_PATH} bytes a unix socket may have")
        try:
            if os.path.exists(path):  # a restarted node's own, left by its dead process
                os.unlink(path)
            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            self.sock.bind(path)
            self.sock.listen(LISTEN_BACKLOG)
            self.sock.setblocking(False)
        except OSError as exc:
            raise DatagramError(f"--datagrams {directory}: cannot listen on {path}: "
                                f"{exc.strerror}") from exc
        self.path = path
        # another thread (zenoh's, a signal handler) wakes the waiting one through this pair
        self._wake_r, self._wake_w = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._ep = select.epoll()  # every connection: what is readable now
        self._lfd, self._wfd = self.sock.fileno(), self._wake_r.fileno()
        self._ep.register(self._lfd, select.EPOLLIN)
        self._ep.register(self._wfd, select.EPOLLIN)
        # what a wait is woken by (wake_on): None, every connection (``_ep``); else an
        # epoll of the listener, the wake-up pair and the connections whose frames wake
        self._waking: frozenset[bytes] | None = None
        self._ep_wake: select.epoll | None = None
        self._fd_wakes: dict[int, bool] = {}  # connection -> in _ep_wake
        # stamp_arrivals: the kernel's time of arrival of the frame last read (wall clock,
        # ns), or None
        self._stamped = False
        self.arrived_unix_ns: int | None = None
        # authenticate: what a connection says first, and who said it (the keyring's)
        self._hello: Callable[[str], bytes | None] | None = None
        self._hello_from: Callable[[bytes], str | None] | None = None
        self._bound: dict[int, str] = {}  # connection -> the role its hello proved
        self.frame_from: str | None = None  # the role of the frame last read (a bound one)
        self.hellos_refused = 0  # first frames that were not a hello that checks
        self._conns: dict[int, socket.socket] = {}  # fd -> a sender's connection
        self._ready: list[int] = []  # fds epoll said were readable, not yet read
        self._hears: list[str] = []
        self._peers: dict[str, _Peer] = {}
        self._routes: dict[str, list[_Peer]] = {}
        self._headers: dict[str, bytes] = {}
        self.dropped: dict[str, int] = {}  # receiver role -> messages it did not get
        self.deferred = 0  # frames held because their receiver's connection was full
        self.max_backlog = max_backlog
        self._behind: set[_Peer] = set()  # receivers with held frames
        self.closed = False

    # -- what this node hears -----------------------------------------------------
    def hear(self, patterns: Iterable[str]) -> None:
        """Add key expressions this node hears here, and say so in its ``.hears`` file
        (written whole, then renamed: a reader never sees half of it)."""
        self._hears += [p for p in patterns if p not in self._hears]
        final = self.dir / f"{self.role}{HEARS_SUFFIX}"
        tmp = final.with_suffix(".tmp")
        tmp.write_text(json.dumps({"role": self.role, "socket": self.path,
                                   "hears": self._hears}))
        os.replace(tmp, final)

    def wake_on(self, keys: Iterable[str] | None) -> None:
        """Be woken from a wait only by frames on ``keys`` (a wake-up from another thread
        and a new connection always wake); None: by every frame (the default). The other
        frames are read as they are found readable: by :meth:`recv`, or once a wait has
        been woken."""
        if keys is None:
            self._waking = None
            if self._ep_wake is not None:
                self._ep_wake.close()
                self._ep_wake = None
            self._fd_wakes.clear()
            return
        self._waking = frozenset(k.encode() for k in keys)
        if self._ep_wake is None:
            self._ep_wake = select.epoll()
            self._ep_wake.register(self._lfd, select.EPOLLIN)
            self._ep_wake.register(self._wfd, select.EPOLLIN)
            for fd in self._conns:  # until its first frame says what it carries
                self._ep_wake.register(fd, select.EPOLLIN)
                self._fd_wakes[fd] = True

    def authenticate(self, hello: Callable[[str], bytes | None],
                     hello_from: Callable[[bytes], str | None]) -> None:
        """Authenticated connections (docs/hardening.md): every connection this node
        opens says ``hello(receiver)`` first; every connection it accepts is bound to the
        role ``hello_from`` finds in its first frame, and after each read ``frame_from`` is
        that role (None: a connection that said no hello that checks, whose frames must
        carry their own tags). A node's frames then need no tag per message on this path:
        the kernel alone writes into a connected socket."""
        self._hello, self._hello_from = hello, hello_from

    @property
    def authenticated(self) -> bool:
        """What this node sends here goes on connections that said who we are."""
        return self._hello is not None

    def _dial(self, p: _Peer) -> socket.socket:
        s = p.connect()
        hello = None if self._hello is None else self._hello(p.role)
        if hello is not None:
            raw = HELLO.encode()
            s.send(bytes((len(raw),)) + raw + hello)  # an empty connection takes it at once
        return s

    def _bind(self, fd: int, frame: bytes) -> None:
        """The first frame of an unbound connection: bound to the role of a hello that
        checks; anything else on it is taken as it is (its own tags are checked)."""
        n = frame[0]
        if frame[1:1 + n] != _HELLO_KEY:
            return
        who = self._hello_from(frame[1 + n:])  # type: ignore[misc]
        if who is None:
            self.hellos_refused += 1
        else:
            self._bound[fd] = who

    def stamp_arrivals(self) -> None:
        """Have the kernel stamp each frame as it arrives (``SO_TIMESTAMPNS``): after a
        read, ``arrived_unix_ns`` says when the frame reached this node's socket, however
        long after it was read. A realtime plant reads its commands at its next period,
        not as they come, and still measures the state-to-command latency to their
        arrival."""
        self._stamped = True
        for c in self._conns.values():
            c.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)

    def _recv_stamped(self, c: socket.socket) -> bytes:
        frame, anc, _, _ = c.recvmsg(MAX_DATAGRAM, _STAMP_SPACE)
        self.arrived_unix_ns = None
        for level, kind, data in anc:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= 16:
                sec, nsec = _TIMESPEC.unpack_from(data)
                self.arrived_unix_ns = sec * 1_000_000_000 + nsec
        return frame

    def _note_key(self, fd: int, frame: bytes) -> None:
        """Whether connection ``fd`` wakes a wait, from the key of a frame it carried."""
        wakes = frame[1:1 + frame[0]] in self._waking  # type: ignore[operator]
        if self._fd_wakes.get(fd) is not wakes:
            ep = self._ep_wake
            if ep is not None:
                try:
                    if wakes:
                        ep.register(fd, select.EPOLLIN)
                    else:
                        ep.unregister(fd)
                except OSError:
                    pass
            self._fd_wakes[fd] = wakes

    def recv(self) -> bytes | None:
        """The next frame (b"" is a wake-up), or None when none is waiting."""
        return self._next(0.0)

    def recv_wait(self, timeout_s: float) -> bytes | None:
        """The next frame (b"" is a wake-up), waiting for one at most ``timeout_s``
        (None: none came). A long wait (a lockstep step's inputs, seconds) is one
        epoll_wait, to the millisecond; a short one (a realtime loop's next period) a
        select() on the epoll, to the microsecond (a millisecond is a whole period at
        1 kHz)."""
        return self._next(timeout_s)

    def _next(self, timeout_s: float) -> bytes | None:
        polled = False
        ready = self._ready
        while True:
            while ready:
                fd = ready.pop()
                frame = self._read(fd)
                if frame is not None:
                    return frame
            if polled:
                return None
            self._poll(timeout_s)
            polled = True

    def _read(self, fd: int) -> bytes | None:
        """One frame of ``fd`` found readable: a connection's frame (``frame_from`` says
        whose), b"" for a wake-up; None when there is nothing to deliver (the listener, a
        hello, a connection that closed)."""
        c = self._conns.get(fd)
        if c is None:
            if fd == self._lfd:
                self._accept()
                return None
            if fd == self._wfd:
                self._drain_wake()
                return b""
            return None
        try:
            frame = self._recv_stamped(c) if self._stamped else c.recv(MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:
            self._forget(fd)
            return None
        if not frame:
            self._forget(fd)  # the sender closed its end
            return None
        if self._hello_from is not None:
            who = self._bound.get(fd)
            if who is None and frame[0] < len(frame) and frame[1:1 + frame[0]] == _HELLO_KEY:
                self._bind(fd, frame)
                return None  # a hello is the path's own, never delivered
            self.frame_from = who
        if self._waking is not None and frame[0] < len(frame):
            self._note_key(fd, frame)
        return frame

    def read_ready(self, on: Callable[[bytes], None], until: float | None = None) -> bool:
        """Hand ``on`` every frame readable now, one at a time as read (what a wait left
        unread first), without waiting; True when a wake-up came meanwhile (another
        thread posted: take its item). ``until`` (time.monotonic()): stop there even if
        more keeps coming (a flood). One look at every connection a round, a frame each:
        what :meth:`recv` does frame by frame, in one call (a realtime step reads its
        inputs here: each call through :meth:`recv` cost ~2 us of Python)."""
        ready, ep, read = self._ready, self._ep, self._read
        woke = False
        n = 0
        while True:
            while ready:
                frame = read(ready.pop())
                if frame is None:
                    continue
                if not frame:
                    woke = True
                    continue
                on(frame)
                n += 1
                if until is not None and n % 32 == 0 and time.monotonic() >= until:
                    return woke
            try:
                events = ep.poll(0)
            except InterruptedError:
                events = []
            if not events:
                return woke
            # the wake-up and the listener first in the list: read last (pop)
            ready[:] = [fd for fd, _ in events if fd == self._wfd or fd == self._lfd]
            ready += [fd for fd, _ in events if fd != self._wfd and fd != self._lfd]

    def _poll(self, timeout_s: float) -> None:
        """What is readable now (or once something is, within ``timeout_s``); the
        connections last in the list, so they are read before the listener and the
        wake-up (a report's wake-up never overtakes the frames sent before it)."""
        ep, wake = self._ep, self._ep_wake
        try:
            if timeout_s <= 0.0:
                events = ep.poll(0)
            elif wake is not None:  # what is readable now; else wait for what wakes us
                events = ep.poll(0)
                if not events:
                    if timeout_s < LONG_WAIT_S:
                        readable, _, _ = select.select((wake,), (), (), timeout_s)
                    else:
                        readable = wake.poll(timeout_s)
                    events = ep.poll(0) if readable else []
            elif timeout_s < LONG_WAIT_S:
                readable, _, _ = select.select((ep,), (), (), timeout_s)
                events = ep.poll(0) if readable else []
            else:
                events = ep.poll(timeout_s)
        except InterruptedError:
            events = []
        lfd, wfd = self._lfd, self._wfd
        ready = self._ready  # in place: the reader holds this list
        ready[:] = [fd for fd, _ in events if fd == wfd or fd == lfd]
        ready += [fd for fd, _ in events if fd != wfd and fd != lfd]

    def _accept(self) -> None:
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:  # none waiting (BlockingIOError), or closed
                return
            c.setblocking(False)
            fd = c.fileno()
            self._conns[fd] = c
            self._ep.register(fd, select.EPOLLIN)
            if self._stamped:
                c.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            if self._ep_wake is not None:  # until its first frame says what it carries
                self._ep_wake.register(fd, select.EPOLLIN)
                self._fd_wakes[fd] = True

    def _forget(self, fd: int) -> None:
        c = self._conns.pop(fd, None)
        self._bound.pop(fd, None)
        if c is not None:
            try:
                self._ep.unregister(fd)
            except OSError:
                pass
            if self._fd_wakes.pop(fd, False) and self._ep_wake is not None:
                try:
                    self._ep_wake.unregister(fd)
                except OSError:
                    pass
            c.close()

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(64):
                pass
        except (BlockingIOError, InterruptedError, OSError):
            pass

    def wake(self) -> None:
        """From any thread: make the waiting thread return from :meth:`recv_wait`. A
        full wake-up queue already wakes it."""
        try:
            self._wake_w.send(b"w")
        except OSError:
            pass

    # -- where a key goes ---------------------------------------------------------
    def refresh(self) -> None:
        """Read who hears what in the directory again (a peer came, went, restarted)."""
        seen: dict[str, _Peer] = {}
        for f in self.dir.glob(f"*{HEARS_SUFFIX}"):
            try:
                raw = json.loads(f.read_text())
                role, path = str(raw["role"]), str(raw["socket"])
                hears = [str(p) for p in raw["hears"]]
            except (OSError, ValueError, KeyError, TypeError):
                continue  # being written, or not ours
            if role == self.role or Path(path).parent != self.dir:
                continue
            old = self._peers.get(role)
            if old is not None and old.path == path and old.hears == hears:
                seen[role] = old
            else:
                if old is not None:
                    old.close()
                    self._behind.discard(old)
                seen[role] = _Peer(role, path, hears)
        for role, old in self._peers.items():
            if role not in seen:
                old.close()
                self._behind.discard(old)
        # the order a frame goes out in: the agents first, the listeners off the fleet's
        # path last. A plant (or bridge) acts on an agent's reply by stepping and sending
        # (at the run's end, ``end``): every agent that hears the same reply has it by
        # then (in the order of the directory, an agent that ended with the run could
        # report one share short: its neighbour's last reply still on its way)
        self._peers = dict(sorted(seen.items(), key=lambda kv: _send_order(kv[0])))
        self._routes.clear()

    def receivers(self, key: str) -> list[str]:
        """The roles ``key`` goes to, in the order it is sent to them."""
        return [p.role for p in self._route(key)]

    def _route(self, key: str) -> list[_Peer]:
        peers = self._routes.get(key)
        if peers is None:
            peers = [p for p in self._peers.values()
                     if any(key_matches(h, key) for h in p.hears)]
            self._routes[key] = peers
        return peers

    def connect_ahead(self, keys: Iterable[str]) -> int:
        """Open now the connections that sending on ``keys`` will take (a send dials a
        receiver it has no connection to): how many. A realtime node does so before its
        first period: every node's first frames of a run dialled at t = 0 (a connection,
        its hello and the receiver's accept and check, in both processes) put a burst on
        a core that had none to spare. A receiver that cannot be reached yet is dialled
        at the first send, as before."""
        opened = 0
        for key in keys:
            for p in self._route(key):
                if p.sock is None:
                    try:
                        self._dial(p)
                        opened += 1
                    except OSError:
                        p.close()
        return opened

    # -- sending ------------------------------------------------------------------
    def send(self, key: str, payload: bytes) -> int:
        """``payload`` on ``key`` to every local node that hears it; returns how many
        receivers did not get it (counted in ``dropped`` by receiver)."""
        peers = self._routes.get(key)
        if peers is None:
            peers = self._route(key)
        if not peers:
            return 0
        head = self._headers.get(key)
        if head is None:
            raw = key.encode()
            if len(raw) > MAX_KEY_BYTES:
                raise ValueError(f"key expression longer than {MAX_KEY_BYTES} bytes: {key}")
            head = self._headers[key] = bytes((len(raw),)) + raw
        frame = head + payload
        lost = 0
        for p in peers:
            if not self._send_to(p, frame):
                lost += 1
                self.dropped[p.role] = self.dropped.get(p.role, 0) + 1
        return lost

    def _send_to(self, p: _Peer, frame: bytes) -> bool:
        """True when ``frame`` went out or waits in ``p``'s backlog; False: lost."""
        if p.backlog:  # keep the order: what waits goes first
            self._flush_peer(p)
            if p.backlog:
                return self._defer(p, frame)
        for attempt in (0, 1):
            try:
                s = p.sock or self._dial(p)
                s.send(frame)
                return True
            except BlockingIOError:  # the connection is full: hold it for later
                return self._defer(p, frame)
            except OSError as exc:
                p.close()  # gone (EPIPE, ECONNREFUSED, ENOENT): dial again once (a restart)
                if attempt or exc.errno not in _GONE:
                    return False
        return False

    def _defer(self, p: _Peer, frame: bytes) -> bool:
        """Hold ``frame`` for ``p`` (its reader is behind): sent by :meth:`flush` as it
        catches up, in order. A backlog as long as ``max_backlog``: a lossless sender
        waits for room, a lossy one drops the oldest held frame (counted)."""
        if len(p.backlog) >= self.max_backlog:
            if self.lossless:
                # wait for it once; a receiver that took nothing meanwhile is stalled: its
                # frames are dropped at once from then on, until it takes one again
                self._flush_peer(p, wait_s=0.0 if p.stalled else self.lossless_wait_s)
                if len(p.backlog) >= self.max_backlog:
                    p.stalled = True
                    return False
            else:
                p.backlog.popleft()
                self.dropped[p.role] = self.dropped.get(p.role, 0) + 1
        p.backlog.append(frame)
        self.deferred += 1
        self._behind.add(p)
        return True

    def _flush_peer(self, p: _Peer, wait_s: float = 0.0) -> None:
        """Send ``p``'s held frames until its queue is full again; with ``wait_s``, wait
        for room up to that long in all."""
        q, s = p.backlog, p.sock
        poller = None
        left_ms = int(wait_s * 1000)
        while q:
            if s is None:  # gone since: what was held for it is lost
                self.dropped[p.role] = self.dropped.get(p.role, 0) + len(q)
                q.clear()
                break
            try:
                s.send(q[0])
                q.popleft()
                p.stalled = False
            except BlockingIOError:
                if left_ms <= 0:
                    return
                if poller is None:
                    poller = select.poll()
                    poller.register(s, select.POLLOUT)
                step = min(left_ms, 100)
                poller.poll(step)
                left_ms -= step
            except OSError:
                p.close()
                s = None
        self._behind.discard(p)

    def behind_peers(self) -> list[_Peer]:
        return list(self._behind)

    @property
    def behind(self) -> bool:
        """Some frames wait for a receiver that is behind (:meth:`flush` them)."""
        return bool(self._behind)

    def flush(self, wait_s: float = 0.0) -> None:
        """Send what waits for receivers that were behind, as far as they take it now
        (with ``wait_s``: waiting for them up to that long each)."""
        for p in list(self._behind):
            self._flush_peer(p, wait_s)

    # -- ending -------------------------------------------------------------------
    def close(self) -> None:
        """Send what is held (waiting for slow receivers up to ``lossless_wait_s``), then
        close the sockets and remove this node's files."""
        if self.closed:
            return
        self.flush(wait_s=self.lossless_wait_s)
        self.closed = True
        for p in self._peers.values():
            p.close()
        for fd in list(self._conns):
            self._forget(fd)
        self._ep.close()
        if self._ep_wake is not None:
            self._ep_wake.close()
        self._wake_r.close()
        self._wake_w.close()
        self.sock.close()
        for suffix in (HEARS_SUFFIX, SOCKET_SUFFIX):
            try:
                os.unlink(self.dir / f"{self.role}{suffix}")
            except OSError:
                pass


class Dispatch:
    """Which handler takes a datagram's payload, by its key: exact keys at once,
    wildcard subscriptions matched once per key and remembered."""

    def __init__(self) -> None:
        self._exact: dict[bytes, list[Callable[[bytes, str], None]]] = {}
        self._patterns: list[tuple[str, Callable[[bytes, str], None]]] = []
        self._matched: dict[bytes, list[Callable[[bytes, str], None]]] = {}
        self.unheard = 0  # datagrams on a key nobody here hears (counted, dropped)

    def add(self, pattern: str, handler: Callable[[bytes, str], None]) -> None:
        if "*" in pattern:
            self._patterns.append((pattern, handler))
        else:
            self._exact.setdefault(pattern.encode(), []).append(handler)
        self._matched.clear()

    def __call__(self, frame: bytes) -> None:
        n = frame[0] if frame else 0
        raw = frame[1:1 + n]
        found = self._matched.get(raw)
        if found is None:
            try:
                key = raw.decode()
            except UnicodeDecodeError:
                self.unheard += 1
                return
            handlers = [*self._exact.get(raw, ()),
                        *(h for p, h in self._patterns if key_matches(p, key))]
            found = (key, handlers)
            if len(self._matched) < MAX_MATCHED_KEYS:
                self._matched[raw] = found
        key, handlers = found
        if not handlers:
            self.unheard += 1
            return
        payload = frame[1 + n:]
        for h in handlers:
            h(payload, key)
