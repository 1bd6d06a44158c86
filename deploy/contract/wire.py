"""The wire contract (docs/distributed.md): key expressions and message types, in one place.

Every node imports this module; nobody re-types a key string. Messages are
msgspec Structs encoded as msgpack arrays (``array_like``: field order is the
layout, no field names on the wire). Every message starts with the same header
(version, sender, seq, stamp_ns) and is validated at decode: wrong version,
wrong sizes or types, NaN/Inf, an id out of range or a robot field that does not
match its key -> :class:`Codec.decode` returns ``None`` and the caller counts
the message in ``messages.invalid``. Decoding never raises.

``stamp_ns`` is the sender's ``time.monotonic_ns()`` at publication. It is only
ever compared with the same process's clock (a command echoes the stamp of the
state it answers, so the plant measures state-to-command latency on its own
clock), so hosts need no clock synchronisation for it.

The control path carries two messages per robot per step (version 2, docs/distributed.md):
the plant's :class:`Sample` (state + perception; in lockstep its arrival is the
tick) and the agent's :class:`Reply` (command + look-ahead plan + the share its
neighbours read from the same key). The leader's states travel in batches ahead
of need; telemetry and the robot states for observers travel in batches off the
path (:class:`Telemetry`, :class:`StateLog`). A message of another wire version is
refused and counted apart (``Codec.wrong_version``), so mixed installs say so.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

import msgspec
import numpy as np

from agents.degradation import MAX_COMMAND_HORIZON
from agents.share import FLOAT_LIMIT, Finite, Share

# 2: Sample, Reply, batched LeaderState/Telemetry, StateLog; 3: safety in Telemetry; 4: no MAC
# fields in Control and NodeReport (every message of a keyed node is authenticated by its
# envelope, deploy/contract/mac.py); 5: a node's CPU time in NodeReport; 6: Sample.own_torques;
# 7: where a node's loop spent its time (NodeReport.step_costs_ns); 8: an agent's deadline
# misses so far in its telemetry (TelemetryRow.deadline_misses)
WIRE_VERSION = 8
MAX_BODIES = 256  # bodies per perception message
MAX_ORDER_CHARS = 32
MAX_ROLE_CHARS = 32
MAX_LAW_ERROR_CHARS = 400  # a law's first error, one line (NodeReport.law_error)
MAX_BATCH = 256  # steps per batched message (leader, telemetry, state log)
MAX_CONTACTS = 10_000  # contact events carried by a plant's report (the count is exact)
MAX_REPORT_SAMPLES = 200_000  # timing samples a report carries (node_runtime.MAX_SAMPLES)
MAX_REPORT_KEYS = 1024  # entries of a report's per-key and per-reason tables
# a report's encoded size, refused before it is decoded: two full timing tables (200 000
# samples each, at most 9 bytes a sample in msgpack: 3.6 MB), contacts (10 000 x ~50 B)
# and the tables (3 x 1024 entries of < 100 B) stay under it
MAX_REPORT_BYTES = 5 * 1024 * 1024

# Every float on the wire is finite and far from the float limit (FLOAT_LIMIT, with the
# share's type in agents/share.py): msgspec checks the bound as it decodes, in C, and NaN
# fails it too. A sender checks its own message the same way before it puts it
# (Node.publish): a NaN never leaves, one schema says what is valid.
Vec2 = tuple[Finite, Finite]
Vec3 = tuple[Finite, Finite, Finite]
Vec4 = tuple[Finite, Finite, Finite, Finite]


# gc=False on every message type: a message is data (numbers, strings, tuples and lists of
# them, nested frozen structs), it can never be part of a reference cycle, so the garbage
# collector need not track it. A recording launcher holds thousands of messages for its
# writer: their tracking made collections walk them, half of what hearing a step cost it
# (131 -> 87 µs a step of paper, measured in one process)
class Message(msgspec.Struct, array_like=True, frozen=True, gc=False):
    v: int  # WIRE_VERSION
    sender: int  # robot id for robot-scoped messages, 0 for leader/plant/launcher
    seq: int  # per publisher, from 0
    stamp_ns: int  # sender's monotonic clock at publication

    # subclasses set ROBOT_FIELD when the message is about one robot (checked
    # against the key it arrived on)
    ROBOT_FIELD: ClassVar[str | None] = None

    # Sizes and the floats' finiteness are the schema's (msgspec.Meta), checked in C as a
    # message decodes; a type that needs more (lengths that must agree) has a
    # __post_init__. One on every type (this base had an empty one) was a Python call per
    # message and per construction: a Sample decoded in 4.0 us with it, ~2 without


class LeaderState(Message, frozen=True):
    """The leader's states for steps k, k+1, ...: one entry on the realtime clock;
    lockstep sends them in batches ahead of need (deploy/nodes/leader.py), so an agent
    never waits a hop for the leader and hears one message per batch, not per step."""

    k: int  # step of the first entry (lockstep) or of the only one (realtime)
    t: Finite  # scenario time of the first entry, s
    q: list[Vec3]  # leader pose [x, y, psi] per step
    q_dot: list[Vec3]

    def __post_init__(self) -> None:
        if not 1 <= len(self.q) <= MAX_BATCH or len(self.q_dot) != len(self.q):
            raise ValueError("bad leader batch")


class SensedBody(msgspec.Struct, array_like=True, frozen=True, gc=False):
    ident: int  # robot id, or -(obstacle index + 1)
    position: Vec2
    velocity: Vec2
    radius: Finite


Bodies = Annotated[list[SensedBody], msgspec.Meta(max_length=MAX_BODIES)]


def within_wire_bound(*tables: Sequence[Sequence[float]]) -> bool:
    """Every value of ``tables`` (rows of floats: a state as ``tolist`` gives it) finite
    and within :data:`FLOAT_LIMIT` (what the receivers' schema asks of a float): one
    check for a whole state, where decoding each message again checks it float by float
    (``Node.publish(checked=True)``). On plain floats: numpy's abs().max() on a (3, 3)
    state cost 3.2 µs, this loop 0.9 µs (and a sleeping plant's caches no numpy code)."""
    limit = FLOAT_LIMIT
    for table in tables:
        for row in table:
            for v in row:
                if not -limit <= v <= limit:  # NaN compares False
                    return False
    return True


def sensed_bodies(bodies) -> list[SensedBody]:
    """Wire form of sensed bodies: rows (ident, x, y, vx, vy, radius) as perception gives
    them (plant/perception.py), or anything with ident, position, velocity, radius."""
    if isinstance(bodies, np.ndarray):  # rows
        return [SensedBody(int(r[0]), (r[1], r[2]), (r[3], r[4]), r[5]) for r in bodies.tolist()]
    return [SensedBody(b.ident, tuple(b.position.tolist()), tuple(b.velocity.tolist()),
                       float(b.radius)) for b in bodies]


class Sample(Message, frozen=True):
    """What the plant (or robot i's CAN bridge) sends agent i each step, in one
    message: the robot's state at t_k and what it perceives. In lockstep its arrival
    is the tick of step k."""

    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    k: int
    t: Finite
    q: Vec3
    q_dot: Vec3
    robots: Bodies
    obstacles: Bodies
    faulted: bool = False  # a bridge reports driver errors / lost heartbeats here
    # the robot moved from the previous sample to this one under the torques its agent
    # computed for that sample; False when they were a look-ahead, held or zero torques
    # (a command late or lost): the agent's observer, eq. (39), then restarts from this
    # measurement instead of integrating an input that never acted (agents/core.py)
    own_torques: bool = True


# the share's one type is the law's (agents/share.py); ShareData, its name here before
# the two were one, still names it
ShareData = Share


class Reply(Message, frozen=True):
    """Agent i's one message per step, on ``robot/i/cmd``: its robot's wheel
    command (and look-ahead plan) for the plant or bridge, and its share for the
    neighbours that listen to it (they read the same key: one put, one message per
    receiver). k = -1 is the initial share, before any command."""

    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    k: int  # step answered (lockstep) or the sample's k (realtime); -1: initial share
    t: Finite
    torques: Vec4  # N m, wheel order of plant/mecanum.py
    v_cmd: Vec3  # fused velocity command (a kinematic plant uses this)
    state_seq: int  # seq of the Sample this command answers
    state_stamp_ns: int  # its stamp_ns, echoed: latency measured on the plant's clock
    share: Share
    # torques predicted for steps k+1, k+2, ...: played if their own command is lost
    # (agents/look_ahead.py); at most MAX_COMMAND_HORIZON entries
    plan: Annotated[list[Vec4], msgspec.Meta(max_length=MAX_COMMAND_HORIZON)] = []


class TelemetryRow(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """One step of one agent, for people and the run's series (never the control path)."""

    k: int
    t: Finite
    q_d: Vec3
    e: Vec3
    s: Vec3
    v_cmd: Vec3
    torques: Vec4
    q0_hat: Vec3
    q_fd: Vec3
    fdb_error: Finite | None  # None when FDB is not active
    # active behaviors, highest priority first, joined by '>'
    order: Annotated[str, msgspec.Meta(max_length=MAX_ORDER_CHARS)]
    nonfinite: bool
    stale_inputs: int = 0  # inputs older than in a fault-free run (held or delayed)
    input_age_s: Finite = 0.0  # age of the freshest leader information, or the state (s)
    speed_factor: Finite = 1.0  # degradation: 1 full speed, 0 down to the degraded speed
    left_out: int = 0  # inputs too old for eq. (14) this step
    safety_dv: Finite = 0.0  # how much the safety filter changed the command (m/s); 0: it did not
    safety_infeasible: bool = False  # no command met every barrier within the limits
    # the agent's deadline misses since its loop started (realtime; 0 on the lockstep clock)
    deadline_misses: Annotated[int, msgspec.Meta(ge=0)] = 0


class Telemetry(Message, frozen=True):
    """An agent's telemetry rows, batched (lockstep: every step; realtime:
    decimated), off the control path: one message per ``TELEMETRY_BATCH`` rows."""

    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    rows: Annotated[list[TelemetryRow], msgspec.Meta(min_length=1, max_length=MAX_BATCH)]


class StateRow(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """The states of a source's robots at one step."""

    k: int
    t: Finite
    q: list[Vec3]
    q_dot: list[Vec3]
    faulted: list[bool]


MAX_REGULAR_BYTES = 2400  # the regular traffic's messages stay under this (see StateLog)


def log_rows_per_batch(robots: int) -> int:
    """State rows per :class:`StateLog` so that a batch stays under
    ``MAX_REGULAR_BYTES`` (~60 B per robot and row): zenoh 1.10 grows a process by
    16-44 MB the first time it moves a message of more than ~3 kB (measured), which
    alone broke the 60 MB budget of an agent."""
    return max(1, min(32, MAX_REGULAR_BYTES // (60 * robots + 24)))


class StateLog(Message, frozen=True):
    """The plant's (or a bridge's) robot states, batched for observers (the run's
    series, the recording, a live view), off the control path."""

    robots: list[int]  # robot ids, in the order of each row
    rows: list[StateRow]

    def __post_init__(self) -> None:
        n = len(self.robots)
        if not 1 <= len(self.rows) <= MAX_BATCH or not 1 <= n <= MAX_BODIES:
            raise ValueError("bad state log")
        for r in self.rows:
            if len(r.q) != n or len(r.q_dot) != n or len(r.faulted) != n:
                raise ValueError("state row does not match its robots")


CONTROL_COMMANDS = ("start", "tick", "end", "stop", "estop")


class LeaderSteer(Message, frozen=True):
    """The launcher's newest command for a leader steered from outside (leader.path =
    "ros2"; agents/steered_leader.py), to the leader alone."""

    velocity: Vec3  # the leader's body twist [vx, vy, wz], m/s and rad/s


class Control(Message, frozen=True):
    command: str  # one of CONTROL_COMMANDS
    k: int = 0  # tick: the step the plant is publishing
    t: Finite = 0.0
    start_unix_ns: int = 0  # start (realtime): when t = 0 is, on the wall clock

    def __post_init__(self) -> None:
        if self.command not in CONTROL_COMMANDS:
            raise ValueError(f"unknown command {self.command!r}")


def control(command: str, seq: int, stamp_ns: int, k: int = 0, t: float = 0.0,
            start_unix_ns: int = 0, sender: int = 0) -> Control:
    """A control message (authenticated, like every message of a keyed node, by the
    envelope its node puts around it: deploy/contract/keyring.py)."""
    return Control(WIRE_VERSION, sender, seq, stamp_ns, command=command, k=k, t=t,
                   start_unix_ns=start_unix_ns)


class ContactRecord(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """One physical contact of two bodies (pybullet plant), for metrics.json."""

    t_start: Finite
    t_end: Finite | None  # None: still touching when the run ended
    body_a: int  # robot id
    body_b: int  # robot id, or -(obstacle index + 1)
    max_depth_m: Finite


class NodeReport(Message, frozen=True):
    """A node's counters and timing, sent once as it ends."""

    role: str
    robot: int  # -1 for leader/plant
    sent: int
    dropped: int
    late: int
    invalid: int
    steps: int
    latency_ns: list[int] = []  # plant: state-to-command latency samples (realtime)
    jitter_ns: list[int] = []  # loop jitter samples (realtime)
    deadline_misses: int = 0
    peak_rss_kb: int = 0  # VmHWM of the node's process (0: unknown)
    received: dict[str, int] = {}  # valid messages received, per key expression
    contacts: list[ContactRecord] | None = None  # plant: physical contacts (None: not simulated)
    contacts_total: int = 0  # every contact event, also those beyond MAX_CONTACTS
    faults: dict[str, dict[str, int]] = {}  # injected faults per edge this node received on
    # plant (realtime) or CAN bridge: robots whose torques were zeroed for want of a
    # fresh command, as (robot, age of its newest command then, s; run time, s)
    command_stops: list[tuple[int, Finite, Finite]] = []
    refused: dict[str, int] = {}  # messages refused on arrival, by reason (forged, implausible)
    law_resets: int = 0  # agent: its law restarted from the robot (a long gap, a non-finite state)
    nonfinite: int = 0  # values the node computed that were NaN or Inf (Node.note_nonfinite)
    zid: str = ""  # this node's zenoh id
    peers: list[str] = []  # the zenoh ids it had a link with as it ended (zenoh's own info)
    nonfinite_commands: int = 0  # agent: steps whose law gave NaN/Inf (zero torques sent)
    stale_samples: int = 0  # agent (realtime): samples too old on arrival, not answered
    # plant (realtime) or CAN bridge: each stretch a robot ran on zero torque for want of a
    # fresh command, as (robot, run time it began, s; how long it lasted, s)
    zero_torque: list[tuple[int, Finite, Finite]] = []
    # plant or CAN bridge: per robot id (as text, as in metrics.json), the commands that asked
    # for more wheel torque than the bound (plant/command.py torque_bound): clipped to it
    torque_clipped: dict[str, int] = {}
    # agent (realtime): steps its loop ran slower than its period allows, robot slowed (agents/pace.py)
    overloaded_steps: int = 0
    # realtime: the node's longest late wake (ns; a stall) and the step it was due for
    longest_late_ns: int = 0
    longest_late_k: int = -1
    # plant (realtime): per robot, in the scenario's order, the steps at which the newest
    # command did not answer the newest state (the agent late or silent)
    unanswered: list[int] = []
    # CPU time of the node's process (every thread, user + system) over its run loop, s, and
    # that loop's wall time, s
    cpu_s: Finite = 0.0
    loop_s: Finite = 0.0
    # plant or CAN bridge: samples and replies it could not keep for the run's recording
    # (its record of them failed to write: deploy/runtime/wire_spool.py)
    unrecorded: int = 0
    # the time its run loop spent in each part of its steps, ns (deploy/runtime/step_costs.py)
    step_costs_ns: dict[str, int] = {}
    # agent that rejoined a running fleet: from its process start to its first command, s
    # (-1: not a rejoin, or it sent none)
    rejoin_s: Finite = -1.0
    # agent on a law of the lab's own (agents/plugged.py): steps it raised, steps whose
    # output was refused (braked instead), steps longer than the period, and the first
    # error's line
    law_errors: int = 0
    law_refused: int = 0
    law_overruns: int = 0
    law_error: Annotated[str, msgspec.Meta(max_length=MAX_LAW_ERROR_CHARS)] = ""

    def __post_init__(self) -> None:
        if min(self.sent, self.dropped, self.late, self.invalid, self.steps, self.nonfinite,
               self.deadline_misses, self.law_resets, self.nonfinite_commands,
               self.stale_samples, self.contacts_total, self.overloaded_steps,
               self.law_errors, self.law_refused, self.law_overruns,
               self.longest_late_ns, self.unrecorded, *self.unanswered) < 0:
            raise ValueError("a negative count")  # a forged "invalid = -1000"
        if (len(self.latency_ns) > MAX_REPORT_SAMPLES or len(self.jitter_ns) > MAX_REPORT_SAMPLES
                or len(self.received) > MAX_REPORT_KEYS or len(self.faults) > MAX_REPORT_KEYS
                or len(self.refused) > MAX_REPORT_KEYS or len(self.command_stops) > 1000
                or len(self.zero_torque) > 1000 or len(self.torque_clipped) > MAX_BODIES
                or len(self.unanswered) > MAX_BODIES or len(self.step_costs_ns) > 32
                or any(v < 0 or len(k) > MAX_ROLE_CHARS for k, v in self.step_costs_ns.items())):
            raise ValueError("report too large")
        if len(self.zid) > MAX_ROLE_CHARS or len(self.peers) > MAX_BODIES or any(
                len(p) > MAX_ROLE_CHARS for p in self.peers):
            raise ValueError("bad link report")
        if len(self.role) > MAX_ROLE_CHARS:
            raise ValueError("role too long")
        if self.contacts is not None and len(self.contacts) > MAX_CONTACTS:
            raise ValueError("too many contact records")


MESSAGE_TYPES = (LeaderState, Sample, Reply, Telemetry, StateLog, Control, NodeReport,
                 LeaderSteer)

_encoder = msgspec.msgpack.Encoder()
# the header of any version: an array whose first element is the version
_HEADER = msgspec.msgpack.Decoder(list)


def encode(msg: Message) -> bytes:
    return _encoder.encode(msg)


class Codec:
    """Decoders for every message type, validating ids against the scenario."""

    def __init__(self, robot_ids: list[int] | tuple[int, ...]) -> None:
        self.robot_ids = frozenset(robot_ids)
        self._decoders = {t: msgspec.msgpack.Decoder(t) for t in MESSAGE_TYPES}
        self._by_subscription: dict[tuple[type, int | None], Callable[[bytes], Any]] = {}
        self.wrong_version = 0  # refused: a header of another wire version
        self.versions_seen: set[int] = set()  # those versions (a mixed install)

    def _note_version(self, data: bytes) -> None:
        """Count a message whose header says another wire version."""
        try:
            head = _HEADER.decode(data)
        except (msgspec.DecodeError, ValueError, TypeError):
            return
        if not head or not isinstance(head[0], int):
            return
        if head[0] != WIRE_VERSION and len(self.versions_seen) < 16:
            self.wrong_version += 1
            self.versions_seen.add(head[0])
        elif head[0] != WIRE_VERSION:
            self.wrong_version += 1

    def check(self, kind: type[Message], data: bytes) -> None:
        """Raise ValueError unless ``data`` decodes as a valid ``kind``: what a sender asks
        of its own message before it goes out (a NaN, a batch too long)."""
        try:
            self._decoders[kind].decode(data)
        except msgspec.DecodeError as exc:
            raise ValueError(f"{kind.__name__}: {exc}") from None

    def decoder_for(self, kind: type[Message], robot: int | None = None
                    ) -> Callable[[bytes], Any]:
        """``lambda data: self.decode(kind, data, robot)``, its checks chosen once for
        ``kind`` and ``robot`` (a subscription: a sample, a reply every step) rather than
        looked up on every message. Kept per (kind, robot) of the run's robots."""
        known = robot is None or robot in self.robot_ids
        found = self._by_subscription.get((kind, robot)) if known else None
        if found is None:
            found = self._decoder(kind, robot)
            if known:
                self._by_subscription[(kind, robot)] = found
        return found

    def _decoder(self, kind: type[Message], robot: int | None) -> Callable[[bytes], Any]:
        dec, ids, note = self._decoders[kind].decode, self.robot_ids, self._note_version
        errors = (msgspec.DecodeError, ValueError, TypeError)
        max_bytes = MAX_REPORT_BYTES if kind is NodeReport else None
        field = kind.ROBOT_FIELD
        sample, state_log = kind is Sample, kind is StateLog

        def decode_one(data: bytes) -> Any:
            if max_bytes is not None and len(data) > max_bytes:
                return None
            try:
                msg = dec(data)
            except errors:
                note(data)
                return None
            if msg.v != WIRE_VERSION:
                note(data)
                return None
            if msg.seq < 0:
                return None
            if field is not None:
                rid = getattr(msg, field)
                if rid not in ids or (robot is not None and rid != robot):
                    return None
            if sample:
                for b in msg.robots:
                    if b.ident >= 0 and b.ident not in ids:
                        return None
            if state_log and not ids.issuperset(msg.robots):
                return None
            return msg
        return decode_one

    def decode(self, kind: type[Message], data: bytes, robot: int | None = None) -> Any:
        """The message, or None when it is invalid (never raises). A report larger
        than ``MAX_REPORT_BYTES`` is refused before it is decoded."""
        return self.decoder_for(kind, robot)(data)


class FleetNameError(ValueError):
    """A fleet name that cannot be a key-expression chunk."""


@dataclass(frozen=True)
class Keys:
    """Key expressions of one fleet: ``omr/<fleet>/...``."""

    fleet: str

    def __post_init__(self) -> None:
        if not self.fleet or any(c in self.fleet for c in "/*$?#"):
            raise FleetNameError(
                f"fleet name {self.fleet!r} must be non-empty, without / * $ ? #")

    @property
    def root(self) -> str:
        return f"omr/{self.fleet}"

    @property
    def everything(self) -> str:
        return f"{self.root}/**"

    @property
    def leader_state(self) -> str:
        return f"{self.root}/leader/state"

    @property
    def leader_steer(self) -> str:
        """Launcher -> leader: a steered leader's newest command (:class:`LeaderSteer`)."""
        return f"{self.root}/leader/steer"

    def sample(self, robot: int) -> str:
        """Plant or bridge -> agent i: state + perception of step k (:class:`Sample`)."""
        return f"{self.root}/robot/{robot}/sample"

    def cmd(self, robot: int) -> str:
        """Agent i -> plant or bridge, and its listening neighbours (:class:`Reply`)."""
        return f"{self.root}/robot/{robot}/cmd"

    def state_log(self, role: str) -> str:
        """A state source's batched robot states, for observers (:class:`StateLog`)."""
        return f"{self.root}/log/{role}"

    @property
    def state_log_all(self) -> str:
        return f"{self.root}/log/*"

    def telemetry(self, robot: int) -> str:
        return f"{self.root}/agent/{robot}/telemetry"

    def ctl(self, command: str) -> str:
        return f"{self.root}/ctl/{command}"

    @property
    def ctl_all(self) -> str:
        return f"{self.root}/ctl/*"

    def report(self, role: str) -> str:
        return f"{self.root}/report/{role}"

    def alive(self, role: str) -> str:
        return f"{self.root}/alive/{role}"

    def ready(self, role: str) -> str:
        return f"{self.root}/ready/{role}"

    def filed(self, role: str) -> str:
        """The launcher's liveliness token: it holds ``role``'s report."""
        return f"{self.root}/filed/{role}"

    @property
    def alive_all(self) -> str:
        return f"{self.root}/alive/*"

    @property
    def ready_all(self) -> str:
        return f"{self.root}/ready/*"

    def role_of(self, key: str) -> str:
        """The last chunk of an alive/ready key: the role name."""
        return key.rsplit("/", 1)[-1]

    def kind_of(self, key: str) -> tuple[type[Message], int | None] | None:
        """Which message type a data key carries (and its robot), or None."""
        parts = key[len(self.root) + 1:].split("/") if key.startswith(self.root + "/") else []
        match parts:
            case ["leader", "state"]:
                return LeaderState, None
            case ["leader", "steer"]:
                return LeaderSteer, None
            case ["robot", r, "sample"] if r.lstrip("-").isdigit():
                return Sample, int(r)
            case ["robot", r, "cmd"] if r.lstrip("-").isdigit():
                return Reply, int(r)
            case ["log", _]:
                return StateLog, None
            case ["agent", r, "telemetry"] if r.lstrip("-").isdigit():
                return Telemetry, int(r)
            case ["ctl", _]:
                return Control, None
            case ["report", _]:
                return NodeReport, None
        return None


def agent_role(robot: int) -> str:
    return f"agent-{robot}"


def bridge_role(robot: int) -> str:
    """The CAN bridge that plays the plant for one robot on hardware."""
    return f"bridge-{robot}"


LEADER_ROLE = "leader"
PLANT_ROLE = "plant"
LAUNCHER_ROLE = "launcher"


def run_roles(robot_ids: list[int]) -> list[str]:
    """Every node role of a run: leader, plant, one agent per robot."""
    return [LEADER_ROLE, PLANT_ROLE, *(agent_role(r) for r in robot_ids)]
