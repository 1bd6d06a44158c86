"""The run's processes: start them, watch them, carry out the fault plan's kills,
pauses and restarts, and stop every one of them by pid, always.

Children are started in their own session (a Ctrl-C reaches only the launcher,
which stops them in order) and get SIGTERM if the launcher itself dies
(``die_with_parent`` in each node).
"""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from deploy.contract.wire import PLANT_ROLE
from deploy.run.kill_schedule import PAUSE, RESUME, KillSchedule
from deploy.run.node_forks import NodeForks, close_early, node_env, take_early, wanted
from deploy.run.plan import Child, restart_of
from deploy.runtime.node_runtime import StopFlag

STOP_GRACE_S = 3.0
REJOIN_GRACE_S = 3.0  # a restarted node may exit this long after the others


class RunFailed(RuntimeError):
    """A child died, or the fleet never came up."""


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM reached the launcher; every child has been stopped."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


def _failure(c: Child, what: str) -> str:
    tail = c.tail()
    return f"{c.role} (pid {c.proc.pid}) {what}" + (f"; its last output:\n{tail}" if tail else "")


def _keys_pipe(text: str) -> int:
    """A pipe holding ``text``, its write end closed: the read end, for a child."""
    r, w = os.pipe()
    data = text.encode()
    if len(data) > 60_000:  # beyond the default pipe (64 KiB): grow it, or the write blocks
        fcntl.fcntl(w, fcntl.F_SETPIPE_SZ, len(data) + 4096)
    with os.fdopen(w, "wb") as f:
        f.write(data)
    return r


