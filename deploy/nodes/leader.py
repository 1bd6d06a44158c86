"""The virtual leader (reference generator) as a process.

lockstep: publishes the leader's states ahead of need, in batches of
``TICK_EVERY`` steps, up to ``LOOKAHEAD`` steps past the newest ``ctl/tick`` (the
plant ticks every ``TICK_EVERY`` steps), so agents never wait a hop for it and
hear one message per batch. realtime: the same ahead of the wall clock, a batch of
``REALTIME_BATCH_S`` (at most ``TICK_EVERY`` steps) each time, one batch ahead of
need: the leader wakes once a batch, not once a period (at 1 kHz a wake alone cost it
~15 µs of CPU, its budget 20 µs a step), and an agent takes the leader of its sample's
own step, as in lockstep (deploy/nodes/agent.py).
"""

from __future__ import annotations

import math
import time

from agents.leader import leader_generator
from agents.steered_leader import SteeredLeader
from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    LAUNCHER_ROLE,
    WIRE_VERSION,
    LeaderState,
    LeaderSteer,
    agent_role,
    within_wire_bound,
)
from deploy.runtime.node_runtime import ControlInbox, Periodic, StopFlag, Timing, publish_report
from deploy.runtime.transport import Node

TICK_EVERY = 32  # lockstep: the plant's ctl/tick every this many steps; the leader's batch
LOOKAHEAD = 2 * TICK_EVERY  # lockstep: states published this far past the newest tick
# realtime: the states of this much time a message, a wake (at most TICK_EVERY steps: 32 ms
# at 1 kHz, 160 ms at 200 Hz). A wake after a long sleep costs ~150-350 µs here (caches
# cold, a message to each agent and the recorder): at 200 Hz the leader spent 58-74 µs a
# step with 20 ms batches, 36-46 with 50 ms, 27-34 with 100 ms (its wait ~140 µs a wake,
# its message ~100). A path known ahead loses nothing by going out further ahead (an
# agent takes up to LOOKAHEAD + TICK_EVERY steps ahead of its sample; a batch goes out
# at most two batches, 2 TICK_EVERY - 1 steps, ahead); a leader steered from outside
# (ROS 2) keeps 50 ms, the delay a command waits for the next batch
REALTIME_BATCH_S = 0.16
EARLY_S = 0.02  # realtime, a path known ahead: the first batches go out this long before t = 0
STEERED_BATCH_S = 0.05


def realtime_batch(dt: float, steered: bool = False) -> int:
    """Realtime: the leader's states a batch (at most ``TICK_EVERY``; the agents accept
    ``LOOKAHEAD`` + ``TICK_EVERY`` steps ahead of their sample)."""
    span = STEERED_BATCH_S if steered else REALTIME_BATCH_S
    return max(1, min(TICK_EVERY, round(span / dt)))


