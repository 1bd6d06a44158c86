"""Four CiA 402 servo drives over CANopen on the robot emulator
(:mod:`bridges.drive_emulator`: the same dynamics, wheel angles, time, truth and bus
faults as the ODrive emulator's).

Each drive is a canopen :class:`canopen.LocalNode` built from the EDS
(``bridges/cia402_drive.eds`` by default): canopen's SDO server answers the host's
configuration, its NMT slave keeps the NMT state and produces the heartbeat (on the
emulator's clock: its periodic sends are tasks the emulator ticks), and its PDO maps,
re-read from the object dictionary when the drive enters OPERATIONAL, say what the
RPDOs carry and the TPDOs send. What the drive does with it:

* Boot: a boot-up message, NMT pre-operational, the heartbeat of 0x1017; the power
  state machine in SWITCH ON DISABLED (:mod:`bridges.cia402`). NMT reset node /
  reset communication boot again with the EDS's values (all of them / 0x1000-0x1FFF).
* PDOs only in NMT OPERATIONAL. An RPDO is applied on receipt (transmission type
  254/255) or at the next SYNC (0-240), written into the object dictionary like an
  SDO download: the controlword drives the state machine (every transition of the
  standard, the fault reset on a rising edge of bit 7). On SYNC the drive samples
  position, velocity and torque and sends its synchronous TPDOs (type n: every n-th).
* Torque only in OPERATION ENABLED and a torque mode (0x6060 = 10 cyclic synchronous
  torque, or 4 profile torque, which ramps to the target at 0x6087): target torque
  (per mille of 0x6076, within 0x6072) x gear ratio (0x6091) at the wheel, clamped to
  the scenario's limit. QUICK STOP ACTIVE ramps the torque it applied to zero at
  0x6087, then (option codes 1-4, 0x605A) goes to SWITCH ON DISABLED; option 0 at once.
* Watchdogs, while OPERATION ENABLED: no SYNC for ``watchdog_timeout_s`` -> FAULT
  0x8100; the host's heartbeat (0x1016: its node id and time) missing beyond its
  time, once heard -> FAULT 0x8130. A fault zeroes the torque, sends an EMCY and
  stays until a fault reset (which sends the EMCY "error reset").
* Fault injection beside the bus faults: ``EmulatorFaults.refuse_enable_node`` never
  enters OPERATION ENABLED (as a drive whose safe torque off input is active: it
  stays SWITCHED ON).

Units: position actual in increments (0x608F per motor turn, times the gear ratio per
wheel turn; int32, wrapping), velocity actual in increments per second, torque actual
and target in per mille of the rated torque.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
from canopen.nmt import COMMAND_TO_STATE
from canopen.sdo import SdoAbortedError

from bridges import cia402 as p
from bridges.cia402_driver import DEFAULT_EDS, Units, load_od, units_of
from bridges.cia402_pdo import PdoLayout
from bridges.drive_emulator import EmulatorFaults, Fleet, RobotEmulator
from bridges.driver import FrameCounters

NMT_ENTER_PRE_OPERATIONAL = 0x80  # the NMT command codes canopen's slave takes
NMT_RESET_NODE, NMT_RESET_COMMUNICATION = 129, 130
SYNC_COB_ID = 0x080
ABORT_VALUE_RANGE = 0x06090030  # SDO abort: value range of parameter exceeded
TORQUE_MODES = (p.MODE_CYCLIC_SYNC_TORQUE, p.MODE_PROFILE_TORQUE)
ERROR_REGISTER_GENERIC_COMMUNICATION = 0x11  # 0x1001 bits 0 (generic) and 4 (communication)
# the objects the drive's behaviour reads (cached; a write makes the cache stale)
PARAMETERS = frozenset({p.MODES_OF_OPERATION, p.MAX_TORQUE, p.QUICK_STOP_OPTION_CODE,
                        p.TORQUE_SLOPE, p.MOTOR_RATED_TORQUE, p.GEAR_RATIO,
                        p.POSITION_ENCODER_RESOLUTION, p.CONSUMER_HEARTBEAT_TIME})
POSITIVE = frozenset({p.MOTOR_RATED_TORQUE, p.GEAR_RATIO, p.POSITION_ENCODER_RESOLUTION})
# the objects the drive samples (at a SYNC, or as an SDO upload reads them), not the store's
LIVE = frozenset({p.STATUSWORD, p.MODES_OF_OPERATION_DISPLAY, p.POSITION_ACTUAL,
                  p.VELOCITY_ACTUAL, p.TORQUE_ACTUAL, p.ERROR_CODE, 0x1001})
TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class _Params:
    """What a drive's behaviour reads of its object dictionary, read once per change."""

    mode: int
    max_torque: int  # per mille
    quick_stop_option: int
    slope_nm_s: float  # the torque slope at the wheel (N m/s)
    units: Units
    consumers: tuple[tuple[int, float], ...]  # (producer node, heartbeat time s) of 0x1016
    nm_per_mille: float  # units.wheel_nm_per_mille, read at every physics tick
    increments_per_rev: float  # units.increments_per_wheel_rev, at every SYNC


