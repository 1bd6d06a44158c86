"""``omnifleet bridge`` (one robot's CAN bridge, a zenoh peer) and
``omnifleet can-check`` (bring-up: who answers on a bus)."""

from __future__ import annotations

import argparse
import sys
import time

from bridges.drivers import DEFAULT_DRIVER, DRIVERS
from deploy.contract.options import EXIT_BAD_INPUT, add_option
from deploy.nodes.can_options import CanBusError, add_can_options, open_bus
from deploy.nodes.cli import add_node_options, run_node, steps_of


def _cmd_bridge(args: argparse.Namespace) -> int:
    from bridges.drivers import make_driver
    from deploy.contract.scenario import load_scenario
    from deploy.contract.wire import bridge_role
    from deploy.nodes.bridge import BridgeNode

    if args.clock != "realtime":
        print("omnifleet bridge: hardware runs on its own clock: use --clock realtime",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    load_scenario(args.scenario).index_of(args.robot)  # fail fast, before the bus
    try:
        bus = open_bus(args)
    except CanBusError as exc:
        print(f"omnifleet bridge: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT

    made = []

    def build(sc, node, stop):
        made.append(BridgeNode(sc, args.robot, node, stop, bus, make_driver(args.driver, args.node_ids),
                          list(args.node_ids), args.command_timeout, args.heartbeat_timeout))
        return made[0]

    def realtime(obj, sc):
        t0 = time.monotonic() if args.self_start else obj.idle_until_start(args.startup_timeout)
        if t0 is not None:
            obj.run_realtime(t0, steps_of(sc, args))

    try:
        return run_node(args, bridge_role(args.robot), args.robot, build, None, realtime)
    finally:
        for bridge in made:
            bridge.close()
        bus.shutdown()


def add_bridge_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bridge", help="run one robot's CAN bridge (in place of the plant for that robot)",
        description="Drives a robot's four motor drivers (--driver, ODrive CANSimple by "
        "default) from robot/<id>/cmd and publishes robot/<id>/state from their encoders "
        "(odometry, eq. 1). Zero torque and idle axes when the command is older than "
        "--command-timeout, on e-stop, on a driver error or a missing heartbeat, and "
        "whenever the bridge leaves.")
    add_node_options(p)
    p.set_defaults(clock="realtime")
    add_option(p, "--robot", required=True)
    add_can_options(p)
    p.add_argument("--driver", choices=sorted(DRIVERS), default=DEFAULT_DRIVER,
                   help=f"the drives' CAN protocol (default {DEFAULT_DRIVER}; bridges/drivers.py)")
    add_option(p, "--command-timeout", help="zero torque when the newest command is older "
               "than this")
    add_option(p, "--heartbeat-timeout")
    p.add_argument("--self-start", action="store_true",
                   help="start the clock now instead of waiting for ctl/start (bring-up)")
    p.set_defaults(func=_cmd_bridge)
