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


FROZEN_FOR_A_WHILE = """
import gc
from deploy.runtime.heap import frozen_heap
tables = [[i] for i in range(100_000)]
with frozen_heap():
    inside = gc.get_freeze_count()
after = gc.get_freeze_count()
print(inside, after)
"""


def test_the_launchers_run_gives_the_heap_back_to_the_collector_after_it():
    """The launcher freezes what start-up built for its run (a pytest process or any other
    caller of the command line lives on after it): everything is walked again after."""
    out = subprocess.run([sys.executable, "-c", FROZEN_FOR_A_WHILE], capture_output=True,
                         text=True, check=True, timeout=60).stdout.split()
    inside, after = map(int, out)
    assert inside >= 100_000 and after == 0


EMULATOR = """
import gc, sys, uuid
from bridges.fleet_emulator import FleetEmulator
from deploy.nodes.emulator_cli import main
run = FleetEmulator.run
def counted(self, *a, **kw):
    print(gc.get_freeze_count(), len(gc.get_objects()))  # as the loop starts
    return run(self, *a, **kw)
FleetEmulator.run = counted
sys.exit(main(["--scenario", "lab", "--robot", "1", "--can-interface", "virtual",
               "--can-channel", f"heap-{uuid.uuid4()}", "--duration", "0.05"]))
"""


def test_the_drive_emulator_loops_on_a_frozen_heap():
    """The CAN fleet's emulator is realtime too, above the bridges (SCHED_FIFO 10): the one
    full collection of a 20 s `lab` run walked its start-up heap for 19 ms, the bridges'
    periods went with it (3-4 steps not simulated on one core, in every run)."""
    out = subprocess.run([sys.executable, "-c", EMULATOR], capture_output=True, text=True,
                         check=True, timeout=120).stdout.split()
    frozen, walked = map(int, out)
    assert frozen >= 20_000  # start-up's imports and tables (~43,000 objects measured)
    assert walked < 0.1 * frozen  # what a full pass walks in the loop
