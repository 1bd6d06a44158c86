"""ODrive CANSimple codec: bytes against the DBC, rejection of everything else; the
host's plug-in in neutral terms (bridges/driver.py)."""

from __future__ import annotations

import math
import re
import struct

import can
import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridges.driver import DriverSettings, DriveState, WheelDriver, WheelReport
from bridges.odrive import (
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    AXIS_STATE_IDLE,
    CMD_GET_BUS_VOLTAGE_CURRENT,
    CMD_GET_ERROR,
    CMD_HEARTBEAT,
    CONTROL_MODE_TORQUE_CONTROL,
    DBC_PATH,
    INPUT_MODE_PASSTHROUGH,
    BusVoltageCurrent,
    ClearErrors,
    DriverErrors,
    EncoderEstimate,
    Estop,
    Heartbeat,
    OdriveCanSimple,
    OdriveDriver,
    Request,
    SetAxisState,
    SetControllerMode,
    SetInputTorque,
)

NODES = (0, 1, 2, 3)
DB = cantools.database.load_file(str(DBC_PATH))  # the reference, independent of the codec

# (frame, DBC message name, its signals, role that decodes it)
CASES = [
    (Heartbeat(1, AXIS_ERROR_WATCHDOG_TIMER_EXPIRED, AXIS_STATE_IDLE, 0, True), "Heartbeat",
     {"Axis_Error": 0x800, "Axis_State": 1, "Procedure_Result": 0, "Trajectory_Done_Flag": 1}, "host"),
    (EncoderEstimate(2, 12.5, -3.25), "Get_Encoder_Estimates",
     {"Pos_Estimate": 12.5, "Vel_Estimate": -3.25}, "host"),
    (DriverErrors(3, 0x4000, 0x800), "Get_Error", {"Active_Errors": 0x4000, "Disarm_Reason": 0x800}, "host"),
    (BusVoltageCurrent(0, 24.0, -1.5), "Get_Bus_Voltage_Current",
     {"Bus_Voltage": 24.0, "Bus_Current": -1.5}, "host"),
    (SetAxisState(1, AXIS_STATE_CLOSED_LOOP_CONTROL), "Set_Axis_State", {"Axis_Requested_State": 8}, "drive"),
    (SetControllerMode(2, CONTROL_MODE_TORQUE_CONTROL, INPUT_MODE_PASSTHROUGH), "Set_Controller_Mode",
     {"Control_Mode": 1, "Input_Mode": 1}, "drive"),
    (SetInputTorque(3, -0.75), "Set_Input_Torque", {"Input_Torque": -0.75}, "drive"),
    (ClearErrors(0), "Clear_Errors", {"Identify": 0}, "drive"),
    (Estop(1), "Estop", {}, "drive"),
]


def frame(arb: int, data: bytes = b"", **kw) -> can.Message:
    return can.Message(arbitration_id=arb, data=data, is_extended_id=kw.pop("is_extended_id", False), **kw)


def codec(role: str = "host", **kw) -> OdriveCanSimple:
    return OdriveCanSimple(NODES, role=role, **kw)


@pytest.mark.parametrize(("msg", "name", "signals", "role"), CASES, ids=[c[1] for c in CASES])
def test_round_trip_and_bytes_equal_the_dbc(msg, name, signals, role):
    c = codec(role)
    f = c.encode(msg)
    ref = DB.get_message_by_name(name)
    assert f.arbitration_id == msg.node << 5 | ref.frame_id
    assert not f.is_extended_id and not f.is_remote_frame
    assert bytes(f.data) == ref.encode(signals) and f.dlc == ref.length
    assert c.decode(f) == msg
    assert c.counters.decoded == 1 and c.counters.rejected == 0


def test_cansimple_ids_and_little_endian_layout():
    # the documented wire format, independent of the DBC file
    f = codec("drive").encode(SetInputTorque(3, 0.5))
    assert f.arbitration_id == 0x06E and bytes(f.data) == struct.pack("<f", 0.5) + bytes(4)
    f = codec().encode(Heartbeat(2, 0x800, 8, 0, True))
    assert f.arbitration_id == 0x041 and bytes(f.data) == struct.pack("<IBBB", 0x800, 8, 0, 1) + bytes(1)
    f = codec().encode(EncoderEstimate(1, 1.0, -2.0))
    assert f.arbitration_id == 0x029 and bytes(f.data) == struct.pack("<ff", 1.0, -2.0)


