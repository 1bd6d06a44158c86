"""tests/suite.py under a signal: pytest ends its own tests' processes, nothing is left,
no further phase starts, and the status says how it ended."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from background_cpu import BackgroundGroup
from procs import running
from suite import SERIAL, SIDE_BY_SIDE

SUITE = Path(__file__).resolve().parent.parent / "suite.py"


SLEEPER = '''
import os, subprocess, sys, time
from pathlib import Path

def test_holds_a_child_until_interrupted():
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        Path(os.environ["SUITE_PIDS"]).write_text(f"{os.getpid()} {child.pid}")
        time.sleep(60)
    finally:  # what a fleet test does: its processes ended by pid
        child.terminate()
        child.wait()
'''


# tests/suite.py started as from a terminal: SIGINT and SIGTERM neither blocked nor ignored.
# The test runs inside a pytest(-xdist) worker, and a blocked or ignored signal is
# inherited through fork and exec (Python then installs no KeyboardInterrupt at all).
AS_FROM_A_TERMINAL = """
import os, signal, sys
for s in (signal.SIGINT, signal.SIGTERM):
    signal.signal(s, signal.SIG_DFL)
signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
os.execv(sys.executable, [sys.executable, *sys.argv[1:]])
"""


def signal_states(root: int) -> list[str]:
    """Each process of ``root``'s session: its state, what it waits in, and its blocked
    and ignored signals (/proc)."""
    out = []
    for pid in sorted(int(d) for d in os.listdir("/proc") if d.isdigit()):
        try:
            if os.getsid(pid) != root:
                continue
            status = Path(f"/proc/{pid}/status").read_text().splitlines()
            wchan = Path(f"/proc/{pid}/wchan").read_text()
        except OSError:
            continue
        keep = [ln.replace("\t", " ") for ln in status
                if ln.startswith(("Name", "State", "SigBlk", "SigIgn", "SigCgt"))]
        out.append(f"{pid} ({', '.join(keep)}, wchan {wchan})")
    return out


def groups_of_suites() -> set[str] | None:
    """The background CPU groups of suites (tests/background_cpu.py) under this process's
    own; None where no group can be made."""
    probe = BackgroundGroup.make(f"omnifleet-probe-{os.getpid()}")
    if probe is None:
        return None
    probe.remove()
    return {str(p) for d in probe.dirs for p in d.parent.glob("omnifleet-suite-*")}


@pytest.mark.parametrize("side_by_side", [False, True], ids=["one-after-the-other", "side-by-side"])
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_ends_the_phase_with_its_processes_and_starts_no_other(
        tmp_path: Path, sig: signal.Signals, status: int, side_by_side: bool) -> None:
    """One after the other, the second phase never starts; side by side (the first in a
    CPU group of its own), both end, and the group with them."""
    groups_before = groups_of_suites()
    if side_by_side and groups_before is None:
        pytest.skip("no CPU group can be made here (root and a cgroup cpu controller): "
                    "the suite runs its phases one after the other, the other case")
    (tmp_path / "test_sleeper.py").write_text(SLEEPER)
    pids = tmp_path / "pids"
    suite = subprocess.Popen(
        [sys.executable, "-c", AS_FROM_A_TERMINAL, str(SUITE), str(tmp_path),
         "-p", "no:cacheprovider", "-q"],
        cwd=tmp_path, env={**os.environ, "SUITE_PIDS": str(pids),
                           SIDE_BY_SIDE: "1" if side_by_side else "0"},
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60.0
        while not pids.exists() or len(pids.read_text().split()) < 2:
            assert suite.poll() is None and time.monotonic() < deadline, "the test never started"
            time.sleep(0.05)
        pytest_pid, child_pid = map(int, pids.read_text().split())
        if sig == signal.SIGINT:  # as a terminal does: to the whole process group
            os.killpg(suite.pid, signal.SIGINT)
        else:
            suite.send_signal(sig)
        try:
            out, _ = suite.communicate(timeout=60.0)
        except subprocess.TimeoutExpired as exc:  # say what each process was doing
            raise AssertionError(f"the suite did not end within 60 s of {sig.name}: "
                                 f"{signal_states(suite.pid)}; its output: {exc.output}") from None
        assert suite.returncode == status, out
        if side_by_side:
            assert "beside the next phase" in out, out
            # its group removed (a group of a suite still running is another test's: the
            # cases of this test may run at once on two workers)
            left = {g for g in groups_of_suites() - groups_before
                    if not running(int(g.rsplit("-", 1)[1]))}
            assert not left, left
        else:
            assert f"== tests: {SERIAL}" not in out  # the second phase never started
        assert not running(pytest_pid) and not running(child_pid), out
    finally:
        if suite.poll() is None:
            os.killpg(suite.pid, signal.SIGKILL)
            suite.wait()
