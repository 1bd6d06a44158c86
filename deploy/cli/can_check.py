"""``omnifleet can-check``'s command line. The check itself (deploy/nodes/can_check.py,
python-can and the DBC) is imported only when it runs: every node process builds
the whole parser, and importing python-can and cantools there cost each ~14 MB."""

from __future__ import annotations

import argparse

from deploy.contract.options import add_option
from deploy.nodes.can_options import add_can_options


def _run(args: argparse.Namespace) -> int:
    from deploy.nodes.can_check import _cmd_can_check

    return _cmd_can_check(args)


def add_can_check_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "can-check", help="bring-up: list the motor drives that answer on a CAN bus",
        description="Lists the drives that answer (of --node-ids; without it, of every node id "
        "the --driver's protocol addresses), brings them up as the bridge does, step by step "
        "(CiA 402: heartbeat, NMT, SDO configuration, PDO mapping, NMT operational), and lists "
        "their state, fault, wheel angle, speed and torque. With --spin, arms each drive step by "
        "step, turns its wheel briefly at a small torque and reports its direction and speed. "
        "Exit 1 when nobody answers or a drive does not come up, 2 for bad input (a node id, "
        "an EDS).")
    add_can_options(p)
    add_option(p, "--listen")
    add_option(p, "--bring-up-timeout")
    p.add_argument("--spin", action="store_true",
                   help="turn each answering wheel briefly (the robot must be on blocks)")
    add_option(p, "--spin-torque")
    add_option(p, "--spin-time")
    p.set_defaults(func=_run)
