"""Every output path is checked before anything runs (deploy/contract/output_paths.py):
exit 2 naming the path and why, nothing simulated, nothing written; and an in-process
run whose folder goes away while it runs leaves its results in a folder it names.

Seen: ``omnifleet run paper --in-process --out /proc/x`` simulated the whole run, then
died with a FileNotFoundError in write_run; the distributed run, ``scenario new`` and
``scenario generate`` died with tracebacks."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest

from deploy.cli import main

BAD = "/proc/omnifleet-nowhere"  # /proc takes no new file, not even for root


@pytest.mark.parametrize("argv, named", [
    (["run", "paper", "--in-process", "--out", BAD], f"--out {BAD}"),
    (["run", "lab", "--out", BAD], f"--out {BAD}"),  # one process per node: none started
    (["record", "--scenario", "lab", "--out", BAD], f"--out {BAD}"),
    (["scenario", "new", f"{BAD}/a.toml"], f"FILE {BAD}/a.toml"),
    (["scenario", "generate", "--robots", "3", "--control-rate", "100", "--out",
      f"{BAD}/g.toml"], f"--out {BAD}/g.toml"),
    (["scenario", "perturb", "lab", "--seed", "1", "--out", f"{BAD}/p.toml"],
     f"--out {BAD}/p.toml"),
    (["safety", "sweep", "lab", "--seeds", "1", "--out", BAD], f"--out {BAD}"),
    (["faults", "sweep", "lab", "--seeds", "1", "--out", BAD], f"--out {BAD}"),
    (["bench", "--quick", "--out", BAD], f"--out {BAD}"),
    (["deploy", "certs", "no-such-hosts.toml", "lab", "--out", BAD], f"--out {BAD}"),
    (["deploy", "plan", "no-such-hosts.toml", "lab", "--write", BAD], f"--write {BAD}"),
    (["emulate", "--scenario", "lab", "--robot", "1", "--can-interface", "virtual",
      "--can-channel", "x", "--truth-out", f"{BAD}/t.npz"], f"--truth-out {BAD}/t.npz"),
], ids=lambda v: " ".join(v[:2]) if isinstance(v, list) else None)
def test_an_output_path_that_cannot_be_written_exits_2_before_anything_runs(argv, named, capsys):
    started = time.monotonic()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert named in err and ("cannot write" in err or "cannot create" in err), err
    assert "Traceback" not in err and "step " not in err  # nothing ran
    assert time.monotonic() - started < 10


def test_a_file_where_a_folder_should_be_is_named(tmp_path, capsys):
    f = tmp_path / "a-file"
    f.write_text("x")
    assert main(["run", "lab", "--in-process", "--out", str(f / "run")]) == 2
    assert f"{f} is a file" in capsys.readouterr().err


def test_an_in_process_run_whose_folder_vanishes_leaves_its_results_where_it_says(
        tmp_path, monkeypatch, capsys):
    """The folder is replaced by a file while the run goes: the results go to a folder
    under the temporary directory, named on stderr and in the summary."""
    import deploy.run.runner as runner

    out = tmp_path / "run"
    real = runner.run_in_process

    def run_then_take_the_folder(*a, **kw):
        result = real(*a, **kw)
        out.rmdir()  # gone (prepare made it) ...
        out.write_text("not a folder any more")  # ... and a file in its place
        return result

    monkeypatch.setattr(runner, "run_in_process", run_then_take_the_folder)
    out.mkdir()
    assert main(["run", "lab", "--in-process", "--plant", "model", "--duration", "0.2",
                 "--no-figures", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    rescued = Path(re.search(r"results go to (\S+)/", cap.err).group(1))
    assert rescued.is_dir() and "omnifleet-rescued-lab-" in rescued.name
    m = json.loads((rescued / "metrics.json").read_text())
    assert m["steps"] == 40 and m["folder"] == str(rescued)
    assert (rescued / "recording.mcap").stat().st_size > 0 and (rescued / "timeseries.npz").exists()
    assert f"written to {rescued}/" in cap.out
    assert out.read_text() == "not a folder any more"  # what took its place is left alone
