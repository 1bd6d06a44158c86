"""ODrive CANSimple (firmware 0.5/0.6 style): the frames as typed values, encoded and
decoded (:class:`OdriveCanSimple`, both roles: the emulator plays the drives with it),
and the host's plug-in behind the neutral :class:`bridges.driver.WheelDriver`
(:class:`OdriveDriver`). Pure encoding: no bus I/O here (the bridge and the emulator
own their buses).

* 11-bit standard frames; arbitration id = ``node_id << 5 | cmd_id`` (node 0..63);
  little-endian payloads. The frame layouts live in ``odrive_cansimple.dbc``
  (messages given for node 0), parsed by cantools; payloads are packed with
  ``int``/``struct`` from the DBC's signal definitions (:class:`_Packing`, equal to
  cantools' encode/decode, tested; cantools itself is ~5-10x slower per frame).
* Drive -> host: Heartbeat (cyclic), Get_Encoder_Estimates (cyclic), Get_Error and
  Get_Bus_Voltage_Current (on request). Host -> drive: Estop, Set_Axis_State,
  Set_Controller_Mode, Set_Input_Torque, Clear_Errors, and remote (RTR) frames
  requesting a drive -> host message (:class:`Request`).
* Accepted lengths: from the bytes the signals need up to the DBC length (8 for
  every frame with a payload, 0 for Estop, 1 for Clear_Errors). So a 4-byte
  Set_Input_Torque, as some ODrive tools send it, is accepted; we always send the
  DBC length.
* **No payload checksum.** CANSimple frames carry no CRC or counter of their own, so
  bit corruption that yields plausible values (a finite float, a known state) cannot
  be detected here. On a real bus the CAN CRC-15 catches that; what this module
  rejects are the implausible leftovers: non-finite floats, unknown state or mode
  values, magnitudes beyond the configured bounds, wrong lengths.

``decode`` never raises: a frame that is not a valid frame for this role is
counted in :class:`FrameCounters` and ``None`` is returned. ``encode`` raises
``ValueError`` for a value that ``decode`` would reject, so everything sent is
decodable.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import can
import cantools

from bridges.driver import (
    DriverSettings,
    DriveState,
    FrameCounters,
    WheelReport,
)

DBC_PATH = Path(__file__).resolve().parent / "odrive_cansimple.dbc"

# --- command ids (cmd_id, the low 5 bits of the arbitration id) -------------------
CMD_HEARTBEAT = 0x001
CMD_ESTOP = 0x002
CMD_GET_ERROR = 0x003
CMD_SET_AXIS_STATE = 0x007
CMD_GET_ENCODER_ESTIMATES = 0x009
CMD_SET_CONTROLLER_MODE = 0x00B
CMD_SET_INPUT_TORQUE = 0x00E
CMD_GET_BUS_VOLTAGE_CURRENT = 0x017
CMD_CLEAR_ERRORS = 0x018
MAX_NODE_ID = 63  # 6 bits: node_id << 5 | cmd_id fits an 11-bit id

# --- axis states (ODrive AXIS_STATE_*) ----------------------------------------------
AXIS_STATE_UNDEFINED = 0
AXIS_STATE_IDLE = 1  # motor off, no torque
AXIS_STATE_CLOSED_LOOP_CONTROL = 8  # the controller runs; torque setpoints are applied
# every state value ODrive firmware defines (5, sensorless control, was removed)
AXIS_STATES = frozenset({0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11, 12, 13, 14})
MAX_PROCEDURE_RESULT = 15  # 0 SUCCESS, 1 BUSY, 2 CANCELLED, 3 DISARMED, ... 15

# --- controller modes (ODrive CONTROL_MODE_* / INPUT_MODE_*) -------------------------
CONTROL_MODE_VOLTAGE_CONTROL = 0
CONTROL_MODE_TORQUE_CONTROL = 1  # Input_Torque is the motor torque setpoint
CONTROL_MODE_VELOCITY_CONTROL = 2
CONTROL_MODE_POSITION_CONTROL = 3  # ODrive's power-up default
INPUT_MODE_INACTIVE = 0
INPUT_MODE_PASSTHROUGH = 1  # setpoints applied as received (no ramp/filter); ODrive's default
MAX_CONTROL_MODE = 3
MAX_INPUT_MODE = 8

# --- axis error bits (ODrive 0.5 AXIS_ERROR_*; Heartbeat.Axis_Error, Get_Error) -------
AXIS_ERROR_NONE = 0x0
AXIS_ERROR_INVALID_STATE = 0x1  # a requested state was refused (see the emulator)
AXIS_ERROR_WATCHDOG_TIMER_EXPIRED = 0x800  # no Set_Input_Torque within the watchdog timeout
AXIS_ERROR_ESTOP_REQUESTED = 0x4000  # an Estop frame was received

# plausibility bounds of the bus measurements (an ODrive bus is at most 56 V)
MAX_BUS_VOLTAGE_V = 100.0
MAX_ABS_BUS_CURRENT_A = 1000.0
UINT32_MAX = 0xFFFF_FFFF

Role = Literal["host", "drive"]


# --- frames --------------------------------------------------------------------------
@dataclass(frozen=True)
class Heartbeat:
    """Drive -> host, cyclic: latched errors, state, last procedure's result."""

    node: int
    axis_error: int
    axis_state: int
    procedure_result: int = 0
    trajectory_done: bool = True


