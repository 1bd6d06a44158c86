"""The motor-driver protocols a bridge can speak, by name (``omnifleet bridge --driver``).

A protocol is a :class:`bridges.protocol.DriverProtocol`: typed frames <-> CAN messages
and the frames that arm, disarm, stop and command an axis. To add one (a CiA 402
drive, say), implement that interface for ``role="host"`` and register its maker here.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from bridges.protocol import DriverProtocol, OdriveCanSimple

DRIVERS: dict[str, Callable[[Sequence[int]], DriverProtocol]] = {
    OdriveCanSimple.name: lambda node_ids: OdriveCanSimple(node_ids, role="host"),
}
DEFAULT_DRIVER = OdriveCanSimple.name


def make_driver(name: str, node_ids: Sequence[int]) -> DriverProtocol:
    """The host side of protocol ``name`` for the drives ``node_ids``."""
    try:
        return DRIVERS[name](node_ids)
    except KeyError:
        raise ValueError(f"unknown driver {name!r}; choose one of {', '.join(sorted(DRIVERS))}") from None
