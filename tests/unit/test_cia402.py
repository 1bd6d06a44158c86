"""CiA 402 over CANopen: the profile's state machine against the standard, the PDO
packing against canopen's, the host driver's frames and decoding (units, unwrapping,
rejection of everything else), and a bad EDS or node id named."""

from __future__ import annotations

import math
import struct

import can
import canopen
import pytest
from canopen.profiles.p402 import State402
from hypothesis import given, settings
from hypothesis import strategies as st

from bridges import cia402 as p
from bridges.cia402_driver import DEFAULT_EDS, Cia402Driver, load_od
from bridges.cia402_pdo import PdoLayout
from bridges.driver import DriverSettings, DriveState, WheelDriver, WheelReport

S = p.State
NODES = (1, 2, 3, 4)
SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP = 0x06, 0x07, 0x0F, 0x00, 0x02
COMMANDS = {"shutdown": SHUTDOWN, "switch on": SWITCH_ON, "enable operation": ENABLE,
            "disable voltage": DISABLE_VOLTAGE, "quick stop": QUICK_STOP}

# The standard's device control (IEC 61800-7-201 / CiA 402-2, "state machine"): the
# state each command leads to from each state, with the transition's number.
STANDARD = {
    (S.SWITCH_ON_DISABLED, "shutdown"): (S.READY_TO_SWITCH_ON, 2),
    (S.READY_TO_SWITCH_ON, "switch on"): (S.SWITCHED_ON, 3),
    (S.READY_TO_SWITCH_ON, "enable operation"): (S.OPERATION_ENABLED, 4),  # 3 + 4
    (S.SWITCHED_ON, "enable operation"): (S.OPERATION_ENABLED, 4),
    (S.OPERATION_ENABLED, "switch on"): (S.SWITCHED_ON, 5),  # "disable operation"
    (S.SWITCHED_ON, "shutdown"): (S.READY_TO_SWITCH_ON, 6),
    (S.READY_TO_SWITCH_ON, "disable voltage"): (S.SWITCH_ON_DISABLED, 7),
    (S.READY_TO_SWITCH_ON, "quick stop"): (S.SWITCH_ON_DISABLED, 7),
    (S.OPERATION_ENABLED, "shutdown"): (S.READY_TO_SWITCH_ON, 8),
    (S.OPERATION_ENABLED, "disable voltage"): (S.SWITCH_ON_DISABLED, 9),
    (S.SWITCHED_ON, "disable voltage"): (S.SWITCH_ON_DISABLED, 10),
    (S.SWITCHED_ON, "quick stop"): (S.SWITCH_ON_DISABLED, 10),
    (S.OPERATION_ENABLED, "quick stop"): (S.QUICK_STOP_ACTIVE, 11),
    (S.QUICK_STOP_ACTIVE, "disable voltage"): (S.SWITCH_ON_DISABLED, 12),
}


@pytest.mark.parametrize("state", list(S), ids=lambda s: s.value)
@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("extra_bits", [0x0000, 0x0170])  # halt and mode-specific bits: no say
def test_every_transition_a_controlword_drives_is_the_standards(state, command, extra_bits):
    cw = COMMANDS[command] | extra_bits
    got = p.next_state(state, cw, previous_controlword=0)
    want = STANDARD.get((state, command), (state, None))
    assert got == want


def test_quick_stop_active_returns_to_operation_only_with_option_codes_5_to_8():
    assert p.next_state(S.QUICK_STOP_ACTIVE, ENABLE, 0) == (S.QUICK_STOP_ACTIVE, None)
    assert p.next_state(S.QUICK_STOP_ACTIVE, ENABLE, 0, quick_stop_holds=True) == \
        (S.OPERATION_ENABLED, 16)


