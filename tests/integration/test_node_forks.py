"""A node forked by the fork server (deploy/nodes/forks.py, deploy/run/node_forks.py) is
the process the supervisor would have spawned: the launcher's own child (waited for and
signalled by pid), in a session of its own, showing its command line, writing its log,
reading its keys from the pipe it was handed, and exiting with the node's own status.
Without a working server every node is spawned as before."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
from procs import pids_with, stat_fields

from deploy.contract.keyring import keyring_text, new_master
from deploy.contract.scenario import load_scenario
from deploy.run import node_forks
from deploy.run.node_forks import ForkedProcess, NodeForks
from deploy.run.plan import Child, key_roles
from deploy.run.supervisor import Supervisor
from deploy.runtime.own_python import python_module

NODES = python_module("deploy.nodes")


def _emulator(tmp_path: Path, marker: str) -> Child:
    """A CAN emulator on a virtual bus: a node that runs until it is stopped."""
    return Child("emulator", None, [*NODES, "emulate", "--scenario", "lab", "--robot", "1",
                                    "--can-interface", "virtual", "--can-channel", marker,
                                    "--truth-out", str(tmp_path / "truth.npz")],
                 tmp_path / "emulator.log", zenoh=False)


def _wait_for(path: Path, text: bytes, proc) -> None:
    deadline = time.monotonic() + 60
    while text not in path.read_bytes():
        assert proc.poll() is None, path.read_text()
        assert time.monotonic() < deadline, path.read_text()
        time.sleep(0.01)  # polling its log, the readiness signal


def test_a_forked_node_is_the_supervisors_child_in_its_own_session_showing_its_command(tmp_path):
    marker = f"forked-{os.getpid()}"
    sup = Supervisor(None)
    sup.start_forks()
    try:
        c = _emulator(tmp_path, marker)
        sup.spawn(c)
        assert isinstance(c.proc, ForkedProcess), sup.forks.broken
        _wait_for(c.log_path, b"on virtual:" + marker.encode(), c.proc)  # its stderr, in its log
        state, ppid, pgrp, session = stat_fields(c.proc.pid)[:4]
        assert int(ppid) == os.getpid()  # handed over: ours to wait for
        assert int(pgrp) == int(session) == c.proc.pid  # its own session, as spawned
        assert pids_with(marker) == {c.proc.pid}  # ps shows its command, nobody else has it
        assert Path(f"/proc/{c.proc.pid}/fd/0").resolve() == Path(os.devnull)
    finally:
        sup.stop_all()  # SIGTERM by pid, reaped here
    assert c.exit_code == 143  # the emulator's own clean exit on SIGTERM
    assert "(SIGTERM); sent " in c.log_path.read_text()
    assert len(np.load(tmp_path / "truth.npz")["t"]) > 0  # its finally ran: truth saved
    assert sup.forks is None  # the server is ended with the children


def test_a_forked_node_reads_its_keys_from_its_pipe_and_exits_with_its_own_status(tmp_path):
    sc = load_scenario("paper")
    master = new_master()
    roles = key_roles(sc, "model")
    texts = {"agent-1": keyring_text(master, "forks", "agent-2", roles),  # another's keys
             "agent-2": "not a keyring"}
    sup = Supervisor(texts.__getitem__)
    sup.start_forks()
    try:
        children = []
        for role in texts:
            robot = int(role[-1])
            c = Child(role, robot, [*NODES, "agent", "--scenario", "paper", "--robot", str(robot),
                                    "--fleet", "forks"], tmp_path / f"{role}.log")
            sup.spawn(c)
            children.append(c)
        for c in children:
            assert isinstance(c.proc, ForkedProcess)
            assert sup.reap(c, block=True)
    finally:
        sup.stop_all()
    for c in children:
        assert c.exit_code == 2, c.log_path.read_text()  # refused, said, exit 2
        assert "--keys-fd" in c.log_path.read_text()  # it read the pipe it was handed
    assert "agent-2" in children[0].log_path.read_text()  # the keys it got were agent-2's


def test_without_a_server_every_node_is_spawned_and_it_says_why(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(node_forks, "python_module", lambda m: python_module("no.such.module"))
    sup = Supervisor(None)
    sup.start_forks()
    try:
        c = _emulator(tmp_path, f"spawned-{os.getpid()}")
        sup.spawn(c)
        assert not isinstance(c.proc, ForkedProcess)  # a subprocess.Popen
        assert sup.forks.broken
        _wait_for(c.log_path, b"on virtual:", c.proc)
    finally:
        sup.stop_all()
    assert c.exit_code == 143
    assert "nodes started by their command line" in capsys.readouterr().err


def test_a_forked_node_is_waited_for_and_signalled_like_a_spawned_one(tmp_path):
    forks = NodeForks()
    forks.start(dict(os.environ))
    log = open(tmp_path / "log", "wb")  # noqa: SIM115 - closed below
    try:
        proc = forks.fork(_emulator(tmp_path, f"wait-{os.getpid()}").argv, dict(os.environ),
                          log.fileno(), None)
        assert proc is not None, forks.broken
        _wait_for(tmp_path / "log", b"on virtual:", proc)  # its handlers are in place
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 143
        assert proc.poll() == 143
        proc.send_signal(signal.SIGTERM)  # ended: nothing to signal, nothing raised
    finally:
        log.close()
        forks.close()
    assert forks.fork([*NODES, "emulate"], dict(os.environ), 1, None) is None  # closed


def test_the_command_line_forks_for_every_run_that_starts_a_fleet(monkeypatch):
    from deploy.cli import starts_a_fleet

    assert starts_a_fleet(["run", "paper", "--plant", "model"])
    assert starts_a_fleet(["run", "lab", "--clock", "realtime"])  # realtime runs fork too
    assert starts_a_fleet(["run", "lab", "--plant", "can-emulated"])
    assert not starts_a_fleet(["run", "paper", "--in-process"])
    assert not starts_a_fleet(["run", "--help"])
    assert not starts_a_fleet(["bench", "--quick"])
    assert node_forks.wanted()
    monkeypatch.setenv("OMNIFLEET_NODE_FORKS", "0")
    assert not node_forks.wanted()


def test_a_run_told_not_to_fork_spawns_its_nodes_and_ends_a_server_started_for_it(
        tmp_path, monkeypatch):
    node_forks.start_early()  # the command line's, before the run read the switch
    server = node_forks._early._server
    assert server.poll() is None
    monkeypatch.setenv("OMNIFLEET_NODE_FORKS", "0")
    sup = Supervisor(None)
    sup.start_forks()
    try:
        assert sup.forks is None and node_forks.take_early() is None
        assert server.returncode is not None  # ended and reaped, not left idle beside the run
        c = _emulator(tmp_path, f"spawned-{os.getpid()}")
        sup.spawn(c)
        assert not isinstance(c.proc, ForkedProcess)
    finally:
        sup.stop_all()


def _our_fork_servers() -> set[int]:
    return {p for p in pids_with("deploy.nodes.forks")
            if (f := stat_fields(p)) is not None and int(f[1]) == os.getpid() and f[0] != "Z"}


def test_a_run_refused_before_it_starts_leaves_no_fork_server(tmp_path, capsys):
    """The command line starts the server before its imports; a run refused by its
    arguments never takes it, and the command ends it on the way out."""
    from deploy.cli import main

    before = _our_fork_servers()
    assert main(["run", "no-such-scenario", "--out", str(tmp_path / "run")]) == 2
    assert "no-such-scenario" in capsys.readouterr().err
    assert _our_fork_servers() == before
    assert node_forks.take_early() is None


NOT_TOLD = """
import os, socket, sys
from deploy.nodes import forks
go_r, go_w = os.pipe()
os.close(go_w)  # the server died before it said the node was handed over
a, b = socket.socketpair()
log = os.open(sys.argv[1], os.O_WRONLY)
forks._become_node({"args": ["agent"], "env": {}}, [log], go_r, a)
print("ran anyway")
"""


def test_a_node_its_server_never_told_to_run_exits_before_anything(tmp_path):
    """A node whose server died (or was ended by a launcher that gave up waiting for its
    answer) before saying it was handed over would run unwatched: it exits at once."""
    import subprocess
    import sys

    log = tmp_path / "log"
    log.write_bytes(b"")
    r = subprocess.run([sys.executable, "-c", NOT_TOLD, str(log)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 1 and "ran anyway" not in r.stdout, r.stderr
    assert log.read_bytes() == b""