class LeaderNode:
    def __init__(self, sc: Scenario, node: Node, stop: StopFlag,
                 with_recorder: bool = False) -> None:
        self.sc, self.node, self.stop = sc, node, stop
        self.generator = leader_generator(sc.leader_spec(), sc.dt)
        self.k_next = 0  # the step whose state the generator holds
        self.timing = Timing()
        self.peers = [agent_role(r) for r, b in zip(sc.robot_ids, sc.leader_weights) if b != 0]
        if with_recorder:
            self.peers.append(LAUNCHER_ROLE)
        self.control = ControlInbox(node, stop)
        self.t0_mono: float | None = None  # realtime: t = 0 of the run on our clock
        self.steered = 0  # steer commands taken (a leader steered from outside)
        if isinstance(self.generator, SteeredLeader):
            node.subscribe(node.keys.leader_steer, LeaderSteer, self._on_steer)
        node.declare_alive()

    def _on_steer(self, msg: LeaderSteer) -> None:
        """The newest command of a leader steered from outside (from the launcher,
        authenticated), received now on the run's clock."""
        if self.t0_mono is None:
            return  # before the run's start: no time to stamp it with (and nothing moves)
        self.generator.steer(msg.velocity, time.monotonic() - self.t0_mono)
        self.steered += 1

    @property
    def steps_done(self) -> int:
        return self.k_next

    def handshake(self, timeout_s: float) -> None:
        missing = self.node.wait_for_roles(self.peers, "alive", timeout_s, self.stop)
        if missing and not self.stop():
            raise TimeoutError(f"leader: no sign of {', '.join(sorted(missing))} "
                               f"after {timeout_s:.0f} s")
        self.node.declare_ready()

    def _publish_next(self, count: int = 1) -> None:
        """The states of the next ``count`` steps, in one message."""
        k = self.k_next
        qs, vs = self.generator.batch(count)
        # every float checked here at once, not by decoding the batch again (Node.publish)
        sent = self.node.publish(self.node.keys.leader_state, lambda seq, stamp: LeaderState(
            WIRE_VERSION, 0, seq, stamp, k=k, t=k * self.sc.dt, q=qs, q_dot=vs),
            checked=within_wire_bound(qs, vs))
        if sent is None and not all(map(math.isfinite, (x for row in qs + vs for x in row))):
            self.node.note_nonfinite(f"leader state at step {k} (not sent)")
        self.k_next += count

    def run_lockstep(self, steps: int) -> None:
        box, ctl = self.node.mailbox, self.control
        while not self.stop():
            limit = min(ctl.tick + LOOKAHEAD, steps - 1)
            while self.k_next <= limit:  # whole batches (the last one: to the end)
                self._publish_next(min(TICK_EVERY, steps - self.k_next))
            box.wait_until(lambda: self.stop() or (
                ctl.tick + LOOKAHEAD >= self.k_next and self.k_next < steps), 3600.0)

    def run_realtime(self, t0_mono: float, steps: int) -> None:
        """Batch b (of ``realtime_batch`` steps) goes out at the start of batch b - 1:
        a batch ahead of the wall clock (batches 0 and 1 of a path known ahead ``EARLY_S``
        before t = 0). A wake more than a batch late skips what is past (published from
        the step now due)."""
        steered = isinstance(self.generator, SteeredLeader)
        n = realtime_batch(self.sc.dt, steered)
        self.t0_mono = t0_mono
        self.node.wake_on(())  # its timer only (it hears nothing on the data path)
        self.node.connect_ahead([self.node.keys.leader_state])
        if not steered:
            self._first_batches_early(t0_mono, min(steps, 2 * n), n)
        ticker = Periodic(t0_mono, n * self.sc.dt, self.timing, self.node.mailbox)
        while not self.stop():
            b = ticker.wait_next(self.stop)
            if b is None or b * n >= steps:
                break
            due = min(steps, (b + 2) * n)  # through the end of the next batch
            while self.k_next < b * n:  # a late wake: what is past is not sent
                self.generator.advance()
                self.k_next += 1
            self._publish_through(due, n)

    def _first_batches_early(self, t0_mono: float, due: int, n: int) -> None:
        """A path known ahead: the states the first wake would send (through the second
        batch) go out ``EARLY_S`` before t = 0 instead, out of the fleet's first
        milliseconds, when every node pays for its first step after the start's lead
        (0.7 ms of the leader's on one core; agents/rehearsal.py). `paper` at 1 kHz on
        one core, 0.3 s runs, 70 alternating pairs: no run diverged against 10, states
        unanswered in time median 25-30 against 30-39 (docs/bench-history.md, "The start
        on one core"). A steered leader's states wait for its commands, which count from
        t = 0."""
        wait = t0_mono - EARLY_S - time.monotonic()
        if wait > 0.0:
            self.node.mailbox.wait_until(self.stop, wait)
        self._publish_through(due, n)

    def _publish_through(self, due: int, n: int) -> None:
        """The states up to step ``due`` (excluded) not sent yet, in batches of ``n``."""
        while self.k_next < due and not self.stop():
            self._publish_next(min(n, due - self.k_next))

    def finish(self) -> None:
        publish_report(self.node, -1, self.k_next, self.timing)