def test_fault_reset_is_a_rising_edge_of_bit_7_and_nothing_else_leaves_fault():
    for cw in (*COMMANDS.values(), 0x8F):
        assert p.next_state(S.FAULT, cw, previous_controlword=0x80)[0] is S.FAULT
    assert p.next_state(S.FAULT, 0x80, previous_controlword=0x06) == (S.SWITCH_ON_DISABLED, 15)
    assert p.next_state(S.FAULT, 0x80, previous_controlword=0x80) == (S.FAULT, None)
    # bit 7 outside FAULT is the reset command too: no transition (enable is not obeyed)
    assert p.next_state(S.SWITCHED_ON, 0x8F, 0x07) == (S.SWITCHED_ON, None)
    for state in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE):  # left on their own
        assert all(p.next_state(state, cw, 0)[1] is None for cw in (*COMMANDS.values(), 0x80))


def test_statusword_patterns_are_canopens_and_round_trip():
    for state in S:
        sw = p.statusword_of(state)
        mask, bits = State402.SW_MASK[state.value]
        assert sw & mask == bits and p.state_of(sw) is state
        assert sw & p.REMOTE
        assert bool(sw & p.VOLTAGE_ENABLED) == (state in (
            S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE))
    # every 16-bit word is either exactly one state or none (then the host counts it invalid)
    for sw in range(0x10000):
        matches = [s for s in S if sw & State402.SW_MASK[s.value][0] == State402.SW_MASK[s.value][1]]
        assert p.state_of(sw) is (matches[0] if matches else None) and len(matches) <= 1


def test_the_commands_are_canopens():
    assert (p.CW_SHUTDOWN, p.CW_SWITCH_ON, p.CW_ENABLE_OPERATION, p.CW_DISABLE_VOLTAGE,
            p.CW_QUICK_STOP) == (SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP)
    assert State402.TRANSITIONTABLE[("SWITCH ON DISABLED", "READY TO SWITCH ON")] == p.CW_SHUTDOWN
    assert State402.TRANSITIONTABLE[("OPERATION ENABLED", "QUICK STOP ACTIVE")] == p.CW_QUICK_STOP


def test_arming_walks_the_drive_through_transitions_2_3_4_and_out_of_a_quick_stop():
    state, path = S.SWITCH_ON_DISABLED, []
    while state is not S.OPERATION_ENABLED:
        state, number = p.next_state(state, p.arming_command(state), 0)
        path.append(number)
    assert path == [2, 3, 4]
    assert p.next_state(S.QUICK_STOP_ACTIVE, p.arming_command(S.QUICK_STOP_ACTIVE), 0) == \
        (S.SWITCH_ON_DISABLED, 12)
    assert p.arming_command(S.FAULT) is None and p.arming_command(None) == SHUTDOWN
    assert [p.neutral(s) for s in (S.SWITCH_ON_DISABLED, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE,
                                   S.FAULT)] == [DriveState.DISABLED, DriveState.ENABLED,
                                                 DriveState.STOPPING, DriveState.FAULT]


# --- PDO packing equals canopen's -----------------------------------------------------------
def _maps():
    node = canopen.RemoteNode(5, load_od(DEFAULT_EDS, 5))
    canopen.Network().add_node(node)
    node.pdo.read(from_od=True)
    return [m for m in (*node.rpdo.values(), *node.tpdo.values()) if m.enabled]


@pytest.mark.parametrize("index", range(3))
@given(data=st.data())
@settings(max_examples=100, deadline=None)
def test_pdo_layout_packs_and_unpacks_as_canopen(index, data):
    m = _maps()[index]
    lay = PdoLayout.of(m)
    values = {}
    for var in m:
        bits = var.length
        signed = var.od.data_type in canopen.objectdictionary.SIGNED_TYPES
        lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
        values[var.index] = data.draw(st.integers(lo, hi))
        var.raw = values[var.index]  # canopen packs it into m.data
    assert lay.pack(values) == bytes(m.data)
    payload = data.draw(st.binary(min_size=lay.length, max_size=8))
    m.data = bytearray(payload)
    assert lay.unpack(payload) == {var.index: var.raw for var in m}


