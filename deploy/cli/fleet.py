"""``omnifleet deploy plan|certs``: a fleet across machines from a hosts file
(:mod:`deploy.contract.hosts`). Bad input exits 2 with the file and key named."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from deploy.contract.hosts import Hosts, HostsError, load_hosts
from deploy.contract.keyring import keyring_text, new_master, write_file
from deploy.contract.options import EXIT_BAD_INPUT, OPTIONS, add_option, check_duration
from deploy.contract.output_paths import check_folder
from deploy.fleet.certs import CA_NAME, make_ca, make_role_cert
from deploy.fleet.deploy_plan import MASTER_FILE, key_roles, keys_file_name


def _load(args: argparse.Namespace):
    from deploy.contract.scenario import load_scenario

    sc = load_scenario(args.scenario)
    return sc, load_hosts(args.hosts, sc)


def make_hosts_certs(hosts: Hosts, out: str | Path, days: int = 365) -> dict[str, Path]:
    """A fleet CA in ``out/ca/`` and, per machine, ``out/<machine>/``: the CA's
    certificate and its roles' certificates, TLS keys and keyrings (each machine gets
    only its own). Returns the machine folders.

    The keyrings (deploy/contract/keyring.py: a key per pair of roles, for the MAC of
    every message) come from a master drawn here, kept beside the CA's key in
    ``out/ca/fleet.master`` (0600): like ``ca.key``, it stays off the robots."""
    out = Path(out)
    (out / CA_NAME).mkdir(parents=True, exist_ok=True)
    ca_cert, ca_key = make_ca(out / CA_NAME, hosts.fleet, days)
    master = new_master()
    write_file(out / CA_NAME / MASTER_FILE, master.hex())
    roles = key_roles(hosts)
    folders = {}
    for machine in hosts.spec.machines:
        d = out / machine
        d.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / CA_NAME / f"{CA_NAME}.pem", d / f"{CA_NAME}.pem")
        for p in hosts.on(machine):
            make_role_cert(d, p.wire_role, ca_cert, ca_key, hosts.addresses(p.wire_role), days)
            if p.wire_role in roles:
                write_file(d / keys_file_name(p.wire_role),
                           keyring_text(master, hosts.fleet, p.wire_role, roles))
        folders[machine] = d
    return folders


def _cmd_plan(args: argparse.Namespace) -> int:
    from deploy.fleet.deploy_plan import RunOptions, plan_text, write_configs

    if args.write:
        check_folder(args.write, "--write")  # OutputPathError: exit 2 (cli.main)
    try:
        sc, hosts = _load(args)
    except HostsError as exc:
        print(f"omnifleet deploy plan: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    check_duration(args.duration, args.control_rate or sc.spec.control_rate_hz)
    run = RunOptions(args.scenario, clock=args.clock, duration_s=args.duration,
                     control_rate_hz=args.control_rate, lost_peer_grace_s=args.lost_peer_grace,
                     plant_kind=args.plant, step_deadline_s=args.step_deadline,
                     record_out=args.record_out)
    if args.write:
        for path in write_configs(hosts, sc, args.write):
            print(f"wrote {path}", file=sys.stderr)
    sys.stdout.write(plan_text(hosts, sc, run))
    return 0


def _cmd_certs(args: argparse.Namespace) -> int:
    check_folder(args.out, "--out")  # OutputPathError: exit 2 (cli.main), before anything
    try:
        _sc, hosts = _load(args)
    except HostsError as exc:
        print(f"omnifleet deploy certs: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    folders = make_hosts_certs(hosts, args.out, args.days)
    print(f"fleet {hosts.fleet}: CA in {Path(args.out) / CA_NAME} (keep ca.key and "
          f"{MASTER_FILE} off the robots); copy each machine's folder to its dir:")
    for machine, d in folders.items():
        print(f"  {machine}: {d} -> {hosts.machine_dir(machine)}/ "
              f"({', '.join(p.wire_role for p in hosts.on(machine))})")
    return 0


def add_deploy_commands(sub: argparse._SubParsersAction) -> None:
    from deploy.contract.plant_registry import add_plant_option
    from deploy.nodes.cli import CLOCKS

    deploy = sub.add_parser(
        "deploy", help="run a fleet across machines: certificates and per-machine commands",
        description="A hosts file (TOML, see deploy/hosts/example.toml and docs/multihost.md) "
        "says which machine runs which role. `deploy certs` makes the fleet's CA and one "
        "certificate per role; `deploy plan` prints every machine's commands and, with "
        "--write, every node's zenoh configuration (TLS endpoints and access control).")
    dsub = deploy.add_subparsers(dest="deploy_command", required=True, metavar="STEP")
    plan = dsub.add_parser("plan", help="print the exact command per machine",
                           description="Print, per machine, the commands to run; with --write "
                           "DIR also write each node's zenoh config to DIR/<machine>/.")
    plan.add_argument("hosts", metavar="HOSTS", help="hosts file (TOML)")
    plan.add_argument("scenario", metavar="SCENARIO", help="scenario file or bundled name")
    plan.add_argument("--write", metavar="DIR",
                      help="write every node's zenoh config to DIR/<machine>/<role>.json5")
    plan.add_argument("--clock", choices=CLOCKS, default="lockstep", help="default: lockstep")
    add_option(plan, "--duration")
    add_option(plan, "--control-rate")
    add_option(plan, "--lost-peer-grace", default=None,
               more_help="given to the agents and the leader (default: theirs)")
    add_plant_option(plan)
    add_option(plan, "--step-deadline", default=None,
               more_help="given to every node (default: theirs, "
               f"{OPTIONS['--step-deadline'].default:g} s)")
    plan.add_argument("--record-out", default="runs/{fleet}", metavar="DIR",
                      help="the recorder's output folder on its machine (default: runs/{fleet})")
    plan.set_defaults(func=_cmd_plan)
    certs = dsub.add_parser("certs", help="make the fleet's CA and one certificate per role",
                            description="Write a new CA to OUT/ca/ and, per machine, OUT/<machine>/ "
                            "with ca.pem and the certificate and key of each of its roles "
                            "(common name = role, the identity the access control matches) "
                            "and its keyring <role>.keys (a key per pair of roles: every "
                            "message is authenticated per sender and receiver; "
                            "docs/hardening.md).")
    certs.add_argument("hosts", metavar="HOSTS", help="hosts file (TOML)")
    certs.add_argument("scenario", metavar="SCENARIO", help="scenario file or bundled name")
    certs.add_argument("--out", required=True, metavar="DIR", help="where to write them")
    add_option(certs, "--days")
    certs.set_defaults(func=_cmd_certs)
