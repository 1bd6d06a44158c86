"""The wire contract (DESIGN §3): key expressions and message types, in one place.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import msgspec

from agents.degradation import MAX_COMMAND_HORIZON

WIRE_VERSION = 1
MAX_BODIES = 256  # bodies per perception message
MAX_ORDER_CHARS = 32
MAX_ROLE_CHARS = 32
MAX_CONTACTS = 10_000  # contact events carried by a plant's report (the count is exact)

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Vec4 = tuple[float, float, float, float]


class Message(msgspec.Struct, array_like=True, frozen=True):
    v: int  # WIRE_VERSION
    sender: int  # robot id for robot-scoped messages, 0 for leader/plant/launcher
    seq: int  # per publisher, from 0
    stamp_ns: int  # sender's monotonic clock at publication

    # subclasses set ROBOT_FIELD when the message is about one robot (checked
    # against the key it arrived on)
    ROBOT_FIELD: ClassVar[str | None] = None

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            _check_finite(name, getattr(self, name))


def _check_finite(name: str, value: Any) -> None:
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{name} is not finite")
    elif isinstance(value, tuple | list):
        for x in value:
            _check_finite(name, x)
    elif isinstance(value, msgspec.Struct):
        for f in value.__struct_fields__:
            _check_finite(f"{name}.{f}", getattr(value, f))


class LeaderState(Message, frozen=True):
    k: int  # step index (lockstep) or -1 (realtime)
    t: float  # scenario time of this state, s
    q: Vec3  # leader pose [x, y, psi]
    q_dot: Vec3


class RobotState(Message, frozen=True):
    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    k: int
    t: float
    q: Vec3
    q_dot: Vec3
    faulted: bool = False  # a bridge reports driver errors / lost heartbeats here


class SensedBody(msgspec.Struct, array_like=True, frozen=True):
    ident: int  # robot id, or -(obstacle index + 1)
    position: Vec2
    velocity: Vec2
    radius: float


def sensed_bodies(bodies) -> list[SensedBody]:
    """Wire form of sensed bodies (anything with ident, position, velocity, radius)."""
    return [SensedBody(b.ident, tuple(b.position.tolist()), tuple(b.velocity.tolist()),
                       float(b.radius)) for b in bodies]


class Perception(Message, frozen=True):
    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    k: int
    t: float
    robots: list[SensedBody]
    obstacles: list[SensedBody]

    def __post_init__(self) -> None:
        if len(self.robots) > MAX_BODIES or len(self.obstacles) > MAX_BODIES:
            raise ValueError("too many bodies")
        super().__post_init__()


class WheelCommand(Message, frozen=True):
    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    k: int  # step answered (lockstep) or the state's k (realtime)
    t: float
    torques: Vec4  # N m, wheel order of plant/mecanum.py
    v_cmd: Vec3  # fused velocity command (a kinematic plant uses this)
    state_seq: int  # seq of the RobotState this command answers
    state_stamp_ns: int  # its stamp_ns, echoed: latency measured on the plant's clock
    # torques predicted for steps k+1, k+2, ...: played if their own command is lost
    # (agents/look_ahead.py); at most MAX_COMMAND_HORIZON entries
    plan: list[Vec4] = []

    def __post_init__(self) -> None:
        if len(self.plan) > MAX_COMMAND_HORIZON:
            raise ValueError("plan too long")
        super().__post_init__()


class NeighbourShare(Message, frozen=True):
    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    k: int  # the step that produced it; -1 is the initial share
    q0_hat: Vec3
    v0_hat: Vec3
    q: Vec3
    q_dot: Vec3
    zeta: Vec3
    zeta_dot: Vec3
    info_age_s: float = 0.0  # how old the sender's leader information is (s)


class Telemetry(Message, frozen=True):
    ROBOT_FIELD: ClassVar[str | None] = "robot"
    robot: int
    k: int
    t: float
    q_d: Vec3
    e: Vec3
    s: Vec3
    v_cmd: Vec3
    torques: Vec4
    q0_hat: Vec3
    q_fd: Vec3
    fdb_error: float | None  # None when FDB is not active
    order: str  # active behaviors, highest priority first, joined by '>'
    nonfinite: bool
    stale_inputs: int = 0  # inputs older than in a fault-free run (held or delayed)
    input_age_s: float = 0.0  # age of the freshest leader information, or the state (s)
    speed_factor: float = 1.0  # degradation: 1 full speed, 0 down to the degraded speed
    left_out: int = 0  # inputs too old for eq. (14) this step

    def __post_init__(self) -> None:
        if len(self.order) > MAX_ORDER_CHARS:
            raise ValueError("order too long")
        super().__post_init__()


CONTROL_COMMANDS = ("start", "tick", "end", "stop", "estop")


class Control(Message, frozen=True):
    command: str  # one of CONTROL_COMMANDS
    k: int = 0  # tick: the step the plant is publishing
    t: float = 0.0
    start_unix_ns: int = 0  # start (realtime): when t = 0 is, on the wall clock

    def __post_init__(self) -> None:
        if self.command not in CONTROL_COMMANDS:
            raise ValueError(f"unknown command {self.command!r}")
        super().__post_init__()


class ContactRecord(msgspec.Struct, array_like=True, frozen=True):
    """One physical contact of two bodies (pybullet plant), for metrics.json."""

    t_start: float
    t_end: float | None  # None: still touching when the run ended
    body_a: int  # robot id
    body_b: int  # robot id, or -(obstacle index + 1)
    max_depth_m: float


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
    command_stops: list[tuple[int, float, float]] = []

    def __post_init__(self) -> None:
        if len(self.role) > MAX_ROLE_CHARS:
            raise ValueError("role too long")
        if self.contacts is not None and len(self.contacts) > MAX_CONTACTS:
            raise ValueError("too many contact records")
        super().__post_init__()


MESSAGE_TYPES = (LeaderState, RobotState, Perception, WheelCommand, NeighbourShare,
                 Telemetry, Control, NodeReport)

_encoder = msgspec.msgpack.Encoder()


def encode(msg: Message) -> bytes:
    return _encoder.encode(msg)


class Codec:
    """Decoders for every message type, validating ids against the scenario."""

    def __init__(self, robot_ids: list[int] | tuple[int, ...]) -> None:
        self.robot_ids = frozenset(robot_ids)
        self._decoders = {t: msgspec.msgpack.Decoder(t) for t in MESSAGE_TYPES}

    def decode(self, kind: type[Message], data: bytes, robot: int | None = None) -> Any:
        """The message, or None when it is invalid (never raises)."""
        try:
            msg = self._decoders[kind].decode(data)
        except (msgspec.DecodeError, ValueError, TypeError):
            return None
        if msg.v != WIRE_VERSION or msg.seq < 0:
            return None
        field = kind.ROBOT_FIELD
        if field is not None:
            rid = getattr(msg, field)
            if rid not in self.robot_ids or (robot is not None and rid != robot):
                return None
        if kind is Perception and any(
            b.ident >= 0 and b.ident not in self.robot_ids for b in msg.robots
        ):
            return None
        return msg


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

    def robot_state(self, robot: int) -> str:
        return f"{self.root}/robot/{robot}/state"

    def perception(self, robot: int) -> str:
        return f"{self.root}/robot/{robot}/perception"

    def cmd(self, robot: int) -> str:
        return f"{self.root}/robot/{robot}/cmd"

    def share(self, robot: int) -> str:
        return f"{self.root}/agent/{robot}/share"

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
            case ["robot", r, "state"] if r.lstrip("-").isdigit():
                return RobotState, int(r)
            case ["robot", r, "perception"] if r.lstrip("-").isdigit():
                return Perception, int(r)
            case ["robot", r, "cmd"] if r.lstrip("-").isdigit():
                return WheelCommand, int(r)
            case ["agent", r, "share"] if r.lstrip("-").isdigit():
                return NeighbourShare, int(r)
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
