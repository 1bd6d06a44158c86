"""Drive emulators: one robot's four wheel drives and its dynamics on a CAN bus
(several robots in one process: :mod:`bridges.fleet_emulator`).

They let the whole chain (bridge, agents) run without hardware: a host on the same
python-can bus (``virtual`` in one process, ``udp_multicast`` across processes,
socketcan/pcan/... unchanged) sees four drives of a protocol. This module holds
what every protocol's emulator shares, :class:`RobotEmulator`: the robot's dynamics,
the wheels' angles, time, ground truth and the injected faults on the bus. A
protocol's emulator (:mod:`bridges.odrive_emulator`, :mod:`bridges.cia402_emulator`)
adds its drives: the frames they take and send, their states, the torque each
applies (:meth:`RobotEmulator.wheel_torques`).

Dynamics: eq. (4) for this one robot via :class:`plant.model_plant.ModelPlant`
(RK4, one sub-step per physics tick: the robot's time constants are >= 0.1 s, a
tick is 1 ms), from the scenario's initial state, with the scenario's disturbance
from the moment the robot's drives are first armed (:class:`ArmedDisturbance`).
Wheel ``w`` is driven by ``node_ids[w]``, in the wheel order of
``plant.mecanum.wheel_matrix``; its angle (turns, integrated from power-up) follows
its speed theta_dot = P T(phi)^T q_dot / R.

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

from bridges.driver import FrameCounters
from bridges.udp_can import send_frames
from plant.disturbance import StartedDisturbance, make_disturbance
from plant.mecanum import MecanumModel
from plant.model_plant import ModelPlant


class Fleet(Protocol):
    """What the emulator reads of a scenario (deploy.contract.scenario.Scenario is one):
    bridges/ stands below deploy/ and takes it by its shape."""

    spec: Any  # .disturbance (kind, scale, constant_nm), .limits.max_wheel_torque_nm

    def index_of(self, robot_id: int) -> int: ...
    def model(self) -> MecanumModel: ...
    def initial_state(self) -> tuple[np.ndarray, np.ndarray]: ...


# frames read per step at most: a busy bus cannot stall the physics. Frames keep coming
# while a step reads (a host sends ~6 per control period, and every frame the drives
# send comes back on udp_multicast); reading until the bus was empty once kept a CiA 402
# fleet emulator, whose drives answer every SYNC, reading for 150 ms at a time while its
# physics fell seconds behind. What is left waits for the next step (a tick, or a batch).
MAX_FRAMES_PER_STEP = 256


@dataclass(frozen=True)
class EmulatorFaults:
    """Faults injected by the emulator (all off by default)."""

    drop_rate: float = 0.0  # probability each frame (both directions) is lost
    corrupt_rate: float = 0.0  # probability an outgoing frame gets 1-3 random bits flipped
    silent_node: int | None = None  # this node id stops answering (no frames, ignores commands) ...
    silent_after_s: float = 0.0  # ... from this time on
    seed: int = 0
    refuse_enable_node: int | None = None  # this drive never enables (safe torque off active)

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


class ArmedDisturbance(StartedDisturbance):
    """The scenario's disturbance d(t) as emulated robots feel it: none before a
    robot's drives are first armed, then d evaluated on that robot's run clock
    (t - the emulator time of its first arming), held afterwards whatever the axes do.

    The scenario defines d(t) for the run, t >= 0. Evaluated from the emulator's own
    start it pushed the unpowered robots for the 0.4-2 s the other processes took to
    come up (1.1 cm and 0.008 rad on lab before t = 0), motion no bridge can have
    counted if it was not listening yet and that a robot standing on a floor with its
    drives idle does not make. Rows: robots (a fleet emulator's plant has several).
    The model plant evaluates it in its kernel (plant/disturbance.py)."""

    def armed(self, row: int, t: float) -> None:
        """Robot ``row``'s drives entered closed loop at emulator time ``t``."""
        self.begin(row, t)


class RobotEmulator:
    """Robot ``robot_id``'s dynamics and four drives of some protocol on ``bus``.

    Time is the emulator's own, from 0 at construction: :meth:`step` advances it to
    ``now_s`` (tests drive it with a virtual clock), :meth:`run` on ``time.monotonic``.
    A protocol's emulator implements :meth:`wheel_torques`, :meth:`_handle` (one
    received frame) and, where its drives act on the clock, :meth:`_drives_tick`
    (watchdogs, ramps), :meth:`_encoders_due` and :meth:`_clock_due`.
    """

    def __init__(self, sc: Fleet, robot_id: int, bus: can.BusABC,
                 node_ids: Sequence[int], encoder_rate_hz: float = 200.0,
                 watchdog_timeout_s: float = 0.2, physics_rate_hz: float = 1000.0,
                 faults: EmulatorFaults = EmulatorFaults()) -> None:  # noqa: B008 - frozen
        ids = [int(n) for n in node_ids]
        if len(ids) != 4 or len(set(ids)) != 4:
            raise ValueError(f"a mecanum robot has 4 wheels: give 4 distinct node ids, got {ids}")
        for name, hz in (("physics_rate_hz", physics_rate_hz), ("encoder_rate_hz", encoder_rate_hz)):
            if not (math.isfinite(hz) and hz > 0):
                raise ValueError(f"{name} must be positive, got {hz}")
        if encoder_rate_hz > physics_rate_hz:
            raise ValueError("the encoder rate cannot exceed physics_rate_hz")
        if not (math.isfinite(watchdog_timeout_s) and watchdog_timeout_s >= 0):
            raise ValueError(f"watchdog_timeout_s must be >= 0 (0: off), got {watchdog_timeout_s}")
        for what, node in (("silent node", faults.silent_node),
                           ("refuse-enable node", faults.refuse_enable_node)):
            if node is not None and node not in ids:
                raise ValueError(f"{what} {node} is not one of the node ids {ids}")
        index = sc.index_of(robot_id)
        self.sc, self.robot_id, self.bus = sc, robot_id, bus
        self.node_ids = tuple(ids)
        self.faults = faults
        self.watchdog_timeout_s = float(watchdog_timeout_s)
        self.counters = EmulatorCounters()
        self._outbox: list[can.Message] = []  # this step's frames, sent together (flush_frames)
        self._wheel_of = {n: w for w, n in enumerate(ids)}
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
        self._next_encoder = 0.0
        self._row = 0  # this robot's row in self.plant (shared by a FleetEmulator)
        # the wheels' kinematics on floats (the physics' tick, a robot after another):
        # numpy on four numbers cost more in dispatch than in arithmetic, cold after the
        # emulator's sleep (bridges/odometry.py)
        self._wheel_rows = tuple(tuple(float(v) for v in row) for row in self.model.P)
        self._wheel_speed = self._wheel_speeds_now()
        self.wheel_rev = [0.0] * 4  # each wheel's angle (turns) since power-up
        self.truth: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.lag: list[tuple[float, float]] = []  # realtime: (t, how far behind the wall clock)
        self.monotonic_origin_s = math.nan  # realtime: time.monotonic() at t = 0
        self._started = False

    # --- what a protocol's emulator adds ------------------------------------------------
    def wheel_torques(self) -> np.ndarray:
        """Torques the drives apply to the wheels now (N m), within the scenario's limit."""
        raise NotImplementedError

    def _handle(self, frame: can.Message) -> None:
        """One frame read from the bus (at the current time), after the injected loss."""
        raise NotImplementedError

    def _drives_tick(self, now: float) -> None:
        """After the physics advanced to ``now``: watchdogs, ramps."""

    def _encoders_due(self, send: bool) -> None:
        """The encoder-rate instant has come (``send`` False: the emulator is behind and
        sheds them)."""

    def _clock_due(self, now: float) -> None:
        """Frames the drives send on their own clock (heartbeats)."""

    def describe_drives(self) -> str:
        """Each drive's state and fault, for a summary line."""
        raise NotImplementedError

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

    def wheel_speeds_radps(self) -> np.ndarray:
        return np.array(self._wheel_speed)

    def _wheel_speeds_now(self) -> list[float]:
        """theta_dot = (1/R) P T(phi)^T q_dot (the inverse of eq. 1; MecanumModel.wheel_speeds)
        at the robot's state now."""
        phi = self.q.tolist()[2]
        vx, vy, w = self.q_dot.tolist()
        c, s = math.cos(phi), math.sin(phi)
        bx, by = c * vx + s * vy, -s * vx + c * vy  # T(phi)^T q_dot
        r = self.model.params.wheel_radius_m
        return [(p0 * bx + p1 * by + p2 * w) / r for p0, p1, p2 in self._wheel_rows]

    def wheel_speed(self, wheel: int) -> float:
        """Wheel ``wheel``'s speed now (rad/s)."""
        return float(self._wheel_speed[wheel])

    def wheel_of(self, node: int) -> int:
        return self._wheel_of[node]

    def sample_lead_s(self) -> float:
        """Realtime: how far the wall clock is past the physics' newest tick (at most a
        tick), for a drive that samples on a frame (a CiA 402 SYNC) between ticks; 0 on a
        virtual clock."""
        return min(self.behind_s(), self._h)

    def behind_s(self) -> float:
        """Realtime: how far the wall clock is past the physics' newest tick; more than a
        tick while the emulator reads a backlog (it was off the CPU). 0 on a virtual clock."""
        if not math.isfinite(self.monotonic_origin_s):
            return 0.0
        return max(time.monotonic() - self.monotonic_origin_s - self.t, 0.0)

    def armed_now(self) -> None:
        """A drive of this robot was armed (enabled) now: the disturbance starts."""
        self.disturbance.armed(self._row, self.t)

    def _silent(self, node: int) -> bool:
        f = self.faults
        return f.silent_node == node and self.t >= f.silent_after_s

    def clamp(self, torque_nm: float) -> float:
        """A torque within the scenario's wheel torque limit."""
        lim = self.max_torque_nm
        return min(max(torque_nm, -lim), lim)

    # --- time -------------------------------------------------------------------------
    def step(self, now_s: float) -> None:
        """Advance to ``now_s``: apply the frames received so far (at the current time),
        then integrate tick by tick, checking the drives and sending due cyclic frames."""
        if not self._started:  # the frames due at t = 0
            self._started = True
            self._send_due()
        self._receive()
        n = math.floor(now_s / self._h + 1e-9) - self._ticks
        for _ in range(max(n, 0)):
            self._tick()
            self.flush_frames()  # each tick's frames at that tick
        self.flush_frames()

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
        """Bookkeeping once the physics has advanced ``ticks`` ticks: wheel angles, the
        drives, the cyclic frames due (encoder frames only if ``send_encoders``: a
        realtime emulator catching up skips the stale ones)."""
        h = self._h * ticks
        self._ticks += ticks
        w_old, w_new = self._wheel_speed, self._wheel_speeds_now()
        self._wheel_speed = w_new
        two_pi, rev = 2.0 * math.pi, self.wheel_rev
        for j in range(4):
            rev[j] += 0.5 * (w_old[j] + w_new[j]) * h / two_pi
        self._drives_tick(self.t)
        self._send_due(send_encoders)

    def _send_due(self, send_encoders: bool = True) -> None:
        """The cyclic frames due at the current time (and a truth sample at the encoder
        rate)."""
        now = self.t
        if now >= self._next_encoder - 1e-9:
            self._next_encoder = max(self._next_encoder + self._encoder_period, now)
            self.truth.append((now, self.q.copy(), self.q_dot.copy()))
            self._encoders_due(send_encoders)
        self._clock_due(now)

    # --- the bus, with the injected faults -----------------------------------------------
    def _send_frame(self, frame: can.Message, node: int) -> None:
        """Put one of drive ``node``'s frames on the bus (or lose or corrupt it)."""
        if self._silent(node):
            self.counters.silenced += 1
            return
        frame.timestamp = self.t
        rng = self._rng
        if self.faults.drop_rate > 0 and rng.random() < self.faults.drop_rate:
            self.counters.dropped_by_fault += 1
            return
        if self.faults.corrupt_rate > 0 and frame.dlc > 0 and rng.random() < self.faults.corrupt_rate:
            frame.data = flip_bits(bytes(frame.data), rng)
            self.counters.corrupted_by_fault += 1
        self._outbox.append(frame)

    def flush_frames(self) -> None:
        """Send the frames of this step, together where the bus can (one datagram on the
        emulated bus, bridges/udp_can.py: the robot's four encoder estimates of a tick
        went out as four, and woke their bridge four times)."""
        out = self._outbox
        if not out:
            return
        self._outbox = []
        try:
            send_frames(self.bus, out)
        except can.CanError:
            self.counters.send_errors += len(out)
            return
        self.counters.sent += len(out)

    def _receive(self) -> None:
        for _ in range(MAX_FRAMES_PER_STEP):
            frame = self.bus.recv(timeout=0)
            if frame is None:
                return
            self.counters.received += 1
            if self.faults.drop_rate > 0 and self._rng.random() < self.faults.drop_rate:
                self.counters.dropped_by_fault += 1
                continue
            self._handle(frame)

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
                 monotonic_origin_s=self.monotonic_origin_s,
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
