"""The plant's record of its samples and replies for the launcher's recording
(deploy/runtime/wire_spool.py): every record read back whole and in order, none half."""

from __future__ import annotations

import os

from deploy.runtime.wire_spool import SpoolReader, SpoolWriter, spool_path


def test_records_come_back_whole_in_order_with_their_key_and_clock(tmp_path):
    w = SpoolWriter(spool_path(tmp_path, "plant"), {"a/1", "b/2"}, flush_bytes=100)
    r = SpoolReader(tmp_path)
    sent = [("a/1" if i % 3 else "b/2", bytes([i % 256]) * (i % 50)) for i in range(300)]
    got = []
    for i, (key, payload) in enumerate(sent):
        w.write(key, payload)
        if i % 17 == 0:  # a reader that looks while the writer writes
            got += r.read()
    w.close()
    got += r.read()
    assert [(k, p) for k, _ns, p in got] == sent
    stamps = [ns for _k, ns, _p in got]
    assert stamps == sorted(stamps) and stamps[0] > 1.7e18  # the wall clock, in ns
    assert r.records == w.written == 300


def test_nothing_is_written_before_a_flush_or_the_threshold(tmp_path):
    w = SpoolWriter(spool_path(tmp_path, "plant"), {"k"}, flush_bytes=1 << 16)
    r = SpoolReader(tmp_path)
    w.write("k", b"x" * 10)
    assert r.read() == []
    w.flush()
    assert [p for _k, _ns, p in r.read()] == [b"x" * 10]
    w.close()


def test_a_half_written_record_is_held_until_it_is_whole(tmp_path):
    path = spool_path(tmp_path, "plant")
    w = SpoolWriter(path, {"k"})
    w.write("k", b"0123456789")
    w.close()
    whole = path.read_bytes()
    path.write_bytes(whole[:-4])  # a writer killed mid-record
    r = SpoolReader(tmp_path)
    assert r.read() == []
    with open(path, "ab") as f:
        f.write(whole[-4:])
    assert [p for _k, _ns, p in r.read()] == [b"0123456789"]


def test_every_process_file_is_read_and_stays_readable_once_its_directory_is_gone(tmp_path):
    first = SpoolWriter(tmp_path / "plant-1.spool", {"k"})
    second = SpoolWriter(tmp_path / "plant-2.spool", {"k"})  # a restarted plant
    first.write("k", b"one")
    second.write("k", b"two")
    r = SpoolReader(tmp_path)
    r.open_all()
    first.close()
    second.close()
    for name in os.listdir(tmp_path):
        os.unlink(tmp_path / name)
    os.rmdir(tmp_path)
    assert sorted(p for _k, _ns, p in r.read()) == [b"one", b"two"]
    r.close()


def test_a_write_that_fails_stops_the_spool_counts_every_record_lost_and_says_so(
        tmp_path, capsys):
    w = SpoolWriter(spool_path(tmp_path, "plant"), {"k"}, flush_bytes=1 << 16)
    w.write("k", b"kept")
    w.flush()
    os.close(w._fd)  # noqa: SLF001 - the disk gone from under it
    w._fd = os.open("/dev/full", os.O_WRONLY)  # noqa: SLF001
    w.write("k", b"held")
    w.write("k", b"held too")
    w.flush()  # fails: both held records lost
    w.write("k", b"after")  # no second complaint, no raise
    w.close()
    assert (w.written, w.lost) == (1, 3)
    assert capsys.readouterr().err.count("cannot write") == 1
    assert [p for _k, _ns, p in SpoolReader(tmp_path).read()] == [b"kept"]


def test_a_record_that_does_not_decode_is_counted_failed_by_the_recording(tmp_path):
    """The launcher's side: the plant's record decoded (SpooledWire) and written by the
    recorder; a record that does not decode is counted, never written, never raised."""
    from deploy.contract.scenario import load_scenario
    from deploy.contract.wire import WIRE_VERSION, Keys, Sample, encode
    from deploy.report.recorder import McapRecorder, messages_in
    from deploy.run.observer import SpooledWire

    sc, keys = load_scenario("paper"), Keys("paper")
    w = SpoolWriter(spool_path(tmp_path, "plant"), {keys.sample(1)})
    sample = Sample(WIRE_VERSION, 0, 0, 5, 1, 0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), [], [])
    w.write(keys.sample(1), encode(sample))
    w.write(keys.sample(1), b"\xc1 not msgpack")
    w.close()
    rec = McapRecorder(tmp_path / "recording.mcap", sim_dt=sc.dt)
    rec.add_source(SpooledWire(sc, keys, SpoolReader(tmp_path)))
    rec.close()
    assert (rec.written, rec.failed) == (1, 1) and "does not decode" in rec.first_error
    assert messages_in(tmp_path / "recording.mcap") == 1
