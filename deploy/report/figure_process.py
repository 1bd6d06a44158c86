"""The run's figures drawn in a process of their own, beside the rest of its outputs.

Drawing the three figures costs ~1.2 s and importing matplotlib ~0.3 s, and the
recording's scene ~0.8 s more, one after the other at the end of every run that
writes both (README command 1). On two cores the figures now start as soon as the
series is known and draw while this process writes the scene, metrics and series.
The child is spawned (a fresh interpreter: the launcher holds zenoh's and the
recorder's threads, which a fork would copy in whatever state they were) and ended by
pid, whatever happens here. Should it fail, the figures are drawn here as before.

Two processes draw: the child forks once it has the series, and the fork draws Fig. 6
while the child draws Figs. 4 and 5 (1.34 s of drawing for ``paper`` on one core; the
launcher's scene takes ~0.9 s beside them). With the child leaving without the
interpreter's teardown, README command 1 went from ~1.9 s to ~1.6 s after the run
(docs/bench-history.md). The fork dies with the child (``die_with_parent``).

A run that will draw can ``prepare`` the child when it starts: the child imports
matplotlib and draws a small plot into memory (fonts, the mathtext of log ticks, the PNG
encoder: ``figures.warm_up``) while the run goes, then waits for the series on a pipe,
so that at the end only the drawing itself (~2 s for ``paper``) is left after the run
(spawning and importing took ~1 s more there; docs/bench-history.md).
"""

from __future__ import annotations

import multiprocessing
import sys
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from deploy.contract.scenario import Scenario
from deploy.report.run_folder import FIGURE_FILES
from deploy.report.timeseries import TimeSeries
from deploy.runtime.parent_death import die_with_parent

JOIN_TIMEOUT_S = 120.0  # three figures take ~2 s; a child stuck this long is ended


def _end_resource_tracker() -> None:
    """Starting a spawned child started multiprocessing's resource tracker, a process of
    its own that ends only when it reads the end of its pipe: after this process has
    exited, as an orphan its parent is no longer there to reap. End it now, by its pid
    (the standard library's own stop: close the pipe, wait for the pid); it starts again
    if anything here needs it."""
    from multiprocessing import resource_tracker

    stop = getattr(resource_tracker._resource_tracker, "_stop", None)
    if stop is not None:
        stop()


# which figures each of the two drawing processes draws (figures.write_figures ``only``):
# Fig. 6 alone took ~0.56 s of paper's 1.34 s, Figs. 4 and 5 together ~0.77 s
DRAWN_HERE, DRAWN_BY_FORK = (0, 1), (2,)


def _draw(sc: Scenario, series: TimeSeries, out_dir: str) -> None:  # in the child
    """The figures, two at once: a fork of this process (matplotlib loaded, fonts
    warm) draws Fig. 6 while this one draws Figs. 4 and 5 and the captions. Should the
    fork fail, or die, this process draws its figure after its own."""
    import os

    from deploy.report.figures import write_figures

    out = Path(out_dir)
    me = os.getpid()
    try:
        pid = os.fork()
    except OSError:
        pid = None
    if pid == 0:  # the fork: its figure, then out, never back into the caller's code
        code = 1
        try:
            if die_with_parent(me):  # (this process ended before the fork could ask: out)
                write_figures(sc, series, out, only=DRAWN_BY_FORK, notes=False)
                code = 0
        finally:
            os._exit(code)
    write_figures(sc, series, out, only=DRAWN_HERE)
    if pid is None or os.waitpid(pid, 0)[1] != 0:
        write_figures(sc, series, out, only=DRAWN_BY_FORK, notes=False)


