"""An agent on the lockstep clock runs under SCHED_BATCH (deploy/runtime/priority.py):
the call must set the policy of the calling process, and only of it."""

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_BATCH"), reason="Linux scheduling policies")

CHILD = """
import os, sys
from deploy.runtime.priority import batch_scheduling
before = os.sched_getscheduler(0)
print(before, batch_scheduling(), os.sched_getscheduler(0), os.sched_getscheduler(os.getppid()))
"""


def test_batch_scheduling_sets_the_calling_process_only():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    before, done, after, parent = int(out[0]), out[1], int(out[2]), int(out[3])
    assert before == os.SCHED_OTHER
    assert done == "True"
    assert after == os.SCHED_BATCH
    assert parent == os.sched_getscheduler(0) == os.SCHED_OTHER