class _ClockedTask:
    """What canopen's ``Network.send_periodic`` returns, sent on the emulator's clock."""

    def __init__(self, drive: _Drive, can_id: int, data: Any, period_s: float) -> None:
        self.drive, self.can_id, self.period_s = drive, can_id, float(period_s)
        self.data = bytes(data or b"")
        self.next_at = drive.emu.t  # python-can's periodic tasks send at once
        self.active = True

    def stop(self) -> None:
        self.active = False

    def update(self, data: Any) -> None:
        self.data = bytes(data)

    def due(self, now: float) -> None:
        if self.active and self.period_s > 0 and now >= self.next_at - 1e-9:
            self.next_at = max(self.next_at + self.period_s, now)
            self.drive.send(self.can_id, self.data)


class _DriveNetwork(canopen.Network):
    """One emulated drive's view of the bus: what its canopen LocalNode sends goes to
    the emulator (its faults, its clock); what it receives, the emulator hands it."""

    def __init__(self, drive: _Drive) -> None:
        super().__init__(None)
        self._drive = drive

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._drive.send(can_id, data)

    def send_periodic(self, can_id: int, data: bytes, period: float,  # type: ignore[override]
                      remote: bool = False) -> _ClockedTask:
        task = _ClockedTask(self._drive, can_id, data, period)
        self._drive.tasks.append(task)
        return task


