"""The figures draw in a spawned process (deploy/report/figure_process.py); spawning
starts multiprocessing's resource tracker too. A finished run leaves no process of its
own behind: neither, nor anything else in its process group."""

from __future__ import annotations

from pathlib import Path

from tests.procs import finish, start


def _group(pgid: int) -> list[str]:
    """The processes (pid and state) whose process group is ``pgid``, zombies included."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()  # state ppid pgrp ...
        if int(fields[2]) == pgid:
            found.append(f"{d.name} {fields[0]} {stat[:stat.rindex(')') + 1]}")
    return found


def test_a_run_with_figures_leaves_no_process_in_its_group(tmp_path):
    out = tmp_path / "run"
    proc = start("run", "lab", "--in-process", "--plant", "model", "--duration", "0.5",
                 "--out", str(out))
    code, _, err = finish(proc)
    assert code in (0, 1), err  # a half-second lab run may not settle: the verdict says so
    assert (out / "fig4_trajectories.png").exists(), err  # drawn by the spawned process
    assert _group(proc.pid) == []
