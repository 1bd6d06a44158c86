"""``omnifleet deploy plan``: the exact command per machine, and the zenoh
configuration file of every node (``--write``).

Topology: every node listens on its own port of its machine's address and
connects to the hub (the router if the hosts file has one, else the plant);
gossip then links every pair of peers directly. With ``tls`` (the default) the
endpoints are ``tls/...``, each config names its role's certificate and holds
the access control of :mod:`deploy.fleet.acl`.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path

from deploy.contract.hosts import RECORDER, ROUTER, Hosts, Placement
from deploy.contract.scenario import Scenario
from deploy.contract.wire import LEADER_ROLE, PLANT_ROLE
from deploy.fleet.acl import access_control, fleet_roles
from deploy.fleet.certs import role_files
from deploy.fleet.zenoh_configs import node_config, write_config


@dataclass(frozen=True)
class RunOptions:
    """What every node of the run must agree on, and where the recorder writes."""

    scenario: str  # as given on the command line (a bundled name or a path on the machines)
    clock: str = "lockstep"
    duration_s: float | None = None
    control_rate_hz: float | None = None
    lost_peer_grace_s: float | None = None
    plant_kind: str | None = None  # default: the scenario's plant.kind
    step_deadline_s: float | None = None  # lockstep: None = the nodes' default (deploy/contract/options.py)
    record_out: str = "runs/{fleet}"


MASTER_FILE = "fleet.master"  # the keyrings' master secret, beside the CA's key


def config_path(hosts: Hosts, p: Placement) -> str:
    return f"{hosts.machine_dir(p.machine)}/{p.wire_role}.json5"


def keys_file_name(wire_role: str) -> str:
    """A role's keyring, beside its certificate (``omnifleet deploy certs``)."""
    return f"{wire_role}.keys"


def key_roles(hosts: Hosts) -> list[str]:
    """The roles of a deployment that hold keyrings: every node but a router (which
    forwards and tags nothing)."""
    return [p.wire_role for p in hosts.placements if p.role != ROUTER]


def zenoh_config_for(hosts: Hosts, sc: Scenario, p: Placement) -> dict:
    """The node's zenoh configuration (paths as they are on its machine)."""
    tls = hosts.spec.tls
    hub = hosts.hub
    connect = [] if p == hub else [hub.endpoint(tls)]
    files = role_files(hosts.machine_dir(p.machine), p.wire_role) if tls else None
    acl = access_control(sc, hosts.fleet, p.wire_role, _roles(hosts, sc)) if tls else None
    return node_config([p.endpoint(tls)], connect, files, acl,
                       mode="router" if p.role == ROUTER else "peer",
                       lease_ms=hosts.spec.lease_ms)


def _roles(hosts: Hosts, sc: Scenario) -> list[str]:
    return fleet_roles(sc, bridges=True, router=hosts.find(ROUTER) is not None)


def command_for(hosts: Hosts, sc: Scenario, p: Placement, run: RunOptions) -> list[str]:
    """argv of the node's command."""
    cfg = config_path(hosts, p)
    exe = hosts.spec.command.split()
    if p.role == ROUTER:
        return [*exe, "router", "--zenoh-config", cfg]
    keys = f"{hosts.machine_dir(p.machine)}/{keys_file_name(p.wire_role)}"
    common = ["--scenario", run.scenario, "--fleet", hosts.fleet, "--clock", run.clock,
              "--zenoh-config", cfg, "--keys", keys]
    if run.duration_s is not None:
        common += ["--duration", repr(run.duration_s)]
    if run.control_rate_hz is not None:
        common += ["--control-rate", repr(run.control_rate_hz)]
    plant = [] if run.plant_kind is None else ["--plant", run.plant_kind]
    if p.role == RECORDER:
        out = run.record_out.replace("{fleet}", hosts.fleet)
        return [*exe, "record", *common, *plant, "--out", out]
    if run.step_deadline_s is not None:
        common += ["--step-deadline", repr(run.step_deadline_s)]
    if hosts.find(RECORDER) is not None:
        common.append("--wait-recorder")
    grace = [] if run.lost_peer_grace_s is None else ["--lost-peer-grace",
                                                       repr(run.lost_peer_grace_s)]
    if p.role == PLANT_ROLE:
        return [*exe, "plant", *common, *plant]
    if p.role == LEADER_ROLE:
        return [*exe, "leader", *common, *grace]
    kind, robot = p.role.split("-", 1)
    if kind == "agent":
        plant_role = [] if hosts.find(f"bridge-{robot}") is None else ["--plant-role",
                                                                     f"bridge-{robot}"]
        return [*exe, "agent", *common, "--robot", robot, *plant_role, *grace]
    can = hosts.spec.machines[p.machine].can
    assert can is not None  # validated
    return [*exe, "bridge", *common, "--robot", robot, "--can-interface", can.interface,
            "--can-channel", can.channel]


START_ORDER = (ROUTER, RECORDER, PLANT_ROLE, LEADER_ROLE)


def _order(p: Placement) -> tuple[int, str]:
    return (START_ORDER.index(p.role) if p.role in START_ORDER else len(START_ORDER), p.role)


def plan_text(hosts: Hosts, sc: Scenario, run: RunOptions) -> str:
    """What ``deploy plan`` prints: per machine, its files and its commands."""
    tls = hosts.spec.tls
    lines = [f"# fleet {hosts.fleet}: scenario {sc.name}, {len(hosts.placements)} nodes, "
             f"{'mutual TLS + access control' if tls else 'plain TCP (no TLS, no ACL)'}; "
             f"every node connects to {hosts.hub.role} at {hosts.hub.endpoint(tls)}",
             "# start the router and the recorder first (nodes wait for the recorder);",
             "# the other nodes in any order: the plant starts the run when all are ready."]
    for machine, m in hosts.spec.machines.items():
        lines.append("")
        lines.append(f"## {machine} ({m.address}): copy {hosts.machine_dir(machine)}/ "
                     f"({'certificates, ' if tls else ''}keyrings and zenoh configs) there")
        for p in sorted(hosts.on(machine), key=_order):
            lines.append(shlex.join(command_for(hosts, sc, p, run)))
    return "\n".join(lines) + "\n"


def write_configs(hosts: Hosts, sc: Scenario, out: str | Path) -> list[Path]:
    """Every node's zenoh config, under ``out/<machine>/<role>.json5`` (to be
    copied to the machine's ``dir``)."""
    written = []
    for p in hosts.placements:
        written.append(write_config(Path(out) / p.machine / f"{p.wire_role}.json5",
                                    zenoh_config_for(hosts, sc, p)))
    return written
