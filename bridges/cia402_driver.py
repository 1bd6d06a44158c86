"""CiA 402 servo drives over CANopen: the host's plug-in (:class:`bridges.driver.WheelDriver`),
built on the ``canopen`` library.

- **Object dictionary** from an EDS file (``--eds``; default: the emulated drive's,
  ``bridges/cia402_drive.eds``), parsed by canopen, one :class:`canopen.RemoteNode`
  per wheel drive. Checked on construction: the profile's objects are there and the
  PDOs map what the cyclic path needs (ValueError naming the file otherwise).
- **Bring-up** (:meth:`Cia402Driver.bring_up`, on the bus before the bridge's reader
  starts): wait for each drive's heartbeat, NMT pre-operational, then by SDO: the
  device type (402), the supported modes (cyclic synchronous torque, else profile
  torque), the units (0x6076 rated torque, 0x6091 gear ratio, 0x608F encoder
  resolution), the mode of operation, the max torque (the scenario's limit), the SYNC
  period, the heartbeats both ways (the drive consumes the host's: its watchdog), the
  quick stop option, the EDS's PDO mapping written and read back; NMT operational.
- **Cyclic path**: per drive one RPDO (controlword, target torque: applied on
  receipt), and TPDOs on every SYNC (statusword, torque actual, error code; position
  and velocity actual). The bridge sends SYNC once per control period and its own
  heartbeat every 50 ms (:meth:`cycle_frames`). The payloads are packed with
  :class:`bridges.cia402_pdo.PdoLayout` from canopen's reading of the mapping.
- **State machine**: arming walks each drive one transition per status received
  (shutdown, switch on, enable operation; a fault reset first where the fault is
  recoverable, :func:`bridges.cia402.arming_command`); disarming is shutdown; the
  e-stop is the drive's own quick stop, held (a later disarm does not undo it).

Units: 1 per mille of target torque is ``rated torque x gear ratio / 1000`` at the
wheel (a wheel turns once per ``gear ratio`` motor turns); a wheel turn is ``encoder
increments per motor turn x gear ratio`` position units; velocity is in increments
per second. ``decode`` never raises (``None`` + a counter), as the ODrive codec.
"""

from __future__ import annotations

import functools
import math
import os
import pickle
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.network import MessageListener
from canopen.nmt import NMT_STATES, NmtError
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from bridges import cia402 as p
from bridges.cia402_pdo import PdoLayout
from bridges.driver import DriveError, DriverSettings, FrameCounters, WheelReport

DEFAULT_EDS = Path(__file__).resolve().with_name("cia402_drive.eds")
HOST_HEARTBEAT_S = 0.05  # the bridge's heartbeat period, consumed by every drive
CONSUMER_HEARTBEAT_MS = 250  # a drive missing the host's heartbeat this long faults (0x8130)
DRIVE_HEARTBEAT_MS = 100  # each drive's heartbeat (its NMT state; the statusword is liveness)
QUICK_STOP_OPTION = 2  # quick stop: brake on the quick stop ramp, then switch on disabled
MAX_ABS_VELOCITY_REV_S = 1e4  # a wheel faster than this is an implausible value
SDO_TIMEOUT_S = 1.0  # per request (a loaded host answers late), two tries
NMT_COMMAND = 0x000
TPDO_FUNCTIONS = (0x180, 0x280, 0x380, 0x480)  # TPDO1-4 of the predefined connection set
SYNC_COB_ID = 0x080
REQUIRED = (p.CONTROLWORD, p.STATUSWORD, p.TARGET_TORQUE, p.POSITION_ACTUAL, p.VELOCITY_ACTUAL,
            p.MODES_OF_OPERATION, p.MOTOR_RATED_TORQUE, p.SUPPORTED_DRIVE_MODES, p.DEVICE_TYPE)


