"""What one message from outside may do to a run's outputs (issue 21): a report is
filed under the role of the key it came on, and its size is bounded."""

from __future__ import annotations

from pathlib import Path

import pytest

from deploy.contract.scenario import load_scenario
from deploy.contract.wire import WIRE_VERSION, Codec, ContactRecord, NodeReport, encode
from deploy.run.launcher import Launcher, LaunchOptions


def report(role: str, **extra) -> NodeReport:
    return NodeReport(WIRE_VERSION, 0, 0, 0, role=role, robot=-1, sent=1, dropped=0, late=0,
                      invalid=0, steps=1, **extra)


def test_a_report_is_filed_under_the_key_it_came_on(tmp_path: Path):
    """Found by probing: a "plant" report sent on report/agent-2 put a fake contact
    and invalid = -1000 into metrics.json."""
    sc = load_scenario("paper")
    launcher = Launcher(sc, LaunchOptions("paper", "model", "lockstep", tmp_path, record=False))
    fake = report("plant", contacts=[ContactRecord(0.1, 0.2, 1, 2, 0.5)], contacts_total=1)
    launcher._on_sample((launcher.keys.report("agent-2"), encode(fake)))
    assert "plant" not in launcher.collector.reports and launcher.invalid == 1
    launcher._on_sample((launcher.keys.report("plant"), encode(report("plant"))))
    assert launcher.collector.reports["plant"].contacts is None


@pytest.mark.parametrize("field, value", [
    ("latency_ns", [1] * 200_001), ("received", {f"k{i}": 1 for i in range(1025)}),
    ("refused", {f"r{i}": 1 for i in range(1025)})])
def test_an_oversized_report_is_refused_at_decode(field, value):
    """A 2 M-sample report took 358 ms to decode in the launcher: sizes are bounded."""
    import msgspec

    ok = encode(report("plant"))
    fields = msgspec.msgpack.decode(ok)
    names = list(NodeReport.__struct_fields__)
    fields += [msgspec.structs.asdict(report("plant"))[n] for n in names[len(fields):]]
    fields[names.index(field)] = value
    assert Codec([1, 2, 3]).decode(NodeReport, msgspec.msgpack.encode(fields)) is None
    assert Codec([1, 2, 3]).decode(NodeReport, ok) is not None
