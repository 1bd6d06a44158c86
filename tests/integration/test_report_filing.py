"""What one message from outside may do to a run's outputs (docs/hardening.md): a report is
filed under the role of the key it came on, and its size is bounded."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from deploy.contract.run_secret import new_secret, report_is_genuine, sign_report
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import WIRE_VERSION, Codec, ContactRecord, NodeReport, encode
from deploy.run.launcher import LaunchOptions, make_observer


def report(role: str, **extra) -> NodeReport:
    return NodeReport(WIRE_VERSION, 0, 0, 0, role=role, robot=-1, sent=1, dropped=0, late=0,
                      invalid=0, steps=1, **extra)


def test_a_report_is_filed_under_the_key_it_came_on(tmp_path: Path):
    """Found by probing: a "plant" report sent on report/agent-2 put a fake contact
    and invalid = -1000 into metrics.json."""
    sc = load_scenario("paper")
    listener = make_observer(sc, LaunchOptions("paper", "model", "lockstep", tmp_path, record=False),
                             new_secret())
    fake = report("plant", contacts=[ContactRecord(0.1, 0.2, 1, 2, 0.5)], contacts_total=1)
    listener.on_sample((listener.keys.report("agent-2"), encode(fake)))
    assert "plant" not in listener.collector.reports and listener.invalid == 1
    signed = sign_report(listener.secret, report("plant"))  # as the run's plant signs it
    listener.on_sample((listener.keys.report("plant"), encode(signed)))
    assert listener.collector.reports["plant"].contacts is None


def test_a_report_not_signed_by_a_node_of_the_run_is_refused(tmp_path: Path):
    """On its own key, a forged report still put a fake contact into metrics.json (and
    a report under a made-up role grew the launcher's table): reports are signed with
    the run's secret like control, and filed only for the run's roles."""
    sc = load_scenario("paper")
    listener = make_observer(sc, LaunchOptions("paper", "model", "lockstep", tmp_path, record=False),
                             new_secret())
    fake = report("plant", contacts=[ContactRecord(0.1, 0.2, 1, 2, 0.5)], contacts_total=1)
    listener.on_sample((listener.keys.report("plant"), encode(fake)))  # unsigned
    listener.on_sample((listener.keys.report("plant"), encode(sign_report("guess", fake))))
    for n in range(100):  # made-up roles, each on its own key, signed by nobody
        listener.on_sample((listener.keys.report(f"x{n}"), encode(report(f"x{n}"))))
    assert listener.collector.reports == {} and listener.forged_reports == 102
    tampered = msgspec.structs.replace(sign_report(listener.secret, report("plant")), late=7)
    listener.on_sample((listener.keys.report("plant"), encode(tampered)))
    assert listener.collector.reports == {}
    signed = sign_report(listener.secret, report("plant", contacts_total=0))
    listener.on_sample((listener.keys.report("plant"), encode(signed)))
    assert listener.collector.reports["plant"] == signed
    assert report_is_genuine(None, fake)  # a recorder across hosts: no secret, the ACL's word


def test_a_report_with_a_negative_count_does_not_decode():
    import msgspec

    bad = msgspec.msgpack.encode(msgspec.structs.astuple(report("plant", nonfinite=0))
                                 [:9] + (-1000,) + msgspec.structs.astuple(report("plant"))[10:])
    assert Codec([1, 2, 3]).decode(NodeReport, bad) is None


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
