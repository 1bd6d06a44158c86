"""Several robots' drive emulators in one process (:mod:`bridges.drive_emulator` is one
robot's four drives, of any protocol): one physics integration for the fleet, every bus
waited on at once."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import can
import numpy as np

from bridges.drive_emulator import ArmedDisturbance, EmulatorFaults, Fleet, RobotEmulator
from bridges.odrive_emulator import OdriveEmulator
from plant.disturbance import make_disturbance
from plant.model_plant import ModelPlant


class FleetEmulator:
    """Several robots' driver emulators in one process: each robot keeps its own bus
    (its own four drives, frames, faults, ground truth), and one :class:`ModelPlant`
    integrates every robot's eq. (4) at once (the same equations row by row as a
    one-robot emulator's; numpy's cost is per call, not per robot).

    Why: on a small host one process per robot, each waking at the physics rate,
    cost more CPU than the host had (docs/hardware.md). :meth:`run` sleeps until the
    next physics tick and reads every bus that holds frames then.
    """

    def __init__(self, sc: Fleet, robots: Sequence[tuple[int, can.BusABC]],
                 node_ids: Sequence[int] = (0, 1, 2, 3), encoder_rate_hz: float = 200.0,
                 heartbeat_rate_hz: float = 10.0, watchdog_timeout_s: float = 0.2,
                 physics_rate_hz: float = 1000.0,
                 faults: Sequence[EmulatorFaults] | EmulatorFaults = EmulatorFaults(),  # noqa: B008
                 emulator: Callable[..., RobotEmulator] = OdriveEmulator) -> None:
        if not robots:
            raise ValueError("a fleet emulator needs at least one robot")
        ids = [rid for rid, _ in robots]
        if len(set(ids)) != len(ids):
            raise ValueError(f"robot ids must be distinct, got {ids}")
        if isinstance(faults, EmulatorFaults):
            faults = [faults] * len(robots)
        if len(faults) != len(robots):
            raise ValueError("give one EmulatorFaults per robot")
        self.sc = sc
        # each robot's drives, of the protocol ``emulator`` plays (bridges/drivers.py)
        self.emulators: list[RobotEmulator] = [
            emulator(sc, rid, bus, node_ids, encoder_rate_hz, heartbeat_rate_hz,
                     watchdog_timeout_s, physics_rate_hz, f)
            for (rid, bus), f in zip(robots, faults, strict=True)]
        q, qd = sc.initial_state()
        rows = [sc.index_of(rid) for rid in ids]
        d = sc.spec.disturbance
        disturbance = ArmedDisturbance(make_disturbance(d.kind, d.scale, tuple(d.constant_nm)),
                                       len(robots))
        self.plant = ModelPlant([e.model for e in self.emulators], q[rows], qd[rows], disturbance,
                                substeps=1)
        for row, e in enumerate(self.emulators):
            e.plant, e._row, e.disturbance = self.plant, row, disturbance
        self._h = self.emulators[0]._h
        self._torques = np.zeros((len(robots), 4))
        self._origin: float | None = None  # realtime: time.monotonic() at t = 0
        self._lag_every_s = 0.01
        self._next_lag = 0.0

    @property
    def t(self) -> float:
        return self.emulators[0].t

    def step(self, now_s: float, behind_s: float | None = None,
             ready: Sequence[int] | None = None) -> None:
        """See :meth:`_step`; each robot's frames of the step go out together at its end,
        and a tick's as it is integrated."""
        try:
            self._step(now_s, behind_s, ready)
        finally:
            for e in self.emulators:
                e.flush_frames()

    def _step(self, now_s: float, behind_s: float | None = None,
              ready: Sequence[int] | None = None) -> None:
        """Every robot as :meth:`RobotEmulator.step`: frames received so far, then
        the physics tick by tick.

        ``behind_s`` (realtime): catching up more than this, the physics advances
        ``behind_s`` at a time in one RK4 step (a host that took the CPU away gets
        the emulator back in step at a fraction of the cost; RK4 over 20 ms is still
        accurate for time constants of 0.1 s and more), the buses are read between
        those steps (so commands queued meanwhile are applied and do not trip the
        watchdogs), and the encoder estimates older than ``behind_s`` are not sent
        (shed: stale, and sending them costs what let the emulator fall behind).
        Heartbeats are always sent. ``ready``: the robots whose bus has frames (from
        ``select``; None: read every bus)."""
        for e in self.emulators:
            if not e._started:
                e._started = True
                e._send_due()
        first = self.emulators[0]
        target = math.floor(now_s / self._h + 1e-9)
        batch = target if behind_s is None else max(1, int(behind_s / self._h + 1e-9))
        torques = self._torques
        readers = self.emulators if ready is None else [self.emulators[i] for i in ready]
        while True:
            for e in readers:
                e._receive()
            readers = self.emulators
            left = target - first._ticks
            if left <= 0:
                return
            # behind by more than behind_s: one RK4 step over a whole batch (the torques
            # are held over it anyway), frames out only for the newest ticks
            k = batch if behind_s is not None and left > batch else 1
            for _ in range(min(left, batch) // k):
                for row, e in enumerate(self.emulators):
                    torques[row] = e.wheel_torques()
                self.plant.step(first.t, k * self._h, torques, None)
                send = behind_s is None or (target - first._ticks - k) * self._h <= behind_s
                for e in self.emulators:
                    e._after_physics(send, k)
                    e.flush_frames()
                if self._origin is not None and first.t >= self._next_lag:
                    # how late this tick was computed (sampled in emulator time, so a
                    # long catch-up weighs as long as it lasted)
                    first.lag.append((first.t, time.monotonic() - self._origin - first.t))
                    self._next_lag = first.t + self._lag_every_s
            if first._ticks >= target:
                return

    def run(self, stop: Callable[[], bool], duration_s: float | None = None,
            lag_every_s: float = 0.01, behind_s: float = 0.02) -> None:
        """Realtime on ``time.monotonic`` until ``stop()`` or ``duration_s``; between
        ticks, sleep, then read the buses that hold frames. Records
        how far behind the wall clock the physics was, every ``lag_every_s``; see
        :meth:`step` for ``behind_s``."""
        import select

        origin = time.monotonic() - self.t
        self._origin, self._lag_every_s, self._next_lag = origin, lag_every_s, self.t
        for e in self.emulators:
            e.monotonic_origin_s = origin
        fds = [_fileno(e.bus) for e in self.emulators]
        can_select = all(fd >= 0 for fd in fds)
        ready: list[int] | None = None  # the buses with frames (None: read them all)
        while not stop():
            now = time.monotonic() - origin
            if duration_s is not None and now >= duration_s:
                self.step(duration_s)
                return
            self.step(now, behind_s, ready)
            ready = None
            delay = (self.emulators[0]._ticks + 1) * self._h - (time.monotonic() - origin)
            if delay > 0:
                # asleep until the next tick, not woken by each frame: a frame acts at the
                # next tick however early it came (the physics integrates tick by tick), and
                # woken by every frame the emulator of the CAN fleet woke ~6,500 times a
                # second for 1,000 ticks (docs/bench-history.md, "The realtime budget")
                time.sleep(delay)
            if can_select:  # an empty read costs a select per bus: read only the ready ones
                readable = select.select(fds, [], [], 0)[0]
                ready = [fds.index(fd) for fd in readable]

    def lag_stats(self) -> dict[str, float]:
        """Median, 99th percentile and largest lag behind the wall clock (s)."""
        lag = np.array([x for _, x in self.emulators[0].lag], float)
        if not len(lag):
            return {"p50": math.nan, "p99": math.nan, "max": math.nan}
        return {"p50": float(np.median(lag)), "p99": float(np.percentile(lag, 99)),
                "max": float(lag.max())}

    def save_truth(self, paths: Sequence[str | Path]) -> None:
        """Each robot's ground truth (:meth:`RobotEmulator.save_truth`), with the
        fleet's lag log in every file."""
        for e, path in zip(self.emulators, paths, strict=True):
            e.lag = self.emulators[0].lag
            e.save_truth(path)


def _fileno(bus: can.BusABC) -> int:
    """The bus's file descriptor to wait on, or -1 (a virtual bus has none)."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, OSError):
        return -1
    return fd if isinstance(fd, int) else -1