@dataclass(frozen=True)
class EncoderEstimate:
    """Drive -> host, cyclic: wheel angle (turns, integrated) and speed (turns/s)."""

    node: int
    position_rev: float
    velocity_rev_s: float


@dataclass(frozen=True)
class DriverErrors:
    """Drive -> host (Get_Error), on request: latched errors, cause of the last disarm."""

    node: int
    active_errors: int
    disarm_reason: int


@dataclass(frozen=True)
class BusVoltageCurrent:
    """Drive -> host (Get_Bus_Voltage_Current), on request."""

    node: int
    voltage_v: float
    current_a: float


@dataclass(frozen=True)
class SetAxisState:
    node: int
    state: int


@dataclass(frozen=True)
class SetControllerMode:
    node: int
    control_mode: int
    input_mode: int


@dataclass(frozen=True)
class SetInputTorque:
    node: int
    torque_nm: float


@dataclass(frozen=True)
class ClearErrors:
    node: int


@dataclass(frozen=True)
class Estop:
    node: int


@dataclass(frozen=True)
class Request:
    """Host -> drive remote (RTR) frame asking for a drive -> host message ``cmd``."""

    node: int
    cmd: int


Frame = (Heartbeat | EncoderEstimate | DriverErrors | BusVoltageCurrent | SetAxisState
         | SetControllerMode | SetInputTorque | ClearErrors | Estop | Request)
REQUESTABLE = frozenset({CMD_HEARTBEAT, CMD_GET_ERROR, CMD_GET_ENCODER_ESTIMATES,
                         CMD_GET_BUS_VOLTAGE_CURRENT})


# --- ODrive CANSimple ----------------------------------------------------------------
@dataclass(frozen=True)
class _Spec:
    cmd: int
    dbc_name: str
    to_signals: Callable[[Any], dict[str, float | int]]
    from_signals: Callable[[int, dict[str, Any]], Frame]
    min_length: int | None = None  # None: the bytes the signals need


