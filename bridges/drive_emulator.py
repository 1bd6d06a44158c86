"""Drive emulator: four ODrive CANSimple axes and one robot's dynamics on a CAN bus
(several robots in one process: :mod:`bridges.fleet_emulator`).

It lets the whole chain (bridge, agents) run without hardware: a host on the same
python-can bus (``virtual`` in one process, ``udp_multicast`` across processes,
socketcan/pcan/... unchanged) sees four drives that arm, take torque setpoints,
report encoder estimates and heartbeats, trip their watchdog and obey Estop.

Axes
----
``node_ids[w]`` drives wheel ``w`` in the wheel order of ``plant.mecanum.wheel_matrix``.
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

Frames sent: a Heartbeat per axis at ``heartbeat_rate_hz``, Get_Encoder_Estimates
per axis at ``encoder_rate_hz`` (wheel angle in turns, integrated from power-up; wheel
speed theta_dot / 2 pi with theta_dot = P T(phi)^T q_dot / R). Get_Error and
Get_Bus_Voltage_Current are answered on request (a remote frame), as ODrive does by
default; the bus is a constant 24 V and the bus current the ideal electrical power
tau * theta_dot / 24 V of the axis.

Dynamics: eq. (4) for this one robot via :class:`plant.model_plant.ModelPlant`
(RK4, one sub-step per physics tick: the robot's time constants are >= 0.1 s, a
tick is 1 ms), from the scenario's initial state, with the scenario's disturbance
from the moment the robot's drives are first armed (:class:`ArmedDisturbance`).

Faults (:class:`EmulatorFaults`) are drawn from a seeded numpy Generator, so a run
of the same frames at the same times is reproducible.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import can
import numpy as np

from bridges.protocol import (
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
    FrameCounters,
    Heartbeat,
    OdriveCanSimple,
    Request,
    SetAxisState,
    SetControllerMode,
    SetInputTorque,
)
from plant.disturbance import make_disturbance
from plant.mecanum import MecanumModel
from plant.model_plant import ModelPlant


class Fleet(Protocol):
    """What the emulator reads of a scenario (deploy.contract.scenario.Scenario is one):
    bridges/ stands below deploy/ and takes it by its shape."""

    spec: Any  # .disturbance (kind, scale, constant_nm), .limits.max_wheel_torque_nm

    def index_of(self, robot_id: int) -> int: ...
    def model(self) -> MecanumModel: ...
    def initial_state(self) -> tuple[np.ndarray, np.ndarray]: ...


BUS_VOLTAGE_V = 24.0
MAX_FRAMES_PER_STEP = 10_000  # a flooded bus cannot stall the physics forever


@dataclass(frozen=True)
class EmulatorFaults:
    """Faults injected by the emulator (all off by default)."""

    drop_rate: float = 0.0  # probability each frame (both directions) is lost
    corrupt_rate: float = 0.0  # probability an outgoing frame gets 1-3 random bits flipped
    silent_node: int | None = None  # this node id stops answering (no frames, ignores commands) ...
    silent_after_s: float = 0.0  # ... from this time on
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("drop_rate", "corrupt_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if not (math.isfinite(self.silent_after_s) and self.silent_after_s >= 0.0):
            raise ValueError(f"silent_after_s must be >= 0, got {self.silent_after_s}")


@dataclass
class EmulatorCounters:
    sent: int = 0  # frames put on the bus
    received: int = 0  # frames read from the bus
    dropped_by_fault: int = 0  # frames lost by drop_rate (either direction)
    corrupted_by_fault: int = 0  # outgoing frames with flipped bits
    silenced: int = 0  # frames the silent node did not send, plus commands it ignored
    send_errors: int = 0  # bus.send raised (buffer full, bus off)
    unencodable: int = 0  # a value the protocol cannot carry (a bus current beyond its bound)
    shed: int = 0  # encoder frames not sent: stale, the realtime emulator was catching up
    protocol: FrameCounters = field(default_factory=FrameCounters)

    def summary(self) -> str:
        p = self.protocol
        return (f"sent {self.sent}, received {self.received} (decoded {p.decoded}, "
                f"unknown id {p.unknown_id}, bad length {p.bad_length}, invalid {p.invalid}, "
                f"other direction {p.ignored_direction}, other frames {p.other_frame}), "
                f"dropped by fault {self.dropped_by_fault}, corrupted by fault "
                f"{self.corrupted_by_fault}, silenced {self.silenced}, send errors "
                f"{self.send_errors}, unencodable {self.unencodable}, shed while behind "
                f"{self.shed}")

    def as_dict(self) -> dict:
        return asdict(self)


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
    position_rev: float = 0.0

    @property
    def armed(self) -> bool:
        return self.state == AXIS_STATE_CLOSED_LOOP_CONTROL


class ArmedDisturbance:
    """The scenario's disturbance d(t) as emulated robots feel it: none before a
    robot's drives are first armed, then d evaluated on that robot's run clock
    (t - the emulator time of its first arming), held afterwards whatever the axes do.

    The scenario defines d(t) for the run, t >= 0. Evaluated from the emulator's own
    start it pushed the unpowered robots for the 0.4-2 s the other processes took to
    come up (1.1 cm and 0.008 rad on lab before t = 0), motion no bridge can have
    counted if it was not listening yet and that a robot standing on a floor with its
    drives idle does not make. Rows: robots (a fleet emulator's plant has several)."""

    def __init__(self, disturbance: Callable[[float], np.ndarray], robots: int) -> None:
        self._d = disturbance
        self._since: list[float | None] = [None] * robots
        self._zero = np.zeros((robots, 4))

    def armed(self, row: int, t: float) -> None:
        """Robot ``row``'s drives entered closed loop at emulator time ``t``."""
        if self._since[row] is None:
            self._since[row] = t

    def __call__(self, t: float) -> np.ndarray:
        if all(s is None for s in self._since):
            return self._zero
        return np.array([self._zero[0] if s is None else self._d(t - s) for s in self._since])


class DriverEmulator:
    """Four CANSimple drives plus robot ``robot_id``'s dynamics on ``bus``.

    Time is the emulator's own, from 0 at construction: :meth:`step` advances it to
    ``now_s`` (tests drive it with a virtual clock), :meth:`run` on ``time.monotonic``.
    """

    def __init__(self, sc: Fleet, robot_id: int, bus: can.BusABC,
                 node_ids: Sequence[int] = (0, 1, 2, 3), encoder_rate_hz: float = 200.0,
                 heartbeat_rate_hz: float = 10.0, watchdog_timeout_s: float = 0.2,
                 physics_rate_hz: float = 1000.0,
                 faults: EmulatorFaults = EmulatorFaults()) -> None:  # noqa: B008 - frozen
        ids = [int(n) for n in node_ids]
        if len(ids) != 4:
            raise ValueError(f"a mecanum robot has 4 wheels: give 4 node ids, got {ids}")
        for name, hz in (("physics_rate_hz", physics_rate_hz), ("encoder_rate_hz", encoder_rate_hz),
                         ("heartbeat_rate_hz", heartbeat_rate_hz)):
            if not (math.isfinite(hz) and hz > 0):
                raise ValueError(f"{name} must be positive, got {hz}")
        if encoder_rate_hz > physics_rate_hz or heartbeat_rate_hz > physics_rate_hz:
            raise ValueError("encoder and heartbeat rates cannot exceed physics_rate_hz")
        if not (math.isfinite(watchdog_timeout_s) and watchdog_timeout_s >= 0):
            raise ValueError(f"watchdog_timeout_s must be >= 0 (0: off), got {watchdog_timeout_s}")
        if faults.silent_node is not None and faults.silent_node not in ids:
            raise ValueError(f"silent node {faults.silent_node} is not one of the node ids {ids}")
        index = sc.index_of(robot_id)
        self.sc, self.robot_id, self.bus = sc, robot_id, bus
        self.node_ids = tuple(ids)
        self.faults = faults
        self.watchdog_timeout_s = float(watchdog_timeout_s)
        self.protocol = OdriveCanSimple(ids, role="drive")
        self.counters = EmulatorCounters(protocol=self.protocol.counters)
        self.axes = [AxisState(n) for n in ids]
        self._axis_of = {n: w for w, n in enumerate(ids)}
        self.model = sc.model()
        q, qd = sc.initial_state()
        d = sc.spec.disturbance
        self.disturbance = ArmedDisturbance(
            make_disturbance(d.kind, d.scale, tuple(d.constant_nm)), 1)
        self.plant = ModelPlant([self.model], q[index:index + 1], qd[index:index + 1],
                                self.disturbance, substeps=1)
        limit = sc.spec.limits.max_wheel_torque_nm
        self.max_torque_nm = float(limit) if math.isfinite(limit) else math.inf
        self._h = 1.0 / physics_rate_hz
        self._ticks = 0
        self._rng = np.random.default_rng(faults.seed)
        self._encoder_period = 1.0 / encoder_rate_hz
        self._heartbeat_period = 1.0 / heartbeat_rate_hz
        self._next_encoder = 0.0
        self._next_heartbeat = 0.0
        self._row = 0  # this robot's row in self.plant (shared by a FleetEmulator)
        self._wheel_speed = self.model.wheel_speeds(float(self.q[2]), self.q_dot)
        self.truth: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.lag: list[tuple[float, float]] = []  # realtime: (t, how far behind the wall clock)
        self._started = False

    # --- state ------------------------------------------------------------------------
    @property
    def t(self) -> float:
        """The emulator's time (s): a whole number of physics ticks."""
        return self._ticks * self._h

    @property
    def q(self) -> np.ndarray:
        return self.plant.q[self._row]

    @property
    def q_dot(self) -> np.ndarray:
        return self.plant.q_dot[self._row]

    def wheel_torques(self) -> np.ndarray:
        """Torques applied to the wheels now (N m): setpoint in closed loop, clamped; else 0."""
        lim = self.max_torque_nm
        return np.array([min(max(a.torque_setpoint_nm, -lim), lim) if a.armed else 0.0
                         for a in self.axes])

    def wheel_speeds_radps(self) -> np.ndarray:
        return self._wheel_speed.copy()

    def _silent(self, node: int) -> bool:
        f = self.faults
        return f.silent_node == node and self.t >= f.silent_after_s

    # --- time -------------------------------------------------------------------------
    def step(self, now_s: float) -> None:
        """Advance to ``now_s``: apply the frames received so far (at the current time),
        then integrate tick by tick, checking watchdogs and sending due cyclic frames."""
        if not self._started:  # the frames due at t = 0
            self._started = True
            self._send_due()
        self._receive()
        n = math.floor(now_s / self._h + 1e-9) - self._ticks
        for _ in range(max(n, 0)):
            self._tick()

    def run(self, stop: Callable[[], bool], duration_s: float | None = None) -> None:
        """Realtime: step every physics tick on ``time.monotonic`` until ``stop()`` or
        ``duration_s`` (emulator time) is reached."""
        origin = time.monotonic() - self.t
        self.monotonic_origin_s = origin  # truth time t is time.monotonic() - this
        while not stop():
            now = time.monotonic() - origin
            if duration_s is not None and now >= duration_s:
                self.step(duration_s)
                return
            self.step(now)
            delay = (self._ticks + 1) * self._h - (time.monotonic() - origin)
            if delay > 0:
                time.sleep(delay)

    def _tick(self) -> None:
        self.plant.step(self.t, self._h, self.wheel_torques()[None, :], None)
        self._after_physics()

    def _after_physics(self, send_encoders: bool = True, ticks: int = 1) -> None:
        """Bookkeeping once the physics has advanced ``ticks`` ticks: encoder angles,
        watchdogs, the cyclic frames due (encoder estimates only if ``send_encoders``:
        a realtime emulator catching up skips the stale ones)."""
        h = self._h * ticks
        self._ticks += ticks
        w_old, w_new = self._wheel_speed, self.model.wheel_speeds(float(self.q[2]), self.q_dot)
        self._wheel_speed = w_new
        for a, wo, wn in zip(self.axes, w_old, w_new, strict=True):
            a.position_rev += 0.5 * (wo + wn) * h / (2.0 * math.pi)
        now = self.t
        if self.watchdog_timeout_s > 0:
            for a in self.axes:
                if a.armed and now - a.last_torque_s > self.watchdog_timeout_s + 1e-12:
                    self._disarm(a, AXIS_ERROR_WATCHDOG_TIMER_EXPIRED)
        self._send_due(send_encoders)

    def _send_due(self, send_encoders: bool = True) -> None:
        """The cyclic frames due at the current time (and a truth sample with the encoders)."""
        now = self.t
        if now >= self._next_encoder - 1e-9:
            self._next_encoder = max(self._next_encoder + self._encoder_period, now)
            self.truth.append((now, self.q.copy(), self.q_dot.copy()))
            if send_encoders:
                for a in self.axes:
                    self._send(self._encoder_frame(a))
            else:
                self.counters.shed += len(self.axes)
        if now >= self._next_heartbeat - 1e-9:
            self._next_heartbeat = max(self._next_heartbeat + self._heartbeat_period, now)
            for a in self.axes:
                self._send(self._heartbeat(a))

    # --- frames out -------------------------------------------------------------------
    def _heartbeat(self, a: AxisState) -> Heartbeat:
        return Heartbeat(a.node, a.axis_error, a.state, a.procedure_result, True)

    def _encoder_frame(self, a: AxisState) -> EncoderEstimate:
        w = self._wheel_speed[self._axis_of[a.node]]
        return EncoderEstimate(a.node, a.position_rev, float(w) / (2.0 * math.pi))

    def _bus_frame(self, a: AxisState) -> BusVoltageCurrent:
        w = self._axis_of[a.node]
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
        frame.timestamp = self.t
        rng = self._rng
        if self.faults.drop_rate > 0 and rng.random() < self.faults.drop_rate:
            self.counters.dropped_by_fault += 1
            return
        if self.faults.corrupt_rate > 0 and frame.dlc > 0 and rng.random() < self.faults.corrupt_rate:
            frame.data = flip_bits(bytes(frame.data), rng)
            self.counters.corrupted_by_fault += 1
        try:
            self.bus.send(frame, timeout=0.01)
        except can.CanError:
            self.counters.send_errors += 1
            return
        self.counters.sent += 1

    # --- frames in --------------------------------------------------------------------
    def _receive(self) -> None:
        for _ in range(MAX_FRAMES_PER_STEP):
            frame = self.bus.recv(timeout=0)
            if frame is None:
                return
            self.counters.received += 1
            if self.faults.drop_rate > 0 and self._rng.random() < self.faults.drop_rate:
                self.counters.dropped_by_fault += 1
                continue
            msg = self.protocol.decode(frame)
            if msg is None:
                continue
            if self._silent(msg.node):
                self.counters.silenced += 1
                continue
            self._apply(self.axes[self._axis_of[msg.node]], msg)

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
                a.state, a.torque_setpoint_nm, a.last_torque_s = AXIS_STATE_CLOSED_LOOP_CONTROL, 0.0, now
                self.disturbance.armed(self._row, now)
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

    # --- ground truth -----------------------------------------------------------------
    def save_truth(self, path: str | Path) -> None:
        """``t`` (k,), ``q`` (k,3), ``q_dot`` (k,3) at the encoder rate, as npz; after
        :meth:`run`, ``monotonic_origin_s`` too (t + it = this host's time.monotonic(),
        the clock every process of the host shares: other processes' samples can be
        matched to the truth in time)."""
        t = np.array([s[0] for s in self.truth], float)
        q = np.array([s[1] for s in self.truth], float).reshape(-1, 3)
        qd = np.array([s[2] for s in self.truth], float).reshape(-1, 3)
        lag = np.array(self.lag, float).reshape(-1, 2)
        np.savez(path, t=t, q=q, q_dot=qd, robot_id=self.robot_id,
                 node_ids=np.array(self.node_ids),
                 monotonic_origin_s=getattr(self, "monotonic_origin_s", np.nan),
                 lag_t=lag[:, 0], lag_s=lag[:, 1],
                 dropped_by_fault=self.counters.dropped_by_fault,
                 corrupted_by_fault=self.counters.corrupted_by_fault)


def flip_bits(data: bytes, rng: np.random.Generator) -> bytes:
    """``data`` with 1-3 distinct random bits flipped (never the same bytes back)."""
    out = bytearray(data)
    nbits = 8 * len(out)
    k = min(int(rng.integers(1, 4)), nbits)
    for bit in rng.choice(nbits, size=k, replace=False):
        out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out)
