"""A run's folder, in process: --out on another run's folder is refused unless --overwrite
(and record's too), --version, progress lines when not on a terminal, the summary names
only the files written (the fleet's interrupted run: tests/e2e/test_run_outputs.py)."""

from __future__ import annotations

import pytest

from deploy.cli import main, package_version
from deploy.run.runner import log_progress


def test_out_on_another_runs_folder_is_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["run", "lab", "--in-process", "--plant", "model", "--duration", "0.05",
            "--no-figures", "--no-record", "--out", str(out)]
    assert main(args) == 0
    (out / "recording.mcap").write_bytes(b"an older run's recording")
    (out / "notes.txt").write_text("mine")  # not a run output: never touched
    before = (out / "metrics.json").read_bytes()
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "already holds a run" in err and "--overwrite" in err and "Traceback" not in err
    assert (out / "metrics.json").read_bytes() == before  # nothing written
    assert main([*args, "--overwrite"]) == 0
    assert not (out / "recording.mcap").exists()  # the old run's recording is gone
    assert (out / "notes.txt").read_text() == "mine"
    assert "removed the previous run's" in capsys.readouterr().err


def test_record_refuses_another_runs_folder_too(tmp_path, capsys):
    out = tmp_path / "rec"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    assert main(["record", "--scenario", "lab", "--out", str(out)]) == 2
    assert "already holds a run" in capsys.readouterr().err


def test_version_comes_from_the_package_metadata(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"omnifleet {package_version()}"
    assert package_version()[0].isdigit()


def test_progress_lines_every_few_seconds_when_not_on_a_terminal(capsys):
    now = [0.0]
    update = log_progress("lab", every_s=5.0, clock=lambda: now[0])
    for k in range(1, 1001):  # 1000 steps over 20 s
        now[0] = k * 0.02
        update(k, 1000)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("lab: step 1/1000")
    assert lines[-1] == "lab: step 1000/1000 (100 %), 20 s"
    assert len(lines) == 5  # at 0.02 s, then every 5 s (5.02, 10.02, 15.02), and the end


def test_the_summary_names_only_what_was_written(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "lab", "--in-process", "--plant", "model", "--duration", "0.05",
                 "--no-figures", "--no-record", "--out", str(out)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "written to" in ln)
    assert line.endswith("(metrics.json, timeseries.npz)")
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "timeseries.npz"]