def test_a_pdo_packs_in_one_struct_and_still_names_what_does_not_fit():
    for m in _maps():  # every PDO the emulated drive maps: end to end from byte 0
        lay = PdoLayout.of(m)
        assert lay.whole is not None and lay.whole.size == lay.length
        first = lay.fields[0][0]
        big = {i: 0 for i, _, _ in lay.fields} | {first: 1 << 40}
        with pytest.raises(ValueError, match=f"0x{first:04X}"):
            lay.pack(big)
    gap = PdoLayout("gap", 0x201, 255, ((0x6040, 0, struct.Struct("<H")),
                                        (0x6071, 4, struct.Struct("<h"))), 6)
    assert gap.whole is None and gap.pack({0x6040: 15, 0x6071: -2}) == \
        struct.pack("<H2xh", 15, -2)


# --- the host driver --------------------------------------------------------------------------
def driver(**kw) -> Cia402Driver:
    return Cia402Driver(DriverSettings(NODES, **kw))


def frame(cob: int, data: bytes = b"", **kw) -> can.Message:
    return can.Message(arbitration_id=cob, data=data, is_extended_id=kw.pop("is_extended_id", False),
                       **kw)


def status(node: int, sw: int, torque_pm: int = 0, error: int = 0) -> can.Message:
    return frame(0x180 + node, struct.pack("<HhH", sw, torque_pm, error))


def motion(node: int, position: int, velocity: int) -> can.Message:
    return frame(0x280 + node, struct.pack("<ii", position, velocity))


def test_is_a_wheel_driver_with_the_edss_mapping_and_units():
    d = driver()
    assert isinstance(d, WheelDriver) and d.name == "cia402"
    control, torque, tpdos = d.layouts(2)
    assert control is torque and control.cob_id == 0x202 and not control.synchronous
    assert [lay.cob_id for lay in tpdos] == [0x182, 0x282] and all(t.synchronous for t in tpdos)
    u = d.units(1)  # the EDS's: 1 N m rated, 2 motor turns per wheel turn, 4096 per motor turn
    assert u.wheel_nm_per_mille == pytest.approx(0.002) and u.increments_per_wheel_rev == 8192
    assert d.max_abs_torque_nm == pytest.approx(32767 * 0.002)


def test_torque_frames_carry_per_mille_of_rated_torque_and_the_current_controlword():
    d = driver()
    f = d.torque_frame(3, 0.5)  # 0.5 N m at the wheel = 250 per mille of 1 N m x 2
    assert f.arbitration_id == 0x203 and bytes(f.data) == struct.pack("<Hh", DISABLE_VOLTAGE, 250)
    assert bytes(d.torque_frame(3, -0.0031).data)[2:] == struct.pack("<h", -2)  # rounded
    for bad in (math.nan, math.inf, 66.0):
        with pytest.raises(ValueError):
            d.torque_frame(3, bad)
    (arm,) = d.arm_frames(3)  # nothing heard yet: shutdown, which enables nothing
    assert bytes(arm.data) == struct.pack("<Hh", SHUTDOWN, -2)
    sync, beat = d.cycle_frames(10.0)
    assert (sync.arbitration_id, bytes(sync.data)) == (0x080, b"")
    assert (beat.arbitration_id, bytes(beat.data)) == (0x77F, b"\x05")  # operational
    assert len(d.cycle_frames(10.01)) == 1 and len(d.cycle_frames(10.06)) == 2  # every 50 ms


