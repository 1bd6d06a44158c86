"""``--ros2 [ENDPOINT]``, ``--ros2-rate``, ``--ros2-namespace`` and ``ROS_DOMAIN_ID``:
parsed and checked before any process starts (a bad one exits 2)."""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass

from deploy.contract.options import add_option
from deploy.ros2.graph import Ros2NameError, check_namespace

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"  # rmw_zenoh's router
DEFAULT_RATE_HZ = 50.0

MAX_DOMAIN_ID = 232  # ROS 2's domain ids (REP 2000: 0..232 on every RMW)


@dataclass(frozen=True)
class Ros2Options:
    endpoint: str = DEFAULT_ENDPOINT
    domain: int = 0  # ROS_DOMAIN_ID
    namespace: str = ""  # absolute ('' none): prefixes every topic but /clock
    rate_hz: float = DEFAULT_RATE_HZ


class Ros2OptionError(ValueError):
    """A --ros2 option or ROS_DOMAIN_ID that cannot be used (exit 2)."""


def add_ros2_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ros2", metavar="ENDPOINT", nargs="?", const=DEFAULT_ENDPOINT,
                   help="publish the fleet as ROS 2 topics in rmw_zenoh's format through the "
                   "Zenoh router at ENDPOINT (default tcp/127.0.0.1:7447, rmw_zenoh's; "
                   "`omnifleet router --listen tcp/127.0.0.1:7447` can be it), on the domain "
                   "of ROS_DOMAIN_ID (default 0); docs/ros2.md")
    add_option(p, "--ros2-rate")
    p.add_argument("--ros2-namespace", metavar="NS", default="",
                   help="--ros2: put every topic but /clock under this ROS 2 namespace")


def ros2_options(args: argparse.Namespace) -> Ros2Options | None:
    """The options of ``args`` (None without --ros2); Ros2OptionError when unusable."""
    if getattr(args, "ros2", None) is None:
        return None
    endpoint = args.ros2.strip()
    if "/" not in endpoint or not endpoint.split("/", 1)[1]:
        raise Ros2OptionError(f"--ros2 {args.ros2!r}: expected a Zenoh endpoint such as "
                              f"{DEFAULT_ENDPOINT}")
    raw = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    if not raw.isdigit() or int(raw) > MAX_DOMAIN_ID:
        raise Ros2OptionError(f"ROS_DOMAIN_ID={raw!r}: expected an integer in 0..{MAX_DOMAIN_ID}")
    try:
        namespace = check_namespace(args.ros2_namespace)
    except Ros2NameError as exc:
        raise Ros2OptionError(f"--ros2-namespace: {exc}") from exc
    return Ros2Options(endpoint=endpoint, domain=int(raw), namespace=namespace,
                       rate_hz=float(args.ros2_rate))