def test_requests_are_remote_frames_decoded_by_the_drive_only():
    f = codec("host").encode(Request(2, CMD_GET_ERROR))
    assert f.is_remote_frame and f.arbitration_id == 2 << 5 | 0x003
    drive, host = codec("drive"), codec("host")
    assert drive.decode(f) == Request(2, CMD_GET_ERROR)
    assert host.decode(f) is None and host.counters.ignored_direction == 1
    assert drive.decode(frame(2 << 5 | 0x00E, is_remote_frame=True)) is None  # not requestable
    assert drive.counters.unknown_id == 1


@given(node=st.sampled_from(NODES), pos=st.floats(-1e6, 1e6), vel=st.floats(-1e4, 1e4),
       torque=st.floats(-1e3, 1e3))
@settings(max_examples=150, deadline=None)
def test_float_round_trip_is_float32_exact(node, pos, vel, torque):
    host, drive = codec("host"), codec("drive")
    e = host.decode(host.encode(EncoderEstimate(node, pos, vel)))
    assert e == EncoderEstimate(node, float(np.float32(pos)), float(np.float32(vel)))
    t = drive.decode(drive.encode(SetInputTorque(node, torque)))
    assert t == SetInputTorque(node, float(np.float32(torque)))


def test_the_driver_plug_in_sends_the_arming_frames_and_reports_in_neutral_terms():
    c = OdriveDriver(DriverSettings(NODES))
    assert isinstance(c, WheelDriver) and c.name == "odrive-cansimple"
    drive = codec("drive")
    # torque control, closed loop, and its heartbeat asked for at once (remote frame)
    assert [drive.decode(f) for f in c.arm_frames(1)] == [
        SetControllerMode(1, CONTROL_MODE_TORQUE_CONTROL, INPUT_MODE_PASSTHROUGH),
        SetAxisState(1, AXIS_STATE_CLOSED_LOOP_CONTROL), Request(1, CMD_HEARTBEAT)]
    assert [drive.decode(f) for f in c.disarm_frames(1)] == [SetInputTorque(1, 0.0),
                                                             SetAxisState(1, AXIS_STATE_IDLE)]
    assert drive.decode(c.torque_frame(2, 1.25)) == SetInputTorque(2, 1.25)
    assert [drive.decode(f) for f in c.estop_frames(3)] == [Estop(3)]
    assert [drive.decode(f) for f in c.clear_faults_frames(0)] == [ClearErrors(0)]
    assert c.cycle_frames(0.0) == []  # its torque frames feed the watchdogs
    # what the drives send, in neutral terms
    assert c.decode(drive.encode(Heartbeat(1, AXIS_ERROR_WATCHDOG_TIMER_EXPIRED, AXIS_STATE_IDLE))) \
        == WheelReport(1, state=DriveState.FAULT, fault=0x800, recoverable=True)
    assert c.decode(drive.encode(Heartbeat(1, 0x4800, AXIS_STATE_IDLE))) \
        == WheelReport(1, state=DriveState.FAULT, fault=0x4800, recoverable=False)
    assert c.decode(drive.encode(Heartbeat(2, 0, AXIS_STATE_CLOSED_LOOP_CONTROL))) \
        == WheelReport(2, state=DriveState.ENABLED, fault=0, recoverable=False)
    assert c.decode(drive.encode(Heartbeat(2, 0, 4))).state is DriveState.STARTING  # calibrating
    assert c.decode(drive.encode(EncoderEstimate(3, 2.5, -1.0))) == WheelReport(3, 2.5, -1.0)
    assert c.describe(2) == "axis state 4, axis error 0x0"  # the newest heartbeat
    assert "watchdog" in c.describe_fault(0x800) and "e-stop" in c.describe_fault(0x4000)