@dataclass
class Units:
    """A drive's units at the wheel (from the EDS, then the drive's own by SDO)."""

    rated_torque_mnm: int = 1000
    gear_motor_revs: int = 1  # 0x6091: motor turns ...
    gear_shaft_revs: int = 1  # ... per this many wheel turns
    encoder_increments: int = 4096  # 0x608F: increments ...
    encoder_motor_revs: int = 1  # ... per this many motor turns

    @property
    def gear(self) -> float:
        return self.gear_motor_revs / self.gear_shaft_revs

    @property
    def wheel_nm_per_mille(self) -> float:
        """N m at the wheel for 1 per mille of the motor's rated torque."""
        return self.rated_torque_mnm * 1e-6 * self.gear

    @property
    def increments_per_wheel_rev(self) -> float:
        return self.encoder_increments / self.encoder_motor_revs * self.gear

    def problem(self) -> str | None:
        if not all(isinstance(x, int) and x > 0 for x in (
                self.rated_torque_mnm, self.gear_motor_revs, self.gear_shaft_revs,
                self.encoder_increments, self.encoder_motor_revs)):
            return (f"rated torque, gear ratio and encoder resolution must be positive, got "
                    f"{self.rated_torque_mnm} mN m, {self.gear_motor_revs}:{self.gear_shaft_revs}, "
                    f"{self.encoder_increments}/{self.encoder_motor_revs}")
        return None


@dataclass
class _Drive:
    """One wheel's drive as the host sees it."""

    id: int
    node: Any  # canopen.RemoteNode
    units: Units
    control: PdoLayout  # the RPDO that carries the controlword
    torque: PdoLayout  # the RPDO that carries the target torque (may be the same)
    tpdos: list[PdoLayout]
    image: dict[int, int] = field(default_factory=dict)  # the RPDO-mapped objects' values
    state: p.State | None = None  # from the newest statusword
    nmt: int | None = None  # from the newest heartbeat
    emcy: int | None = None  # the newest emergency code
    raw_position: int | None = None  # int32 position actual, to unwrap
    turns: float = 0.0  # the wheel's angle, unwrapped
    quick_stopped: bool = False  # an e-stop's quick stop is held

    def frames(self, *layouts: PdoLayout) -> list[can.Message]:
        out, seen = [], set()
        for lay in layouts:
            if lay.cob_id not in seen:
                seen.add(lay.cob_id)
                out.append(can.Message(arbitration_id=lay.cob_id, data=lay.pack(self.image),
                                       is_extended_id=False))
        return out


def load_od(eds: str | Path, node: int) -> Any:
    """The object dictionary of ``eds`` for ``node``, checked for what the bridge
    needs (ValueError naming the file and what is missing); a copy of its own.

    The file is parsed once per node id and version of the file, then copied
    (pickle): 5.6 ms to parse against 0.7 ms to copy, and a driver or an emulator reads
    it for each of its drives (a fuzz test built 884 drivers' drives)."""
    try:
        stat = os.stat(eds)
        return pickle.loads(_parsed_od(str(eds), stat.st_mtime_ns, stat.st_size, node))
    except OSError as exc:
        raise ValueError(f"EDS {eds}: cannot be read as an object dictionary: "
                         f"{type(exc).__name__}: {exc}") from None


@functools.lru_cache(maxsize=64)
def _parsed_od(eds: str, _mtime_ns: int, _size: int, node: int) -> bytes:
    """:func:`load_od`'s parse and checks, pickled (an error is raised, not cached)."""
    try:
        od = canopen.import_od(eds, node)
    except Exception as exc:  # configparser, KeyError, ValueError, OSError: all mean a bad file
        raise ValueError(f"EDS {eds}: cannot be read as an object dictionary: "
                         f"{type(exc).__name__}: {exc}") from None
    missing = [f"0x{i:04X}" for i in REQUIRED if i not in od]
    if missing:
        raise ValueError(f"EDS {eds}: not a CiA 402 drive for this bridge: no object "
                         f"{', '.join(missing)}")
    return pickle.dumps(od)


