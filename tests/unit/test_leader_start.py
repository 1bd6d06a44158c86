"""A realtime leader whose path is known ahead sends its first two batches before t = 0
(deploy/nodes/leader.py ``EARLY_S``), out of the fleet's first milliseconds; the states
are those its first wake sent, and the rest follow on the wall clock as before."""

import time

from fuzz_fakes import FakeNode

from deploy.contract.wire import LeaderState
from deploy.nodes.leader import EARLY_S, LeaderNode, realtime_batch
from deploy.runtime.node_runtime import StopFlag


class LeaderFakeNode(FakeNode):
    """FakeNode with what a realtime leader also calls, each publish timed."""

    def __init__(self) -> None:
        super().__init__([1, 2, 3], role="leader")
        self.sent_at: list[float] = []

    def declare_alive(self) -> None:
        pass

    def wake_on(self, keys) -> None:
        pass

    def connect_ahead(self, keys) -> None:
        pass

    def publish(self, key, factory, checked=False):
        self.sent_at.append(time.monotonic())
        return super().publish(key, factory, checked)


def test_a_known_path_sends_its_first_two_batches_before_t0(paper):
    node = LeaderFakeNode()
    leader = LeaderNode(paper, node, StopFlag())
    n = realtime_batch(paper.dt)
    t0 = time.monotonic() + 3 * EARLY_S
    leader.run_realtime(t0, 3 * n)
    states = [m for _, m in node.published if isinstance(m, LeaderState)]
    assert [m.k for m in states] == [0, n, 2 * n]  # every step once, in order
    assert [len(m.q) for m in states] == [n, n, n]
    before = [at < t0 for at in node.sent_at]
    assert before == [True, True, False]  # the third on the wall clock, a batch ahead
    assert node.sent_at[0] >= t0 - EARLY_S - 0.005  # not before it was due