def test_other_nodes_and_unknown_commands_are_counted():
    host, drive = codec("host"), codec("drive")
    other = OdriveCanSimple([7], role="host").encode(Heartbeat(7, 0, 1))
    assert host.decode(other) is None and host.counters.unknown_id == 1
    assert drive.decode(frame(1 << 5 | 0x00D, bytes(8))) is None  # Set_Input_Vel: not in this subset
    assert drive.decode(frame(1 << 5 | 0x01F, bytes(8))) is None
    assert drive.counters.unknown_id == 2
    # each side ignores the other direction
    assert host.decode(drive.encode(SetInputTorque(1, 0.1))) is None
    assert drive.decode(host.encode(Heartbeat(1, 0, 8))) is None
    assert host.counters.ignored_direction == 1 and drive.counters.ignored_direction == 1


def test_extended_error_and_fd_frames_are_not_cansimple():
    host = codec()
    good = host.encode(Heartbeat(1, 0, 8))
    ext = frame(good.arbitration_id, bytes(good.data), is_extended_id=True)
    err = frame(0, is_error_frame=True)
    fd = frame(good.arbitration_id, bytes(good.data), is_fd=True)
    assert [host.decode(f) for f in (ext, err, fd)] == [None, None, None]
    assert host.counters.other_frame == 3 and host.counters.decoded == 0


@pytest.mark.parametrize(("role", "arb", "length", "ok"), [
    ("host", 0x021, 7, True),  # heartbeat: 49 bits of signals fit 7 bytes; the DBC says 8
    ("host", 0x021, 6, False),
    ("host", 0x029, 7, False),  # encoder estimates: 8 exactly
    ("host", 0x029, 8, True),
    ("drive", 0x02E, 3, False),  # torque: a float32 needs 4
    ("drive", 0x02E, 4, True),  # as some ODrive tools send it
    ("drive", 0x02E, 8, True),
    ("drive", 0x038, 0, True),  # Clear_Errors: 0 or 1
    ("drive", 0x038, 1, True),
    ("drive", 0x038, 2, False),
    ("drive", 0x022, 0, True),  # Estop: no payload
    ("drive", 0x022, 1, False),
    ("drive", 0x027, 3, False),
])
def test_lengths(role, arb, length, ok):
    c = codec(role)
    out = c.decode(frame(arb, bytes(length)))
    assert (out is not None) == ok
    assert c.counters.bad_length == (0 if ok else 1)


@pytest.mark.parametrize(("role", "arb", "data"), [
    ("host", 0x029, struct.pack("<ff", math.nan, 1.0)),
    ("host", 0x029, struct.pack("<ff", 1.0, math.inf)),
    ("host", 0x029, struct.pack("<ff", 1.0, 2e4)),  # |vel| beyond the 1e4 rev/s bound
    ("host", 0x021, struct.pack("<IBBBB", 0, 5, 0, 1, 0)),  # axis state 5 does not exist
    ("host", 0x021, struct.pack("<IBBBB", 0, 8, 99, 1, 0)),  # no such procedure result
    ("host", 0x037, struct.pack("<ff", -1.0, 0.0)),  # negative bus voltage
    ("host", 0x037, struct.pack("<ff", math.nan, 0.0)),
    ("drive", 0x02E, struct.pack("<f", math.nan) + bytes(4)),
    ("drive", 0x02E, struct.pack("<f", -5e3) + bytes(4)),  # beyond the 1e3 N m bound
    ("drive", 0x027, struct.pack("<II", 200, 0)),
    ("drive", 0x02B, struct.pack("<II", 1, 42)),
])
def test_implausible_values_are_invalid(role, arb, data):
    c = codec(role)
    assert c.decode(frame(arb, data)) is None
    assert c.counters.invalid == 1 and c.counters.decoded == 0


def test_bounds_are_configurable():
    c = OdriveCanSimple(NODES, max_abs_velocity_rev_s=10.0)
    assert c.decode(frame(0x029, struct.pack("<ff", 0.0, 10.5))) is None
    assert c.decode(frame(0x029, struct.pack("<ff", 0.0, 9.5))) == EncoderEstimate(1, 0.0, 9.5)


