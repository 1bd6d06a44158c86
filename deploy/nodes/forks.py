"""The nodes' fork server: ``python -P -m deploy.nodes.forks FD``, started by the launcher.

Every node of a run is the same program, ``python -P -m deploy.nodes COMMAND ...``, and
each one used to spend ~0.15 s of CPU importing numpy, msgspec, zenoh and the project
before doing anything of its own (README command 1: five of them at once on 2 cores;
every short fleet run of the test suite too). This process imports all of that once and
then forks a node per request, already imported: the node's own start-up is then its
arguments, its scenario and its session (docs/bench-history.md).

The launcher stays the parent of every node (``deploy/run/node_forks.py``): it makes
itself the *child subreaper* for the moment of a request, this server forks twice and
the middle process exits at once, so the node is handed to the launcher, which waits
for it, signals it and reaps it by pid exactly as a process it had started itself.

A request is one datagram on the ``SOCK_SEQPACKET`` socket ``FD``: JSON ``{"args":
[...], "env": {...}}`` with the node's log file (and, for a zenoh node, its keyring
pipe) passed along as file descriptors. The answer is ``{"pid": N}``. The node, before
it runs:

- waits until it is the launcher's child (the server says so once the middle process
  is reaped), then starts its own session (``start_new_session`` of a spawned node);
- writes to its log (stdout and stderr) and reads nothing (stdin ``/dev/null``);
- takes the environment it was sent (``ZENOH_RUNTIME`` is read when its first session
  opens, after the fork), and writes its output unbuffered (``PYTHONUNBUFFERED``);
- shows its own command line (``ps``, ``/proc/PID/cmdline``: the tests find a run's
  processes by it) through ``setproctitle``;
- then runs ``deploy.nodes.__main__.main`` on a fresh stack: the server's loop is left
  by an exception, so the node exits as a spawned one does (its ``finally`` blocks,
  ``atexit``, the interpreter's own shutdown).

The server imports nothing a node might not need, and not pybullet: a forked node starts
with the server's pages, and an agent's peak RSS is a target of its own. It runs no
thread (``os.fork`` of a threaded process is unsafe), ends when the launcher closes its
end of the socket, and gets SIGTERM if the launcher dies.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import sys

from setproctitle import setproctitle

MAX_REQUEST = 1 << 20  # the request's JSON (the node's arguments and environment)
MAX_FDS = 2  # its log file, and its keyring pipe


class _Node(Exception):  # noqa: N818 - not an error: the way out of the server's loop
    """Raised in a forked node: it leaves the server's loop with what it has to run."""

    def __init__(self, args: list[str]) -> None:
        super().__init__(args)
        self.args = args


def _preload() -> None:
    """What every node imports before its first line of its own (~0.15 s of CPU)."""
    import zenoh  # noqa: F401 - its runtime starts with the first session, in the node

    import deploy.nodes.__main__  # noqa: F401 - every node command and its parser
    import deploy.nodes.agent  # noqa: F401
    import deploy.nodes.leader  # noqa: F401
    import deploy.nodes.plant  # noqa: F401


def _become_node(request: dict, fds: list[int], go: int, server: socket.socket) -> list[str]:
    """In the forked node: its session, streams, environment and title; its arguments."""
    server.close()
    if os.read(go, 1) != b"g":  # the server died before it knew this node was handed over
        os._exit(1)  # (the launcher gave up on it, or it was killed): never run unwatched
    os.close(go)
    os.setsid()
    log = fds[0]
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.dup2(log, 1)
    os.dup2(log, 2)
    for fd in (null, log):
        if fd > 2:
            os.close(fd)
    args = list(request["args"])
    if len(fds) > 1:  # the keyring pipe: the number it has in this process
        args += ["--keys-fd", str(fds[1])]
    # before the environment changes: setproctitle finds the command line's memory by
    # walking from the environment's, as the process started
    setproctitle(" ".join(request.get("title", [sys.executable, *args])))
    os.environ.clear()
    os.environ.update(request["env"])
    if os.environ.get("PYTHONUNBUFFERED"):
        for stream in (sys.stdout, sys.stderr):
            stream.reconfigure(write_through=True)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    return args


def _fork_node(request: dict, fds: list[int], server: socket.socket) -> int:
    """Fork the node twice (the middle process exits: the node goes to the launcher, the
    subreaper); returns its pid. In the node, raises :class:`_Node`."""
    go_r, go_w = os.pipe()
    pid_r, pid_w = os.pipe()
    middle = os.fork()
    if middle == 0:  # the middle process: fork the node, say its pid, leave
        try:
            node = os.fork()
        except BaseException:  # noqa: BLE001 - the server hears of it (no pid)
            os._exit(1)
        if node == 0:
            try:
                for fd in (go_w, pid_r, pid_w):
                    os.close(fd)
                args = _become_node(request, fds, go_r, server)
            except BaseException:  # noqa: BLE001 - never back into the server's loop
                import traceback

                traceback.print_exc()
                os._exit(1)
            raise _Node(args)
        os.write(pid_w, node.to_bytes(8, "little"))
        os._exit(0)
    os.close(go_r)
    os.close(pid_w)
    os.waitpid(middle, 0)  # gone: its child is the launcher's now
    raw = os.read(pid_r, 8)
    os.close(pid_r)
    try:
        if len(raw) != 8:
            raise OSError("the middle process died before it forked the node")
        os.write(go_w, b"g")  # the node may go on
    finally:
        os.close(go_w)
    return int.from_bytes(raw, "little")


def serve(server: socket.socket) -> None:
    """Answer requests until the launcher closes its end. Raises :class:`_Node` in a node."""
    while True:
        try:
            data, fds, _flags, _addr = socket.recv_fds(server, MAX_REQUEST, MAX_FDS)
        except InterruptedError:
            continue
        if not data:
            return  # the launcher left
        try:
            pid = _fork_node(json.loads(data), fds, server)
            answer = {"pid": pid}
        except _Node:
            raise
        except Exception as exc:  # noqa: BLE001 - said to the launcher, which spawns instead
            answer = {"error": f"{type(exc).__name__}: {exc}"}
        for fd in fds:
            os.close(fd)
        server.send(json.dumps(answer).encode())


def main(argv: list[str]) -> int:
    from deploy.runtime.parent_death import die_with_parent

    if not die_with_parent():  # the launcher ended before this server could ask
        return 1
    server = socket.socket(fileno=int(argv[0]))
    _preload()
    try:
        serve(server)
    except _Node as node:
        from deploy.nodes.__main__ import main as node_main

        sys.argv = [sys.argv[0], *node.args]
        return node_main(node.args)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
