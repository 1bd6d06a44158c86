"""The four drives as the bridge last heard them, in neutral terms
(:class:`bridges.driver.WheelReport`): wheel angles and speeds, torque estimates,
states and faults. Pure bookkeeping fed with decoded reports and the bridge's
clock; no I/O, no protocol.

A robot is **faulted** when any drive reports a fault that is not recoverable, or
when a drive that was heard has sent no status (an ODrive heartbeat, a CiA 402
statusword) for longer than ``heartbeat_timeout_s``, or was never heard
``heartbeat_timeout_s`` after the bridge started, or when the bridge gave up on a
drive (:meth:`DriverMonitor.give_up`: one that never became enabled). A recoverable
fault (a watchdog, a lost heartbeat or SYNC) only says the drive stopped because the
bridge fell silent (a host that was off the CPU): the bridge clears it when it arms
the drive again.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import pi

from bridges.driver import DriveState, WheelReport


@dataclass
class AxisView:
    """One wheel's drive as last heard: the neutral wheel state."""

    node: int
    status_at: float | None = None  # the newest status (state) report
    state: DriveState | None = None  # None: no status heard yet
    fault: int = 0  # the drive's fault code, 0: none
    recoverable: bool = False  # ... only the host's silence (see the module doc)
    encoder_at: float | None = None
    encoder_sampled_s: float = 0.0  # when the bus took the newest encoder frame (its clock)
    velocity_rev_s: float = 0.0
    position_rev: float = 0.0
    torque_nm: float | None = None  # the drive's estimate, if it reports one

    @property
    def fatal(self) -> bool:
        return bool(self.fault) and not self.recoverable


class DriverMonitor:
    def __init__(self, node_ids: list[int] | tuple[int, ...], heartbeat_timeout_s: float,
                 started_at: float) -> None:
        self.axes = [AxisView(n) for n in node_ids]
        self._by_node = {a.node: a for a in self.axes}
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.started_at = started_at
        self.given_up: dict[int, str] = {}  # node -> why the bridge gave up on it
        # encoder estimates as complete sets: every axis heard once more since the last set,
        # each angle carried to the instant of the set's newest frame (_complete_set).
        # The four drives' frames of one burst arrive one after another; angles taken
        # between them mix two instants, which odometry reads as a turn that the next
        # period undoes, leaving a random walk (0.2-0.9 cm over a 60 s lab run).
        self._waiting = {a.node for a in self.axes}  # axes not heard since the last set
        # (float tuples: a bridge reads them once a period, numpy on four numbers costs
        # more than the arithmetic; bridges/odometry.py)
        self._set_rev: tuple[float, ...] | None = None  # the newest complete set's angles (turns)
        self._set_rev_s: tuple[float, ...] = (0.0,) * len(self.axes)  # ... and speeds (turns/s)
        self._set_at: float | None = None  # ... and when, on average, they arrived
        self._first_set: tuple[float, ...] | None = None  # the first complete set's angles

    def feed(self, report: WheelReport, now_s: float, sampled_s: float | None = None) -> None:
        """A drive's report, heard at ``now_s`` (the bridge's clock); ``sampled_s``: when
        the bus took its frame (python-can's ``timestamp``: the kernel's receive time on
        socketcan and udp_multicast, untouched by a reader thread waiting for the GIL),
        on any clock of its own; None: ``now_s``."""
        axis = self._by_node.get(report.node)
        if axis is None:
            return
        if report.state is not None:
            axis.status_at, axis.state = now_s, report.state
        if report.fault is not None:
            axis.fault, axis.recoverable = report.fault, report.recoverable
        if report.torque_nm is not None:
            axis.torque_nm = report.torque_nm
        if report.position_rev is not None and report.velocity_rev_s is not None:
            axis.encoder_at = now_s
            axis.encoder_sampled_s = now_s if sampled_s is None else sampled_s
            axis.velocity_rev_s, axis.position_rev = report.velocity_rev_s, report.position_rev
            self._waiting.discard(axis.node)
            if not self._waiting:
                self._complete_set()

    def give_up(self, node: int, why: str) -> None:
        """The bridge will not drive this robot again: ``node`` is faulted for good."""
        self.given_up.setdefault(node, why)

    def _complete_set(self) -> None:
        # each angle carried to the set's newest frame by its own speed: a set can hold
        # frames of two bursts (a bridge that first heard a burst's last drives completes
        # every later set across two bursts, and drives on their own timers never send
        # together); left as heard, the wheels a burst behind read as a turn whenever the
        # speeds change (0.03 rad in the first 0.2 s of a can-emulated lab run). By the
        # bus's times: the reader's own clock spread one burst's frames over up to a GIL
        # switch interval (5 ms), which carried them apart instead
        newest = max(a.encoder_sampled_s for a in self.axes)
        self._set_rev = tuple([a.position_rev + a.velocity_rev_s * _behind(newest, a)
                               for a in self.axes])
        self._set_rev_s = tuple([a.velocity_rev_s for a in self.axes])
        self._set_at = sum(a.encoder_at for a in self.axes) / len(self.axes)  # type: ignore[misc]
        if self._first_set is None:
            self._first_set = self._set_rev
        self._waiting = {a.node for a in self.axes}

    def wheel_speeds_radps(self) -> tuple[float, ...]:
        """The newest complete set's wheel speeds (0 before one), in the wheel order of
        eq. (1)."""
        return tuple([v * (2.0 * pi) for v in self._set_rev_s])

    def wheel_positions_rev(self) -> tuple[float, ...] | None:
        """The newest complete set's wheel angles (turns), in the wheel order of eq. (1);
        None until every axis has sent an encoder estimate."""
        return self._set_rev

    def first_positions_rev(self) -> tuple[float, ...] | None:
        """The first complete set's wheel angles (turns): one burst of estimates, to
        measure the first rotation from; None until then."""
        return self._first_set

    def encoder_age_s(self, now_s: float) -> float | None:
        """How long ago, on average over the axes, the newest complete set arrived;
        None until there is one."""
        return None if self._set_at is None else now_s - self._set_at

    def fault_reasons(self, now_s: float) -> list[str]:
        out = []
        for a in self.axes:
            if a.fatal:
                out.append(f"node {a.node}: fault 0x{a.fault:x}")
            last = a.status_at if a.status_at is not None else self.started_at
            if now_s - last > self.heartbeat_timeout_s:
                out.append(f"node {a.node}: no status for {now_s - last:.2f} s")
            if a.node in self.given_up:
                out.append(f"node {a.node}: {self.given_up[a.node]}")
        return out

    def faulted(self, now_s: float) -> bool:
        return bool(self.fault_reasons(now_s))


# frames within this of the set's newest are one burst, taken as heard: a burst's frames
# reach the bus one after another (0.05-0.3 ms apart, measured on the emulated fleet) with
# angles of one instant, and carrying them by that spread put ~0.5 mm back into the
# odometry's median drift. Two bursts are an encoder period apart (10 ms by default)
MIN_CARRY_S = 0.001
# a frame older than this within a set is taken as heard (a clock that jumped, a bus
# without times): carried that far, a wrong speed would cost more than the skew it fixes
MAX_CARRY_S = 0.05


def _behind(newest_s: float, axis: AxisView) -> float:
    """How far (s) to carry ``axis``'s angle forward to the set's newest frame."""
    behind = newest_s - axis.encoder_sampled_s
    return behind if MIN_CARRY_S < behind <= MAX_CARRY_S else 0.0