@pytest.mark.parametrize("msg", [
    SetInputTorque(1, math.nan), SetInputTorque(1, 2e3), SetInputTorque(9, 0.0),
    EncoderEstimate(1, 1e39, 0.0),  # overflows float32 to inf on the wire
    Heartbeat(1, 0, 5), Heartbeat(1, -1, 8), SetAxisState(0, 77), Request(0, 0x00E),
])
def test_encode_refuses_what_decode_would_reject(msg):
    with pytest.raises(ValueError):
        codec().encode(msg)


@given(node=st.sampled_from([*NODES, 0, 9]),
       torque=st.one_of(st.floats(-2.5, 2.5), st.floats(allow_nan=True, allow_infinity=True)))
@settings(max_examples=300, deadline=None)
def test_the_torque_frame_is_the_general_encoding_of_its_command(node, torque):
    """The command's short path (four frames a period) gives the frame ``encode`` gives,
    and refuses what it refuses, with its reason."""
    c = OdriveCanSimple(NODES, max_abs_torque_nm=2.5)
    try:
        general = c.encode(SetInputTorque(node, torque))
    except ValueError as exc:
        with pytest.raises(ValueError, match=re.escape(str(exc))):
            c.torque_frame(node, torque)
        return
    fast = c.torque_frame(node, torque)
    assert (fast.arbitration_id, bytes(fast.data), fast.dlc, fast.is_extended_id,
            fast.is_remote_frame) == (general.arbitration_id, bytes(general.data), general.dlc,
                                      general.is_extended_id, general.is_remote_frame)


@given(node=st.sampled_from([*NODES, 9]),
       pos=st.one_of(st.floats(-1e6, 1e6), st.floats(allow_nan=True, allow_infinity=True)),
       vel=st.one_of(st.floats(-12.0, 12.0), st.floats(allow_nan=True, allow_infinity=True),
                     st.sampled_from([10.0, 10.0000001, -10.0000001, 9.9999999])))
@settings(max_examples=400, deadline=None)
def test_the_encoder_frame_is_the_general_encoding_of_its_estimate(node, pos, vel):
    """An emulated drive's encoder estimates by the short path: the frame ``encode`` gives,
    and what it refuses (a velocity past the bound once rounded to float32 too)."""
    c = OdriveCanSimple(NODES, role="drive", max_abs_velocity_rev_s=10.0)
    try:
        general = c.encode(EncoderEstimate(node, pos, vel))
    except ValueError as exc:
        with pytest.raises(ValueError, match=re.escape(str(exc))):
            c.encoder_frame(node, pos, vel)
        return
    fast = c.encoder_frame(node, pos, vel)
    assert (fast.arbitration_id, bytes(fast.data), fast.dlc, fast.is_extended_id) == (
        general.arbitration_id, bytes(general.data), general.dlc, general.is_extended_id)


def test_a_torque_bound_beyond_float32_takes_the_checked_path():
    c = OdriveCanSimple(NODES, max_abs_torque_nm=1e39)
    with pytest.raises(ValueError, match="cannot encode"):
        c.torque_frame(1, 5e38)  # beyond float32: refused, as encode refuses it
    assert c.decode(c.torque_frame(1, 0.5)) is None  # a host's codec: a command is not for it
    assert codec("drive").decode(c.torque_frame(1, 0.5)) == SetInputTorque(1, 0.5)


def test_bad_constructor_arguments():
    for ids in ([], [64], [1, 1]):
        with pytest.raises(ValueError):
            OdriveCanSimple(ids)
    with pytest.raises(ValueError):
        OdriveCanSimple(NODES, role="bridge")


frames = st.builds(
    lambda arb, ext, data, remote, err: can.Message(
        arbitration_id=arb if ext else arb & 0x7FF, is_extended_id=ext, data=None if remote else data,
        is_remote_frame=remote, is_error_frame=err, dlc=len(data), check=False),
    st.integers(0, 0x1FFFFFFF), st.booleans(), st.binary(max_size=8), st.booleans(), st.booleans())