class Cia402Driver:
    """The drives ``settings.node_ids`` (1..127), CiA 402 over CANopen, seen from the host."""

    name = "cia402"
    # a new statusword comes with every SYNC: each one takes arming one transition on
    rearm_after_s = 0.0

    def __init__(self, settings: DriverSettings) -> None:
        ids = tuple(int(n) for n in settings.node_ids)
        host = int(settings.host_node_id)
        if not ids or len(set(ids)) != len(ids) or not all(1 <= n <= 127 for n in ids):
            raise ValueError(f"CANopen node ids must be distinct, in 1..127, got {list(ids)}")
        if not 1 <= host <= 127 or host in ids:
            raise ValueError(f"the host's heartbeat node id {host} must be in 1..127 and not a "
                             f"drive's ({list(ids)})")
        for what, x in (("control period", settings.period_s),
                        ("report rate", settings.report_rate_hz)):
            if not (math.isfinite(x) and x > 0):
                raise ValueError(f"the {what} must be positive, got {x}")
        self.settings = settings
        self.node_ids = ids
        self.host_node_id = host
        self.eds = Path(settings.eds) if settings.eds else DEFAULT_EDS
        self.counters = FrameCounters()
        self.network = canopen.Network()  # the bus is attached for bring-up only
        self._drives: dict[int, _Drive] = {}
        self._tpdo_by_cob: dict[int, tuple[_Drive, PdoLayout]] = {}
        self._next_heartbeat = -math.inf
        self._max_abs_torque_nm: float | None = None  # known once every drive's units are
        self.syncs_sent = 0
        self._drive(ids[0])  # the EDS is read and checked now (the others when used)

    # --- the drives ---------------------------------------------------------------------
    def _drive(self, n: int) -> _Drive:
        d = self._drives.get(n)
        if d is None:
            d = self._drives[n] = self._make_drive(n)
            for lay in d.tpdos:
                self._tpdo_by_cob[lay.cob_id] = (d, lay)
        return d

    def _make_drive(self, n: int) -> _Drive:
        od = load_od(self.eds, n)
        node = canopen.RemoteNode(n, od)
        self.network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        node.sdo.MAX_RETRIES = 2
        node.pdo.read(from_od=True)  # the mapping the bridge will write
        # the EDS's units until bring-up reads the drive's own (an EDS may leave them out)
        try:
            units = units_of(lambda i, s=None: _od_default(od, i, s))
        except (KeyError, TypeError, ValueError):
            units = Units()
        return self._with_mapping(n, node, units if units.problem() is None else Units())

    def _with_mapping(self, n: int, node: Any, units: Units) -> _Drive:
        where = f"EDS {self.eds}" if not self._drives.get(n) else f"node {n}"
        try:
            rx = [PdoLayout.of(m) for m in node.rpdo.values() if m.enabled]
            tx = [PdoLayout.of(m) for m in node.tpdo.values() if m.enabled]
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

        def one(layouts: list[PdoLayout], index: int, kind: str) -> PdoLayout:
            found = [lay for lay in layouts if lay.maps(index)]
            if len(found) != 1:
                raise ValueError(f"{where}: object 0x{index:04X} must be mapped to exactly one "
                                 f"enabled {kind}, found {len(found)}")
            return found[0]

        control = one(rx, p.CONTROLWORD, "RPDO")
        torque = one(rx, p.TARGET_TORQUE, "RPDO")
        one(tx, p.STATUSWORD, "TPDO")
        if one(tx, p.POSITION_ACTUAL, "TPDO") is not one(tx, p.VELOCITY_ACTUAL, "TPDO"):
            raise ValueError(f"{where}: position and velocity actual must travel in one TPDO "
                             "(odometry takes them as one sample)")
        for lay in tx:
            if not lay.synchronous:
                raise ValueError(f"{where}: {lay.name} is sent on events (transmission type "
                                 f"{lay.trans_type}); the bridge samples on SYNC (0-240)")
        image = {index: 0 for lay in rx for index, _, _ in lay.fields}
        image[p.CONTROLWORD] = p.CW_DISABLE_VOLTAGE
        if p.MODES_OF_OPERATION in image:
            image[p.MODES_OF_OPERATION] = p.MODE_CYCLIC_SYNC_TORQUE
        return _Drive(n, node, units, control, torque, tx, image)

    def layouts(self, n: int) -> tuple[PdoLayout, PdoLayout, list[PdoLayout]]:
        """Drive ``n``'s RPDOs (controlword, target torque) and TPDOs."""
        d = self._drive(n)
        return d.control, d.torque, list(d.tpdos)

    def units(self, n: int) -> Units:
        return self._drive(n).units

    def state(self, n: int) -> p.State | None:
        """Drive ``n``'s state as its newest statusword said."""
        return self._drive(n).state

    @property
    def max_abs_torque_nm(self) -> float:
        """The largest |wheel torque| every drive's target torque (int16 per mille) holds."""
        if self._max_abs_torque_nm is None:
            self._max_abs_torque_nm = min(32767 * self._drive(n).units.wheel_nm_per_mille
                                          for n in self.node_ids)
        return self._max_abs_torque_nm

    # --- bring-up -----------------------------------------------------------------------
    def bring_up(self, bus: can.BusABC, timeout_s: float, say: Callable[[str], None]) -> None:
        """NMT and SDO configuration of every drive (see the module doc); DriveError
        naming the drive and the step that failed."""
        self.network.bus = bus
        notifier = can.Notifier(bus, [MessageListener(self.network)], timeout=0.05)
        try:
            deadline = time.monotonic() + timeout_s
            for n in self.node_ids:
                self._bring_up(self._drive(n), deadline, say)
        finally:
            notifier.stop()
            self.network.bus = None

    def _bring_up(self, d: _Drive, deadline: float, say: Callable[[str], None]) -> None:
        n, node = d.id, d.node
        try:
            state = node.nmt.wait_for_heartbeat(max(0.05, deadline - time.monotonic()))
            say(f"node {n}: heartbeat heard, NMT {state}")
        except NmtError:
            say(f"node {n}: no heartbeat in time; trying SDO")
        try:
            node.nmt.state = "PRE-OPERATIONAL"
            say(f"node {n}: NMT pre-operational (PDOs stop; configuration by SDO)")
            device = node.sdo[p.DEVICE_TYPE].raw
            if device & 0xFFFF != p.PROFILE_NUMBER:
                raise DriveError(f"node {n}: device type 0x{device:08X} is not a CiA 402 drive")
            modes = node.sdo[p.SUPPORTED_DRIVE_MODES].raw
            if modes & p.SUPPORTS_CST:
                mode, mode_name = p.MODE_CYCLIC_SYNC_TORQUE, "cyclic synchronous torque"
            elif modes & p.SUPPORTS_PT:
                mode, mode_name = p.MODE_PROFILE_TORQUE, "profile torque (no cyclic synchronous torque)"
            else:
                raise DriveError(f"node {n}: supports neither cyclic synchronous nor profile "
                                 f"torque (0x6502 = 0x{modes:08X})")
            say(f"node {n}: SDO 0x1000 device type 0x{device:08X} (CiA 402); 0x6502 modes "
                f"0x{modes:08X}: {mode_name}")
            d.units = units_of(lambda i, s=None: node.sdo[i].raw if s is None else node.sdo[i][s].raw)
            self._max_abs_torque_nm = None
            if d.units.problem():
                raise DriveError(f"node {n}: {d.units.problem()}")
            u = d.units
            say(f"node {n}: SDO 0x6076 rated torque {u.rated_torque_mnm} mN m, 0x6091 gear "
                f"{u.gear_motor_revs}:{u.gear_shaft_revs}, 0x608F {u.encoder_increments} "
                f"increments per {u.encoder_motor_revs} motor turn: 1 per mille = "
                f"{u.wheel_nm_per_mille * 1e3:.3f} mN m at the wheel, "
                f"{u.increments_per_wheel_rev:g} increments per wheel turn")
            node.sdo[p.MODES_OF_OPERATION].raw = mode
            shown = node.sdo[p.MODES_OF_OPERATION_DISPLAY].raw
            if shown != mode:
                raise DriveError(f"node {n}: mode of operation {mode} written, 0x6061 shows {shown}")
            if p.MODES_OF_OPERATION in d.image:
                d.image[p.MODES_OF_OPERATION] = mode
            limit = self.settings.max_wheel_torque_nm
            if math.isfinite(limit) and p.MAX_TORQUE in node.object_dictionary:
                per_mille = max(1, min(0x7FFF, math.floor(limit / u.wheel_nm_per_mille + 1e-9)))
                node.sdo[p.MAX_TORQUE].raw = per_mille
                say(f"node {n}: SDO 0x6060 mode {mode}, 0x6061 shows it; 0x6072 max torque "
                    f"{per_mille} per mille ({per_mille * u.wheel_nm_per_mille:.3f} N m at the "
                    "wheel: the scenario's limit)")
            else:
                say(f"node {n}: SDO 0x6060 mode {mode}, 0x6061 shows it")
            self._write_timing(d, say)
            for m in node.tpdo.values():  # the drives report at report_rate_hz
                if m.enabled:
                    m.trans_type = self.sync_divider
            self._adopt(d, self._with_mapping(n, node, d.units))
            node.rpdo.save()
            node.tpdo.save()
            node.rpdo.read()  # back from the drive: what it holds is what the bridge packs
            node.tpdo.read()
            fresh = self._with_mapping(n, node, d.units)
            if (fresh.control, fresh.torque, fresh.tpdos) != (d.control, d.torque, d.tpdos):
                raise DriveError(f"node {n}: the PDO mapping read back differs from the one "
                                 "written")
            unique = {lay.cob_id: lay for lay in (d.control, d.torque, *d.tpdos)}
            say(f"node {n}: PDO mapping written by SDO and read back: "
                + "; ".join(_describe(node, lay) for lay in unique.values()))
            node.nmt.state = "OPERATIONAL"
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise DriveError(f"node {n}: SDO failed: {exc}") from None
        self._wait_operational(d, deadline)
        say(f"node {n}: NMT operational: PDOs on, SYNC every "
            f"{self.settings.period_s * 1e3:g} ms from the bridge")

    @property
    def sync_divider(self) -> int:
        """The TPDOs' transmission type: every n-th SYNC, for report_rate_hz."""
        n = round(1.0 / (self.settings.period_s * self.settings.report_rate_hz))
        return max(1, min(240, n))

    def _adopt(self, d: _Drive, fresh: _Drive) -> None:
        """Drive ``d`` packs and unpacks with ``fresh``'s layouts from now on."""
        for lay in d.tpdos:
            self._tpdo_by_cob.pop(lay.cob_id, None)
        d.control, d.torque, d.tpdos = fresh.control, fresh.torque, fresh.tpdos
        for lay in d.tpdos:
            self._tpdo_by_cob[lay.cob_id] = (d, lay)

    def _write_timing(self, d: _Drive, say: Callable[[str], None]) -> None:
        node, od = d.node, d.node.object_dictionary
        done = []
        if p.COMMUNICATION_CYCLE_PERIOD in od:
            node.sdo[p.COMMUNICATION_CYCLE_PERIOD].raw = round(self.settings.period_s * 1e6)
            done.append(f"0x1006 SYNC period {round(self.settings.period_s * 1e6)} us")
        if p.PRODUCER_HEARTBEAT_TIME in od:
            node.sdo[p.PRODUCER_HEARTBEAT_TIME].raw = DRIVE_HEARTBEAT_MS
            done.append(f"0x1017 heartbeat {DRIVE_HEARTBEAT_MS} ms")
        if p.CONSUMER_HEARTBEAT_TIME in od:
            node.sdo[p.CONSUMER_HEARTBEAT_TIME][1].raw = (self.host_node_id << 16) | CONSUMER_HEARTBEAT_MS
            done.append(f"0x1016 the host's (node {self.host_node_id}) heartbeat within "
                        f"{CONSUMER_HEARTBEAT_MS} ms")
        else:
            say(f"node {d.id}: WARNING: no 0x1016: the drive cannot watch the host's heartbeat")
        if p.QUICK_STOP_OPTION_CODE in od:
            node.sdo[p.QUICK_STOP_OPTION_CODE].raw = QUICK_STOP_OPTION
            done.append(f"0x605A quick stop option {QUICK_STOP_OPTION} (ramp, then switch on disabled)")
        say(f"node {d.id}: SDO " + ", ".join(done))

    def _wait_operational(self, d: _Drive, deadline: float) -> None:
        nmt = d.node.nmt
        while True:
            left = deadline - time.monotonic()
            try:
                if nmt.wait_for_heartbeat(max(0.05, min(left, 0.5))) == "OPERATIONAL":
                    return
            except NmtError:
                pass
            if time.monotonic() > deadline:
                raise DriveError(f"node {d.id}: not operational after the NMT start "
                                 f"(heartbeat says {nmt.state})")

    # --- frames out -----------------------------------------------------------------------
    def _command(self, n: int, controlword: int) -> list[can.Message]:
        d = self._drive(n)
        d.image[p.CONTROLWORD] = controlword
        return d.frames(d.control)

    def arm_frames(self, node: int) -> list[can.Message]:
        """The next transition toward OPERATION ENABLED from the newest status (none
        from a fault: :meth:`clear_faults_frames` first)."""
        d = self._drive(node)
        cw = p.arming_command(d.state)
        if cw is None:
            return []
        d.quick_stopped = False
        return self._command(node, cw)

    def disarm_frames(self, node: int) -> list[can.Message]:
        """Zero target torque and shutdown (power stage off, transition 8); a quick
        stop in progress is held instead."""
        d = self._drive(node)
        d.image[p.TARGET_TORQUE] = 0
        cw = p.CW_QUICK_STOP if d.quick_stopped else p.CW_SHUTDOWN
        d.image[p.CONTROLWORD] = cw
        return d.frames(d.torque, d.control)

    def estop_frames(self, node: int) -> list[can.Message]:
        """The drive's own quick stop (transition 11): it brakes on its ramp and ends in
        SWITCH ON DISABLED (option code 2)."""
        d = self._drive(node)
        d.quick_stopped = True
        d.image[p.TARGET_TORQUE] = 0
        d.image[p.CONTROLWORD] = p.CW_QUICK_STOP
        return d.frames(d.torque, d.control)

    def clear_faults_frames(self, node: int) -> list[can.Message]:
        """A fault reset (a rising edge of bit 7, transition 15) for a drive in FAULT;
        nothing otherwise."""
        d = self._drive(node)
        if d.state is not p.State.FAULT:
            return []
        out = []
        if d.image[p.CONTROLWORD] & p.FAULT_RESET_BIT:  # bit 7 already high: lower it first
            out += self._command(node, p.CW_DISABLE_VOLTAGE)
        return out + self._command(node, p.CW_FAULT_RESET)

    def torque_frame(self, node: int, torque_nm: float) -> can.Message:
        """The target torque in per mille of rated torque (rounded); ValueError for a
        torque that is not finite or beyond what the frame holds."""
        d = self._drives.get(node) or self._drive(node)
        tau = float(torque_nm)
        if not math.isfinite(tau) or abs(tau) > self.max_abs_torque_nm:
            raise ValueError(f"cannot encode a torque of {torque_nm!r} N m for node {node}")
        d.image[p.TARGET_TORQUE] = max(-32767, min(32767, round(tau / d.units.wheel_nm_per_mille)))
        lay = d.torque
        return can.Message(arbitration_id=lay.cob_id, data=lay.pack(d.image), is_extended_id=False)

    def cycle_frames(self, now_s: float) -> list[can.Message]:
        """SYNC (the drives apply nothing on it: the RPDO is applied on receipt; they
        sample and send their TPDOs), and the host's heartbeat when due."""
        out = [can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)]
        self.syncs_sent += 1
        if now_s >= self._next_heartbeat:
            self._next_heartbeat = now_s + HOST_HEARTBEAT_S
            out.append(can.Message(arbitration_id=0x700 + self.host_node_id, data=bytes([5]),
                                   is_extended_id=False))
        return out

    def describe_fault(self, code: int) -> str:
        return p.describe_error(code) if code else "0x0000 (none)"

    def describe(self, node: int) -> str:
        d = self._drive(node)
        words = [d.state.value if d.state is not None else "no statusword yet",
                 f"NMT {NMT_STATES.get(d.nmt, '?') if d.nmt is not None else '?'}"]
        if d.emcy:
            words.append(f"last EMCY {p.describe_error(d.emcy)}")
        return ", ".join(words)

    # --- frames in ------------------------------------------------------------------------
    def decode(self, frame: can.Message) -> WheelReport | None:
        """What ``frame`` says of a wheel, or None (counted). Never raises."""
        try:
            return self._decode(frame)
        except Exception:  # noqa: BLE001 - a malformed frame object must not end the caller
            self.counters.invalid += 1
            return None

    def _decode(self, frame: can.Message) -> WheelReport | None:
        c = self.counters
        if frame.is_error_frame or frame.is_extended_id or frame.is_fd or frame.is_remote_frame:
            c.other_frame += 1
            return None
        cob = int(frame.arbitration_id)
        data = bytes(frame.data or b"")
        if not 0 <= cob <= 0x7FF:
            c.unknown_id += 1
            return None
        if frame.dlc != len(data) or len(data) > 8:
            c.bad_length += 1
            return None
        hit = self._tpdo_by_cob.get(cob)
        node, function = cob & 0x7F, cob & 0x780
        if hit is None and function in TPDO_FUNCTIONS and node in self.node_ids \
                and node not in self._drives:  # its object dictionary, read when first heard
            self._drive(node)
            hit = self._tpdo_by_cob.get(cob)
        if hit is not None:
            d, lay = hit
            if len(data) < lay.length:
                c.bad_length += 1
                return None
            report = self._tpdo_report(d, lay.unpack(data))
            if report is None:
                c.invalid += 1
                return None
            c.decoded += 1
            return report
        if cob in (NMT_COMMAND, SYNC_COB_ID) or node == self.host_node_id and function == 0x700:
            c.ignored_direction += 1
            return None
        if node not in self.node_ids:
            c.unknown_id += 1
            return None
        if function in (0x200, 0x300, 0x400, 0x500, 0x600):  # RPDOs, SDO requests: ours
            c.ignored_direction += 1
            return None
        if function == 0x700:  # heartbeat (or boot-up: 0)
            if len(data) != 1:
                c.bad_length += 1
                return None
            if data[0] & 0x7F not in NMT_STATES:
                c.invalid += 1
                return None
            if node in self._drives:
                self._drives[node].nmt = data[0] & 0x7F
        elif function == 0x080:  # emergency
            if len(data) != 8:
                c.bad_length += 1
                return None
            if node in self._drives:
                self._drives[node].emcy = int.from_bytes(data[:2], "little")
        elif function == 0x580:  # an SDO answer (bring-up's, or anyone's)
            if len(data) != 8:
                c.bad_length += 1
                return None
        else:  # a TPDO this mapping does not enable
            c.unknown_id += 1
            return None
        c.decoded += 1
        return WheelReport(node)

    def _tpdo_report(self, d: _Drive, values: dict[int, int | float]) -> WheelReport | None:
        state = fault = None
        recoverable = False
        if p.STATUSWORD in values:
            state = p.state_of(int(values[p.STATUSWORD]))
            if state is None:
                return None
            code = int(values.get(p.ERROR_CODE, 0))
            is_fault = state in (p.State.FAULT, p.State.FAULT_REACTION_ACTIVE)
            fault = (code or p.ERROR_GENERIC) if is_fault else 0
            recoverable = is_fault and fault in p.RECOVERABLE_ERRORS
        u = d.units
        torque = None
        if p.TORQUE_ACTUAL in values:
            torque = int(values[p.TORQUE_ACTUAL]) * u.wheel_nm_per_mille
        position = velocity = None
        if p.POSITION_ACTUAL in values and p.VELOCITY_ACTUAL in values:
            velocity = int(values[p.VELOCITY_ACTUAL]) / u.increments_per_wheel_rev
            if abs(velocity) > MAX_ABS_VELOCITY_REV_S:
                return None
            raw = int(values[p.POSITION_ACTUAL])
            if d.raw_position is not None:  # int32 increments wrap: take the short way
                step = (raw - d.raw_position + (1 << 31)) % (1 << 32) - (1 << 31)
                d.turns += step / u.increments_per_wheel_rev
            else:
                d.turns = raw / u.increments_per_wheel_rev
            d.raw_position = raw
            position = d.turns
        if state is not None:
            d.state = state
        return WheelReport(d.id, position, velocity, torque,
                           None if state is None else p.neutral(state), fault, recoverable)


