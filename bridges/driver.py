"""What a bridge needs from any motor drive, in neutral terms (docs/hardware.md).

A robot's four wheel drives speak one CAN protocol; a :class:`WheelDriver` is that
protocol seen from the host: the frames that arm, disarm, stop, clear and command a
wheel, the frames due once per control period, and what a received frame says of a
wheel (:class:`WheelReport`: angle, speed, torque estimate, the drive's state and
fault). The bridge, its monitor, odometry and ``omnifleet can-check`` use nothing
else, so they drive every protocol the same way. The plug-ins are named in
:mod:`bridges.drivers`: ODrive CANSimple (:mod:`bridges.odrive`) and CiA 402 over
CANopen (:mod:`bridges.cia402_driver`).

Frames only, except for :meth:`WheelDriver.bring_up`: a protocol that configures
its drives before the cyclic path (CANopen: NMT and SDO) does it there, on the bus,
before the bridge's own reader starts. ``decode`` never raises: a frame it cannot
use is counted in :class:`FrameCounters` and ``None`` is returned.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:  # annotations only: the command line names drivers without python-can
    import can


class DriveState(enum.Enum):
    """A drive's state in neutral terms (each plug-in maps its own onto these)."""

    DISABLED = "disabled"  # power stage off, no torque; can be armed
    STARTING = "starting"  # on its way to ENABLED, or busy with a procedure of its own
    ENABLED = "enabled"  # torque setpoints are applied
    STOPPING = "stopping"  # the drive's own quick stop: braking, then DISABLED
    FAULT = "fault"  # a latched fault: cleared before the drive can be armed again


@dataclass(frozen=True, slots=True)
class WheelReport:
    """What one received frame says of one wheel's drive; ``None``: not in this frame.

    ``position_rev`` is the wheel's angle in turns, integrated (not wrapped);
    ``torque_nm`` the drive's estimate of the torque on the wheel. ``fault`` is the
    drive's own fault code (0: none; shown in hex, :meth:`WheelDriver.describe_fault`
    names it); ``recoverable`` says the fault only means the drive stopped itself
    because the host fell silent (a watchdog, a lost heartbeat or SYNC): the bridge
    clears it when it arms the drive again. Any other fault stops the robot."""

    node: int
    position_rev: float | None = None
    velocity_rev_s: float | None = None
    torque_nm: float | None = None
    state: DriveState | None = None
    fault: int | None = None
    recoverable: bool = False


@dataclass
class FrameCounters:
    """What ``decode`` made of the frames it was given (each frame counted once)."""

    decoded: int = 0
    unknown_id: int = 0  # a node id not ours, or an id not in this protocol
    bad_length: int = 0  # a data length the frame's layout does not allow
    invalid: int = 0  # non-finite float, unknown state/mode value, implausible magnitude
    ignored_direction: int = 0  # a host->drive frame seen by the host, or vice versa
    other_frame: int = 0  # extended id, error frame, CAN FD: not this protocol

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    @property
    def rejected(self) -> int:
        return self.unknown_id + self.bad_length + self.invalid + self.ignored_direction \
            + self.other_frame


@dataclass(frozen=True)
class DriverSettings:
    """What a driver is made from: the drives and what the host wants of them."""

    node_ids: tuple[int, ...]  # the wheels' drives, in the wheel order of eq. (1)
    period_s: float = 0.005  # the bridge's control period (CiA 402: SYNC at this period)
    max_wheel_torque_nm: float = math.inf  # the scenario's limit (a CiA 402 drive is told it)
    eds: str | None = None  # CiA 402: the drives' EDS file (None: the emulated drive's)
    # how often the drives report angles and states (CiA 402: its TPDOs every n-th SYNC;
    # an ODrive's rates are set in the drive): ODrive's default encoder message rate
    report_rate_hz: float = 100.0
    host_node_id: int = 127  # CiA 402: the node id of the bridge's own heartbeat


class DriveError(RuntimeError):
    """The drives could not be brought up (no answer, refused configuration)."""


@runtime_checkable
class WheelDriver(Protocol):
    """One robot's wheel drives on one bus, seen from the host.

    ``arm_frames`` may depend on what the drive last reported (a CiA 402 drive is
    walked through its state machine one transition per status): the bridge sends
    them again to a drive that, in a status received ``rearm_after_s`` or more
    after the last ones, still is not ENABLED."""

    name: str
    node_ids: tuple[int, ...]
    counters: FrameCounters
    max_abs_torque_nm: float  # the largest |wheel torque| a frame can carry
    rearm_after_s: float

    def bring_up(self, bus: can.BusABC, timeout_s: float, say: Callable[[str], None]) -> None:
        """Configure the drives on ``bus`` before the cyclic path (DriveError if they
        do not come up within ``timeout_s``); ``say`` hears each step."""
        ...

    def decode(self, frame: can.Message) -> WheelReport | None: ...

    def arm_frames(self, node: int) -> list[can.Message]: ...

    def disarm_frames(self, node: int) -> list[can.Message]: ...

    def estop_frames(self, node: int) -> list[can.Message]: ...

    def clear_faults_frames(self, node: int) -> list[can.Message]: ...

    def torque_frame(self, node: int, torque_nm: float) -> can.Message: ...

    def cycle_frames(self, now_s: float) -> list[can.Message]:
        """Frames due once per control period, after the torques (CiA 402: SYNC and
        the host's heartbeat; ODrive: none, its torque frames feed the watchdog)."""
        ...

    def describe_fault(self, code: int) -> str: ...

    def describe(self, node: int) -> str:
        """The drive's state in its protocol's own words, as last heard (can-check)."""
        ...
