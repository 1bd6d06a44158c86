"""The hosts file: which machine runs which role of a fleet (TOML).

```toml
fleet = "lab1"               # keys are omr/<fleet>/...
port = 7447                  # first listen port on each machine; each node takes the next
tls = true                   # mutual TLS + access control between nodes (default: true)
lease_ms = 10000             # zenoh link lease: a cut link is declared dead after it
dir = "/etc/omnifleet/lab1"  # on each machine: its certificates and zenoh configs
command = "omnifleet"        # how omnifleet is called on the machines

[machines.base]
address = "192.168.10.1"
roles = ["router", "plant", "leader", "recorder"]

[machines.robot1]
address = "192.168.10.11"
roles = ["agent-1"]
```

Roles: ``plant``, ``leader``, ``recorder`` (``omnifleet record``), ``router``
(``omnifleet router``), ``agent-<id>`` and ``bridge-<id>`` (a robot on CAN; its
machine then needs ``can = {interface = "socketcan", channel = "can0"}``).
``dir`` may contain ``{machine}``. Every error names the file and the key
(:class:`HostsError`, exit code 2 at the CLI).
"""

from __future__ import annotations

import ipaddress
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

import msgspec

from deploy.contract.scenario import Scenario
from deploy.contract.schema_hints import hint
from deploy.contract.wire import LAUNCHER_ROLE, LEADER_ROLE, PLANT_ROLE, FleetNameError, Keys

ROUTER = "router"
RECORDER = "recorder"
SINGLE_ROLES = (PLANT_ROLE, LEADER_ROLE, RECORDER, ROUTER)
_ROBOT_ROLE = re.compile(r"^(agent|bridge)-(\d+)$")
_MACHINE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class HostsError(ValueError):
    """A hosts file that cannot be deployed, with the file and key named."""


