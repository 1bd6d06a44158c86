"""A realtime node freezes its start-up heap before its loop (deploy/runtime/heap.py):
what start-up built is out of every later collection, and what the loop makes is still
collected. In a child process: freezing is for the rest of a process's life."""

import subprocess
import sys

CHILD = """
import gc
from deploy.runtime.heap import freeze_startup_heap
tables = [[i] for i in range(100_000)]  # start-up's tables: alive for good
garbage = [[]]; garbage[0].append(garbage)  # a cycle start-up no longer holds
del garbage
freeze_startup_heap()
frozen = gc.get_freeze_count()
walked = len(gc.get_objects())  # what a full collection walks now
loop = [[]]; loop[0].append(loop); del loop  # a cycle made by the loop
print(frozen, walked, gc.collect())
"""


def test_start_up_is_frozen_and_the_loop_still_collected():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    frozen, walked, collected = map(int, out)
    assert frozen >= 100_000  # the tables, out of every pass
    assert walked < 1_000  # a pass walks almost nothing of start-up
    assert collected >= 2  # the loop's cycle (two lists) is collected as before
