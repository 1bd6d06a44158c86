"""The figures draw in a spawned process (deploy/report/figure_process.py); spawning
starts multiprocessing's resource tracker too. A finished run leaves no process of its
own behind: neither, nor anything else in its process group. A child prepared when the
run starts draws what it is sent at the end, is replaced when it died meanwhile, and is
ended by pid when the run never gets to its figures."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest
from procs import finish, in_group, running, start, stat_fields

from deploy.contract.scenario import load_scenario
from deploy.report.figure_process import FigureProcess
from deploy.report.run_folder import FIGURE_FILES
from deploy.run.runner import run_in_process


def test_a_run_with_figures_leaves_no_process_in_its_group(tmp_path):
    out = tmp_path / "run"
    proc = start("run", "lab", "--in-process", "--plant", "model", "--duration", "0.5",
                 "--out", str(out))
    code, _, err = finish(proc)
    assert code in (0, 1), err  # a half-second lab run may not settle: the verdict says so
    assert (out / "fig4_trajectories.png").exists(), err  # drawn by the spawned process
    assert in_group(proc.pid) == []


@pytest.fixture(scope="module")
def lab_run():
    sc = load_scenario("lab")
    return sc, run_in_process(sc, "model", 0.3).series


def test_a_prepared_figure_process_draws_the_run_it_is_sent(tmp_path, lab_run):
    sc, series = lab_run
    drawing = FigureProcess()
    drawing.prepare()  # it imports and warms up while "the run goes"
    try:
        drawing.start(sc, series, tmp_path)
        assert drawing.finish()
    finally:
        drawing.stop()
    for name in FIGURE_FILES:
        assert (tmp_path / name).stat().st_size > 0, name


def test_a_prepared_child_that_died_is_replaced_by_one_spawned_then(tmp_path, lab_run):
    sc, series = lab_run
    drawing = FigureProcess()
    drawing.prepare()
    try:
        child = drawing._proc
        os.kill(child.pid, signal.SIGKILL)
        child.join(10.0)
        drawing.start(sc, series, tmp_path)
        assert drawing.finish()
    finally:
        drawing.stop()
    assert (tmp_path / FIGURE_FILES[0]).stat().st_size > 0


def _children_of(pid: int) -> list[int]:
    return [int(d.name) for d in Path("/proc").iterdir() if d.name.isdigit()
            and (f := stat_fields(d.name)) is not None and int(f[1]) == pid and f[0] != "Z"]


def test_a_fork_that_dies_leaves_its_figure_to_the_process_that_forked_it(tmp_path, lab_run,
                                                                            monkeypatch):
    """Two processes draw the figures (a fork draws Fig. 6): should the fork fail, its
    figure is drawn after the others, and every figure is there."""
    from deploy.report import figure_process, figures

    sc, series = lab_run
    real, me = figures.write_figures, os.getpid()

    def dies_in_the_fork(*args, **kw):
        if os.getpid() != me:
            os._exit(9)
        return real(*args, **kw)

    monkeypatch.setattr(figures, "write_figures", dies_in_the_fork)
    figure_process._draw(sc, series, str(tmp_path))
    for name in FIGURE_FILES:
        assert (tmp_path / name).stat().st_size > 0, name


def test_the_fork_that_draws_ends_with_the_figure_process(tmp_path, lab_run, monkeypatch):
    """The figure process ended by pid mid-drawing (Ctrl-C, an error in the run's
    process) takes the fork drawing beside it along: no orphan draws on. Here both
    would draw for an hour."""
    import multiprocessing

    from deploy.report import figure_process, figures

    sc, series = lab_run
    monkeypatch.setattr(figures, "write_figures", lambda *a, **kw: time.sleep(3600))
    child = multiprocessing.get_context("fork").Process(
        target=figure_process._draw, args=(sc, series, str(tmp_path)), daemon=True)
    child.start()
    forks: list[int] = []
    try:
        deadline = time.monotonic() + 60.0
        while not (forks := _children_of(child.pid)) and time.monotonic() < deadline:
            time.sleep(0.01)  # polls for the fork to exist; the test judges what follows
        assert forks, "the figure process never forked"
    finally:
        child.kill()
        child.join()
    deadline = time.monotonic() + 10.0
    while any(running(f) for f in forks) and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        assert not any(running(f) for f in forks), "the fork outlived the figure process"
    finally:
        for f in forks:
            if running(f):
                os.kill(f, signal.SIGKILL)


def test_a_run_that_never_gets_to_its_figures_ends_the_prepared_child(lab_run):
    drawing = FigureProcess()
    drawing.prepare()
    pid = drawing._proc.pid
    drawing.stop()  # a failed or interrupted run (deploy/cli/run.py)
    assert not running(pid)


def test_a_child_that_cannot_start_early_is_started_after_the_run(tmp_path, lab_run, monkeypatch,
                                                                 capsys):
    """No process to be had when the run starts (a limit, a full /dev/shm): the run goes
    on, and the figures are drawn by a child spawned at the end, as before."""
    import multiprocessing

    from deploy.report import figure_process

    real = multiprocessing.get_context("spawn")

    def refused() -> None:
        raise OSError(11, "Resource temporarily unavailable")

    class Refused:  # the context of the first spawn: its process cannot start
        Pipe = staticmethod(real.Pipe)

        @staticmethod
        def Process(*args, **kwargs):
            proc = real.Process(*args, **kwargs)
            proc.start = refused
            return proc

    contexts = iter([Refused])
    monkeypatch.setattr(figure_process.multiprocessing, "get_context",
                        lambda kind: next(contexts, real))
    sc, series = lab_run
    drawing = FigureProcess()
    drawing.prepare()
    assert "could not start early" in capsys.readouterr().err
    try:
        drawing.start(sc, series, tmp_path)
        assert drawing.finish()
    finally:
        drawing.stop()
    assert (tmp_path / FIGURE_FILES[0]).stat().st_size > 0


def test_figures_are_drawn_by_the_run_when_no_child_can_start(tmp_path, lab_run, monkeypatch,
                                                             capsys):
    """Neither early nor late: write_run draws them itself (nothing of the run lost)."""
    from deploy.report import figure_process
    from deploy.report.outputs import write_run

    class NoProcess:
        @staticmethod
        def Pipe(*args, **kwargs):
            raise OSError(24, "Too many open files")

        @staticmethod
        def Process(*args, **kwargs):
            raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(figure_process.multiprocessing, "get_context", lambda kind: NoProcess)
    sc, series = lab_run
    drawing = FigureProcess()
    drawing.prepare()
    metrics = write_run(sc, series, tmp_path, "model", "lockstep", 1.0, drawing=drawing)
    err = capsys.readouterr().err
    assert "could not start early" in err and "drawing them here" in err
    for name in ("metrics.json", "timeseries.npz", *FIGURE_FILES):
        assert (tmp_path / name).stat().st_size > 0, name
    assert metrics["files"][:2] == ["metrics.json", "timeseries.npz"]


def test_started_again_for_the_same_folder_it_draws_once(tmp_path, lab_run):
    """The run starts the figures as soon as its series is final; writing the outputs
    asks again for the same folder: the same child goes on, nothing is drawn twice."""
    sc, series = lab_run
    drawing = FigureProcess()
    drawing.prepare()
    try:
        drawing.start(sc, series, tmp_path)
        pid = drawing._proc.pid
        drawing.start(sc, series, tmp_path)
        assert drawing._proc.pid == pid
        assert drawing.finish()
    finally:
        drawing.stop()
    for name in FIGURE_FILES:
        assert (tmp_path / name).stat().st_size > 0, name


def _half_a_figure_then_wait(path: str) -> None:  # in a child
    with open(path, "wb") as f:
        f.write(b"\x89PNG half")
    time.sleep(3600)


def test_a_drawing_stopped_midway_leaves_no_half_figure(tmp_path):
    import multiprocessing

    drawing = FigureProcess()
    half = tmp_path / FIGURE_FILES[0]
    child = multiprocessing.get_context("fork").Process(
        target=_half_a_figure_then_wait, args=(str(half),), daemon=True)
    child.start()
    deadline = time.monotonic() + 30.0
    while not half.exists() and time.monotonic() < deadline:
        time.sleep(0.01)  # polls for the half figure; the test judges what follows
    drawing._proc, drawing._drawing_into = child, tmp_path  # a child drawing into tmp_path
    drawing.stop()
    assert not running(child.pid)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
