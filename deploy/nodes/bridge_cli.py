"""``omnifleet bridge``: one robot's CAN bridge, a zenoh peer in place of the plant."""

from __future__ import annotations

import argparse
import sys
import time

from deploy.contract.options import EXIT_BAD_INPUT, add_option
from deploy.nodes.can_options import (
    CanBusError,
    DriverOptionError,
    add_can_options,
    make_driver,
    open_bus,
)
from deploy.nodes.cli import (
    EXIT_STARTUP,
    add_node_options,
    add_spool_option,
    run_node,
    run_scenario,
    steps_of,
)


def _cmd_bridge(args: argparse.Namespace) -> int:
    from bridges.driver import DriveError
    from deploy.contract.wire import bridge_role
    from deploy.nodes.bridge import BridgeNode

    if args.clock != "realtime":
        print("omnifleet bridge: hardware runs on its own clock: use --clock realtime",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    sc = run_scenario(args)
    sc.index_of(args.robot)  # fail fast, before the bus
    try:  # a bad node id or EDS is named before the bus is touched
        driver = make_driver(args, sc.dt, sc.spec.limits.max_wheel_torque_nm)
        bus = open_bus(args)
    except (CanBusError, DriverOptionError) as exc:
        print(f"omnifleet bridge: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:  # configure the drives (CiA 402: NMT, SDO) before the bridge reads the bus
        driver.bring_up(bus, args.startup_timeout,
                        lambda line: print(f"omnifleet bridge: {line}", file=sys.stderr, flush=True))
    except DriveError as exc:
        print(f"omnifleet bridge: the drives did not come up: {exc}", file=sys.stderr)
        bus.shutdown()
        return EXIT_STARTUP

    made = []

    def build(sc, node, stop):
        made.append(BridgeNode(sc, args.robot, node, stop, bus, driver, list(driver.node_ids),
                               args.command_timeout, args.heartbeat_timeout, args.spool))
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
        description="Drives a robot's four motor drives (--driver: ODrive CANSimple by "
        "default, or CiA 402 over CANopen, configured first by NMT and SDO) from "
        "robot/<id>/cmd and publishes robot/<id>/state from their encoders (odometry, eq. 1). "
        "Zero torque and disarmed drives when the command is older than --command-timeout, "
        "on e-stop (CiA 402: the drives' own quick stop), on a drive fault or a missing "
        "status, for a drive that never becomes enabled, and whenever the bridge leaves. "
        "Exit 2 for a bad node id or EDS, 4 when the drives do not come up.")
    add_node_options(p)
    p.set_defaults(clock="realtime")
    add_option(p, "--robot", required=True)
    add_can_options(p)
    add_option(p, "--command-timeout", help="zero torque when the newest command is older "
               "than this")
    add_option(p, "--heartbeat-timeout")
    add_spool_option(p, "every sample sent and every command heard")
    p.add_argument("--self-start", action="store_true",
                   help="start the clock now instead of waiting for ctl/start (bring-up)")
    p.set_defaults(func=_cmd_bridge)
