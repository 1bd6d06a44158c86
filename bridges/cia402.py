"""The CiA 402 drive profile (IEC 61800-7-201): its power state machine, the
controlword commands that drive it and the statusword that reports it. Pure: no bus,
no object dictionary. The host (:mod:`bridges.cia402_driver`) walks a drive through
it; the emulator (:mod:`bridges.cia402_emulator`) is a drive that obeys it.

State machine (the standard's transition numbers)::

    NOT READY TO SWITCH ON --1 (automatic)--> SWITCH ON DISABLED
    SWITCH ON DISABLED --2 shutdown--> READY TO SWITCH ON
    READY TO SWITCH ON --3 switch on--> SWITCHED ON  (--3+4 switch on + enable operation)
    SWITCHED ON --4 enable operation--> OPERATION ENABLED
    OPERATION ENABLED --5 disable operation--> SWITCHED ON
    SWITCHED ON --6 shutdown--> READY TO SWITCH ON
    READY TO SWITCH ON --7 disable voltage | quick stop--> SWITCH ON DISABLED
    OPERATION ENABLED --8 shutdown--> READY TO SWITCH ON
    OPERATION ENABLED --9 disable voltage--> SWITCH ON DISABLED
    SWITCHED ON --10 disable voltage | quick stop--> SWITCH ON DISABLED
    OPERATION ENABLED --11 quick stop--> QUICK STOP ACTIVE
    QUICK STOP ACTIVE --12 disable voltage (or the quick stop done, option codes 1-4)--> SWITCH ON DISABLED
    any state --13 a fault--> FAULT REACTION ACTIVE --14 (automatic)--> FAULT
    FAULT --15 fault reset (a rising edge of controlword bit 7)--> SWITCH ON DISABLED
    QUICK STOP ACTIVE --16 enable operation (option codes 5-8)--> OPERATION ENABLED

Only OPERATION ENABLED applies the target torque; QUICK STOP ACTIVE brakes.

Controlword bits: 0 switch on, 1 enable voltage, 2 quick stop (0 = stop), 3 enable
operation, 7 fault reset. The command values are canopen's own
(:class:`canopen.profiles.p402.State402`), fault reset aside. Statusword bits: 0 ready
to switch on, 1 switched on, 2 operation enabled, 3 fault, 4 voltage enabled, 5 quick
stop (0 = active), 6 switch on disabled, 7 warning, 9 remote; the state is read with
canopen's masks (``State402.SW_MASK``).
"""

from __future__ import annotations

import enum

from canopen.profiles.p402 import OperationMode, State402

from bridges.driver import DriveState

# --- objects of the profile (index) and of CiA 301 the drive uses ------------------------
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION_CODE = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064  # position units: encoder increments (factor group at 1)
VELOCITY_ACTUAL = 0x606C  # velocity units: increments per second
TARGET_TORQUE = 0x6071  # per mille of the motor's rated torque
MAX_TORQUE = 0x6072  # per mille of rated torque
MOTOR_RATED_TORQUE = 0x6076  # mN m
TORQUE_ACTUAL = 0x6077  # per mille of rated torque
TORQUE_SLOPE = 0x6087  # per mille of rated torque per second
POSITION_ENCODER_RESOLUTION = 0x608F  # sub 1 encoder increments / sub 2 motor revolutions
GEAR_RATIO = 0x6091  # sub 1 motor revolutions / sub 2 shaft (wheel) revolutions
SUPPORTED_DRIVE_MODES = 0x6502
DEVICE_TYPE = 0x1000  # low 16 bits: the profile number, 402
COMMUNICATION_CYCLE_PERIOD = 0x1006  # us: the SYNC period
CONSUMER_HEARTBEAT_TIME = 0x1016  # sub n: node id << 16 | time in ms
PRODUCER_HEARTBEAT_TIME = 0x1017  # ms
PROFILE_NUMBER = 402

