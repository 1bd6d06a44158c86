"""The transport floor: one hop between two processes on this machine, over zenoh
and over a raw UDP socket (the physical limit for Python here). Three zenoh paths:
``runtime``, the nodes' own (a direct callback on zenoh's receive thread puts the
payload on a ``queue.SimpleQueue``, the working thread takes it; zenoh's default
transport over a unix socket), ``lowlatency`` (the same on zenoh's low-latency
transport: ``omnifleet run --zenoh-transport lowlatency``), and ``indirect``, the
path before wire v2 (zenoh's default indirect callback on a Python thread, a
Condition hand-off, over TCP), so they are compared in one sitting.

Measured as ping-pong: the parent sends a 200-byte payload, a child process
echoes it, the parent waits for the echo; one hop = round trip / 2. The child is
ended by pid whatever happens.

Also runnable alone as the echo side: ``python -m deploy.bench.transport echo
runtime|indirect|udp ADDRESS``.
"""

from __future__ import annotations

import os
import queue
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from typing import Any

PAYLOAD = b"x" * 200
WARMUP = 200
PATHS = ("runtime", "lowlatency", "indirect")


def _zenoh_session(path: str, listen: str | None = None, connect: str | None = None):
    import zenoh

    from deploy.runtime.transport import zenoh_config

    return zenoh.open(zenoh_config(None, [listen] if listen else [], [connect] if connect else [],
                                   gossip=False, lowlatency=path == "lowlatency"))


def _receiver(session: Any, key: str, path: str) -> tuple[Any, Callable[[float], bytes | None]]:
    """A subscription and its ``get(timeout)``, the way ``path`` receives."""
    import zenoh

    if path != "indirect":
        box: queue.SimpleQueue = queue.SimpleQueue()
        sub = session.declare_subscriber(key, zenoh.handlers.Callback(
            lambda s: box.put(s.payload.to_bytes()), indirect=False))

        def get(timeout: float) -> bytes | None:
            try:
                return box.get(timeout=timeout)
            except queue.Empty:
                return None
        return sub, get
    cond, items = threading.Condition(), []

    def on_sample(s: Any) -> None:
        with cond:
            items.append(s.payload.to_bytes())
            cond.notify_all()
    sub = session.declare_subscriber(key, on_sample)

    def get_indirect(timeout: float) -> bytes | None:
        with cond:
            if not cond.wait_for(lambda: items, timeout):
                return None
            return items.pop(0)
    return sub, get_indirect


def _publisher(session: Any, key: str) -> Any:
    import zenoh

    return session.declare_publisher(key, express=True,
                                     congestion_control=zenoh.CongestionControl.BLOCK)


def _echo_zenoh(path: str, endpoint: str) -> None:
    session = _zenoh_session(path, connect=endpoint)
    pub = _publisher(session, "bench/pong")
    sub, get = _receiver(session, "bench/ping", path)
    session.liveliness().declare_token("bench/echo")
    while True:
        data = get(60.0)
        if data is None or data == b"stop":
            break
        pub.put(data)
    sub.undeclare()
    session.close()


def _echo_udp(port: str) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", int(port)))
    while True:
        data, peer = sock.recvfrom(4096)
        if data == b"stop":
            return
        sock.sendto(data, peer)


def _child(kind: str, address: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "deploy.bench.transport", "echo", kind, address],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _end(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def zenoh_hop_us(round_trips: int, path: str = "runtime", over: str | None = None) -> float:
    """Median one-way zenoh hop (µs) between this process and an echo child that
    both receive the way ``path`` does (see the module's docstring). ``over``:
    ``unixsock`` (a run's default: a socket in a private directory) or ``tcp``
    (loopback, what any local process can reach); default: unixsock, TCP for
    ``indirect``."""
    from deploy.run.plan import free_tcp_port

    where = tempfile.mkdtemp(prefix="omnifleet-hop-")
    over = over or ("tcp" if path == "indirect" else "unixsock")
    endpoint = (f"unixsock-stream/{where}/hop.sock" if over == "unixsock"
                else f"tcp/127.0.0.1:{free_tcp_port()}")
    session = _zenoh_session(path, listen=endpoint)
    child = _child(path, endpoint)
    try:
        ready = threading.Event()
        sub, get = _receiver(session, "bench/pong", path)
        watch = session.liveliness().declare_subscriber(
            "bench/echo", lambda _s: ready.set(), history=True)
        if not ready.wait(30.0):
            raise RuntimeError("zenoh echo process did not come up: "
                               + child.stderr.read().decode(errors="replace")[-500:])
        pub = _publisher(session, "bench/ping")
        times = []
        for i in range(WARMUP + round_trips):
            t0 = time.perf_counter_ns()
            pub.put(PAYLOAD)
            if get(5.0) is None:
                raise RuntimeError("zenoh echo lost a message")
            if i >= WARMUP:
                times.append(time.perf_counter_ns() - t0)
        pub.put(b"stop")
        sub.undeclare()
        watch.undeclare()
        return statistics.median(times) / 2e3
    finally:
        _end(child)
        session.close()
        for name in os.listdir(where):
            os.unlink(os.path.join(where, name))
        os.rmdir(where)


def udp_hop_us(round_trips: int) -> float:
    """Median one-way UDP hop (µs) between this process and an echo child."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.5)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    child = _child("udp", str(port))
    try:
        target = ("127.0.0.1", port)
        deadline = time.monotonic() + 30.0
        while True:  # until the child's socket answers
            sock.sendto(b"hello", target)
            try:
                sock.recvfrom(4096)
                break
            except (TimeoutError, ConnectionRefusedError):
                if time.monotonic() > deadline or child.poll() is not None:
                    raise RuntimeError("udp echo process did not come up") from None
        sock.settimeout(5.0)
        times = []
        for i in range(WARMUP + round_trips):
            t0 = time.perf_counter_ns()
            sock.sendto(PAYLOAD, target)
            sock.recvfrom(4096)
            if i >= WARMUP:
                times.append(time.perf_counter_ns() - t0)
        sock.sendto(b"stop", target)
        return statistics.median(times) / 2e3
    finally:
        _end(child)
        sock.close()


if __name__ == "__main__":
    if len(sys.argv) != 4 or sys.argv[1] != "echo" or sys.argv[2] not in (*PATHS, "udp"):
        sys.exit("usage: python -m deploy.bench.transport echo runtime|lowlatency|indirect|udp "
                 "ADDRESS")
    if sys.argv[2] == "udp":
        _echo_udp(sys.argv[3])
    else:
        _echo_zenoh(sys.argv[2], sys.argv[3])
