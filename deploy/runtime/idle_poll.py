"""A core kept from halting while a realtime fleet runs on it (``omnifleet run
--keep-cores-awake``): one process per core, pinned to it, spinning at the lowest
priority the kernel has.

Why (measured on the 2-core development VM, a Firecracker guest with no cpuidle
driver, docs/bench-history.md "A core that halts"): the CAN fleet at 200 Hz pinned to
one core leaves it idle ~15-30 % of the time in many short gaps, and each gap halts the
virtual CPU (HLT, an exit to the hypervisor). Every node then woke into a CPU that had
to be resumed and had lost its caches: with a spinner below everything on that core,
3 alternating pairs, CiA 402: the bridges' CPU 816-936 -> 630-806 µs a step, the
agents' 340-416 -> 275-346, the emulator's 1,220-1,303 -> 1,058-1,178, and in 2 pairs
of 3 jitter p99 6.0-6.8 -> 1.0-1.2 ms and 168-279 -> 0 steps not simulated (the
third pair both FAIL, the hour slow). A core that is never idle (the paper at 1 kHz on
one core) gains nothing. On both cores the nodes' CPU fell as much (bridges 688-720 ->
554-589 µs) but jitter p99 rose 0.48-0.58 -> 1.4-2.0 ms: a guest that keeps both of
its CPUs busy is preempted by its host (steal 2 -> 46 ticks in 20 s).

What it costs and why it never takes a core from the fleet: SCHED_IDLE (below every
nice level) and its own autogroup at nice 19, so a node of any policy runs before it;
the realtime nodes run under SCHED_FIFO, which the kernel runs before any of it. Only
so: on the lockstep clock (its nodes of the normal and batch policies) a lockstep
``paper`` took 4-6x its wall time with a spinner on each core (9-13 s -> 42-58 s):
its nodes hand their core over after each send (``sched_yield``, priority.hand_over),
and a spinner that is runnable then takes it for a slice. ``omnifleet run`` refuses the
option there and without SCHED_FIFO (``--priority 0``), and keeps no core awake when the
host refused a node SCHED_FIFO (a CAN fleet in a CPU group without realtime time had no
state heard in a 1 s run beside spinners: deploy/run/awake.py, ``not_realtime``). The
core shows busy for the run's duration (power, and a host's share of a guest's time).
The process dies with the launcher (PR_SET_PDEATHSIG) and is ended by pid when the
fleet's run ends.
"""

from __future__ import annotations

import os
import sys

from deploy.runtime.parent_death import die_with_parent

LOWEST_NICE = 19


def lower_to_idle() -> list[str]:
    """This process at the lowest priority: SCHED_IDLE, nice 19, its autogroup at nice 19
    (where the kernel has them); what was refused, as phrases."""
    refused = []
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError) as exc:
        refused.append(f"SCHED_IDLE ({exc})")
    try:
        os.setpriority(os.PRIO_PROCESS, 0, LOWEST_NICE)
    except OSError as exc:
        refused.append(f"nice {LOWEST_NICE} ({exc.strerror})")
    try:
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(LOWEST_NICE))
    except FileNotFoundError:
        pass  # no autogroups: the nice value alone counts
    except OSError as exc:
        refused.append(f"autogroup nice {LOWEST_NICE} ({exc.strerror})")
    return refused


def spin(core: int, parent: int) -> None:
    """Pinned to ``core`` at the lowest priority, busy until killed or until ``parent``
    (the pid of the process that started it) ends."""
    if not die_with_parent(parent):  # it ended before the kernel was told to say so
        return
    os.sched_setaffinity(0, {core})
    refused = lower_to_idle()
    if refused:  # it would compete with what it is meant to leave the core to: leave
        print(f"idle_poll: not lowered ({', '.join(refused)}); not spinning", file=sys.stderr)
        return
    while True:
        pass


def main(argv: list[str]) -> int:
    if len(argv) != 2 or not all(a.isdigit() for a in argv):
        print("usage: python -m deploy.runtime.idle_poll CORE PARENT_PID", file=sys.stderr)
        return 2
    spin(int(argv[0]), int(argv[1]))
    return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
