"""Every numeric command-line option, once: its flag, range, metavar, help and default.

``omnifleet run`` and every node and tool command (agent, plant, leader, bridge,
emulate, can-check, record, faults sweep, bench, scenario generate, deploy plan/certs,
view) add their numeric options with :func:`add_option`; argparse then refuses a value
outside the option's range (NaN, inf, zero, negative, too large) with exit code 2 and a
message naming the flag, before anything runs. :func:`check_duration` is the one check
that needs the scenario: a run shorter than one control period has no step to take.

Imports nothing of the project, so the scenario schema can share its ranges
(:data:`MAX_RATE_HZ`).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any

MAX_RATE_HZ = 100_000.0  # a control, encoder or physics rate: 10 us per step at most
MAX_WAIT_S = 1e6  # ~11.6 days: longer waits overflow the OS's timeouts, and mean a typo
MAX_PRIORITY = 20  # nice -20 is the most Linux gives
MAX_SPIN_TORQUE_NM = 0.5  # can-check --spin: bring-up is not the place for more
MAX_CAN_NODE_ID = 127  # CANopen's largest; each protocol checks its own range (bridges/drivers.py)
MAX_ROBOTS = 256  # a perception message carries at most 256 bodies (wire.MAX_BODIES)

DEFAULT_STEP_DEADLINE_S = 2.0
DEFAULT_STARTUP_TIMEOUT_S = 60.0
DEFAULT_COMMAND_TIMEOUT_S = 0.1


# Bad input, refused before anything ran (an option out of range, a scenario error, a used
# --out): the exit code of every omnifleet command for it, declared here only. (0: done;
# 1: failed, a FAIL verdict with --check, a node or the recorder failed.)
EXIT_BAD_INPUT = 2


class OptionError(ValueError):
    """An option's value that cannot be run; the message names the flag (exit code 2)."""