class Supervisor:
    """Owns the run's child processes (``children``, in start order)."""

    def __init__(self, keyring_of: Callable[[str], str] | None,
                 run_dir: Path | None = None) -> None:
        # each zenoh node's keyring (deploy/contract/keyring.py), by role: handed to it on a
        # pipe (--keys-fd), never in its environment (/proc/PID/environ shows that to the
        # same user), on its command line or on disk
        self.keyring_of = keyring_of
        self.run_dir = run_dir  # the run's sockets (a restarted node's old one is removed)
        self.children: list[Child] = []
        self.forks: NodeForks | None = None  # the nodes' fork server, once started

    def start_forks(self) -> None:
        """Start the nodes' fork server now, so that it has imported what the nodes need
        by the time they start (deploy/nodes/forks.py); without it
        (``OMNIFLEET_NODE_FORKS=0`` in the environment: node_forks.wanted) each node is
        started by its command line, and a node the fault plan restarts on a loaded core
        takes ~0.9 s to import what it needs before its first command (forked, 0.07-0.15
        s), its robot on zero torque meanwhile. :meth:`stop_all` ends it."""
        if not wanted():
            close_early()  # a server started before the switch was turned off
        elif self.forks is None:
            self.forks = take_early()  # started by the command line before its imports
            if self.forks is None:
                self.forks = NodeForks()
                self.forks.start(node_env())

    def start(self, children: list[Child]) -> None:
        for c in children:
            self.spawn(c)

    def spawn(self, child: Child) -> None:
        child.log_path.parent.mkdir(parents=True, exist_ok=True)
        child.log = open(child.log_path, "wb")  # noqa: SIM115 - closed in reap
        env = node_env()
        keys = None
        if child.zenoh and self.keyring_of is not None:
            keys = _keys_pipe(self.keyring_of(child.role))
        try:
            forked = None
            if self.forks is not None:
                forked = self.forks.fork(child.argv, env, child.log.fileno(), keys)
            child.proc = forked or subprocess.Popen(
                child.argv if keys is None else [*child.argv, "--keys-fd", str(keys)],
                stdout=child.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=env, start_new_session=True, pass_fds=() if keys is None else (keys,),
            )
        finally:
            if keys is not None:
                os.close(keys)  # the child has its own copy
        self.children.append(child)

    def reap(self, child: Child, block: bool) -> bool:
        """Collect the child's exit status; True once it has exited."""
        if child.exit_code is not None or child.proc is None:
            return True
        try:
            pid, status, usage = os.wait4(child.proc.pid, 0 if block else os.WNOHANG)
        except ChildProcessError:
            pid, status, usage = child.proc.pid, 0, None
        if pid == 0:
            return False
        child.exit_code = os.waitstatus_to_exitcode(status)
        if usage is not None:  # what a process with no report of its own cost (the emulator)
            child.cpu_s = usage.ru_utime + usage.ru_stime
        child.proc.returncode = child.exit_code
        if child.log is not None:
            child.log.close()
        return True

    def check(self, ended: bool) -> bool:
        """Raise :class:`RunFailed` if a child died; returns whether the run has ended
        (``ended``, or the plant exited 0: it does so only after sending ``end``, which
        a launcher behind on a large fleet's traffic may not have read yet)."""
        for c in self.children:
            if c.killed or not self.reap(c, block=False) or (ended and c.exit_code == 0):
                continue
            if c.exit_code != 0:
                raise RunFailed(_failure(c, f"exited with code {c.exit_code}"))
            ended = ended or c.role == PLANT_ROLE
        return ended

    def stop_all(self) -> None:
        """SIGTERM every live child by pid, SIGKILL after a grace period, reap all; then
        end the nodes' fork server."""
        live = [c for c in self.children if c.proc is not None and not self.reap(c, False)]
        for c in live:
            try:
                os.kill(c.proc.pid, signal.SIGTERM)
                os.kill(c.proc.pid, signal.SIGCONT)  # a paused one (fault plan) hears it too
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + STOP_GRACE_S
        while live and time.monotonic() < deadline:
            live = [c for c in live if not self.reap(c, False)]
            time.sleep(0.02)
        for c in live:
            try:
                os.kill(c.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.reap(c, block=True)
        if self.forks is not None:
            self.forks.close()
            self.forks = None

    def apply_kills(self, kills: KillSchedule, t: float) -> None:
        """The fault plan's process kills (SIGKILL: a crash, no goodbye), pauses and
        restarts (the agent rejoins the running fleet) due at run time ``t``."""
        for event in kills.due(t):
            # kill or pause: the live process of that role; restart: the one killed
            child = [c for c in self.children if c.role == event.process
                     and c.killed == event.restart][-1]
            if event.restart:
                if self.run_dir is not None:  # the killed node's socket file stays behind it
                    (self.run_dir / f"{child.role}.sock").unlink(missing_ok=True)
                again = restart_of(child, self.run_dir)
                self.spawn(again)
                kills.log(event, t, again.proc.pid)
            elif event.action in (PAUSE, RESUME):  # off the CPU and back, as a starved host
                os.kill(child.proc.pid, signal.SIGSTOP if event.action == PAUSE else signal.SIGCONT)
                kills.log(event, t, child.proc.pid)
            else:
                child.killed = True
                os.kill(child.proc.pid, signal.SIGKILL)
                self.reap(child, block=True)
                kills.log(event, t, child.proc.pid)

    def wait_for_exit(self, stop: StopFlag, wait: Callable[[float], None],
                      timeout_s: float = 20.0) -> None:
        """After ``end``: every node sends its report and exits 0; then the children
        that run until stopped (emulators) are stopped. ``wait(s)`` hears the fleet
        meanwhile, for at most ``s`` seconds. Raises :class:`RunFailed` naming each
        node that did not exit 0."""
        deadline = time.monotonic() + timeout_s
        nodes = [c for c in self.children if not c.stop_after_run]
        steady = [c for c in nodes if not c.restarted]
        others_done_at = None
        while time.monotonic() < deadline:
            if stop():
                raise Interrupted(stop.reason)
            if all(self.reap(c, False) for c in steady):
                others_done_at = others_done_at or time.monotonic()
                if (all(self.reap(c, False) for c in nodes)
                        or time.monotonic() > others_done_at + REJOIN_GRACE_S):
                    break
            wait(0.02)
        for c in nodes:
            # a restarted node still starting when the run ended (a loaded host: imports and
            # the handshake took longer than the run had left) missed the end: stop it
            if c.restarted and self._terminate(c):
                c.never_rejoined = True  # it has no report to send (run_figures.py)
                print(f"omnifleet run: {c.role} (restarted) was still rejoining when the run "
                      "ended: stopped", file=sys.stderr)
        for c in self.children:
            if c.stop_after_run:
                self._terminate(c)  # stopped as planned
        bad = [c for c in self.children if c.exit_code not in (0,) and not c.killed]
        if bad:
            raise RunFailed("; ".join(
                _failure(c, "did not exit" if c.exit_code is None
                         else f"exited with code {c.exit_code}") for c in bad))

    def _terminate(self, c: Child, timeout_s: float = 10.0) -> bool:
        """SIGTERM a child still running; True (and exit code 0) if it ended by it."""
        if self.reap(c, False):
            return False
        c.proc.send_signal(signal.SIGTERM)
        until = time.monotonic() + timeout_s
        while not self.reap(c, False) and time.monotonic() < until:
            time.sleep(0.02)
        if c.exit_code in (-signal.SIGTERM, 143):
            c.exit_code = 0
            return True
        return False
