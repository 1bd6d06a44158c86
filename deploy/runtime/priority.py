"""A process's CPU priority on a shared host (Linux): what ``--priority N`` does
for the driver emulator and for every node on the realtime clock.

Two things, each where the host permits it:

- **SCHED_FIFO at priority N** for the process's main thread and every thread it
  starts afterwards (zenoh's, opened later): a runnable control loop then takes a core
  from anything under the normal policy (the launcher, the figures, the host's other
  programs) at once, and loops of one priority run in the order they woke (the order
  the plant sent its samples) instead of the fair scheduler's order, which changed from
  period to period. 30 agents at 100 Hz on 2 cores (10 s runs, pybullet, 3 pairs, nice
  alone against SCHED_FIFO): commands the plant did not have by its next step 1,254,
  2,438, 388 -> 367, 45, 38; state-to-command latency p99 13.6, 15.4, 9.4 -> 8.4, 6.9,
  7.1 ms; the agents' deadline misses 111, 155, 57 -> 53, 5, 6 (docs/bench-history.md). The
  kernel's limit on realtime tasks (``sched_rt_runtime_us``, 95 % of each second by
  default) leaves the host a share should a loop never sleep. A node leaves the policy
  when its loop ends (``leave_realtime_scheduling``): its report and last flushes ran
  at the priority of the loops still going and held them back (every agent of such a
  run missed the run's last sample).
- **nice -N, and its autogroup too**: the fallback where SCHED_FIFO is refused, and
  the process's priority after its loop. On Linux with autogroups every session is one
  scheduling group of equal weight, so a process's own nice value counts only against
  its session's other processes; the launcher starts every child in a session of its
  own, and one busy program elsewhere on a 2-core host then takes as much CPU as any
  control loop. Raising the autogroup's nice too is what gives the loop the CPU
  (docs/hardware.md: one busy-loop process beside a can-emulated lab run stalled agents
  ~100 ms and failed the settling bound).

Both need CAP_SYS_NICE (or RLIMIT_RTPRIO and RLIMIT_NICE); without it the process says
so and runs at normal priority.
"""

from __future__ import annotations

import argparse
import os

from deploy.contract.options import MAX_PRIORITY, add_option

EMULATOR_PRIORITY = 10  # the driver emulator's (can-emulated): it plays the world
# every other node's on the realtime clock (``omnifleet run --priority``): below the
# emulator and the plant, above whatever else the host runs
REALTIME_PRIORITY = 5
# the simulated plant that many more above the other realtime nodes (``world_priority``)
WORLD_ABOVE_AGENTS = 5


def world_priority(n: int) -> int:
    """The realtime plant's priority when the other nodes of the run have ``n`` (0: none
    raised, nor the plant's): it plays the world and its period is the fleet's clock, as
    the driver emulator's is on CAN (EMULATOR_PRIORITY above REALTIME_PRIORITY). At the
    same priority 30 agents woken at once by its samples shared the two cores with it
    and held it back: the agents' state-to-command latency p50 ~5-6 ms at 100 Hz; with
    the plant above them 2.3-3.2 ms (10 s runs, 4 pairs with the model plant, 3 with
    pybullet), p99 7-14 -> 6-8 ms; ``lab`` at 1 kHz latency p99 0.63-0.67 -> 0.60-0.64 ms
    (docs/bench-history.md)."""
    return 0 if n <= 0 else min(n + WORLD_ABOVE_AGENTS, MAX_PRIORITY)


def raise_priority(n: int) -> str:
    """SCHED_FIFO at priority ``n`` for this thread and the threads it starts after,
    nice -n for it and, on Linux with autogroups, for its autogroup too; what was done,
    as a sentence."""
    done, refused = [], []
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(n))
        done.append(f"SCHED_FIFO {n}")
    except AttributeError:  # not Linux
        pass
    except OSError as exc:
        refused.append(f"SCHED_FIFO {n} ({exc.strerror})")
    try:
        os.setpriority(os.PRIO_PROCESS, 0, -n)
        done.append(f"nice -{n}")
    except OSError as exc:
        refused.append(f"nice -{n} ({exc.strerror})")
    try:
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(-n))
        done.append(f"autogroup nice -{n}")
    except FileNotFoundError:
        pass  # no autogroups: nothing to do
    except OSError as exc:
        refused.append(f"autogroup nice -{n} ({exc.strerror})")
    return ("priority raised: " + ", ".join(done) if done else "priority not raised") + (
        "; refused: " + ", ".join(refused) if refused else "")


def under_fifo(pid: int) -> bool:
    """Whether process ``pid`` runs under SCHED_FIFO (False once gone, or not Linux)."""
    try:
        return os.sched_getscheduler(pid) == os.SCHED_FIFO
    except (AttributeError, OSError):
        return False


def over_realtime_limit_words(share: float, limit: float) -> str:
    """What realtime processes that took ``share`` of the cores, above the kernel's
    ``limit`` (``sched_rt_runtime_us`` / ``sched_rt_period_us``), met: the words of the
    first second's warning and of the run's summary."""
    return (f"{share:.1%}, above the {limit:.0%} the kernel lets them have "
            "(sched_rt_runtime_us): it holds all of them, the plant too, for the rest of each "
            "second where they need more")


def leave_realtime_scheduling() -> None:
    """Back to the normal policy (its nice value kept) for this thread, if it ran under
    SCHED_FIFO: a node whose loop has ended (its report, its last flushes)."""
    try:
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or refused: the policy stays
        pass


def batch_scheduling() -> bool:
    """This process under SCHED_BATCH (Linux; no privilege needed): the scheduler lets
    it finish its slice instead of preempting the process that woke it. For an agent
    on the lockstep clock: the plant sends one sample to each agent in turn, and on
    two cores each woken agent used to preempt the plant mid-send (wakeup
    preemption), so the last agent heard its sample ~190 µs after the first. With
    the agents batch the paper's lockstep run took 6-13 % less wall time
    (docs/bench-history.md). Never for the realtime clock, where a late wake is a late
    command. Whether it was set."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or a kernel without it
        return False
    return True


def hand_over() -> None:
    """Let a process that waits for a core have this one now, before this process goes
    on with its own bookkeeping (``sched_yield``): right after a send that woke the
    next link of the chain (a lockstep plant's samples, an agent's reply).

    Lockstep: three agents share two cores with the plant, and the step waits for the
    last agent. An agent that kept its core after its reply (telemetry, its tables) or
    the plant after its samples (state log, stamps) held back an agent that had its
    sample and waited to start. The paper's lockstep run, 8 alternating pairs each:
    agents handing over 0.95 of the run's time, the plant too another 0.95; the bench
    side by side 1.97-2.02x -> 2.14-2.15x real time (docs/bench-history.md).

    Realtime: an agent hands over after its reply too (30 agents at 100 Hz on 2 cores:
    3x fewer deadline misses in the bench's scale runs, lab at 1 kHz and the CAN fleet
    unchanged); the realtime plant does not (its state-to-command latency p50 rose by
    ~1 ms with 30 agents, the misses no fewer than with the agents' alone)."""
    os.sched_yield()


def add_priority_argument(p: argparse.ArgumentParser, why: str) -> None:
    """``--priority N`` (deploy/contract/options.py) with why this command may want it."""
    add_option(p, "--priority", more_help=why)
