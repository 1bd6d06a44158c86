"""The figures draw in a spawned process (deploy/report/figure_process.py); spawning
starts multiprocessing's resource tracker too. A finished run leaves no process of its
own behind: neither, nor anything else in its process group."""

from __future__ import annotations

from procs import finish, in_group, start


def test_a_run_with_figures_leaves_no_process_in_its_group(tmp_path):
    out = tmp_path / "run"
    proc = start("run", "lab", "--in-process", "--plant", "model", "--duration", "0.5",
                 "--out", str(out))
    code, _, err = finish(proc)
    assert code in (0, 1), err  # a half-second lab run may not settle: the verdict says so
    assert (out / "fig4_trajectories.png").exists(), err  # drawn by the spawned process
    assert in_group(proc.pid) == []
