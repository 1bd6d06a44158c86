"""The four drivers as the bridge last heard them: wheel speeds from encoder
estimates, axis states and errors from heartbeats. Pure bookkeeping fed with
decoded frames and the bridge's clock; no I/O.

A robot is **faulted** when any axis reports an error other than its watchdog, or
when an axis that was
heard has been silent (no heartbeat) for longer than ``heartbeat_timeout_s``, or
when an axis was never heard ``heartbeat_timeout_s`` after the bridge started.
A watchdog expiry only says the drive stopped because the bridge fell silent (a
host that was off the CPU): the bridge clears it when it arms the axis again.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import pi

import numpy as np

from bridges.protocol import (
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    DriverErrors,
    EncoderEstimate,
    Heartbeat,
)

RECOVERABLE_ERRORS = AXIS_ERROR_WATCHDOG_TIMER_EXPIRED


@dataclass
class AxisView:
    node: int
    heartbeat_at: float | None = None
    axis_state: int = 0
    axis_error: int = 0
    active_errors: int = 0
    encoder_at: float | None = None
    velocity_rev_s: float = 0.0
    position_rev: float = 0.0


class DriverMonitor:
    def __init__(self, node_ids: list[int] | tuple[int, ...], heartbeat_timeout_s: float,
                 started_at: float) -> None:
        self.axes = [AxisView(n) for n in node_ids]
        self._by_node = {a.node: a for a in self.axes}
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.started_at = started_at
        # encoder estimates as complete sets: every axis heard once more since the last set.
        # The four drives' frames of one burst arrive one after another; angles taken
        # between them mix two instants, which odometry reads as a turn that the next
        # period undoes, leaving a random walk (0.2-0.9 cm over a 60 s lab run).
        self._waiting = {a.node for a in self.axes}  # axes not heard since the last set
        self._set_rev: np.ndarray | None = None  # the newest complete set's angles (turns)
        self._set_rev_s = np.zeros(len(self.axes))  # ... and speeds (turns/s)
        self._set_at: float | None = None  # ... and when, on average, they arrived
        self._first_set: np.ndarray | None = None  # the first complete set's angles

    def feed(self, msg: object, now_s: float) -> None:
        axis = self._by_node.get(getattr(msg, "node", -1))
        if axis is None:
            return
        if isinstance(msg, Heartbeat):
            axis.heartbeat_at = now_s
            axis.axis_state, axis.axis_error = msg.axis_state, msg.axis_error
        elif isinstance(msg, EncoderEstimate):
            axis.encoder_at = now_s
            axis.velocity_rev_s, axis.position_rev = msg.velocity_rev_s, msg.position_rev
            self._waiting.discard(axis.node)
            if not self._waiting:
                self._complete_set()
        elif isinstance(msg, DriverErrors):
            axis.active_errors = msg.active_errors

    def _complete_set(self) -> None:
        self._set_rev = np.array([a.position_rev for a in self.axes])
        self._set_rev_s = np.array([a.velocity_rev_s for a in self.axes])
        self._set_at = sum(a.encoder_at for a in self.axes) / len(self.axes)  # type: ignore[misc]
        if self._first_set is None:
            self._first_set = self._set_rev
        self._waiting = {a.node for a in self.axes}

    def wheel_speeds_radps(self) -> np.ndarray:
        """The newest complete set's wheel speeds (0 before one), in the wheel order of
        eq. (1)."""
        return self._set_rev_s * (2.0 * pi)

    def wheel_positions_rev(self) -> np.ndarray | None:
        """The newest complete set's wheel angles (turns), in the wheel order of eq. (1);
        None until every axis has sent an encoder estimate."""
        return self._set_rev

    def first_positions_rev(self) -> np.ndarray | None:
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
            fatal = a.axis_error & ~RECOVERABLE_ERRORS
            if fatal or a.active_errors:
                out.append(f"node {a.node}: error 0x{fatal | a.active_errors:x}")
            last = a.heartbeat_at if a.heartbeat_at is not None else self.started_at
            if now_s - last > self.heartbeat_timeout_s:
                out.append(f"node {a.node}: no heartbeat for {now_s - last:.2f} s")
        return out

    def faulted(self, now_s: float) -> bool:
        return bool(self.fault_reasons(now_s))