def _draw_when_told(jobs: Connection) -> None:  # in the child
    """Get ready to draw (imports, fonts), then draw the one job sent on ``jobs``; a
    closed pipe (the run failed, or was stopped) ends the child quietly."""
    import os
    import signal

    # Ctrl-C on the terminal reaches this child too: the run's process ends it by pid
    # (``stop``), after its own outputs; no traceback of an interrupted wait here
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # its imports and fonts must not take a core from the run's own processes starting
    # (lowest priority: it gets what they leave; at the end the cores are free anyway)
    os.nice(19)
    from deploy.report.figures import warm_up

    warm_up()
    try:
        sc, series, out_dir = jobs.recv()
    except EOFError:
        return
    _draw(sc, series, out_dir)
    # drawn, every file closed: out without the interpreter's teardown of matplotlib's
    # modules, which the run's process would wait for
    os._exit(0)


class FigureProcess:
    """``start`` the figures of a run; ``finish`` waits for them (True: drawn)."""

    def __init__(self) -> None:
        self._proc: Any = None
        self._jobs: Connection | None = None  # to a prepared child
        self._drawing_into: Path | None = None  # where the child was sent to draw

    def prepare(self) -> None:
        """Spawn the child now, to get ready while the run goes (``start`` sends it the
        series); ``stop`` ends it when the run does not get that far."""
        if self._proc is not None:
            return
        ctx = multiprocessing.get_context("spawn")
        theirs = None
        try:
            theirs, self._jobs = ctx.Pipe(duplex=False)
            self._proc = ctx.Process(target=_draw_when_told, args=(theirs,),
                                     name="omnifleet-figures", daemon=True)
            self._proc.start()
        except OSError as exc:  # no process or pipe to be had now: ``start`` tries again
            print(f"omnifleet: the figure process could not start early ({exc}); it starts "
                  "after the run", file=sys.stderr, flush=True)
            self.stop()
        finally:
            if theirs is not None:
                theirs.close()  # the child's end: ours is closed by then, or never opened

    def start(self, sc: Scenario, series: TimeSeries, out_dir: Path) -> None:
        """Draw the figures of ``series`` into ``out_dir``: by the prepared child, or by
        one spawned now. Started already for ``out_dir`` (as soon as the run's series was
        final): nothing more."""
        if self._proc is not None and self._drawing_into == Path(out_dir):
            return
        if self._jobs is not None and self._proc is not None and self._proc.is_alive():
            try:
                self._jobs.send((sc, series, str(out_dir)))
                self._drawing_into = Path(out_dir)
                return
            except OSError:  # the child is gone: one spawned now draws instead
                pass
        self.stop()
        ctx = multiprocessing.get_context("spawn")
        try:
            self._proc = ctx.Process(target=_draw, args=(sc, series, str(out_dir)),
                                     name="omnifleet-figures", daemon=True)
            self._proc.start()
            self._drawing_into = Path(out_dir)
        except OSError as exc:  # ``finish`` says False: the figures are drawn by the caller
            print(f"omnifleet: the figure process could not start ({exc}); drawing them here",
                  file=sys.stderr, flush=True)
            self._proc = None

    def finish(self) -> bool:
        self._close_jobs()
        self._drawing_into = None
        p, self._proc = self._proc, None
        if p is None:
            return False
        try:
            p.join(JOIN_TIMEOUT_S)
        finally:
            if p.is_alive():
                p.kill()
                p.join()
            _end_resource_tracker()
        if p.exitcode != 0:
            print(f"omnifleet: the figure process ended with {p.exitcode}; drawing them here",
                  file=sys.stderr, flush=True)
        return p.exitcode == 0

    def stop(self) -> None:
        """End the child by pid (an error or Ctrl-C here); the figures it was drawing,
        cut short, are removed (none is left half written)."""
        self._close_jobs()
        p, self._proc = self._proc, None
        into, self._drawing_into = self._drawing_into, None
        if p is not None and p.is_alive():
            p.kill()
            p.join()
            if into is not None:
                for name in FIGURE_FILES:
                    (into / name).unlink(missing_ok=True)
        if p is not None:
            _end_resource_tracker()

    def _close_jobs(self) -> None:
        if self._jobs is not None:
            self._jobs.close()
            self._jobs = None