_SPECS: dict[type, _Spec] = {
    Heartbeat: _Spec(
        CMD_HEARTBEAT, "Heartbeat",
        lambda m: {"Axis_Error": m.axis_error, "Axis_State": m.axis_state,
                   "Procedure_Result": m.procedure_result,
                   "Trajectory_Done_Flag": int(bool(m.trajectory_done))},
        lambda n, s: Heartbeat(n, int(s["Axis_Error"]), int(s["Axis_State"]),
                               int(s["Procedure_Result"]), bool(s["Trajectory_Done_Flag"]))),
    Estop: _Spec(CMD_ESTOP, "Estop", lambda m: {}, lambda n, s: Estop(n)),
    DriverErrors: _Spec(
        CMD_GET_ERROR, "Get_Error",
        lambda m: {"Active_Errors": m.active_errors, "Disarm_Reason": m.disarm_reason},
        lambda n, s: DriverErrors(n, int(s["Active_Errors"]), int(s["Disarm_Reason"]))),
    SetAxisState: _Spec(
        CMD_SET_AXIS_STATE, "Set_Axis_State",
        lambda m: {"Axis_Requested_State": m.state},
        lambda n, s: SetAxisState(n, int(s["Axis_Requested_State"]))),
    EncoderEstimate: _Spec(
        CMD_GET_ENCODER_ESTIMATES, "Get_Encoder_Estimates",
        lambda m: {"Pos_Estimate": m.position_rev, "Vel_Estimate": m.velocity_rev_s},
        lambda n, s: EncoderEstimate(n, float(s["Pos_Estimate"]), float(s["Vel_Estimate"]))),
    SetControllerMode: _Spec(
        CMD_SET_CONTROLLER_MODE, "Set_Controller_Mode",
        lambda m: {"Control_Mode": m.control_mode, "Input_Mode": m.input_mode},
        lambda n, s: SetControllerMode(n, int(s["Control_Mode"]), int(s["Input_Mode"]))),
    SetInputTorque: _Spec(
        CMD_SET_INPUT_TORQUE, "Set_Input_Torque",
        lambda m: {"Input_Torque": m.torque_nm},
        lambda n, s: SetInputTorque(n, float(s["Input_Torque"]))),
    BusVoltageCurrent: _Spec(
        CMD_GET_BUS_VOLTAGE_CURRENT, "Get_Bus_Voltage_Current",
        lambda m: {"Bus_Voltage": m.voltage_v, "Bus_Current": m.current_a},
        lambda n, s: BusVoltageCurrent(n, float(s["Bus_Voltage"]), float(s["Bus_Current"]))),
    ClearErrors: _Spec(CMD_CLEAR_ERRORS, "Clear_Errors", lambda m: {"Identify": 0},
                       lambda n, s: ClearErrors(n), min_length=0),  # Identify is optional
}