class _Drive:
    """One emulated CiA 402 drive: a canopen LocalNode and the profile's behaviour."""

    def __init__(self, emu: Cia402Emulator, node_id: int, eds: Path, heartbeat_ms: int,
                 refuse_enable: bool) -> None:
        self.emu, self.id, self.eds = emu, node_id, eds
        self.wheel = emu.wheel_of(node_id)
        self.refuse_enable = refuse_enable
        self.tasks: list[_ClockedTask] = []
        self.network = _DriveNetwork(self)
        self.node = self.network.create_node(node_id, load_od(eds, node_id))
        self.node.add_read_callback(self._read)
        self.node.add_write_callback(self._write)
        self.heartbeat_ms = heartbeat_ms
        self.state = p.State.NOT_READY_TO_SWITCH_ON
        self.previous_cw = 0
        self.target = 0  # per mille
        self.applied_nm = 0.0  # the torque on the wheel now
        self.error_code = 0
        self.enabled_at = 0.0
        self.last_sync: float | None = None
        self.syncs = 0
        self.heartbeats: dict[int, float] = {}  # producer node -> when its heartbeat came
        self.rpdos: dict[int, PdoLayout] = {}
        self.tpdos: list[PdoLayout] = []
        self.tpdo_stored: dict[int, tuple[int, ...]] = {}  # a TPDO's objects from the store
        self.pending: dict[int, bytes] = {}  # synchronous RPDOs waiting for SYNC
        self.cw_received = 0  # controlwords obeyed (by RPDO or SDO), for the tests
        self._stale = True
        self._cached: _Params | None = None
        # _target_nm's value until the target or a parameter is written (None: stale);
        # read twice a physics tick (the torque applied, the drive's tick)
        self._target_cache: float | None = None

    # --- the bus ------------------------------------------------------------------------
    def send(self, can_id: int, data: Any) -> None:
        self.emu._send_frame(can.Message(arbitration_id=can_id, data=bytes(data),
                                         is_extended_id=False), self.id)

    @property
    def nmt(self) -> str:
        """The NMT state canopen's slave keeps ("PRE-OPERATIONAL", "OPERATIONAL", ...)."""
        return self.node.nmt.state

    @property
    def operational(self) -> bool:
        return self.nmt == "OPERATIONAL"

    def boot(self, reset: int = NMT_RESET_NODE) -> None:
        """Power-up (or an NMT reset): the EDS's values again, boot-up, pre-operational."""
        store = self.node.data_store
        if reset == NMT_RESET_NODE:
            store.clear()
            self.state = p.State.SWITCH_ON_DISABLED  # transition 1 done during the boot
            self.error_code, self.target, self.applied_nm, self.previous_cw = 0, 0, 0.0, 0
            self._target_cache = None
        else:
            for index in [i for i in store if i < 0x2000]:
                del store[index]
        store[p.PRODUCER_HEARTBEAT_TIME] = {0: struct.pack("<H", self.heartbeat_ms)}
        for task in self.tasks:
            task.stop()
        self.tasks.clear()
        self.rpdos, self.tpdos, self.pending, self.heartbeats = {}, [], {}, {}
        self._stale = True
        self.node.nmt.send_command(NMT_RESET_NODE)  # boot-up message (state 0)
        self.node.nmt.send_command(NMT_ENTER_PRE_OPERATIONAL)  # the heartbeat starts

    def on_nmt(self, data: bytes) -> bool:
        """An NMT command for everyone or for this drive; False if not one."""
        command, target = data[0], data[1]
        if target not in (0, self.id):
            return True
        if command not in COMMAND_TO_STATE:
            return False
        was = self.operational
        self.node.nmt.on_command(0, data, self.emu.t)  # canopen's NMT slave: state, heartbeat
        if command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            self.boot(command)
        elif self.operational and not was:
            self._read_pdos()
        return True

    def _read_pdos(self) -> None:
        """The PDO configuration as the object dictionary holds it now (canopen reads it)."""
        self.node.rpdo.read()
        self.node.tpdo.read()
        self.rpdos = {m.cob_id: PdoLayout.of(m) for m in self.node.rpdo.values() if m.enabled}
        self.tpdos = [PdoLayout.of(m) for m in self.node.tpdo.values() if m.enabled]
        self.tpdo_stored = {lay.cob_id: tuple(i for i, _, _ in lay.fields if i not in LIVE)
                            for lay in self.tpdos}
        self.pending = {}
        self.emu._index_rpdos()

    def on_sync(self, now: float, lead_s: float, backlog: bool) -> None:
        """Apply the synchronous RPDOs, sample and send the TPDOs due. A SYNC read at
        the emulator time of the one before while the emulator reads a backlog
        (``backlog``: more than a tick behind the wall clock) samples nothing new: its
        TPDOs are shed and counted, as the ODrive emulator sheds stale encoder estimates
        (sending them kept a starved emulator falling further behind). Two SYNCs within
        one tick of an emulator on time are two SYNCs (a bridge's late period, then its
        next on time): shed, the second's TPDOs left the bridge without encoder data for
        14-20 ms and its pose stepped back (`lab` on one core). ``lead_s``: how far the
        wall clock is past the physics' newest tick (:meth:`RobotEmulator.sample_lead_s`),
        read once for the robot's drives: they sample on the same SYNC."""
        if not self.operational:
            return
        stale = self.last_sync == now and backlog
        self.last_sync = now
        self.syncs += 1
        for cob_id, data in list(self.pending.items()):
            self._apply_rpdo(self.rpdos[cob_id], data)
        self.pending.clear()
        sampled = None  # the live objects, sampled once for this SYNC's TPDOs
        for lay in self.tpdos:
            if lay.synchronous and (lay.trans_type == 0 or self.syncs % lay.trans_type == 0):
                if stale:
                    self.emu.counters.shed += 1
                    continue
                if sampled is None:
                    sampled = self._live(lead_s)
                stored = self.tpdo_stored.get(lay.cob_id)
                values = sampled if not stored else \
                    {**sampled, **{i: self._stored(i) for i in stored}}
                self.send(lay.cob_id, lay.pack(values))

    def on_rpdo(self, lay: PdoLayout, data: bytes) -> None:
        if not self.operational:
            return
        if lay.synchronous:
            self.pending[lay.cob_id] = bytes(data[:lay.length])
        else:
            self._apply_rpdo(lay, data)

    def _apply_rpdo(self, lay: PdoLayout, data: bytes) -> None:
        """The mapped objects written as canopen's ``LocalNode.set_data`` writes them (the
        write callbacks, then the store), without its per-call lookups: the layout
        already holds each object's place and size (an RPDO per drive per period)."""
        store = self.node.data_store
        for index, offset, packing in lay.fields:
            raw = data[offset:offset + packing.size]
            self._write(index, 0, None, raw)
            store.setdefault(index, {})[0] = raw

    def on_heartbeat(self, producer: int, now: float) -> None:
        self.heartbeats[producer] = now

    # --- the object dictionary's live values -------------------------------------------
    def _read(self, index: int, subindex: int, od: Any) -> int | None:
        if index in LIVE:  # sampled at the wall clock
            return self._live(self.emu.sample_lead_s())[index]
        return None

    def _stored(self, index: int) -> int:
        """Object ``index``'s value as the object dictionary holds it."""
        od = self.node.object_dictionary[index]
        return od.decode_raw(self.node.get_data(index, 0))

    def _live(self, lead_s: float) -> dict[int, int]:
        """The objects the drive samples, the position ``lead_s`` past the newest physics
        tick: a SYNC's TPDOs take them at once (the drive samples them together)."""
        par, emu, w = self.params, self.emu, self.wheel
        per_rev = par.increments_per_rev
        speed = emu.wheel_speed(w)
        # sampled now, between physics ticks: carried from the newest tick at the wheel's
        # speed (a SYNC read at the tick's time reported a position up to a tick old: 2 mm
        # of odometry drift median at lab's speeds, 200 Hz physics)
        rev = float(emu.wheel_rev[w]) + speed / TWO_PI * lead_s
        raw = round(rev * per_rev)
        v = round(float(speed) * (per_rev / TWO_PI))
        error = self.error_code
        return {
            p.STATUSWORD: p.statusword_of(self.state),
            p.ERROR_CODE: error,
            0x1001: ERROR_REGISTER_GENERIC_COMMUNICATION if error else 0,
            p.MODES_OF_OPERATION_DISPLAY: par.mode,
            p.POSITION_ACTUAL: (raw + (1 << 31)) % (1 << 32) - (1 << 31),  # int32, wrapping
            p.VELOCITY_ACTUAL: max(-(1 << 31), min((1 << 31) - 1, v)),
            p.TORQUE_ACTUAL: max(-32768, min(32767, round(self.applied_nm / par.nm_per_mille))),
        }

    def _object(self, index: int, sub: int | None = None) -> Any:
        od = self.node.object_dictionary
        var = od[index] if sub is None else od[index][sub]
        return var.decode_raw(self.node.get_data(index, 0 if sub is None else sub))

    @property
    def params(self) -> _Params:
        if self._stale or self._cached is None:
            self._cached = self._read_params()
            self._stale = False
            self._target_cache = None
        return self._cached

    def _read_params(self) -> _Params:
        od = self.node.object_dictionary
        units = units_of(self._object)
        if units.problem():
            raise ValueError(f"EDS {self.eds}: {units.problem()}")
        consumers = []
        if p.CONSUMER_HEARTBEAT_TIME in od:
            for sub in od[p.CONSUMER_HEARTBEAT_TIME]:
                value = int(self._object(p.CONSUMER_HEARTBEAT_TIME, sub)) if sub else 0
                producer, ms = (value >> 16) & 0x7F, value & 0xFFFF
                if producer and ms:
                    consumers.append((producer, ms / 1000.0))
        slope = float(self._object(p.TORQUE_SLOPE)) if p.TORQUE_SLOPE in od else math.inf
        return _Params(
            mode=int(self._object(p.MODES_OF_OPERATION)),
            max_torque=int(self._object(p.MAX_TORQUE)) if p.MAX_TORQUE in od else 0x7FFF,
            quick_stop_option=int(self._object(p.QUICK_STOP_OPTION_CODE))
            if p.QUICK_STOP_OPTION_CODE in od else 2,
            slope_nm_s=slope * units.wheel_nm_per_mille, units=units,
            consumers=tuple(consumers), nm_per_mille=units.wheel_nm_per_mille,
            increments_per_rev=units.increments_per_wheel_rev)

    def _write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        """An SDO download or an RPDO: the objects that act (called before the value is
        stored; raising SdoAbortedError refuses it)."""
        if index in PARAMETERS:
            self._stale = True
        if index in POSITIVE and subindex and not int.from_bytes(data[:4], "little"):
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if index == p.CONTROLWORD:
            self._controlword(int.from_bytes(data[:2], "little"))
        elif index == p.TARGET_TORQUE:
            self.target = int.from_bytes(data[:2], "little", signed=True)
            self._target_cache = None
        elif index == p.MODES_OF_OPERATION:
            mode = int.from_bytes(data[:1], "little", signed=True)
            bit = {p.MODE_CYCLIC_SYNC_TORQUE: p.SUPPORTS_CST, p.MODE_PROFILE_TORQUE: p.SUPPORTS_PT}
            if mode != 0 and not int(self._object(p.SUPPORTED_DRIVE_MODES)) & bit.get(mode, 0):
                raise SdoAbortedError(ABORT_VALUE_RANGE)

    # --- the state machine --------------------------------------------------------------
    def _controlword(self, cw: int) -> None:
        self.cw_received += 1
        option = self.params.quick_stop_option
        new, _ = p.next_state(self.state, cw, self.previous_cw, quick_stop_holds=5 <= option <= 8)
        self.previous_cw = cw
        if new is p.State.OPERATION_ENABLED and self.refuse_enable:
            return  # safe torque off: enabling is refused, the drive stays where it is
        self._enter(new, option)

    def _enter(self, new: p.State, option: int = 2) -> None:
        old, self.state = self.state, new
        if new is old:
            return
        now = self.emu.t
        if new is p.State.OPERATION_ENABLED:
            self.enabled_at = now
            self.applied_nm = 0.0 if old is not p.State.QUICK_STOP_ACTIVE else self.applied_nm
            self.emu.armed_now()
        elif new is p.State.QUICK_STOP_ACTIVE and option == 0:
            self._enter(p.State.SWITCH_ON_DISABLED)  # 0: disable the drive function at once
        elif new is p.State.SWITCH_ON_DISABLED and old is p.State.FAULT:
            self.error_code = 0
            self.node.emcy.reset()
        if self.state not in (p.State.OPERATION_ENABLED, p.State.QUICK_STOP_ACTIVE):
            self.applied_nm = 0.0

    def fault(self, code: int) -> None:
        """Transitions 13 and 14: the torque off, the error latched and announced."""
        if self.state in (p.State.FAULT, p.State.FAULT_REACTION_ACTIVE):
            return
        self.error_code = code
        self.state, self.applied_nm = p.State.FAULT, 0.0
        self.node.emcy.send(code, ERROR_REGISTER_GENERIC_COMMUNICATION)

    def tick(self, now: float, h: float) -> None:
        """After the physics advanced by ``h`` to ``now``: ramps and watchdogs."""
        par = self.params
        if self.state is p.State.QUICK_STOP_ACTIVE:
            step = par.slope_nm_s * h
            self.applied_nm = 0.0 if abs(self.applied_nm) <= step else \
                self.applied_nm - math.copysign(step, self.applied_nm)
            if self.applied_nm == 0.0 and 1 <= par.quick_stop_option <= 4:
                self._enter(p.State.SWITCH_ON_DISABLED)  # transition 12, the stop done
            return
        if self.state is not p.State.OPERATION_ENABLED:
            return
        watchdog = self.emu.watchdog_timeout_s
        since = self.enabled_at if self.last_sync is None else max(self.last_sync, self.enabled_at)
        if watchdog > 0 and now - since > watchdog + 1e-12:
            self.fault(p.ERROR_COMMUNICATION)
            return
        for producer, limit_s in par.consumers:
            heard = self.heartbeats.get(producer)
            if heard is not None and now - max(heard, self.enabled_at) > limit_s + 1e-12:
                self.fault(p.ERROR_HEARTBEAT)
                return
        target_nm = self._target_nm()
        if par.mode == p.MODE_PROFILE_TORQUE and math.isfinite(par.slope_nm_s):
            step = par.slope_nm_s * h
            delta = target_nm - self.applied_nm
            self.applied_nm = target_nm if abs(delta) <= step else \
                self.applied_nm + math.copysign(step, delta)
        else:
            self.applied_nm = target_nm

    def _target_nm(self) -> float:
        """The target torque at the wheel (N m): 0 outside a torque mode, within 0x6072
        and the scenario's limit."""
        nm = self._target_cache
        if nm is None or self._stale:
            par = self.params  # (a stale cache read anew)
            if par.mode not in TORQUE_MODES:
                nm = 0.0
            else:
                per_mille = max(-par.max_torque, min(par.max_torque, self.target))
                nm = self.emu.clamp(per_mille * par.nm_per_mille)
            self._target_cache = nm
        return nm

    def wheel_torque(self) -> float:
        """What the drive applies to its wheel now (N m)."""
        state = self.state
        if state is p.State.OPERATION_ENABLED:
            if self.params.mode == p.MODE_CYCLIC_SYNC_TORQUE:
                return self._target_nm()  # CST: the newest target, between the physics ticks too
            return self.applied_nm
        return self.applied_nm if state is p.State.QUICK_STOP_ACTIVE else 0.0


