"""Which message of a faulty edge gets through: a pure function of (seed, edge, step).

Every decision is drawn from a hash of the plan's seed, the edge's name, the
message's step index and a purpose tag, not from a random generator advanced
by arrivals: the in-process runner and every process of a distributed run
decide the same for the same message, whatever order messages arrive in. That
is what makes a lockstep run with faults reproducible bit for bit and equal to
the in-process reference.

Time windows (partitions) are judged on the message's step: t = k dt.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass, field

from deploy.contract.fault_plan import FaultPlan, LinkFaults, edge_name

DELIVERED = "delivered"
DROPPED = "dropped"  # independent loss
BURST = "burst"  # Gilbert-Elliott loss
PARTITIONED = "partitioned"
OUTCOMES = (DELIVERED, DROPPED, BURST, PARTITIONED)

_TAG_DROP, _TAG_BURST_MOVE, _TAG_BURST_LOSS = 1, 2, 3
_SCALE = 1.0 / 2**64


def _uniform(seed: int, edge_key: bytes, k: int, tag: int) -> float:
    """A number in [0, 1) fixed by its arguments."""
    digest = hashlib.blake2b(struct.pack("<QqB", seed, k, tag) + edge_key, digest_size=8).digest()
    return int.from_bytes(digest, "little") * _SCALE


@dataclass
class EdgeFaults:
    """The decisions of one directed edge."""

    name: str
    seed: int
    spec: LinkFaults
    dt: float
    lag_steps: int = 0  # lockstep: the delay in whole steps
    _key: bytes = b""
    _bad_k: int = -1  # Gilbert-Elliott state known up to this step
    _bad: bool = False

    def __post_init__(self) -> None:
        self._key = self.name.encode()
        self.lag_steps = round(self.spec.delay_s / self.dt)

    def outcome(self, k: int) -> str:
        """What happens to the message of step ``k`` on this edge."""
        s = self.spec
        t = k * self.dt
        for start, end in s.partitions:
            if start <= t < end:
                return PARTITIONED
        if s.burst is not None:
            b = s.burst
            loss = b.loss_bad if self._burst_bad(k) else b.loss_good
            if loss > 0.0 and _uniform(self.seed, self._key, k, _TAG_BURST_LOSS) < loss:
                return BURST
        if s.drop > 0.0 and _uniform(self.seed, self._key, k, _TAG_DROP) < s.drop:
            return DROPPED
        return DELIVERED

    def delivered(self, k: int) -> bool:
        return self.outcome(k) == DELIVERED

    def _burst_bad(self, k: int) -> bool:
        """The Gilbert-Elliott state at step k: the chain from step 0 (good),
        one transition per step, each drawn from the hash (so any process can
        compute it, and going back recomputes from the start)."""
        b = self.spec.burst
        assert b is not None
        if k < self._bad_k:
            self._bad_k, self._bad = -1, False
        while self._bad_k < k:
            self._bad_k += 1
            u = _uniform(self.seed, self._key, self._bad_k, _TAG_BURST_MOVE)
            self._bad = (u >= b.p_exit) if self._bad else (u < b.p_enter)
        return self._bad


@dataclass
class EdgeCount:
    """Per edge: messages judged, and what happened to them."""

    messages: int = 0
    dropped: int = 0
    burst: int = 0
    partitioned: int = 0
    delayed: int = 0

    def add(self, outcome: str, delayed: bool) -> None:
        self.messages += 1
        if outcome == DROPPED:
            self.dropped += 1
        elif outcome == BURST:
            self.burst += 1
        elif outcome == PARTITIONED:
            self.partitioned += 1
        elif delayed:
            self.delayed += 1

    def as_dict(self) -> dict[str, int]:
        return {"messages": self.messages, "dropped": self.dropped, "burst": self.burst,
                "partitioned": self.partitioned, "delayed": self.delayed}


@dataclass
class FaultModel:
    """Every faulty edge of a run, and the count of what was injected on each."""

    plan: FaultPlan | None
    dt: float
    edges: dict[tuple[str, str], EdgeFaults] = field(default_factory=dict)
    counts: dict[str, EdgeCount] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.plan is not None:
            for (src, dst), spec in self.plan.links.items():
                self.edges[(src, dst)] = EdgeFaults(edge_name(src, dst), self.plan.seed, spec,
                                                    self.dt)

    def edge(self, src: str, dst: str) -> EdgeFaults | None:
        """None: a perfect link (nothing injected, nothing counted)."""
        return self.edges.get((src, dst))

    def judge(self, edge: EdgeFaults, k: int) -> bool:
        """Decide and count the message of step k; True when it gets through."""
        outcome = edge.outcome(k)
        count = self.counts.get(edge.name)
        if count is None:
            count = self.counts[edge.name] = EdgeCount()
        count.add(outcome, edge.spec.delay_s > 0.0)
        return outcome == DELIVERED

    def report(self) -> dict[str, dict[str, int]]:
        return {name: c.as_dict() for name, c in sorted(self.counts.items())}

    @property
    def max_lag_steps(self) -> int:
        return max((e.lag_steps for e in self.edges.values()), default=0)


def merge_reports(reports: list[dict[str, dict[str, int]]]) -> dict[str, dict[str, int]]:
    """Per-edge counts from several processes (each edge has one receiver)."""
    out: dict[str, dict[str, int]] = {}
    for rep in reports:
        for name, c in rep.items():
            acc = out.setdefault(name, dict.fromkeys(c, 0))
            for key, v in c.items():
                acc[key] = acc.get(key, 0) + v
    return dict(sorted(out.items()))


def fault_metrics(plan: FaultPlan, edges: dict[str, dict[str, int]],
                  kills: list[dict] | None = None) -> dict:
    """The ``faults`` section of metrics.json: the plan, every injected fault
    per edge and in total, and the processes killed (and restarted)."""
    totals = {key: sum(c.get(key, 0) for c in edges.values())
              for key in EdgeCount().as_dict()}
    return {"plan": plan.path, "seed": plan.seed, "edges": edges, "totals": totals,
            "kills": kills or []}