class _Packing:
    """One DBC message's payload packed with ``int``/``struct`` instead of cantools.

    Built from the DBC's own signal definitions (start bit, length, sign, float), so
    the DBC stays the one description of the frames; only the per-frame work is
    cheaper (cantools costs ~5-20 us a frame, this ~1-2 us; the emulator and the
    bridge each handle ~1600 frames/s per robot). Supports what CANSimple uses:
    little-endian, unscaled integer fields of any bit length and byte-aligned
    float32 fields. ``unsupported`` is the reason another DBC message would need
    cantools (the codec then uses cantools for it).
    """

    def __init__(self, message: Any) -> None:
        self.length = message.length
        self.ints: list[tuple[str, int, int, bool, float | None, float | None]] = []
        self.floats: list[tuple[str, int]] = []
        self.unsupported: str | None = None
        for s in message.signals:
            if (s.byte_order != "little_endian" or s.scale != 1 or s.offset != 0
                    or s.is_multiplexer or s.multiplexer_ids):
                self.unsupported = f"signal {s.name}: scaled, big-endian or multiplexed"
            elif s.is_float:
                if s.length != 32 or s.start % 8:
                    self.unsupported = f"signal {s.name}: not a byte-aligned float32"
                self.floats.append((s.name, s.start // 8))
            else:
                self.ints.append((s.name, s.start, s.length, s.is_signed, s.minimum, s.maximum))

    def encode(self, signals: dict[str, Any]) -> bytes:
        """The payload, as cantools' ``encode(signals, strict=True)`` gives it; ``ValueError``
        where cantools raises (a value outside the signal's range or its bits)."""
        raw = 0
        for name, start, length, signed, lo, hi in self.ints:
            v = signals[name]
            if isinstance(v, bool):
                v = int(v)
            if not isinstance(v, int):
                raise ValueError(f"{name}: {v!r} is not an integer")
            if (lo is not None and v < lo) or (hi is not None and v > hi):
                raise ValueError(f"{name}: {v} outside [{lo}, {hi}]")
            if not (-(1 << (length - 1)) <= v < (1 << (length - 1)) if signed
                    else 0 <= v < (1 << length)):
                raise ValueError(f"{name}: {v} does not fit {length} bits")
            raw |= (v & ((1 << length) - 1)) << start
        buf = bytearray(raw.to_bytes(self.length, "little"))
        for name, offset in self.floats:
            try:
                struct.pack_into("<f", buf, offset, signals[name])
            except (OverflowError, struct.error) as exc:  # beyond float32, not a number
                raise ValueError(f"{name}: {exc}") from None
        return bytes(buf)

    def decode(self, data: bytes) -> dict[str, Any]:
        """The signals of a payload of the DBC length, as cantools' ``decode`` gives them."""
        raw = int.from_bytes(data, "little")
        out: dict[str, Any] = {}
        for name, start, length, signed, _, _ in self.ints:
            v = (raw >> start) & ((1 << length) - 1)
            if signed and v >> (length - 1):
                v -= 1 << length
            out[name] = v
        for name, offset in self.floats:
            out[name] = struct.unpack_from("<f", data, offset)[0]
        return out


FLOAT32_MAX = 3.4028234663852886e38  # the largest finite float32
_TWO_FLOATS = struct.Struct("<ff")


@dataclass(frozen=True)
class _Layout:
    """One DBC message as the codec uses it."""

    spec: _Spec
    message: Any  # cantools Message
    packing: _Packing | None  # fast packing of the same layout (None: cantools)
    length: int  # DBC length: what we send, the most we accept
    min_length: int  # bytes the signals need: the least we accept
    to_host: bool  # sent by the drive


_DB_CACHE: list[Any] = []


def load_dbc() -> Any:
    """The CANSimple DBC as a cantools database (parsed once per process)."""
    if not _DB_CACHE:
        _DB_CACHE.append(cantools.database.load_file(str(DBC_PATH)))
    return _DB_CACHE[0]


def arbitration_id(node: int, cmd: int) -> int:
    """node_id << 5 | cmd_id."""
    return (node << 5) | cmd


def _finite(*xs: float) -> bool:
    return all(math.isfinite(x) for x in xs)


def _uint32(*xs: int) -> bool:
    return all(isinstance(x, int) and 0 <= x <= UINT32_MAX for x in xs)


class OdriveCanSimple:
    """ODrive CANSimple for the drives ``node_ids``, seen from ``role``.

    ``role="host"`` decodes what drives send (heartbeats, estimates, errors, bus
    measurements); ``role="drive"`` decodes what a host sends (commands, requests).
    A frame of the other direction is counted as ``ignored_direction``.
    """

    name = "odrive-cansimple"

    def __init__(self, node_ids: Sequence[int], max_abs_velocity_rev_s: float = 1e4,
                 max_abs_torque_nm: float = 1e3, role: Role = "host") -> None:
        ids = [int(n) for n in node_ids]
        if not ids or any(not 0 <= n <= MAX_NODE_ID for n in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"node ids must be distinct integers in 0..{MAX_NODE_ID}, got {ids}")
        if role not in ("host", "drive"):
            raise ValueError(f"role must be 'host' or 'drive', got {role!r}")
        if not (max_abs_velocity_rev_s > 0 and max_abs_torque_nm > 0):
            raise ValueError("the velocity and torque bounds must be positive")
        self.node_ids = frozenset(ids)
        self.role: Role = role
        self.max_abs_velocity_rev_s = float(max_abs_velocity_rev_s)
        self.max_abs_torque_nm = float(max_abs_torque_nm)
        self.counters = FrameCounters()
        db = load_dbc()
        self._by_type: dict[type, _Layout] = {}
        self._by_cmd: dict[int, _Layout] = {}
        for cls, spec in _SPECS.items():
            m = db.get_message_by_name(spec.dbc_name)
            if m.frame_id != spec.cmd:
                raise RuntimeError(f"{DBC_PATH.name}: {spec.dbc_name} has id {m.frame_id:#x}, "
                                   f"expected {spec.cmd:#x}")
            need = max(((s.start + s.length + 7) // 8 for s in m.signals), default=0)
            if spec.min_length is not None:
                need = spec.min_length
            packing = _Packing(m)
            layout = _Layout(spec, m, None if packing.unsupported else packing, m.length, need,
                             "ODrive" in m.senders)
            self._by_type[cls] = layout
            self._by_cmd[spec.cmd] = layout
        self._torque_packing = self._torque_struct()
        enc = self._by_type[EncoderEstimate]  # two float32, position then velocity: "<ff"
        self._encoder_packed = enc.packing is not None and not enc.packing.ints and \
            enc.packing.floats == [("Pos_Estimate", 0), ("Vel_Estimate", 4)] and enc.length == 8

    def encoder_frame(self, node: int, position_rev: float, velocity_rev_s: float
                      ) -> can.Message:
        """:meth:`encode` of ``EncoderEstimate(node, position_rev, velocity_rev_s)``, the same
        frame and the same refusals (tests/unit/test_can_protocol.py), without the message
        object, the signals' dict and the decode it checks the float32 values with: an
        emulated drive sends one a wheel at the encoder rate."""
        pos, vel = float(position_rev), float(velocity_rev_s)
        bound, finite = self.max_abs_velocity_rev_s, math.isfinite
        if not self._encoder_packed or node not in self.node_ids or not (
                finite(pos) and finite(vel)) or abs(vel) > bound:
            return self.encode(EncoderEstimate(node, pos, vel))  # its refusal says why
        try:
            data = _TWO_FLOATS.pack(pos, vel)
        except (OverflowError, struct.error):
            return self.encode(EncoderEstimate(node, pos, vel))
        pos32, vel32 = _TWO_FLOATS.unpack(data)  # what the bus carries, as decode reads it
        if not (finite(pos32) and finite(vel32)) or abs(vel32) > bound:
            return self.encode(EncoderEstimate(node, pos, vel))
        return can.Message(arbitration_id=(node << 5) | CMD_GET_ENCODER_ESTIMATES,
                           is_extended_id=False, data=data, dlc=8)

    def _torque_struct(self) -> struct.Struct | None:
        """Set_Input_Torque's payload as one ``struct`` (None: the DBC lays it out
        otherwise than one float32 at byte 0 of its frame, or float32 cannot hold every
        torque within the bound: :meth:`encode` checks those)."""
        lay = self._by_type[SetInputTorque]
        p = lay.packing
        if p is None or p.ints or len(p.floats) != 1 or p.floats[0][1] != 0 or lay.length < 4 \
                or not self.max_abs_torque_nm <= FLOAT32_MAX:
            return None
        return struct.Struct(f"<f{lay.length - 4}x")

    # --- plausibility, shared by encode and decode ---------------------------------
    def problem(self, msg: Frame) -> str | None:
        """Why ``msg`` is not a valid frame (``None`` if it is)."""
        if not isinstance(msg.node, int) or msg.node not in self.node_ids:
            return f"node {msg.node!r} is not one of {sorted(self.node_ids)}"
        match msg:
            case Heartbeat():
                if not _uint32(msg.axis_error):
                    return "axis_error is not a uint32"
                if msg.axis_state not in AXIS_STATES:
                    return f"unknown axis state {msg.axis_state}"
                if not 0 <= msg.procedure_result <= MAX_PROCEDURE_RESULT:
                    return f"unknown procedure result {msg.procedure_result}"
            case EncoderEstimate():
                if not _finite(msg.position_rev, msg.velocity_rev_s):
                    return "non-finite encoder estimate"
                if abs(msg.velocity_rev_s) > self.max_abs_velocity_rev_s:
                    return f"|velocity| {abs(msg.velocity_rev_s):.3g} rev/s beyond the bound"
            case DriverErrors():
                if not _uint32(msg.active_errors, msg.disarm_reason):
                    return "error words are not uint32"
            case BusVoltageCurrent():
                if not _finite(msg.voltage_v, msg.current_a):
                    return "non-finite bus measurement"
                if not (0.0 <= msg.voltage_v <= MAX_BUS_VOLTAGE_V
                        and abs(msg.current_a) <= MAX_ABS_BUS_CURRENT_A):
                    return "implausible bus voltage or current"
            case SetAxisState():
                if msg.state not in AXIS_STATES:
                    return f"unknown axis state {msg.state}"
            case SetControllerMode():
                if not (0 <= msg.control_mode <= MAX_CONTROL_MODE
                        and 0 <= msg.input_mode <= MAX_INPUT_MODE):
                    return f"unknown control/input mode {msg.control_mode}/{msg.input_mode}"
            case SetInputTorque():
                if not _finite(msg.torque_nm):
                    return "non-finite torque"
                if abs(msg.torque_nm) > self.max_abs_torque_nm:
                    return f"|torque| {abs(msg.torque_nm):.3g} N m beyond the bound"
            case Request():
                if msg.cmd not in REQUESTABLE:
                    return f"cmd {msg.cmd:#x} cannot be requested"
            case ClearErrors() | Estop():
                pass
            case _:
                return f"not a CANSimple frame: {type(msg).__name__}"
        return None

    # --- encode ---------------------------------------------------------------------
    def encode(self, msg: Frame) -> can.Message:
        """The CAN frame of ``msg``; ``ValueError`` if ``decode`` would reject it."""
        why = self.problem(msg)
        if why is not None:
            raise ValueError(f"cannot encode {msg!r}: {why}")
        if isinstance(msg, Request):
            layout = self._by_cmd[msg.cmd]
            return can.Message(arbitration_id=arbitration_id(msg.node, msg.cmd),
                               is_extended_id=False, is_remote_frame=True, dlc=layout.length)
        layout = self._by_type[type(msg)]
        try:
            signals = layout.spec.to_signals(msg)
            data = (layout.packing.encode(signals) if layout.packing is not None
                    else layout.message.encode(signals, strict=True))
        except (cantools.database.EncodeError, ValueError, TypeError) as exc:
            raise ValueError(f"cannot encode {msg!r}: {exc}") from exc
        if isinstance(msg, EncoderEstimate | BusVoltageCurrent) or (
                isinstance(msg, SetInputTorque) and not self.max_abs_torque_nm <= FLOAT32_MAX):
            # float32 overflow becomes inf on the wire: refuse what would decode invalid (a
            # torque within a bound float32 holds needs no check: every torque frame, 800 a
            # second a robot at 200 Hz, was decoded again here)
            if self._decode_payload(layout, msg.node, bytes(data)) is None:
                raise ValueError(f"cannot encode {msg!r}: not representable as float32")
        return can.Message(arbitration_id=arbitration_id(msg.node, layout.spec.cmd),
                           is_extended_id=False, data=data, dlc=len(data))

    # --- decode ---------------------------------------------------------------------
    def decode(self, frame: can.Message) -> Frame | None:
        """The frame's value, or ``None`` (counted) if it is not a valid frame for this
        role. Never raises."""
        try:
            return self._decode(frame)
        except Exception:  # noqa: BLE001 - a malformed frame object must not end the caller
            self.counters.invalid += 1
            return None

    def _decode(self, frame: can.Message) -> Frame | None:
        c = self.counters
        if frame.is_error_frame or frame.is_extended_id or frame.is_fd:
            c.other_frame += 1
            return None
        arb = int(frame.arbitration_id)
        node, cmd = arb >> 5, arb & 0x1F
        if not 0 <= arb <= 0x7FF or node not in self.node_ids:
            c.unknown_id += 1
            return None
        if frame.is_remote_frame:
            if self.role == "host":  # a request, as some host sends it
                c.ignored_direction += 1
                return None
            if cmd not in REQUESTABLE:
                c.unknown_id += 1
                return None
            c.decoded += 1
            return Request(node, cmd)
        layout = self._by_cmd.get(cmd)
        if layout is None:
            c.unknown_id += 1
            return None
        if layout.to_host != (self.role == "host"):
            c.ignored_direction += 1
            return None
        data = bytes(frame.data or b"")
        if not layout.min_length <= len(data) <= layout.length or frame.dlc != len(data):
            c.bad_length += 1
            return None
        msg = self._decode_payload(layout, node, data)
        if msg is None:
            c.invalid += 1
            return None
        c.decoded += 1
        return msg

    def _decode_payload(self, layout: _Layout, node: int, data: bytes) -> Frame | None:
        padded = data.ljust(layout.length, b"\0")
        signals = (layout.packing.decode(padded) if layout.packing is not None
                   else layout.message.decode(padded, decode_choices=False, scaling=True))
        msg = layout.spec.from_signals(node, signals)
        return msg if self.problem(msg) is None else None

    # --- the frames the host plug-in sends ----------------------------------------------
    def arm_frames(self, node: int) -> list[can.Message]:
        """Torque control with passthrough input, then closed loop (errors are not
        cleared: a latched error needs an explicit :class:`ClearErrors`)."""
        return [
            self.encode(SetControllerMode(node, CONTROL_MODE_TORQUE_CONTROL, INPUT_MODE_PASSTHROUGH)),
            self.encode(SetAxisState(node, AXIS_STATE_CLOSED_LOOP_CONTROL)),
        ]

    def disarm_frames(self, node: int) -> list[can.Message]:
        """Zero torque, then IDLE."""
        return [self.encode(SetInputTorque(node, 0.0)),
                self.encode(SetAxisState(node, AXIS_STATE_IDLE))]

    def torque_frame(self, node: int, torque_nm: float) -> can.Message:
        """:meth:`encode` of ``SetInputTorque(node, torque_nm)``, the same frame and the same
        refusals (tests/unit/test_can_protocol.py), without the message object, the plausibility
        match and the signals' dict: four of these a period are a bridge's command, and the
        general path cost 6.7 µs a frame here against 1.3."""
        fast = self._torque_packing
        tau = float(torque_nm)
        if fast is None or node not in self.node_ids or not abs(tau) <= self.max_abs_torque_nm:
            return self.encode(SetInputTorque(node, tau))  # its refusal says why
        return can.Message(arbitration_id=(node << 5) | CMD_SET_INPUT_TORQUE,
                           is_extended_id=False, data=fast.pack(tau), dlc=fast.size)

    def estop_frames(self, node: int) -> list[can.Message]:
        """Estop: the drive latches AXIS_ERROR_ESTOP_REQUESTED and disarms."""
        return [self.encode(Estop(node))]

    def clear_errors_frames(self, node: int) -> list[can.Message]:
        return [self.encode(ClearErrors(node))]


# --- the host's plug-in ----------------------------------------------------------------
_ERROR_NAMES = {AXIS_ERROR_INVALID_STATE: "invalid state requested",
                AXIS_ERROR_WATCHDOG_TIMER_EXPIRED: "watchdog expired",
                AXIS_ERROR_ESTOP_REQUESTED: "e-stop"}


def neutral_state(axis_state: int, axis_error: int) -> DriveState:
    """An ODrive axis state in neutral terms. ODrive has no fault state: an error
    disarms the axis to IDLE with its bits latched, which is FAULT here."""
    if axis_state == AXIS_STATE_CLOSED_LOOP_CONTROL:
        return DriveState.ENABLED
    if axis_error:
        return DriveState.FAULT
    if axis_state in (AXIS_STATE_IDLE, AXIS_STATE_UNDEFINED):
        return DriveState.DISABLED
    return DriveState.STARTING  # calibration, start-up sequences, ...


class OdriveDriver:
    """ODrive CANSimple behind :class:`bridges.driver.WheelDriver`: the host-role codec,
    its frames mapped to neutral reports. Nothing to configure over the bus (the
    drives' watchdog and CAN rates are set in their own configuration)."""

    name = OdriveCanSimple.name
    # heartbeats come at 10 Hz: an axis still idle this long after its arming frames
    # missed them (a lost frame, a drive that rebooted) and is asked again
    rearm_after_s = 0.25

    def __init__(self, settings: DriverSettings) -> None:
        self.codec = OdriveCanSimple(settings.node_ids, role="host")
        self.node_ids = tuple(settings.node_ids)
        self.counters = self.codec.counters
        self.max_abs_torque_nm = self.codec.max_abs_torque_nm
        self._heartbeats: dict[int, Heartbeat] = {}

    def bring_up(self, bus: can.BusABC, timeout_s: float, say: Callable[[str], None]) -> None:
        say("ODrive CANSimple: nothing to configure over the bus (watchdog, CAN rates and "
            "node ids live in each drive's own configuration)")

    def decode(self, frame: can.Message) -> WheelReport | None:
        msg = self.codec.decode(frame)
        match msg:
            case Heartbeat():
                self._heartbeats[msg.node] = msg
                return WheelReport(msg.node, state=neutral_state(msg.axis_state, msg.axis_error),
                                   fault=msg.axis_error, recoverable=_recoverable(msg.axis_error))
            case EncoderEstimate():
                return WheelReport(msg.node, position_rev=msg.position_rev,
                                   velocity_rev_s=msg.velocity_rev_s)
            case DriverErrors():
                return WheelReport(msg.node, fault=msg.active_errors,
                                   recoverable=_recoverable(msg.active_errors))
            case BusVoltageCurrent():
                return WheelReport(msg.node)  # nothing the neutral report carries
        return None

    def arm_frames(self, node: int) -> list[can.Message]:
        """Torque control, closed loop, and a heartbeat asked for at once (a remote
        frame): the bridge drives no wheel until every axis says closed loop, and the
        cyclic heartbeat comes only every 100 ms."""
        return [*self.codec.arm_frames(node), self.codec.encode(Request(node, CMD_HEARTBEAT))]

    def disarm_frames(self, node: int) -> list[can.Message]:
        return self.codec.disarm_frames(node)

    def estop_frames(self, node: int) -> list[can.Message]:
        return self.codec.estop_frames(node)

    def clear_faults_frames(self, node: int) -> list[can.Message]:
        return self.codec.clear_errors_frames(node)

    def torque_frame(self, node: int, torque_nm: float) -> can.Message:
        return self.codec.torque_frame(node, torque_nm)

    def cycle_frames(self, now_s: float) -> list[can.Message]:
        return []  # the torque frames of every period feed the drives' watchdogs

    def describe(self, node: int) -> str:
        hb = self._heartbeats.get(node)
        if hb is None:
            return "no heartbeat yet"
        return f"axis state {hb.axis_state}, axis error 0x{hb.axis_error:x}"

    def describe_fault(self, code: int) -> str:
        names = [n for bit, n in _ERROR_NAMES.items() if code & bit]
        rest = code & ~sum(_ERROR_NAMES)
        if rest:
            names.append(f"axis error bits 0x{rest:x}")
        return f"0x{code:x} ({', '.join(names)})" if names else "0x0 (none)"


def _recoverable(bits: int) -> bool:
    """Only the watchdog: the drive stopped itself because the host fell silent."""
    return bool(bits) and not bits & ~AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
