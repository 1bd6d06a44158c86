"""The supervisor ends every process it started by pid (SIGTERM, then SIGKILL after
the grace period), and names a child that died."""

from __future__ import annotations

import os
import sys
import time
import types

import pytest

from deploy.run.plan import Child
from deploy.run.supervisor import RunFailed, Supervisor

SLEEPER = "import time; print('up', flush=True); time.sleep(60)"
STUBBORN = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
            "print('up', flush=True); time.sleep(60)")


def _started(sup: Supervisor, tmp_path, role: str, code: str) -> Child:
    c = Child(role, None, [sys.executable, "-c", code], tmp_path / f"{role}.log")
    sup.spawn(c)
    return c


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_stop_all_ends_every_child_by_pid_even_one_that_ignores_sigterm(tmp_path, monkeypatch):
    from deploy.run import supervisor

    monkeypatch.setattr(supervisor, "STOP_GRACE_S", 0.3)  # the grace is a constant: shorter here
    sup = Supervisor(None)
    try:
        polite = _started(sup, tmp_path, "polite", SLEEPER)
        stubborn = _started(sup, tmp_path, "stubborn", STUBBORN)
        for c in (polite, stubborn):  # wait until each runs its own code (not a sleep)
            while b"up" not in c.log_path.read_bytes():
                assert c.proc.poll() is None, c.log_path.read_text()
                time.sleep(0.01)  # polling its output, the readiness signal
    finally:
        sup.stop_all()
    assert polite.exit_code == -15  # SIGTERM
    assert stubborn.exit_code == -9  # SIGKILL after the grace period
    assert not _alive(polite.proc.pid) and not _alive(stubborn.proc.pid)


def test_a_child_that_died_fails_the_run_naming_it_and_its_last_output(tmp_path):
    sup = Supervisor(None)
    try:
        c = _started(sup, tmp_path, "agent-2", "import sys; print('boom'); sys.exit(3)")
        sup.reap(c, block=True)
        with pytest.raises(RunFailed, match=r"agent-2 \(pid \d+\) exited with code 3(.|\n)*boom"):
            sup.check(ended=False)
    finally:
        sup.stop_all()


def test_the_plant_exiting_cleanly_ends_the_run():
    """The plant exits 0 only after publishing ``end``; a launcher behind on traffic
    may see the exit first: that is the end of the run, not a crash."""
    sup = Supervisor(None)
    done = types.SimpleNamespace(pid=4242)  # an exited process: only its pid is read
    sup.children = [Child("agent-1", 1, [], os.devnull, done, exit_code=0)]
    assert not sup.check(ended=False)
    sup.children.append(Child("plant", None, [], os.devnull, done, exit_code=0))
    assert sup.check(ended=False)


# reads its pipe as a node does (to the end: one os.read may return part of a keyring
# larger than the pipe's buffer), and says so in one line (the supervisor's children
# write unbuffered: print's pieces would be separate writes the test could see half of)
KEYS_READER = ("import sys, hashlib; from deploy.contract.keyring import read_fd; "
               "data = read_fd(int(sys.argv[sys.argv.index('--keys-fd') + 1])); "
               "sys.stdout.write('got ' + hashlib.sha256(data).hexdigest() + '\\n'); "
               "sys.stdout.flush(); import time; time.sleep(60)")


def test_a_child_gets_its_keys_on_a_pipe_never_in_its_environment_or_command_line(tmp_path):
    """Every same-user process can read /proc/PID/environ and /proc/PID/cmdline: the
    run's secret sat in every node's environment, and a stop signed with it was obeyed.
    Each node's keyring now travels on a pipe the child reads once."""
    import hashlib

    texts = {"agent-2": "K" * 70_000 + "agent-2", "plant": "P" * 100 + "plant"}  # one > 64 KiB
    sup = Supervisor(texts.__getitem__)
    try:
        children = [_started(sup, tmp_path, role, KEYS_READER) for role in texts]
        for c in children:
            while b"\n" not in c.log_path.read_bytes():  # its whole line
                assert c.proc.poll() is None, c.log_path.read_text()
                time.sleep(0.01)  # polling its output, the readiness signal
            want = hashlib.sha256(texts[c.role].encode()).hexdigest()
            assert c.log_path.read_text().split()[1] == want  # the whole keyring, intact
            for where in ("environ", "cmdline"):
                seen = open(f"/proc/{c.proc.pid}/{where}", "rb").read()
                assert texts[c.role][-8:].encode() not in seen and b"K" * 32 not in seen
            assert "--keys-fd" not in c.argv  # a restart gets a new pipe, not this number
    finally:
        sup.stop_all()
