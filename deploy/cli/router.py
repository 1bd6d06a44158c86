"""``omnifleet router``'s command line (its configuration: deploy/fleet/router.py)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from deploy.contract.options import EXIT_BAD_INPUT
from deploy.fleet.router import router_config
from deploy.runtime.transport import TransportError


def _cmd_router(args: argparse.Namespace) -> int:
    import zenoh

    if not args.zenoh_config and not args.listen:
        print("omnifleet router: give --zenoh-config FILE or --listen ENDPOINT", file=sys.stderr)
        return EXIT_BAD_INPUT
    cfg = router_config(args.zenoh_config, args.listen, args.connect)
    try:
        session = zenoh.open(cfg)
    except Exception as exc:
        raise TransportError(f"cannot open the router: {exc}") from exc
    done = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: done.set())
    print(f"omnifleet router: zid {session.info.zid()} up", file=sys.stderr, flush=True)
    try:
        done.wait()
    finally:
        session.close()
    return 0


def add_router_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a zenoh router for a site (zenoh Python API)",
                       description="A zenoh router: nodes connect to it, it forwards between "
                       "them and enforces the access control of its configuration.")
    p.add_argument("--zenoh-config", metavar="FILE", help="a zenoh JSON5 config file "
                   "(mode is forced to router)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="another router to connect to (repeatable)")
    p.set_defaults(func=_cmd_router)
