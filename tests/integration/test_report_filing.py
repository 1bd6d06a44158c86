"""What one message from outside may do to a run's outputs (docs/hardening.md): a report is
filed under the role of the key it came on, and its size is bounded."""

from __future__ import annotations

from pathlib import Path

import pytest

from deploy.contract.keyring import Keyring, keyring_text, new_master
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import WIRE_VERSION, Codec, ContactRecord, Keys, NodeReport, encode
from deploy.run.launcher import LaunchOptions, make_observer


def report(role: str, **extra) -> NodeReport:
    fields = {"sent": 1, "dropped": 0, "late": 0, "invalid": 0, "steps": 1} | extra
    return NodeReport(WIRE_VERSION, 0, 0, 0, role=role, robot=-1, **fields)


def _run_keys(sc, master: bytes) -> dict[str, Keyring]:
    """The keyrings of a run of ``sc`` (fleet = its name), the launcher's included."""
    roles = ["leader", "plant", *(f"agent-{r}" for r in sc.robot_ids), "launcher"]
    return {r: Keyring.from_text(keyring_text(master, sc.name, r, roles), "test", r, sc,
                                 Keys(sc.name)) for r in roles}


def _listener(sc, tmp_path: Path, keys: dict[str, Keyring] | None):
    return make_observer(sc, LaunchOptions("paper", "model", "lockstep", tmp_path, record=False),
                         None if keys is None else keys["launcher"])


def test_a_report_is_filed_under_the_key_it_came_on(tmp_path: Path):
    """Found by probing: a "plant" report sent on report/agent-2 put a fake contact
    and invalid = -1000 into metrics.json. Without keys (a recorder across hosts given
    none: the ACL's word) the key still decides."""
    sc = load_scenario("paper")
    listener = _listener(sc, tmp_path, None)
    fake = report("plant", contacts=[ContactRecord(0.1, 0.2, 1, 2, 0.5)], contacts_total=1)
    listener.on_sample((listener.keys.report("agent-2"), encode(fake)))
    assert "plant" not in listener.collector.reports and listener.invalid == 1
    listener.on_sample((listener.keys.report("plant"), encode(report("plant"))))
    assert listener.collector.reports["plant"].contacts is None


def test_a_report_not_tagged_by_its_node_is_refused_before_decoding(tmp_path: Path):
    """On its own key, a forged report still put a fake contact into metrics.json (and
    a report under a made-up role grew the launcher's table): only the report's own
    node can tag it for the launcher."""
    sc = load_scenario("paper")
    keys = _run_keys(sc, new_master())
    listener = _listener(sc, tmp_path, keys)
    k = listener.keys
    fake = report("plant", contacts=[ContactRecord(0.1, 0.2, 1, 2, 0.5)], contacts_total=1)
    listener.on_sample((k.report("plant"), encode(fake)))  # no envelope
    guessed = _run_keys(sc, new_master())  # another run's keys
    listener.on_sample((k.report("plant"), guessed["plant"].seal(encode(fake), k.report("plant"))))
    # agent 2's own keys, on the plant's key: it does not send that key
    listener.on_sample((k.report("plant"), keys["agent-2"].seal(encode(fake), k.report("plant"))))
    for n in range(100):  # made-up roles, each on its own key, sent by nobody
        listener.on_sample((k.report(f"x{n}"), keys["plant"].seal(encode(report(f"x{n}")),
                                                                 k.report(f"x{n}"))))
    assert listener.collector.reports == {}
    assert listener.refused() == {"launcher: report: unsigned": 1,
                                  "launcher: report: MAC does not check": 1,
                                  "launcher: report: not signed by a sender of this key": 101}
    sealed = bytearray(keys["plant"].seal(encode(report("plant", steps=5)), k.report("plant")))
    sealed[10] ^= 1  # touched on the way
    listener.on_sample((k.report("plant"), bytes(sealed)))
    assert listener.collector.reports == {}
    real = report("plant", contacts_total=0)
    listener.on_sample((k.report("plant"), keys["plant"].seal(encode(real), k.report("plant"))))
    assert listener.collector.reports["plant"] == real


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


def test_samples_and_replies_the_plant_could_not_keep_fail_the_recording(tmp_path: Path):
    """The plant keeps the samples and replies for the recording (wire_spool.py); a
    write of it that failed (a full disk) is in its report, and the recording is then
    incomplete: said, counted as lost, and the run's verdict fails on it."""
    from deploy.report.recorder import McapRecorder
    from deploy.report.verdict import judge

    sc = load_scenario("paper")
    listener = _listener(sc, tmp_path, None)
    listener.recorder = McapRecorder(tmp_path / "recording.mcap")
    try:
        listener.note_unrecorded()  # no report yet: nothing to say
        listener.on_sample((listener.keys.report("plant"), encode(report("plant"))))
        listener.note_unrecorded()  # a whole record: nothing to say
        assert listener.recorder.summary().get("error") is None
        listener.collector.reports.clear()
        listener.on_sample((listener.keys.report("plant"),
                            encode(report("plant", unrecorded=120))))
        listener.note_unrecorded()
    finally:
        listener.recorder.close()
    summary = listener.recorder.summary()
    assert "could not keep 120 of its samples and replies" in summary["error"]
    assert summary["lost"] == 120
    from healthy_metrics import healthy_realtime

    assert judge(healthy_realtime())["pass"]
    verdict = judge(healthy_realtime(recording=summary))
    assert not verdict["pass"]
    assert any("the recording failed" in r for r in verdict["reasons"])