@dataclass(frozen=True)
class Bound:
    """The values an option accepts: a finite number (or an integer) between ``lo``
    and ``hi``, each end open or closed."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False

    def holds(self, x: float) -> bool:
        if not math.isfinite(x):
            return False
        above = x > self.lo if self.lo_open else x >= self.lo
        below = x < self.hi if self.hi_open else x <= self.hi
        return above and below

    def describe(self) -> str:
        kind = "an integer" if self.integer else "a finite number"
        lo, hi = _num(self.lo), _num(self.hi)
        if math.isinf(self.lo) and math.isinf(self.hi):
            return kind
        if math.isinf(self.hi):
            return f"{kind} {'>' if self.lo_open else '>='} {lo}"
        if math.isinf(self.lo):
            return f"{kind} {'<' if self.hi_open else '<='} {hi}"
        if self.integer:
            return f"{kind} in {lo}..{hi}"
        return f"{kind} in {'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}"

    def parse(self, text: str) -> float | int:
        """The value of ``text``, or argparse.ArgumentTypeError saying what is expected."""
        try:
            x: float | int = int(text) if self.integer else float(text)
        except (TypeError, ValueError):
            x = math.nan
        if not self.holds(x):
            raise argparse.ArgumentTypeError(f"expected {self.describe()}, got {text!r}")
        return x


def _num(x: float) -> str:
    if not math.isfinite(x) or x != int(x) or abs(x) >= 1e6:
        return f"{x:g}"
    return str(int(x))


POSITIVE = Bound(0.0, lo_open=True)
NON_NEGATIVE = Bound(0.0)
PROBABILITY = Bound(0.0, 1.0)
RATE = Bound(0.0, MAX_RATE_HZ, lo_open=True)
WAIT = Bound(0.0, MAX_WAIT_S, lo_open=True)
WAIT_OR_ZERO = Bound(0.0, MAX_WAIT_S)
COUNT = Bound(1, integer=True)
SEED = Bound(0, integer=True)


@dataclass(frozen=True)
class Option:
    """One option: its flag, range, metavar, help and default (None: none)."""

    flag: str
    bound: Bound
    metavar: str
    help: str
    default: Any = None


# Every numeric option of every command. A command may give its own default or add a
# sentence of help; the range and the meaning are these.
OPTIONS: dict[str, Option] = {o.flag: o for o in (
    Option("--duration", POSITIVE, "S",
           "simulate S seconds instead of the scenario's duration_s (at least one control "
           "period)"),
    Option("--control-rate", RATE, "HZ",
           f"step every node at HZ instead of the scenario's control_rate_hz (at most "
           f"{MAX_RATE_HZ:g}; docs/control-rate.md)"),
    Option("--ros2-rate", Bound(0.0, 1000.0, lo_open=True), "HZ",
           "--ros2: publish each ROS 2 topic at most HZ times a (wall-clock) second; rows "
           "between are skipped and counted", 50.0),
    Option("--step-deadline", WAIT, "S",
           "lockstep: how long a node waits for a step's inputs before going on with what "
           "it last had, counted as late", DEFAULT_STEP_DEADLINE_S),
    Option("--startup-timeout", WAIT, "S", "how long to wait for every peer to come up",
           DEFAULT_STARTUP_TIMEOUT_S),
    Option("--lost-peer-grace", WAIT_OR_ZERO, "S",
           "agent/leader: when the plant's liveliness token goes (a cut link), wait this "
           "long for it to come back before giving up (0: at once)", 0.0),
    Option("--robot", Bound(1, integer=True), "ID",
           "the robot's id in the scenario (ids start at 1; 0 is the leader)"),
    Option("--silent-node", Bound(0, MAX_CAN_NODE_ID, integer=True), "N",
           "fault: this node id stops sending and ignores commands ..."),
    Option("--refuse-enable", Bound(0, MAX_CAN_NODE_ID, integer=True), "N",
           "fault: this node id never becomes enabled (as a drive whose safe torque off is "
           "active)"),
    Option("--command-timeout", WAIT, "S",
           "realtime: zero a robot's torques when its newest command is older than this",
           DEFAULT_COMMAND_TIMEOUT_S),
    Option("--heartbeat-timeout", WAIT, "S", "a driver silent this long faults the robot", 0.35),
    Option("--priority", Bound(0, MAX_PRIORITY, integer=True), "N",
           "run this process's loop under SCHED_FIFO at priority N, and at nice -N (its "
           "session's autogroup too, where Linux groups processes by session); needs "
           "CAP_SYS_NICE or RLIMIT_RTPRIO and RLIMIT_NICE, without it the process says so "
           "and runs at normal priority; 0 leaves it", 0),
    Option("--encoder-rate", RATE, "HZ", "ODrive: Get_Encoder_Estimates rate per axis (CiA 402: "
           "the TPDOs follow the host's SYNC); the rate of the ground truth", 200.0),
    Option("--heartbeat-rate", RATE, "HZ", "heartbeat rate per axis (CiA 402: at power-up; the "
           "bridge sets its own)", 10.0),
    Option("--physics-rate", RATE, "HZ", "RK4 physics ticks per second", 1000.0),
    Option("--watchdog-timeout", WAIT_OR_ZERO, "S",
           "an armed axis without Set_Input_Torque (ODrive) or SYNC (CiA 402) for this long "
           "stops with a watchdog fault; 0 turns the watchdog off", 0.2),
    Option("--drop-rate", PROBABILITY, "P",
           "fault: probability that a frame (either direction) is lost", 0.0),
    Option("--corrupt-rate", PROBABILITY, "P",
           "fault: probability that a sent frame gets 1-3 bits flipped", 0.0),
    Option("--silent-after", WAIT_OR_ZERO, "S",
           "... from S seconds after start (default: 0; needs --silent-node)"),
    Option("--listen", WAIT, "S", "how long to listen for heartbeats and encoders", 1.0),
    Option("--bring-up-timeout", WAIT, "S", "how long the drives may take to answer their "
           "configuration (CiA 402: heartbeat, SDO, NMT)", 5.0),
    Option("--spin-torque", Bound(-MAX_SPIN_TORQUE_NM, MAX_SPIN_TORQUE_NM), "NM",
           f"torque for --spin, not 0, at most {MAX_SPIN_TORQUE_NM} N m either way", 0.05),
    Option("--spin-time", WAIT, "S", "how long each wheel is driven", 0.5),
    Option("--bitrate", COUNT, "B", "bus bitrate, for interfaces that take one"),
    Option("--seeds", COUNT, "K", "seeds per drop rate", 5),
    Option("--jobs", COUNT, "N", "in-process runs at once (default: the number of cores)"),
    Option("--obstacle-jitter", NON_NEGATIVE, "M",
           "move every obstacle uniformly within this many metres (default: two robot radii)"),
    Option("--start-jitter", NON_NEGATIVE, "M",
           "move every start uniformly within this many metres (default: one robot radius)"),
    Option("--repeats", COUNT, "N", "repeats per figure (default: 3, --quick: 1)"),
    Option("--robots", Bound(1, MAX_ROBOTS, integer=True), "N", "how many robots"),
    Option("--seed", SEED, "K", "random seed"),
    Option("--days", COUNT, "N", "validity in days", 365),
    Option("--keys-fd", Bound(0, 1 << 20, integer=True), "N",
           "read this node's keyring from the pipe N (how `omnifleet run` hands each node "
           "its keys: never in its environment or on disk)"),
    Option("--speed", Bound(0.0, 1e3, lo_open=True), "X", "playback speed", 1.0),
)}

_UNSET: Any = object()


def add_option(p: argparse.ArgumentParser, flag: str, *, default: Any = _UNSET,
               help: str | None = None, more_help: str = "", required: bool = False,
               dest: str | None = None, action: str | None = None) -> argparse.Action:
    """Add ``flag`` (a key of :data:`OPTIONS`) to ``p``, its range checked on parse.

    ``default``/``help`` replace the option's own (a command whose default differs,
    or where the option means something narrower); ``more_help`` is appended. The
    range is always the option's own."""
    opt = OPTIONS[flag]
    default = opt.default if default is _UNSET else default
    text = help if help is not None else opt.help
    if more_help:
        text = f"{text}; {more_help}"
    if default is not None and not required:
        text = f"{text} (default: {_num(default) if isinstance(default, int | float) else default})"
    kwargs: dict[str, Any] = {"type": opt.bound.parse, "metavar": opt.metavar,
                              "help": text.replace("%", "%%"), "required": required}
    if not required:
        kwargs["default"] = default
    if dest is not None:
        kwargs["dest"] = dest
    if action is not None:
        kwargs["action"] = action
    return p.add_argument(flag, **kwargs)


def check_value(flag: str, value: float | int | None) -> None:
    """The range check of ``flag`` for a value that did not come through argparse
    (a Python caller); OptionError naming the flag."""
    if value is None:
        return
    bound = OPTIONS[flag].bound
    if not bound.holds(float(value)):
        raise OptionError(f"{flag}: expected {bound.describe()}, got {value!r}")


def check_duration(duration_s: float | None, control_rate_hz: float,
                   flag: str = "--duration") -> None:
    """A run takes at least one control step: ``duration_s`` (None: the scenario's,
    checked when it loads) must be at least one period 1/``control_rate_hz``."""
    if duration_s is None:
        return
    check_value(flag, duration_s)
    if duration_s * control_rate_hz < 1.0:
        raise OptionError(f"{flag} {duration_s:g} s is shorter than one control period "
                          f"({1.0 / control_rate_hz:g} s at {control_rate_hz:g} Hz): "
                          "nothing would run")