def test_arming_follows_the_status_and_the_e_stop_is_the_drives_quick_stop_held():
    d = driver()
    cw = lambda frames: [struct.unpack_from("<H", bytes(f.data))[0] for f in frames]  # noqa: E731
    for sw, want in ((0x0240, SHUTDOWN), (0x0231, SWITCH_ON), (0x0233, ENABLE), (0x0237, ENABLE)):
        d.decode(status(1, sw))
        assert cw(d.arm_frames(1)) == [want]
    assert cw(d.clear_faults_frames(1)) == []  # not in fault: nothing to reset
    assert cw(d.disarm_frames(1)) == [SHUTDOWN]  # transition 8: power off
    assert cw(d.estop_frames(1)) == [QUICK_STOP]
    assert cw(d.disarm_frames(1)) == [QUICK_STOP]  # the quick stop is not undone
    d.decode(status(1, 0x0208, error=0x8130))  # a fault: reset with a rising edge of bit 7
    assert d.arm_frames(1) == []
    assert cw(d.clear_faults_frames(1)) == [0x80]
    assert cw(d.clear_faults_frames(1)) == [0x00, 0x80]  # bit 7 was high: lowered first
    d.decode(status(1, 0x0240))
    assert cw(d.arm_frames(1)) == [SHUTDOWN] and cw(d.disarm_frames(1)) == [SHUTDOWN]


def test_statuses_and_motion_in_neutral_terms():
    d = driver()
    r = d.decode(status(2, 0x0237, torque_pm=-125))
    assert r == WheelReport(2, torque_nm=pytest.approx(-0.25), state=DriveState.ENABLED, fault=0)
    r = d.decode(status(2, 0x0208, error=0x8130))  # heartbeat lost: recoverable
    assert (r.state, r.fault, r.recoverable) == (DriveState.FAULT, 0x8130, True)
    r = d.decode(status(2, 0x0208, error=0x2310))  # over-current: not recoverable
    assert (r.state, r.fault, r.recoverable) == (DriveState.FAULT, 0x2310, False)
    r = d.decode(status(2, 0x0208))  # a fault the drive gives no code for
    assert r.fault == p.ERROR_GENERIC and not r.recoverable
    assert d.decode(status(2, 0x0231, error=0x4310)).fault == 0  # a warning: not a fault
    r = d.decode(motion(3, 8192 * 3, -4096))
    assert (r.position_rev, r.velocity_rev_s, r.state) == (3.0, -0.5, None)
    assert d.describe(2) == "READY TO SWITCH ON, NMT ?"


def test_position_is_unwrapped_across_the_int32_boundary():
    d = driver()
    top = (1 << 31) - 100
    first = d.decode(motion(1, top, 0)).position_rev
    after = d.decode(motion(1, -(1 << 31) + 100, 0)).position_rev  # 200 increments on, wrapped
    assert after - first == pytest.approx(200 / 8192)
    back = d.decode(motion(1, top, 0)).position_rev
    assert back == pytest.approx(first)


@pytest.mark.parametrize(("f", "counter"), [
    (frame(0x281, bytes(7)), "bad_length"),  # motion needs 8
    (frame(0x181, bytes(5)), "bad_length"),  # status needs 6
    (frame(0x181, struct.pack("<HhH", 0x0001, 0, 0)), "invalid"),  # no state has this pattern
    (frame(0x281, struct.pack("<ii", 0, 8192 * 20000)), "invalid"),  # 20000 rev/s
    (frame(0x201, bytes(4)), "ignored_direction"),  # our own RPDO, heard back
    (frame(0x080), "ignored_direction"),  # SYNC
    (frame(0x77F, b"\x05"), "ignored_direction"),  # our heartbeat
    (frame(0x000, b"\x01\x00"), "ignored_direction"),  # NMT
    (frame(0x602, bytes(8)), "ignored_direction"),  # an SDO request
    (frame(0x189, bytes(6)), "unknown_id"),  # node 9 is not ours
    (frame(0x381, bytes(8)), "unknown_id"),  # a TPDO the mapping does not enable
    (frame(0x701, b"\x05\x00"), "bad_length"),
    (frame(0x701, b"\x33"), "invalid"),  # no such NMT state
    (frame(0x181, bytes(6), is_extended_id=True), "other_frame"),
    (frame(0x181, is_remote_frame=True), "other_frame"),
    (frame(0, is_error_frame=True), "other_frame"),
])
def test_what_is_not_a_valid_frame_for_the_host_is_counted(f, counter):
    d = driver()
    assert d.decode(f) is None
    c = d.counters.as_dict()
    assert c[counter] == 1 and sum(c.values()) == 1


