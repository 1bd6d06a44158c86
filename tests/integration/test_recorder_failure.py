"""The recorder never dies on a value, and a recording that fails anyway fails the run
loudly (docs/hardening.md).

Found by probing: one message with seq >= 2^32 killed the MCAP writer thread; the
launcher printed a traceback and exited 0, everything after was held in memory
(133 -> 285 MB in 8 s) and 183 messages were missing from the file while its summary
and metrics.recording.messages still counted them.
"""

from __future__ import annotations

import json
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import Writer

from deploy.cli import main
from deploy.contract import wire
from deploy.report.recorder import McapRecorder, messages_in

KEY = "omr/f/ctl/tick"


def tick(seq: int, k: int = 1) -> wire.Control:
    return wire.Control(wire.WIRE_VERSION, 0, seq, 5, command="tick", k=k)


def file_count(path) -> tuple[int, int]:
    """(messages the summary claims, messages a reader gets)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        claimed = reader.get_summary().statistics.message_count
    return claimed, messages_in(path)


def test_a_seq_past_2_to_the_32_is_written_and_the_thread_lives(tmp_path):
    rec = McapRecorder(tmp_path / "r.mcap")
    for seq in (2**32, 2**32 + 7, 2**63, 2**64 - 1, 3):
        rec.add(KEY, 1_700_000_000_000_000_000, tick(seq))
    rec._wake.set()
    rec._drain()
    assert rec._thread.is_alive()
    rec.close()
    assert rec.written == 5 and rec.failed == 0 and rec.broken is None
    assert file_count(tmp_path / "r.mcap") == (5, 5)


def _failing_after(n: int, monkeypatch) -> list[int]:
    """Writer.add_message raises OSError (a full disk) from its (n+1)-th call on."""
    calls = [0]
    real = Writer.add_message

    def add_message(self, *a, **kw):
        calls[0] += 1
        if calls[0] > n:
            raise OSError(28, "No space left on device")
        return real(self, *a, **kw)
    monkeypatch.setattr(Writer, "add_message", add_message)
    return calls


def test_a_failing_writer_breaks_loudly_and_the_count_is_what_the_file_holds(
        tmp_path, monkeypatch, capsys):
    _failing_after(3, monkeypatch)
    rec = McapRecorder(tmp_path / "r.mcap")
    for k in range(10):
        rec.add(KEY, 1, tick(k, k))
    rec._drain()
    assert rec.broken is not None and "No space left" in rec.broken
    for k in range(10, 1000):  # after the failure nothing is queued: memory stays flat
        rec.add(KEY, 1, tick(k, k))
    assert len(rec._queue) == 0
    rec.close()
    assert rec.written == 3 and rec.lost == 997
    summary = rec.summary()
    assert summary["messages"] == 3 and summary["lost"] == 997 and "error" in summary
    assert messages_in(tmp_path / "r.mcap") == 3
    assert "recorder: FAILED" in capsys.readouterr().err


def test_a_dead_writer_thread_is_said_not_silent(tmp_path, monkeypatch):
    rec = McapRecorder(tmp_path / "r.mcap")

    def boom():
        raise SystemExit("killed")  # not an Exception: what once ended the thread silently
    monkeypatch.setattr(rec, "_drain", boom)
    rec._wake.set()
    rec._thread.join(2.0)
    assert not rec._thread.is_alive() and rec.broken is not None and "SystemExit" in rec.broken
    rec.add(KEY, 1, tick(1))
    assert rec.lost >= 1 and len(rec._queue) == 0
    monkeypatch.undo()
    rec.close()


def test_a_run_whose_recording_fails_exits_non_zero_and_is_not_a_pass(tmp_path, monkeypatch,
                                                                      capsys):
    _failing_after(50, monkeypatch)
    out = tmp_path / "run"
    code = main(["run", "lab", "--in-process", "--plant", "model", "--duration", "0.3",
                 "--no-figures", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and "the recording failed" in err
    m = json.loads((out / "metrics.json").read_text())
    assert m["recording"]["messages"] == messages_in(out / "recording.mcap") == 50
    assert m["recording"]["lost"] > 0
    assert not m["verdict"]["pass"] and not m["verdict"]["complete"]
    assert any("recording failed" in r for r in m["verdict"]["reasons"])


def test_a_disk_full_at_the_last_flush_is_a_broken_recording_not_a_crash(capsys):
    """The file's buffer is flushed last by ``close``: on a full disk (``/dev/full``) that
    raised out of the recorder (the run's outputs never written) instead of failing it."""
    rec = McapRecorder(Path("/dev/full"))
    for k in range(3):  # less than a chunk and a buffer: nothing reaches the disk before close
        rec.add(KEY, 1, tick(k, k))
    rec.close()
    assert rec.broken is not None and "No space left" in rec.broken
    assert rec.summary()["error"] == rec.broken
    assert "recorder: FAILED" in capsys.readouterr().err