# --- controlword commands ---------------------------------------------------------------
CW_SHUTDOWN = State402.CW_SHUTDOWN  # 0x06: transitions 2, 6, 8
CW_SWITCH_ON = State402.CW_SWITCH_ON  # 0x07: transition 3 (and 5, "disable operation")
CW_ENABLE_OPERATION = State402.CW_OPERATION_ENABLED  # 0x0F: transitions 4, 16 (3+4)
CW_DISABLE_VOLTAGE = State402.CW_DISABLE_VOLTAGE  # 0x00: transitions 7, 9, 10, 12
CW_QUICK_STOP = State402.CW_QUICK_STOP  # 0x02: transitions 7, 10, 11
CW_FAULT_RESET = 0x80  # bit 7; its rising edge: transition 15
FAULT_RESET_BIT = 0x80

# --- modes of operation -----------------------------------------------------------------
MODE_CYCLIC_SYNC_TORQUE = OperationMode.CYCLIC_SYNCHRONOUS_TORQUE  # 10
MODE_PROFILE_TORQUE = OperationMode.PROFILED_TORQUE  # 4, where a drive lacks CST
SUPPORTS_CST = OperationMode.SUPPORTED["CYCLIC SYNCHRONOUS TORQUE"]  # 0x6502 bit 9
SUPPORTS_PT = OperationMode.SUPPORTED["PROFILED TORQUE"]  # 0x6502 bit 3

# --- emergency error codes (CiA 301) the bridge and the emulator use --------------------
ERROR_GENERIC = 0x1000  # a fault whose drive reports no error code
ERROR_COMMUNICATION = 0x8100  # here: the SYNC stopped while operation was enabled
ERROR_HEARTBEAT = 0x8130  # life guard or heartbeat error: the host's heartbeat stopped
RECOVERABLE_ERRORS = frozenset({ERROR_COMMUNICATION, ERROR_HEARTBEAT})
ERROR_NAMES = {
    ERROR_GENERIC: "generic error",
    ERROR_COMMUNICATION: "communication: SYNC lost",
    ERROR_HEARTBEAT: "heartbeat of the host lost",
    0x2310: "continuous over-current",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4310: "drive over-temperature",
    0x7300: "sensor (encoder) error",
    0x8611: "following error",
}


