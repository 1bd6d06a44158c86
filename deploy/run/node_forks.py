"""The launcher's side of the nodes' fork server (deploy/nodes/forks.py): a node forked
from one process that imported every node's modules once, handed to the launcher as its
own child.

:class:`NodeForks` starts the server (``start``), asks it for one node at a time
(``fork``) and ends it by pid (``close``). While it waits for an answer this process is
the *child subreaper* (Linux ``PR_SET_CHILD_SUBREAPER``): the server forks twice and the
middle process exits, so the node is re-parented here. The flag is set only for that
moment, so that no other orphan of this process's descendants lands here meanwhile.

:class:`ForkedProcess` is what the supervisor reads of a ``subprocess.Popen`` (``pid``,
``returncode``, ``poll``, ``wait``, signals): the node is this process's child, so
``os.waitpid`` reaps it as any other.

When the server cannot fork (not Linux, it failed to start or died, it answered an
error), ``fork`` returns None, says why once on stderr, and the caller spawns the node
with its command line as before: slower to start, the same node.
"""

from __future__ import annotations

import ctypes
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping

from deploy.runtime.own_python import child_env, python_module

PR_SET_CHILD_SUBREAPER = 36
SWITCH = "OMNIFLEET_NODE_FORKS"  # "0" in the environment: every node started by its command line
# zenoh's runtime pools cut to one worker each: a node needs no more, and every
# thread is a wake-up competing for 2 cores (the hop 80 -> 60 µs p50, ping-pong)
ZENOH_RUNTIME = ("(app: (worker_threads: 1), acc: (worker_threads: 1), "
                 "tx: (worker_threads: 1), rx: (worker_threads: 1), net: (worker_threads: 1))")
NODES = python_module("deploy.nodes")
ANSWER_TIMEOUT_S = 60.0  # the first answer waits for the server's imports (a loaded host)
CLOSE_GRACE_S = 2.0


def node_env() -> dict[str, str]:
    """The environment a node starts with (deploy/runtime/own_python.py), unbuffered."""
    env = child_env({**os.environ, "PYTHONUNBUFFERED": "1"})
    env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
    return env


def wanted() -> bool:
    """Whether a run forks its nodes (on either clock), unless switched off by
    ``OMNIFLEET_NODE_FORKS=0``. On the wall clock forked nodes take less CPU a step than
    spawned ones: `paper` at 1 kHz on 2 cores, 19 alternating pairs in four sittings, the
    fleet's CPU a step (the launcher aside) 0.90x (0.81-1.08x, below 1 in 16 pairs); the
    CAN fleet with CiA 402 drives pinned to one core 0.80-0.90x (3 pairs). Realtime runs had
    spawned their nodes since forked ones left `paper` unsettled in 3 of 6 pairs; with a
    late agent now stepping its law on each sample it missed, they pass alike (15 and 16
    of those 19 pairs, in noisy hours) (docs/bench-history.md, "Realtime nodes forked")."""
    return os.environ.get(SWITCH, "1") != "0"


def _subreaper(on: bool) -> bool:
    """This process the child subreaper (or not); whether the kernel took it."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class ForkedProcess:
    """A forked node, this process's child: the part of ``subprocess.Popen`` the
    supervisor and the tests use."""

    def __init__(self, pid: int, args: list[str]) -> None:
        self.pid = pid
        self.args = args
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped by the supervisor, which set returncode
                return self.returncode
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.poll() is not None:
            return self.returncode  # type: ignore[return-value]
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            fd = os.pidfd_open(self.pid)  # readable once it has exited
        except OSError:  # gone already, or a kernel without pidfds: poll instead
            fd = None
        try:
            while self.poll() is None:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
                if fd is not None:
                    select.select([fd], [], [], left)
                else:
                    time.sleep(0.01 if left is None else min(0.01, left))
        finally:
            if fd is not None:
                os.close(fd)
        return self.returncode  # type: ignore[return-value]

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class NodeForks:
    """The fork server of one run, started by :meth:`start`, ended by :meth:`close`."""

    def __init__(self) -> None:
        self._sock: socket.socket | None = None
        self._server: subprocess.Popen | None = None
        self.broken: str | None = None  # why nodes are spawned instead (said once)

    def start(self, env: Mapping[str, str]) -> None:
        """Start the server (it imports while the launcher goes on); ``env``: the nodes'
        environment (deploy/runtime/own_python.py)."""
        if not sys.platform.startswith("linux"):
            self.broken = "not Linux"
            return
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self._server = subprocess.Popen(
                [*python_module("deploy.nodes.forks"), str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, env=dict(env), start_new_session=True)
        except OSError as exc:
            ours.close()
            self._give_up(f"the fork server did not start: {exc}")
            return
        finally:
            theirs.close()
        self._sock = ours

    def fork(self, argv: list[str], env: Mapping[str, str], log_fd: int,
             keys_fd: int | None) -> ForkedProcess | None:
        """The node ``argv`` (``python -P -m deploy.nodes ...``) forked, writing to
        ``log_fd``, its keyring on ``keys_fd``; None when the caller must spawn it."""
        if self._sock is None or self.broken or argv[:len(NODES)] != NODES:
            return None
        request = json.dumps({"args": argv[len(NODES):], "env": dict(env),
                              "title": argv}).encode()
        fds = [log_fd] if keys_fd is None else [log_fd, keys_fd]
        if not _subreaper(True):
            self._give_up("this kernel refused PR_SET_CHILD_SUBREAPER")
            return None
        try:
            socket.send_fds(self._sock, [request], fds)
            ready, _, _ = select.select([self._sock], [], [], ANSWER_TIMEOUT_S)
            answer = json.loads(self._sock.recv(4096) or b"{}") if ready else {}
        except (OSError, ValueError) as exc:
            answer = {"error": f"{type(exc).__name__}: {exc}"}
        finally:
            _subreaper(False)
        if "pid" not in answer:
            self._give_up(answer.get("error", "the fork server did not answer"))
            return None
        return ForkedProcess(int(answer["pid"]), argv)

    def _give_up(self, why: str) -> None:
        """Spawn from now on, and end the server: a node it forks after this (an answer
        given up on) would find it gone before it was told to run, and exits."""
        if self.broken is None:
            self.broken = why
            print(f"omnifleet run: nodes started by their command line ({why})",
                  file=sys.stderr, flush=True)
        if self._server is not None and self._server.poll() is None:
            self._server.kill()
        self.close()

    def close(self) -> None:
        """End the server: it leaves when its socket closes; by pid after a grace."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._server is not None:
            try:
                self._server.wait(CLOSE_GRACE_S)
            except subprocess.TimeoutExpired:
                self._server.kill()
                self._server.wait()
            self._server = None


# The command line starts the server first thing, before its own imports (~0.2 s of CPU,
# which the server's then spend beside it): the first supervisor of the process takes it.
_early: NodeForks | None = None


def start_early() -> None:
    """Start this process's fork server now, for the run it is about to launch (nothing
    when that run spawns its nodes: ``OMNIFLEET_NODE_FORKS=0``)."""
    global _early
    if _early is None and wanted():
        _early = NodeForks()
        _early.start(node_env())


def take_early() -> NodeForks | None:
    """The server :func:`start_early` started, now the caller's to close (once)."""
    global _early
    forks, _early = _early, None
    return forks


def close_early() -> None:
    """End a server started early that no run took (the command ended before its run)."""
    forks = take_early()
    if forks is not None:
        forks.close()
