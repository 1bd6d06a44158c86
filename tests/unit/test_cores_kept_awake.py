"""``omnifleet run --keep-cores-awake`` (deploy/run/awake.py, deploy/runtime/idle_poll.py):
one spinner per core, pinned to it, below everything (SCHED_IDLE, nice 19, an autogroup
of its own at nice 19, never the launcher's), ended by pid however the run is left; and
refused where it would take cores from the nodes (lockstep, nodes not under SCHED_FIFO)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from deploy.run.awake import cores_kept_awake
from tests.procs import stat_fields

pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling policies")


def _policy(pid: int) -> tuple[int, set[int], int, str]:
    """(policy, affinity, nice, autogroup line) of a live process, once it has lowered
    itself (its autogroup last), or as they are after a bound for a loaded machine."""
    deadline = time.monotonic() + 30.0
    while True:
        with open(f"/proc/{pid}/autogroup") as f:
            group = f.read().strip()
        if group.endswith("nice 19") or time.monotonic() > deadline:
            break
        time.sleep(0.02)  # polling: the child lowers itself right after its interpreter starts
    return (os.sched_getscheduler(pid), os.sched_getaffinity(pid),
            os.getpriority(os.PRIO_PROCESS, pid), group)


def _group_id(line: str) -> str:
    """The autogroup's name in a /proc/PID/autogroup line; the kernel prints nothing for
    the root autogroup (a process whose session began at boot, as a CI runner's may)."""
    return line.split()[0] if line else "the root autogroup"


def _child_raising_its_priority(after_a_line: bool) -> subprocess.Popen:
    """A process that asks for SCHED_FIFO 1 (after a line on its stdin, if so asked),
    prints "fifo" or "refused" (no privilege, or a CPU group without realtime time), then
    sleeps until killed."""
    return subprocess.Popen([sys.executable, "-c", f"""
import os, sys, time
if {after_a_line}:
    sys.stdin.readline()
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    print("fifo", flush=True)
except OSError:
    print("refused", flush=True)
time.sleep(30)
"""], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def test_one_spinner_a_core_below_everything_in_an_autogroup_of_its_own():
    with open("/proc/self/autogroup") as f:
        ours = f.read().strip()
    cores = sorted(os.sched_getaffinity(0))
    with cores_kept_awake(set(cores)) as pids:
        assert len(pids) == len(cores)
        seen = [_policy(pid) for pid in pids]
    for (policy, affinity, nice, group), core in zip(seen, cores, strict=True):
        assert policy == os.SCHED_IDLE and affinity == {core} and nice == 19
        assert group.endswith("nice 19") and _group_id(group) != _group_id(ours)
    with open("/proc/self/autogroup") as f:
        assert f.read().strip() == ours  # the launcher's own group left as it was
    assert not any(stat_fields(pid) for pid in pids)  # ended by pid and reaped: not even a zombie


def test_the_spinners_end_when_the_run_inside_fails():
    pids: list[int] = []
    with pytest.raises(RuntimeError), cores_kept_awake({min(os.sched_getaffinity(0))}) as started:
        pids += started
        raise RuntimeError("the run failed")
    assert pids and not any(stat_fields(pid) for pid in pids)  # gone, not even a zombie


def test_no_core_no_spinner():
    with cores_kept_awake(None) as pids:
        assert pids == []


@pytest.mark.parametrize("args", [
    ("--keep-cores-awake",),  # lockstep (the default clock)
    ("--clock", "realtime", "--priority", "0", "--keep-cores-awake"),
])
def test_refused_where_it_would_take_the_nodes_cores(args, tmp_path):
    out = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "lab", *args,
                          "--out", str(tmp_path / "run")], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2, out.stderr
    assert "--keep-cores-awake needs --clock realtime" in out.stderr
    assert not (tmp_path / "run").exists()  # refused before anything ran


def test_a_node_not_under_sched_fifo_keeps_the_cores_as_they_are():
    """A spinner beside a node of the normal policy takes the core each time the node
    hands it over: the launcher keeps no core awake unless every node runs under
    SCHED_FIFO (deploy/run/awake.py, not_realtime); a process that is gone counts as not."""
    from deploy.run.awake import not_realtime

    normal = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    try:
        assert not_realtime({"agent-1": normal.pid, "bridge-1": gone.pid}) == ["agent-1",
                                                                               "bridge-1"]
    finally:
        normal.kill()
        normal.wait()
    fifo = _child_raising_its_priority(after_a_line=False)
    try:
        got = fifo.stdout.readline().strip()
        assert not_realtime({"agent-1": fifo.pid}) == ([] if got == "fifo" else ["agent-1"])
    finally:
        fifo.kill()
        fifo.wait()


def test_a_child_that_raises_its_priority_after_the_nodes_are_ready_is_waited_for():
    """The driver emulator has no readiness of its own and raises its priority as its loop
    begins, on a loaded core after the zenoh nodes said they were ready: the launcher gives
    it time (refused_realtime) instead of refusing the spinners at once, which once left a
    one-core CAN run without them. A ready node not under SCHED_FIFO refuses them at once."""
    from deploy.run.awake import refused_realtime

    late = _child_raising_its_priority(after_a_line=True)  # once the check waits for it
    normal = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    answers: list[str] = []

    def raise_it_then_go_on() -> bool:  # the launcher's stop flag, asked at each poll
        if not answers:
            late.stdin.write("go\n")
            late.stdin.flush()
            answers.append(late.stdout.readline().strip())
        return answers[0] == "refused"  # no wait for what the host refused

    def never() -> bool:
        raise AssertionError("a ready node was refused: nothing else is waited for")

    try:
        assert refused_realtime({"agent-1": normal.pid}, {"emulator": late.pid}, 60.0,
                                never) == ["agent-1"]
        got = refused_realtime({}, {"emulator": late.pid}, 60.0, raise_it_then_go_on)
        assert answers and got == ([] if answers[0] == "fifo" else ["emulator"])
    finally:
        for p in (late, normal):
            p.kill()
            p.wait()
