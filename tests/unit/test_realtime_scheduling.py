"""``--priority N`` on the realtime clock (deploy/runtime/priority.py): SCHED_FIFO at N
for the node's thread and the threads it starts after (zenoh's), nice -N beside it, and
back to the normal policy, nice kept, when the loop ends. In a child process: a policy
is for the rest of a process's life. Without the privilege the refusal is said and
nothing changes."""

import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="Linux scheduling policies")

CHILD = """
import json, os, threading
from deploy.runtime.priority import leave_realtime_scheduling, raise_priority
said = raise_priority(3)
loop = os.sched_getscheduler(0)
started = []
t = threading.Thread(target=lambda: started.append(os.sched_getscheduler(0)))
t.start(); t.join()
leave_realtime_scheduling()
print(json.dumps({"said": said, "loop": loop, "started": started[0],
                  "after": os.sched_getscheduler(0), "nice": os.getpriority(os.PRIO_PROCESS, 0)}))
"""


def test_the_loop_runs_fifo_its_threads_too_and_leaves_it_keeping_its_nice():
    got = json.loads(subprocess.run([sys.executable, "-c", CHILD], capture_output=True,
                                    text=True, check=True, timeout=60).stdout)
    if "SCHED_FIFO 3 (" in got["said"]:  # refused: said so, and nothing changed
        assert got["loop"] == got["started"] == got["after"] == os.SCHED_OTHER
        return
    assert "SCHED_FIFO 3" in got["said"]
    assert got["loop"] == os.SCHED_FIFO
    assert got["started"] == os.SCHED_FIFO  # a thread started after inherits it
    assert got["after"] == os.SCHED_OTHER  # the loop's end: the normal policy again
    if "nice -3" in got["said"] and "nice -3 (" not in got["said"]:
        assert got["nice"] == -3  # kept after the loop
