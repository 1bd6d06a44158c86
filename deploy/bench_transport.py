"""The transport floor: one hop between two processes on this machine, over zenoh
(the runtime's own path: a put, a subscriber callback, a wake-up of the waiting
thread) and over a raw UDP socket (the physical limit for Python here).

Measured as ping-pong: the parent sends a 200-byte payload, a child process
echoes it, the parent waits for the echo; one hop = round trip / 2. The child is
ended by pid whatever happens.

Also runnable alone as the echo side: ``python -m deploy.bench_transport echo
zenoh|udp ADDRESS``.
"""

from __future__ import annotations

import socket
import statistics
import subprocess
import sys
import threading
import time

PAYLOAD = b"x" * 200
WARMUP = 200


def _zenoh_session(listen: str | None = None, connect: str | None = None):
    import zenoh

    from deploy.transport import zenoh_config

    return zenoh.open(zenoh_config(None, [listen] if listen else [], [connect] if connect else []))


def _echo_zenoh(endpoint: str) -> None:
    session = _zenoh_session(connect=endpoint)
    import zenoh

    pub = session.declare_publisher("bench/pong", express=True,
                                    congestion_control=zenoh.CongestionControl.BLOCK)
    done = threading.Event()

    def on_ping(sample) -> None:
        data = sample.payload.to_bytes()
        if data == b"stop":
            done.set()
        else:
            pub.put(data)

    sub = session.declare_subscriber("bench/ping", on_ping)
    session.liveliness().declare_token("bench/echo")
    done.wait()
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
    return subprocess.Popen([sys.executable, "-m", "deploy.bench_transport", "echo", kind, address],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _end(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def zenoh_hop_us(round_trips: int) -> float:
    """Median one-way zenoh hop (µs) between this process and an echo child."""
    from deploy.launcher import free_tcp_port

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    session = _zenoh_session(listen=endpoint)
    import zenoh

    child = _child("zenoh", endpoint)
    try:
        arrived = threading.Event()
        ready = threading.Event()
        sub = session.declare_subscriber("bench/pong", lambda _s: arrived.set())
        watch = session.liveliness().declare_subscriber(
            "bench/echo", lambda _s: ready.set(), history=True)
        if not ready.wait(30.0):
            raise RuntimeError("zenoh echo process did not come up: "
                               + child.stderr.read().decode(errors="replace")[-500:])
        pub = session.declare_publisher("bench/ping", express=True,
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        times = []
        for i in range(WARMUP + round_trips):
            arrived.clear()
            t0 = time.perf_counter_ns()
            pub.put(PAYLOAD)
            if not arrived.wait(5.0):
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
    if len(sys.argv) != 4 or sys.argv[1] != "echo" or sys.argv[2] not in ("zenoh", "udp"):
        sys.exit("usage: python -m deploy.bench_transport echo zenoh|udp ADDRESS")
    (_echo_zenoh if sys.argv[2] == "zenoh" else _echo_udp)(sys.argv[3])