def test_heartbeats_emergencies_and_sdo_answers_are_decoded_without_wheel_news():
    d = driver()
    assert d.decode(frame(0x701, b"\x05")) == WheelReport(1)
    assert d.decode(frame(0x081, struct.pack("<HB5s", 0x2310, 1, b""))) == WheelReport(1)
    assert d.decode(frame(0x581, bytes(8))) == WheelReport(1)
    assert d.counters.decoded == 3
    assert d.describe(1) == "no statusword yet, NMT OPERATIONAL, last EMCY 0x2310 (continuous over-current)"


frames = st.builds(
    lambda arb, ext, data, remote, err: can.Message(
        arbitration_id=arb if ext else arb & 0x7FF, is_extended_id=ext, data=None if remote else data,
        is_remote_frame=remote, is_error_frame=err, dlc=len(data), check=False),
    st.one_of(st.integers(0, 0x7FF), st.sampled_from([0x181, 0x281, 0x701, 0x81, 0x581])),
    st.booleans(), st.binary(max_size=8), st.booleans(), st.booleans())


@given(st.lists(frames, min_size=1, max_size=20))
@settings(max_examples=200, deadline=None)
def test_garbage_never_raises_and_every_frame_is_counted_once(batch):
    d = driver()
    for f in batch:
        r = d.decode(f)
        assert r is None or isinstance(r, WheelReport)
    k = d.counters
    assert k.decoded + k.rejected == len(batch)


# --- a bad EDS or node id is named -------------------------------------------------------------
@pytest.mark.parametrize("ids", [(0, 1, 2, 3), (1, 2, 3, 128), (1, 1, 2, 3), (1, 2, 3, 127)])
def test_bad_node_ids_are_named(ids):
    with pytest.raises(ValueError, match="node id"):
        Cia402Driver(DriverSettings(ids))  # 127 is the host's heartbeat


def _eds_without(tmp_path, what: str, replace: str = "") -> str:
    text = DEFAULT_EDS.read_text().replace(what, replace)
    path = tmp_path / "drive.eds"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(("edit", "says"), [
    (("[6071]", "[6999]"), "no object 0x6071"),
    (("DefaultValue=0x60640020", "DefaultValue=0x60640018"), "not mapped as a whole number"),
    (("DefaultValue=0x60640020\nPDOMapping=0\n\n[1A01sub2]", "DefaultValue=0x60410010\n"
      "PDOMapping=0\n\n[1A01sub2]"), "mapped"),  # position gone from the TPDOs
    (("ParameterName=Transmission type\nObjectType=0x7\nDataType=0x0005\nAccessType=rw\n"
      "DefaultValue=1", "ParameterName=Transmission type\nObjectType=0x7\nDataType=0x0005\n"
      "AccessType=rw\nDefaultValue=255"), "sent on events"),
])
def test_a_bad_eds_is_named_with_what_is_wrong(tmp_path, edit, says):
    path = _eds_without(tmp_path, *edit)
    with pytest.raises(ValueError) as exc:
        Cia402Driver(DriverSettings(NODES, eds=path))
    assert path in str(exc.value) and says in str(exc.value)


def test_a_file_that_is_no_eds_is_named(tmp_path):
    junk = tmp_path / "junk.eds"
    junk.write_text("[6040\nthis is not an EDS")
    for path in (str(junk), str(tmp_path / "missing.eds")):
        with pytest.raises(ValueError, match="EDS .*cannot be read") as exc:
            Cia402Driver(DriverSettings(NODES, eds=path))
        assert path in str(exc.value)