@given(st.lists(frames, min_size=1, max_size=20), st.sampled_from(["host", "drive"]))
@settings(max_examples=200, deadline=None)
def test_garbage_never_raises_and_every_frame_is_counted_once(batch, role):
    c = codec(role)
    for f in batch:
        out = c.decode(f)
        assert out is None or c.problem(out) is None  # whatever passes is a valid frame
    k = c.counters
    assert k.decoded + k.rejected == len(batch)


@given(st.binary(min_size=8, max_size=8), st.sampled_from([0x001, 0x003, 0x009, 0x017]))
@settings(max_examples=200, deadline=None)
def test_random_payloads_of_real_ids(data, cmd):
    c = codec()
    out = c.decode(frame(1 << 5 | cmd, data))
    k = c.counters
    assert (out is None) == (k.invalid == 1) and k.decoded + k.invalid == 1
    if isinstance(out, EncoderEstimate | BusVoltageCurrent):
        vals = [getattr(out, f) for f in out.__dataclass_fields__ if f != "node"]
        assert all(math.isfinite(v) for v in vals)


def test_a_malformed_message_object_is_counted_not_raised():
    c = codec()
    f = frame(0x029, bytes(8))
    f.data = None  # python-can allows it
    f.dlc = 8
    assert c.decode(f) is None
    assert c.decode(object()) is None  # type: ignore[arg-type]
    assert c.counters.bad_length == 1 and c.counters.invalid == 1


def test_bus_voltage_request_ids():
    f = codec().encode(Request(3, CMD_GET_BUS_VOLTAGE_CURRENT))
    assert f.arbitration_id == 3 << 5 | 0x17 and f.dlc == 8


# --- the fast packing equals cantools, for every message of the DBC ----------------------
def _signal_values(m) -> st.SearchStrategy:
    """Signal values for message ``m``: in range, at the bounds, beyond them."""
    parts = {}
    for s in m.signals:
        if s.is_float:
            parts[s.name] = st.one_of(st.floats(width=32), st.floats(allow_nan=False),
                                      st.sampled_from([0.0, -0.0, 3.4028234e38, 3.5e38, 1e-45]))
        else:
            hi = (1 << s.length) - 1
            parts[s.name] = st.one_of(st.integers(0, hi), st.sampled_from([0, hi, hi + 1, -1]))
    return st.fixed_dictionaries(parts)


def _cantools_encode(m, signals):
    try:
        return m.encode(signals, strict=True)
    except Exception:  # noqa: BLE001 - any refusal counts as a refusal
        return None


def _fast_encode(p, signals):
    try:
        return p.encode(signals)
    except ValueError:
        return None


def _same(a: dict, b: dict) -> bool:
    """Equal signal values (NaN equals NaN: a payload may carry one)."""
    def eq(x, y) -> bool:
        return (math.isnan(x) and math.isnan(y)) if isinstance(x, float) and math.isnan(x) else x == y

    return a.keys() == b.keys() and all(eq(a[k], b[k]) for k in a)


@pytest.mark.parametrize("name", [m.name for m in DB.messages])
@given(data=st.data())
@settings(max_examples=300, deadline=None)
def test_fast_packing_equals_cantools_for_every_dbc_message(name, data):
    from bridges.odrive import _Packing

    m = DB.get_message_by_name(name)
    p = _Packing(m)
    assert p.unsupported is None, p.unsupported  # CANSimple needs no cantools at run time
    signals = data.draw(_signal_values(m))
    ref = _cantools_encode(m, signals)
    got = _fast_encode(p, signals)
    if ref is None or got is None:
        # both refuse, except cantools packing a finite float beyond float32 as inf, which
        # the codec refuses later anyway (it would decode as invalid)
        beyond = [s.name for s in m.signals if s.is_float and abs(signals[s.name]) > 3.4028235e38]
        assert got is None and (ref is None or beyond), (signals, ref, got)
    else:
        assert got == bytes(ref), signals
    payload = data.draw(st.binary(min_size=m.length, max_size=m.length))
    ref_sig = m.decode(payload, decode_choices=False, scaling=True)
    assert _same(p.decode(payload), ref_sig), payload.hex()
