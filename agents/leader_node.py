"""The virtual leader (reference generator) as a process.

lockstep: publishes the leader state of step k ahead of need — up to
``LOOKAHEAD`` steps past the newest ``ctl/tick`` — so agents never wait a hop
for it. realtime: publishes at the scenario's rate on its own clock.
"""

from __future__ import annotations

from agents.leader import LeaderGenerator
from deploy.node_runtime import ControlInbox, Periodic, StopFlag, Timing, publish_report
from deploy.scenario import Scenario
from deploy.transport import Node
from deploy.wire import LAUNCHER_ROLE, WIRE_VERSION, LeaderState, agent_role

LOOKAHEAD = 2


class LeaderNode:
    def __init__(self, sc: Scenario, node: Node, stop: StopFlag,
                 with_recorder: bool = False) -> None:
        self.sc, self.node, self.stop = sc, node, stop
        self.generator = LeaderGenerator(sc.leader_spec(), sc.dt)
        self.k_next = 0  # the step whose state the generator holds
        self.timing = Timing()
        self.peers = [agent_role(r) for r, b in zip(sc.robot_ids, sc.leader_weights) if b != 0]
        if with_recorder:
            self.peers.append(LAUNCHER_ROLE)
        self.control = ControlInbox(node, stop)
        node.declare_alive()

    @property
    def steps_done(self) -> int:
        return self.k_next

    def handshake(self, timeout_s: float) -> None:
        missing = self.node.wait_for_roles(self.peers, "alive", timeout_s, self.stop)
        if missing and not self.stop():
            raise TimeoutError(f"leader: no sign of {', '.join(sorted(missing))} "
                               f"after {timeout_s:.0f} s")
        self.node.declare_ready()

    def _publish_next(self) -> None:
        k = self.k_next
        q, v = self.generator.state()
        self.node.publish(self.node.keys.leader_state, lambda seq, stamp: LeaderState(
            WIRE_VERSION, 0, seq, stamp, k=k, t=k * self.sc.dt,
            q=tuple(q.tolist()), q_dot=tuple(v.tolist())))
        self.generator.advance()
        self.k_next += 1

    def run_lockstep(self, steps: int) -> None:
        box, ctl = self.node.mailbox, self.control
        while not self.stop():
            with box.lock:
                tick = ctl.tick
            while self.k_next <= min(tick + LOOKAHEAD, steps - 1):
                self._publish_next()
            box.wait_until(lambda: self.stop() or (
                ctl.tick + LOOKAHEAD >= self.k_next and self.k_next < steps), 3600.0)

    def run_realtime(self, t0_mono: float, steps: int) -> None:
        ticker = Periodic(t0_mono, self.sc.dt, self.timing)
        while not self.stop():
            k = ticker.wait_next(self.stop)
            if k is None or k >= steps:
                break
            while self.k_next < k:  # catch up after a late wake, publishing only step k
                self.generator.advance()
                self.k_next += 1
            self._publish_next()

    def finish(self) -> None:
        publish_report(self.node, -1, self.k_next, self.timing)