class Cia402Emulator(RobotEmulator):
    """Four CiA 402 drives (canopen LocalNodes) plus robot ``robot_id``'s dynamics on
    ``bus``. ``heartbeat_rate_hz``: the drives' heartbeat at power-up (0x1017; the host
    sets its own); ``watchdog_timeout_s``: the SYNC a drive in OPERATION ENABLED may
    miss before it faults (0: never)."""

    def __init__(self, sc: Fleet, robot_id: int, bus: can.BusABC,
                 node_ids: Sequence[int] = (1, 2, 3, 4), encoder_rate_hz: float = 200.0,
                 heartbeat_rate_hz: float = 10.0, watchdog_timeout_s: float = 0.2,
                 physics_rate_hz: float = 1000.0,
                 faults: EmulatorFaults = EmulatorFaults(),  # noqa: B008 - frozen
                 eds: str | Path | None = None) -> None:
        if not all(1 <= int(n) <= 127 for n in node_ids):
            raise ValueError(f"CANopen node ids are 1..127, got {list(node_ids)}")
        if not (math.isfinite(heartbeat_rate_hz) and 0 < heartbeat_rate_hz <= 1000):
            raise ValueError(f"heartbeat_rate_hz must be in (0, 1000], got {heartbeat_rate_hz}")
        super().__init__(sc, robot_id, bus, node_ids, encoder_rate_hz, watchdog_timeout_s,
                         physics_rate_hz, faults)
        self.eds = Path(eds) if eds else DEFAULT_EDS
        self.counters.protocol = FrameCounters()
        ms = max(1, round(1000.0 / heartbeat_rate_hz))
        self.drives = [_Drive(self, n, self.eds, ms, faults.refuse_enable_node == n)
                       for n in self.node_ids]
        self._by_id = {d.id: d for d in self.drives}
        self._rpdo_of: dict[int, tuple[_Drive, PdoLayout]] = {}
        self._own: set[int] = set()
        self._booted = False
        self._last_tick = 0.0

    def _index_rpdos(self) -> None:
        self._rpdo_of = {cob: (d, lay) for d in self.drives for cob, lay in d.rpdos.items()}
        # what the drives send: heard back on a bus that echoes, never ours to act on
        self._own = {c for d in self.drives for c in (0x580 + d.id, 0x700 + d.id, 0x080 + d.id,
                                                      *(lay.cob_id for lay in d.tpdos))}

    def wheel_torques(self) -> np.ndarray:
        return np.array([d.wheel_torque() for d in self.drives])

    def describe_drives(self) -> str:
        return ", ".join(f"{d.id}: {d.state.value}, error 0x{d.error_code:04x}, NMT {d.nmt}"
                         for d in self.drives)

    # --- the clock ----------------------------------------------------------------------
    def _clock_due(self, now: float) -> None:
        if not self._booted:
            self._booted = True
            for d in self.drives:
                d.boot()
            self._index_rpdos()
        for d in self.drives:
            for task in d.tasks:
                if task.active:
                    task.due(now)
                else:  # stopped (an NMT reset, a heartbeat time written): forget it
                    d.tasks = [t for t in d.tasks if t.active]

    def _drives_tick(self, now: float) -> None:
        h, self._last_tick = now - self._last_tick, now
        f = self.faults
        silent = f.silent_node if now >= f.silent_after_s else None  # (_silent, at now)
        for d in self.drives:
            if d.id != silent:
                d.tick(now, h)

    # --- frames in --------------------------------------------------------------------
    def _handle(self, frame: can.Message) -> None:
        c = self.counters.protocol
        try:
            ok = self._dispatch(frame, c)
        except Exception:  # noqa: BLE001 - canopen choking on a frame must not end the emulator
            ok = False
            c.invalid += 1
        if ok:
            c.decoded += 1

    def _dispatch(self, frame: can.Message, c: FrameCounters) -> bool:
        if frame.is_error_frame or frame.is_extended_id or frame.is_fd or frame.is_remote_frame:
            c.other_frame += 1
            return False
        cob, data = int(frame.arbitration_id), bytes(frame.data or b"")
        if frame.dlc != len(data) or len(data) > 8 or not 0 <= cob <= 0x7FF:
            c.bad_length += 1
            return False
        now = self.t
        if cob == 0x000:  # NMT
            if len(data) != 2:
                c.bad_length += 1
                return False
            for d in self._listening():
                if not d.on_nmt(data):
                    c.invalid += 1
                    return False
            return True
        if cob == SYNC_COB_ID:
            if len(data) > 1:
                c.bad_length += 1
                return False
            behind = self.behind_s()
            lead, backlog = min(behind, self._h), behind > self._h
            for d in self._listening():
                d.on_sync(now, lead, backlog)
            return True
        hit = self._rpdo_of.get(cob)
        if hit is not None:
            d, lay = hit
            if len(data) < lay.length:
                c.bad_length += 1
                return False
            if self._silent(d.id):
                self.counters.silenced += 1
                return True
            d.on_rpdo(lay, data)
            return True
        if cob in self._own:
            c.ignored_direction += 1
            return False
        node, function = cob & 0x7F, cob & 0x780
        if function == 0x600 and node in self._by_id:  # an SDO request
            if len(data) != 8:
                c.bad_length += 1
                return False
            d = self._by_id[node]
            if self._silent(node):
                self.counters.silenced += 1
            else:
                d.network.notify(cob, bytearray(data), now)  # canopen's SDO server answers
            return True
        if function == 0x700 and node:  # another node's heartbeat (the host's)
            if len(data) != 1:
                c.bad_length += 1
                return False
            for d in self._listening():
                d.on_heartbeat(node, now)
            return True
        c.unknown_id += 1
        return False

    def _listening(self) -> list[_Drive]:
        out = [d for d in self.drives if not self._silent(d.id)]
        self.counters.silenced += len(self.drives) - len(out)
        return out

    # --- for tests and the command line ---------------------------------------------------
    def drive(self, node: int) -> _Drive:
        return self._by_id[node]

    def states(self) -> list[p.State]:
        return [d.state for d in self.drives]
