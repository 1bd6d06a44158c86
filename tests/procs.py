"""Processes a test starts: the omnifleet CLI in its own session, always ended by
pid (its whole process group) even when the test fails."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def start(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    """``omnifleet ARGS`` (in ``env``, else this process's environment)."""
    return subprocess.Popen(
        [sys.executable, "-m", "deploy.cli", *args], cwd=REPO, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True, env=env,
    )


def finish(proc: subprocess.Popen, timeout: float = 240) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=timeout)
        return proc.returncode, out, err
    finally:
        kill_run(proc)


def interrupt(proc: subprocess.Popen, timeout: float = 60) -> tuple[int, str, str]:
    """Ctrl-C for a process that runs until its --duration or a signal (a driver
    emulator once the bridge it played for has ended): it ends as it does at the end of
    its duration, exit 130 (0 when it had ended already), then :func:`finish`."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    return finish(proc, timeout)


def kill_run(proc: subprocess.Popen, fleet: str | None = None) -> None:
    """End a run started by :func:`start`, by pid, whatever state it is in: its process
    group if it still lives, then any process left whose command line names ``fleet``."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    for pid in pids_with(fleet) if fleet else ():
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def can_check_beside_emulator(bus: list[str], timeout: float = 120,
                              env: dict[str, str] | None = None) -> tuple[int, str, str]:
    """``omnifleet can-check --spin`` against an ``omnifleet emulate`` of lab's robot 2 on
    ``bus`` (the CAN options, ``--driver`` among them): can-check's (status, stdout,
    stderr); the emulator ended by pid whatever happened.

    Once more, with a new emulator, when a drive's watchdog expired: can-check feeds each
    drive's watchdog every period, so an expiry says the scheduler held can-check (or the
    emulator) past the watchdog's timeout on a loaded machine (a CI run beside other work:
    one drive of four refused to enable, its watchdog expired); the second try must
    pass on its own."""
    rc, out, err = _can_check_once(bus, timeout, env)
    if "watchdog expired" in out:
        print(f"can-check beside the emulator: a drive's watchdog expired (starved), once "
              f"more:\n{out}", file=sys.stderr)
        rc, out, err = _can_check_once(bus, timeout, env)
    return rc, out, err


def _can_check_once(bus: list[str], timeout: float,
                    env: dict[str, str] | None) -> tuple[int, str, str]:
    emulator = start("emulate", "--scenario", "lab", "--robot", "2", *bus, "--duration", "30",
                     env=env)
    try:
        return finish(start("can-check", *bus, "--listen", "1.5", "--spin", "--spin-torque",
                            "0.3", "--spin-time", "0.3", env=env), timeout=timeout)
    finally:
        if emulator.poll() is None:
            emulator.kill()
            emulator.wait()


def pids_with(text: str) -> set[int]:
    """Live processes whose command line contains ``text``."""
    found = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if text in cmd and int(d.name) != os.getpid():
                found.add(int(d.name))
    return found


def stat_fields(pid: int | str) -> list[str] | None:
    """The fields of ``/proc/PID/stat`` after the command name (state, ppid, pgrp, ...),
    or None when there is no such process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat[stat.rindex(")") + 2:].split()


def running(pid: int) -> bool:
    """Whether ``pid`` is a process that still runs (a zombie has ended)."""
    fields = stat_fields(pid)
    return fields is not None and fields[0] != "Z"


def in_group(pgid: int) -> list[str]:
    """The processes (pid and state) whose process group is ``pgid``, zombies included."""
    found = []
    for d in Path("/proc").iterdir():
        fields = stat_fields(d.name) if d.name.isdigit() else None
        if fields is not None and int(fields[2]) == pgid:
            found.append(f"{d.name} {fields[0]}")
    return found


def assert_same_series(a, b, atol: float = 1e-9) -> None:
    """Two runs' TimeSeries agree column by column: floats within atol (NaN where
    NaN), everything else exactly."""
    import numpy as np

    from deploy.report.timeseries import COLUMNS

    assert a.steps == b.steps
    for name in COLUMNS:
        x, y = getattr(a, name), getattr(b, name)
        if x.dtype.kind == "f":
            assert np.allclose(x, y, rtol=0, atol=atol, equal_nan=True), name
        else:
            assert np.array_equal(x, y), name