def _od_default(od: Any, index: int, sub: int | None = None) -> Any:
    var = od[index] if sub is None else od[index][sub]
    value = var.value if var.value is not None else var.default
    if value is None:
        raise ValueError(f"0x{index:04X} has no value")
    return value


def units_of(read: Callable[..., Any]) -> Units:
    """The units from ``read(index, sub)``; the gear ratio and encoder resolution are
    optional objects (1:1, and the EDS's resolution where absent)."""
    u = Units(rated_torque_mnm=int(read(p.MOTOR_RATED_TORQUE)))
    for index, names in ((p.GEAR_RATIO, ("gear_motor_revs", "gear_shaft_revs")),
                         (p.POSITION_ENCODER_RESOLUTION, ("encoder_increments", "encoder_motor_revs"))):
        try:
            a, b = int(read(index, 1)), int(read(index, 2))
        except (KeyError, SdoAbortedError):
            continue
        setattr(u, names[0], a)
        setattr(u, names[1], b)
    return u


def _describe(node: Any, lay: PdoLayout) -> str:
    od = node.object_dictionary
    names = ", ".join(od[index].name for index, _, _ in lay.fields)
    rx = lay.name.startswith("Rx")
    when = (("applied on" if rx else "sent") + (f" on every {lay.trans_type}. SYNC"
                                                if 1 < lay.trans_type <= 240 else " on every SYNC")
            if lay.synchronous else "applied on receipt" if rx else "sent on events")
    return f"{lay.name} 0x{lay.cob_id:03X} [{names}] {when}"
