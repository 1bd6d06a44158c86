"""`omnifleet scenario list|show|check|generate`: exit codes, messages, and a
generated scenario that loads, has the shape asked for, and reproduces."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.cli import main
from deploy.contract.scenario import has_spanning_tree, load_scenario


def run(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        rc = main(list(argv))
    except SystemExit as exc:  # argparse's own usage errors
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def test_list_names_every_bundled_scenario(capsys):
    rc, out, _ = run(capsys, "scenario", "list")
    assert rc == 0
    for name in ("paper", "lab", "reference-code"):
        assert any(line.startswith(name) and "robots" in line for line in out.splitlines())


def test_show_prints_a_scenario_that_loads(capsys, tmp_path):
    rc, out, _ = run(capsys, "scenario", "show", "lab")
    assert rc == 0
    copy = tmp_path / "copy.toml"
    copy.write_text(out)
    assert load_scenario(copy).spec == load_scenario("lab").spec
    rc, _, err = run(capsys, "scenario", "show", "lemniscate")
    assert rc == 2 and "lemniscate" in err and "paper" in err


def test_check_says_valid_or_names_the_key(capsys, tmp_path):
    assert run(capsys, "scenario", "check", "paper")[0] == 0
    bad = tmp_path / "bad.toml"
    from deploy.contract.scenario import resolve_path

    bad.write_text(resolve_path("lab").read_text().replace("duration_s", "duraton_s", 1))
    rc, _, err = run(capsys, "scenario", "check", str(bad))
    assert rc == 2 and "duraton_s" in err and "Traceback" not in err


@pytest.mark.parametrize("n", [1, 7, 30])
def test_generate_writes_the_fleet_asked_for(capsys, tmp_path, n):
    out = tmp_path / f"fleet-{n}.toml"
    rc, stdout, err = run(capsys, "scenario", "generate", "--robots", str(n),
                          "--control-rate", "50", "--duration", "3", "--out", str(out))
    assert rc == 0, err
    assert str(out) in stdout
    sc = load_scenario(out)
    assert sc.n == n and sc.dt == pytest.approx(0.02) and sc.spec.duration_s == 3
    assert has_spanning_tree(sc.adjacency, np.asarray(sc.leader_weights, float))
    q, _ = sc.initial_state()
    gaps = np.linalg.norm(q[:, None, :2] - q[None, :, :2], axis=2) + np.eye(n) * 1e9
    assert gaps.min() > 2 * sc.spec.robot.body_radius_m  # nobody starts touching


def test_generate_with_a_seed_jitters_the_starts_reproducibly(capsys, tmp_path):
    paths = [tmp_path / f"{name}.toml" for name in ("a", "b", "c", "fixed")]
    for path, seed in zip(paths, ("3", "3", "4", None), strict=True):
        extra = () if seed is None else ("--seed", seed)
        assert run(capsys, "scenario", "generate", "--robots", "6", "--control-rate", "100",
                   "--out", str(path), *extra)[0] == 0
    a, b, c, fixed = (load_scenario(p).initial_state()[0] for p in paths)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.abs(a - fixed)[:, :2].max() <= 0.1 + 0.05 + 1e-9  # within the jitter


@pytest.mark.parametrize("argv, word", [
    (("--robots", "0", "--control-rate", "100"), "--robots"),
    (("--robots", "3", "--control-rate", "nan"), "--control-rate"),
    (("--robots", "3", "--control-rate", "-5"), "--control-rate"),
    (("--robots", "3", "--control-rate", "100", "--duration", "inf"), "--duration"),
    (("--robots", "3", "--control-rate", "100", "--duration", "0"), "--duration"),
])
def test_generate_refuses_bad_numbers(capsys, tmp_path, argv, word):
    out = tmp_path / "x.toml"
    rc, _, err = run(capsys, "scenario", "generate", *argv, "--out", str(out))
    assert rc == 2 and word in err and not out.exists()


def test_generate_does_not_overwrite_without_force(capsys, tmp_path):
    out = tmp_path / "x.toml"
    out.write_text("mine")
    args = ("scenario", "generate", "--robots", "2", "--control-rate", "100", "--out", str(out))
    rc, _, err = run(capsys, *args)
    assert rc == 2 and "--force" in err and out.read_text() == "mine"
    assert run(capsys, *args, "--force")[0] == 0 and load_scenario(out).n == 2


def test_new_writes_the_commented_starter_named_after_the_file(capsys, tmp_path):
    out = tmp_path / "my fleet.toml"
    rc, stdout, err = run(capsys, "scenario", "new", str(out))
    assert rc == 0, err
    text = out.read_text()
    sc = load_scenario(out)
    assert sc.name == "my-fleet" and sc.n == 3  # a usable fleet name from the file's
    assert text.count("\n#") >= 5 and "docs/scenarios.md" in text  # commented for a reader
    assert "scenario check" in stdout


def test_new_from_a_bundled_scenario_copies_it(capsys, tmp_path):
    out = tmp_path / "mine.toml"
    assert run(capsys, "scenario", "new", str(out), "--from", "paper")[0] == 0
    mine, paper = load_scenario(out).spec, load_scenario("paper").spec
    assert mine.name == "mine"
    import msgspec

    assert msgspec.structs.replace(mine, name="paper") == paper
    rc, _, err = run(capsys, "scenario", "new", str(tmp_path / "x.toml"), "--from", "lemniscate")
    assert rc == 2 and "lemniscate" in err and "paper" in err
    assert not (tmp_path / "x.toml").exists()


def test_new_does_not_overwrite_without_force(capsys, tmp_path):
    out = tmp_path / "mine.toml"
    out.write_text("mine")
    rc, _, err = run(capsys, "scenario", "new", str(out))
    assert rc == 2 and "--force" in err and out.read_text() == "mine"
    assert run(capsys, "scenario", "new", str(out), "--force")[0] == 0 and load_scenario(out).n == 3


def test_the_starter_runs_clean(tmp_path):
    """What `scenario new` writes is a fleet that works: on the model plant every robot
    settles before sqrt(2) T_p, nothing touches, nothing is non-finite."""
    from deploy.cli.scenario import STARTER
    from deploy.report.metrics import compute_metrics
    from deploy.report.verdict import judge
    from deploy.run.runner import run_in_process

    sc = load_scenario(STARTER)
    result = run_in_process(sc, "model", None)
    m = compute_metrics(sc, result.series, "model", "lockstep", result.wall_time_s)
    v = judge(m)
    assert v["pass"], v["reasons"]
    assert m["contacts"] == 0 and m["min_robot_gap_m"] > 0


def test_a_reader_that_went_away_ends_the_listing_quietly():
    """`omnifleet scenario list | head -1`: the pipe's reader is gone when the listing
    writes; the command stops as a tool killed by SIGPIPE does (141), with no traceback.
    The read end is closed before the command starts, so its first write meets it."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run([sys.executable, "-m", "deploy.cli", "scenario", "list"],
                              cwd=Path(__file__).resolve().parents[2], stdout=write_end,
                              stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(write_end)
    err = done.stderr.decode()
    assert done.returncode == 128 + signal.SIGPIPE, err
    assert "Traceback" not in err and "BrokenPipe" not in err