class Can(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    interface: str
    channel: str


class MachineEntry(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    address: str
    roles: list[str]
    port: int | None = None  # this machine's first listen port (default: the file's)
    can: Can | None = None


class HostsFileSpec(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    fleet: str
    machines: dict[str, MachineEntry]
    port: int = 7447
    tls: bool = True
    lease_ms: int | None = None
    dir: str = "/etc/omnifleet/{fleet}"
    command: str = "omnifleet"


@dataclass(frozen=True)
class Placement:
    """One node: its role (as the hosts file names it), the machine, its endpoint."""

    role: str
    machine: str
    address: str
    port: int

    @property
    def wire_role(self) -> str:
        """The role's name on the wire and in its certificate (recorder -> launcher)."""
        return LAUNCHER_ROLE if self.role == RECORDER else self.role

    def endpoint(self, tls: bool) -> str:
        host = f"[{self.address}]" if ":" in self.address else self.address
        return f"{'tls' if tls else 'tcp'}/{host}:{self.port}"


@dataclass(frozen=True)
class Hosts:
    path: Path
    spec: HostsFileSpec
    placements: list[Placement]

    @property
    def fleet(self) -> str:
        return self.spec.fleet

    def machine_dir(self, machine: str) -> str:
        return self.spec.dir.replace("{fleet}", self.fleet).replace("{machine}", machine)

    def on(self, machine: str) -> list[Placement]:
        return [p for p in self.placements if p.machine == machine]

    def find(self, role: str) -> Placement | None:
        return next((p for p in self.placements if p.role == role), None)

    @property
    def hub(self) -> Placement:
        """Where every node connects: the router if there is one, else the plant
        (or, with robots on CAN only, the leader)."""
        for role in (ROUTER, PLANT_ROLE, LEADER_ROLE):
            p = self.find(role)
            if p is not None:
                return p
        raise AssertionError("validated hosts have a leader")

    def addresses(self, wire_role: str) -> list[str]:
        """The addresses a role is reached on (its certificate's alternative names)."""
        return [p.address for p in self.placements if p.wire_role == wire_role]


def _fail(path: Path, key: str, msg: str) -> HostsError:
    return HostsError(f"{path}: {key}: {msg}")


def load_hosts(path: str | Path, sc: Scenario) -> Hosts:
    """Read and check a hosts file against the scenario it will run."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except OSError as exc:
        raise HostsError(f"{path}: cannot read: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        raise HostsError(f"{path}: not valid TOML (not UTF-8 text): {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise HostsError(f"{path}: not valid TOML: {exc}") from exc
    machines = raw.pop("machines", None)
    if not isinstance(machines, dict):
        raise _fail(path, "machines", "missing: a [machines.<name>] table per machine")
    spec = _convert(path, "", raw | {"machines": {}}, HostsFileSpec)
    spec.machines = {name: _convert(path, f"machines.{name}", m, MachineEntry)
                     for name, m in machines.items()}
    try:
        Keys(spec.fleet)
    except FleetNameError as exc:
        raise _fail(path, "fleet", str(exc)) from exc
    _check_port(path, "port", spec.port)
    if spec.lease_ms is not None and not 100 <= spec.lease_ms <= 600_000:
        raise _fail(path, "lease_ms", "must be within [100, 600000] ms")
    if not spec.machines:
        raise _fail(path, "machines", "no machine listed")
    placements: list[Placement] = []
    seen: dict[str, str] = {}
    for name, m in spec.machines.items():
        key = f"machines.{name}"
        if not _MACHINE.match(name):
            raise _fail(path, key, "a machine name is letters, digits, '.', '_', '-'")
        _check_address(path, f"{key}.address", m.address)
        port = m.port if m.port is not None else spec.port
        _check_port(path, f"{key}.port", port)
        for i, role in enumerate(m.roles):
            _check_role(path, f"{key}.roles", role, sc, m)
            if role in seen:
                raise _fail(path, f"{key}.roles", f"{role} is already placed on {seen[role]}")
            seen[role] = name
            placements.append(Placement(role, name, m.address, port + i))
            _check_port(path, f"{key}.roles", port + i)
    _check_complete(path, seen, sc)
    return Hosts(path, spec, placements)


def _convert(path: Path, prefix: str, raw: object, kind: type):
    try:
        return msgspec.convert(raw, kind)
    except msgspec.ValidationError as exc:
        # msgspec says e.g. "Object contains unknown field `adress`" or "... - at `$.port`"
        msg, _, where = str(exc).partition(" - at `$")
        key = ".".join(x for x in (prefix, where.rstrip("`").lstrip(".")) if x)
        raise _fail(path, key or "(top level)", msg + hint(str(exc), kind)) from exc


def _check_port(path: Path, key: str, port: int) -> None:
    if not 1 <= port <= 65535:
        raise _fail(path, key, f"port {port} is not within 1..65535")


def _check_address(path: Path, key: str, address: str) -> None:
    try:
        ipaddress.ip_address(address)
        return
    except ValueError:
        pass
    if not re.match(r"^[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?$", address):
        raise _fail(path, key, f"{address!r} is neither an IP address nor a host name")


def _check_role(path: Path, key: str, role: str, sc: Scenario, m: MachineEntry) -> None:
    if role in SINGLE_ROLES:
        return
    match = _ROBOT_ROLE.match(role)
    if match is None:
        raise _fail(path, key, f"unknown role {role!r} (plant, leader, recorder, router, "
                    "agent-<id>, bridge-<id>)")
    robot = int(match.group(2))
    if robot not in sc.robot_ids:
        raise _fail(path, key, f"{role}: scenario {sc.name!r} has no robot {robot} "
                    f"(its robots are {', '.join(map(str, sc.robot_ids))})")
    if match.group(1) == "bridge" and m.can is None:
        raise _fail(path, key, f"{role} needs the machine's CAN bus: "
                    'can = {interface = "socketcan", channel = "can0"}')


def _check_complete(path: Path, seen: dict[str, str], sc: Scenario) -> None:
    missing = [f"agent-{r}" for r in sc.robot_ids if f"agent-{r}" not in seen]
    if LEADER_ROLE not in seen:
        missing.insert(0, LEADER_ROLE)
    if missing:
        raise _fail(path, "machines", f"no machine runs {', '.join(missing)}")
    bridges = [r for r in sc.robot_ids if f"bridge-{r}" in seen]
    if PLANT_ROLE in seen and bridges:
        raise _fail(path, "machines", "the plant simulates every robot: it cannot run with "
                    f"bridges ({', '.join(f'bridge-{r}' for r in bridges)})")
    if PLANT_ROLE not in seen:
        if len(bridges) != sc.n:
            raise _fail(path, "machines", "no plant: every robot then needs its bridge-<id>")
        raise _fail(path, "machines", "robots on CAN only (bridges, no plant) need a time "
                    "keeper announcing the run's start; across machines that is not built yet "
                    "(use `omnifleet run --plant can-emulated` on one machine)")
