"""Four ODrive CANSimple axes on the robot emulator (:mod:`bridges.drive_emulator`):
they arm, take torque setpoints, report encoder estimates and heartbeats, trip their
watchdog and obey Estop.

Axes
----
Each axis powers up IDLE in ODrive's default controller mode (position control,
passthrough input). Only torque control is emulated, so:

* ``Set_Controller_Mode`` stores the modes.
* ``Set_Axis_State(CLOSED_LOOP_CONTROL)`` enters closed loop only with no latched
  error and modes TORQUE_CONTROL + PASSTHROUGH; otherwise the request is refused:
  ``AXIS_ERROR_INVALID_STATE`` is latched and the axis stays IDLE. Entering closed
  loop zeroes the torque setpoint and feeds the watchdog.
* ``Set_Axis_State(IDLE)`` disarms. Any other requested state is refused as above
  (the emulated drives are calibrated already).
* ``Set_Input_Torque`` stores the setpoint and feeds the watchdog (in any state, as
  ODrive does). The wheel gets it only in closed loop, clamped to the scenario's
  ``limits.max_wheel_torque_nm``; in IDLE the wheel gets 0.
* Watchdog (``watchdog_timeout_s`` > 0): in closed loop with no Set_Input_Torque for
  longer than the timeout, ``AXIS_ERROR_WATCHDOG_TIMER_EXPIRED`` is latched, the axis
  goes IDLE and its torque is 0.
* ``Estop`` latches ``AXIS_ERROR_ESTOP_REQUESTED`` and disarms the addressed axis.
* ``Clear_Errors`` clears the latched errors (the state stays IDLE; re-arm explicitly).
  Every error disarms the axis; ``Disarm_Reason`` keeps the bits of the last disarm.
* ``EmulatorFaults.refuse_enable_node`` never enters closed loop (its enable input
  off: it stays IDLE without an error).

Frames sent: a Heartbeat per axis at ``heartbeat_rate_hz``, Get_Encoder_Estimates
per axis at ``encoder_rate_hz`` (the wheel's angle in turns, integrated from
power-up, and its speed theta_dot / 2 pi). Get_Error and Get_Bus_Voltage_Current
are answered on request (a remote frame), as ODrive does by default; the bus is a
constant 24 V and the bus current the ideal electrical power tau * theta_dot / 24 V
of the axis.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import can
import numpy as np

from bridges.drive_emulator import EmulatorFaults, Fleet, RobotEmulator
from bridges.odrive import (
    AXIS_ERROR_ESTOP_REQUESTED,
    AXIS_ERROR_INVALID_STATE,
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    AXIS_STATE_IDLE,
    CMD_GET_BUS_VOLTAGE_CURRENT,
    CMD_GET_ENCODER_ESTIMATES,
    CMD_GET_ERROR,
    CMD_HEARTBEAT,
    CONTROL_MODE_POSITION_CONTROL,
    CONTROL_MODE_TORQUE_CONTROL,
    INPUT_MODE_PASSTHROUGH,
    BusVoltageCurrent,
    ClearErrors,
    DriverErrors,
    EncoderEstimate,
    Estop,
    Frame,
    Heartbeat,
    OdriveCanSimple,
    Request,
    SetAxisState,
    SetControllerMode,
    SetInputTorque,
)

BUS_VOLTAGE_V = 24.0


@dataclass
class AxisState:
    """One emulated drive axis (mutable)."""

    node: int
    state: int = AXIS_STATE_IDLE
    control_mode: int = CONTROL_MODE_POSITION_CONTROL  # ODrive's power-up default
    input_mode: int = INPUT_MODE_PASSTHROUGH
    axis_error: int = 0
    disarm_reason: int = 0
    procedure_result: int = 0
    torque_setpoint_nm: float = 0.0
    last_torque_s: float = 0.0

    @property
    def armed(self) -> bool:
        return self.state == AXIS_STATE_CLOSED_LOOP_CONTROL


class OdriveEmulator(RobotEmulator):
    """Four CANSimple drives plus robot ``robot_id``'s dynamics on ``bus``."""

    def __init__(self, sc: Fleet, robot_id: int, bus: can.BusABC,
                 node_ids: Sequence[int] = (0, 1, 2, 3), encoder_rate_hz: float = 200.0,
                 heartbeat_rate_hz: float = 10.0, watchdog_timeout_s: float = 0.2,
                 physics_rate_hz: float = 1000.0,
                 faults: EmulatorFaults = EmulatorFaults()) -> None:  # noqa: B008 - frozen
        if not (math.isfinite(heartbeat_rate_hz) and 0 < heartbeat_rate_hz <= physics_rate_hz):
            raise ValueError(f"heartbeat_rate_hz must be positive and at most the physics rate, "
                             f"got {heartbeat_rate_hz}")
        super().__init__(sc, robot_id, bus, node_ids, encoder_rate_hz, watchdog_timeout_s,
                         physics_rate_hz, faults)
        self.protocol = OdriveCanSimple(self.node_ids, role="drive")
        self.counters.protocol = self.protocol.counters
        self.axes = [AxisState(n) for n in self.node_ids]
        self._heartbeat_period = 1.0 / heartbeat_rate_hz
        self._next_heartbeat = 0.0

    def wheel_torques(self) -> np.ndarray:
        """Setpoint in closed loop, clamped to the scenario's limit; else 0 (N m)."""
        return np.array([self.clamp(a.torque_setpoint_nm) if a.armed else 0.0
                         for a in self.axes])

    def describe_drives(self) -> str:
        return ", ".join(f"{a.node}: state {a.state} error 0x{a.axis_error:x}" for a in self.axes)

    # --- the clock ----------------------------------------------------------------------
    def _drives_tick(self, now: float) -> None:
        if self.watchdog_timeout_s > 0:
            for a in self.axes:
                if a.armed and now - a.last_torque_s > self.watchdog_timeout_s + 1e-12:
                    self._disarm(a, AXIS_ERROR_WATCHDOG_TIMER_EXPIRED)

    def _encoders_due(self, send: bool) -> None:
        if not send:
            self.counters.shed += len(self.axes)
            return
        two_pi, codec = 2.0 * math.pi, self.protocol
        for a in self.axes:  # what _send(_encoder_frame(a)) sends, by the codec's short path
            if self._silent(a.node):
                self.counters.silenced += 1
                continue
            w = self.wheel_of(a.node)
            try:
                frame = codec.encoder_frame(a.node, self.wheel_rev[w], self._wheel_speed[w] / two_pi)
            except ValueError:
                self.counters.unencodable += 1
                continue
            self._send_frame(frame, a.node)

    def _clock_due(self, now: float) -> None:
        if now >= self._next_heartbeat - 1e-9:
            self._next_heartbeat = max(self._next_heartbeat + self._heartbeat_period, now)
            for a in self.axes:
                self._send(self._heartbeat(a))

    # --- frames out -------------------------------------------------------------------
    def _heartbeat(self, a: AxisState) -> Heartbeat:
        return Heartbeat(a.node, a.axis_error, a.state, a.procedure_result, True)

    def _encoder_frame(self, a: AxisState) -> EncoderEstimate:
        w = self.wheel_of(a.node)
        return EncoderEstimate(a.node, float(self.wheel_rev[w]),
                               float(self._wheel_speed[w]) / (2.0 * math.pi))

    def _bus_frame(self, a: AxisState) -> BusVoltageCurrent:
        w = self.wheel_of(a.node)
        power_w = float(self.wheel_torques()[w] * self._wheel_speed[w])
        return BusVoltageCurrent(a.node, BUS_VOLTAGE_V, power_w / BUS_VOLTAGE_V)

    def _send(self, msg: Frame) -> None:
        if self._silent(msg.node):
            self.counters.silenced += 1
            return
        try:
            frame = self.protocol.encode(msg)
        except ValueError:  # e.g. the bus current of wheels driven hard with no torque limit
            self.counters.unencodable += 1
            return
        self._send_frame(frame, msg.node)

    # --- frames in --------------------------------------------------------------------
    def _handle(self, frame: can.Message) -> None:
        msg = self.protocol.decode(frame)
        if msg is None:
            return
        if self._silent(msg.node):
            self.counters.silenced += 1
            return
        self._apply(self.axes[self.wheel_of(msg.node)], msg)

    def _apply(self, a: AxisState, msg: Frame) -> None:
        now = self.t
        match msg:
            case SetInputTorque():
                a.torque_setpoint_nm = msg.torque_nm
                a.last_torque_s = now
            case SetControllerMode():
                a.control_mode, a.input_mode = msg.control_mode, msg.input_mode
                if a.armed and not self._torque_mode(a):
                    self._disarm(a, AXIS_ERROR_INVALID_STATE)
            case SetAxisState() if msg.state == AXIS_STATE_IDLE:
                a.state, a.torque_setpoint_nm = AXIS_STATE_IDLE, 0.0
            case SetAxisState() if msg.state == AXIS_STATE_CLOSED_LOOP_CONTROL:
                if a.armed:
                    return
                if a.axis_error or not self._torque_mode(a):
                    self._disarm(a, AXIS_ERROR_INVALID_STATE)
                    return
                if a.node == self.faults.refuse_enable_node:
                    return  # its enable input is off: it stays idle, without an error
                a.state, a.torque_setpoint_nm, a.last_torque_s = AXIS_STATE_CLOSED_LOOP_CONTROL, 0.0, now
                self.armed_now()
                a.procedure_result = 0
            case SetAxisState():
                self._disarm(a, AXIS_ERROR_INVALID_STATE)
            case Estop():
                self._disarm(a, AXIS_ERROR_ESTOP_REQUESTED)
            case ClearErrors():
                a.axis_error = 0
                a.procedure_result = 0
            case Request() if msg.cmd == CMD_HEARTBEAT:
                self._send(self._heartbeat(a))
            case Request() if msg.cmd == CMD_GET_ERROR:
                self._send(DriverErrors(a.node, a.axis_error, a.disarm_reason))
            case Request() if msg.cmd == CMD_GET_ENCODER_ESTIMATES:
                self._send(self._encoder_frame(a))
            case Request() if msg.cmd == CMD_GET_BUS_VOLTAGE_CURRENT:
                self._send(self._bus_frame(a))

    @staticmethod
    def _torque_mode(a: AxisState) -> bool:
        return a.control_mode == CONTROL_MODE_TORQUE_CONTROL and a.input_mode == INPUT_MODE_PASSTHROUGH

    @staticmethod
    def _disarm(a: AxisState, error_bits: int) -> None:
        a.axis_error |= error_bits
        a.disarm_reason = error_bits
        a.state, a.torque_setpoint_nm = AXIS_STATE_IDLE, 0.0
