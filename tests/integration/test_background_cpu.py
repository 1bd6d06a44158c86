"""The suite's CPU group for its background phase (tests/background_cpu.py): a process
moved there takes its children with it, its CPU time is read back from the group, and
the group goes away with them. Needs root and a cgroup cpu controller (else skipped:
the suite then runs its phases one after the other)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from background_cpu import USAGE_ENV, BackgroundGroup, background_usage_s, usage_s

BUSY = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\n"


def test_usage_is_read_from_either_cgroup_version(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "cpuacct.usage").write_text("2500000000\n")
    (tmp_path / "cpu.stat").write_text("usage_usec 1500000\nuser_usec 1000000\n")
    (tmp_path / "bad").write_text("what\n")
    assert usage_s(tmp_path / "cpuacct.usage") == 2.5
    assert usage_s(tmp_path / "cpu.stat") == 1.5
    assert usage_s(tmp_path / "bad") is None and usage_s(tmp_path / "missing") is None
    monkeypatch.delenv(USAGE_ENV, raising=False)
    assert background_usage_s() is None  # not beside a background phase
    monkeypatch.setenv(USAGE_ENV, str(tmp_path / "cpu.stat"))
    assert background_usage_s() == 1.5


def test_a_process_and_its_children_run_and_are_counted_in_the_group() -> None:
    group = BackgroundGroup.make(f"omnifleet-test-{os.getpid()}")
    if group is None:
        pytest.skip("no CPU group can be made here (root and a cgroup cpu controller)")
    try:
        before = usage_s(group.usage)
        parent = subprocess.Popen([sys.executable, "-c",
                                   f"import subprocess, sys\nsys.stdin.readline()\n"
                                   f"subprocess.run([sys.executable, '-c', {BUSY!r}], check=True)"],
                                  stdin=subprocess.PIPE, text=True)
        try:
            group.add(parent.pid)
            own = Path(f"/proc/{parent.pid}/cgroup").read_text()
            assert f"/omnifleet-test-{os.getpid()}" in own
            parent.communicate("go\n", timeout=60)  # its child starts now, in the group
        finally:
            if parent.poll() is None:
                parent.kill()
                parent.wait()
        assert parent.returncode == 0
        taken = usage_s(group.usage) - before
        assert taken >= 0.25  # the grandchild's 0.3 s of CPU
    finally:
        group.remove()
    assert not any(d.exists() for d in group.dirs)