class State(enum.Enum):
    """The power states of the standard, named as it names them."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


# the statusword bits 0-3, 5, 6 of each state (the masks are canopen's State402.SW_MASK)
_STATE_BITS = {
    State.NOT_READY_TO_SWITCH_ON: 0x00,
    State.SWITCH_ON_DISABLED: 0x40,
    State.READY_TO_SWITCH_ON: 0x21,
    State.SWITCHED_ON: 0x23,
    State.OPERATION_ENABLED: 0x27,
    State.QUICK_STOP_ACTIVE: 0x07,
    State.FAULT_REACTION_ACTIVE: 0x0F,
    State.FAULT: 0x08,
}
VOLTAGE_ENABLED = 0x10  # statusword bit 4
REMOTE = 0x200  # statusword bit 9: the controlword is obeyed
_POWERED = {State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
            State.QUICK_STOP_ACTIVE}


def _state_of_bits(bits: int) -> State | None:
    for state in State:
        mask, pattern = State402.SW_MASK[state.value]
        if bits & mask == pattern:
            return state
    return None


# statusword bits 0-3, 5, 6 (mask 0x6F) -> state, every combination worked out once
_STATE_OF_BITS = {bits: _state_of_bits(bits) for bits in range(0x80) if bits & 0x10 == 0}


def state_of(statusword: int) -> State | None:
    """The state a statusword reports (None: a bit pattern of no state)."""
    return _STATE_OF_BITS[statusword & 0x6F]


def statusword_of(state: State) -> int:
    """The statusword a drive in ``state`` reports (voltage enabled where the power
    stage has voltage, remote always)."""
    return _STATE_BITS[state] | (VOLTAGE_ENABLED if state in _POWERED else 0) | REMOTE


def next_state(state: State, controlword: int, previous_controlword: int,
               quick_stop_holds: bool = False) -> tuple[State, int | None]:
    """The state a drive in ``state`` goes to on ``controlword`` (the one before it:
    ``previous_controlword``, for the fault reset edge), with the transition's number
    (None: no transition). ``quick_stop_holds``: the quick stop option code is 5-8, so
    enable operation leaves QUICK STOP ACTIVE (transition 16)."""
    cw = controlword & 0xFFFF
    if state is State.FAULT:
        rising = cw & FAULT_RESET_BIT and not previous_controlword & FAULT_RESET_BIT
        return (State.SWITCH_ON_DISABLED, 15) if rising else (state, None)
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE):
        return state, None  # the drive leaves these on its own (1, 14)
    if cw & FAULT_RESET_BIT:
        return state, None  # bit 7 set: no command (the reset acts in FAULT only)
    disable_voltage = cw & 0x02 == 0
    quick_stop = not disable_voltage and cw & 0x04 == 0
    shutdown = cw & 0x07 == 0x06
    switch_on = cw & 0x0F == 0x07
    enable = cw & 0x0F == 0x0F
    match state:
        case State.SWITCH_ON_DISABLED:
            if shutdown:
                return State.READY_TO_SWITCH_ON, 2
        case State.READY_TO_SWITCH_ON:
            if disable_voltage or quick_stop:
                return State.SWITCH_ON_DISABLED, 7
            if switch_on:
                return State.SWITCHED_ON, 3
            if enable:
                return State.OPERATION_ENABLED, 4  # 3 + 4 at once
        case State.SWITCHED_ON:
            if disable_voltage or quick_stop:
                return State.SWITCH_ON_DISABLED, 10
            if shutdown:
                return State.READY_TO_SWITCH_ON, 6
            if enable:
                return State.OPERATION_ENABLED, 4
        case State.OPERATION_ENABLED:
            if disable_voltage:
                return State.SWITCH_ON_DISABLED, 9
            if quick_stop:
                return State.QUICK_STOP_ACTIVE, 11
            if shutdown:
                return State.READY_TO_SWITCH_ON, 8
            if switch_on:
                return State.SWITCHED_ON, 5
        case State.QUICK_STOP_ACTIVE:
            if disable_voltage:
                return State.SWITCH_ON_DISABLED, 12
            if enable and quick_stop_holds:
                return State.OPERATION_ENABLED, 16
    return state, None


def arming_command(state: State | None) -> int | None:
    """The controlword that takes a drive one transition closer to OPERATION ENABLED
    (None: none does; a fault is reset first, and a drive initialising or reacting to
    a fault gets there by itself). Unknown state: shutdown, which enables nothing."""
    match state:
        case None | State.SWITCH_ON_DISABLED:
            return CW_SHUTDOWN  # 2
        case State.READY_TO_SWITCH_ON:
            return CW_SWITCH_ON  # 3
        case State.SWITCHED_ON | State.OPERATION_ENABLED:
            return CW_ENABLE_OPERATION  # 4 (held once there)
        case State.QUICK_STOP_ACTIVE:
            return CW_DISABLE_VOLTAGE  # 12, then 2, 3, 4
    return None


_NEUTRAL = {
    State.NOT_READY_TO_SWITCH_ON: DriveState.STARTING,
    State.SWITCH_ON_DISABLED: DriveState.DISABLED,
    State.READY_TO_SWITCH_ON: DriveState.STARTING,
    State.SWITCHED_ON: DriveState.STARTING,
    State.OPERATION_ENABLED: DriveState.ENABLED,
    State.QUICK_STOP_ACTIVE: DriveState.STOPPING,
    State.FAULT_REACTION_ACTIVE: DriveState.FAULT,
    State.FAULT: DriveState.FAULT,
}


def neutral(state: State) -> DriveState:
    return _NEUTRAL[state]


def describe_error(code: int) -> str:
    """An emergency error code with its name (CiA 301 classes for the others)."""
    name = ERROR_NAMES.get(code)
    if name is None:
        from canopen.emcy import EmcyError

        name = EmcyError(code, 0, b"", 0.0).get_desc() or "unknown"
    return f"0x{code:04x} ({name})"
