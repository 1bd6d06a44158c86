"""The wheel-drive protocols a bridge can speak, by name (``--driver``).

A protocol is a :class:`bridges.driver.WheelDriver` for the host (the bridge,
``omnifleet can-check``) and a drive emulator that plays four such drives and the
robot's dynamics (``omnifleet emulate``). To add one, implement both and register
their makers: here, with :func:`register_driver` (this process only), or as an entry
point of group ``omnifleet.drivers`` in an installed package (every process of a fleet:
docs/extending.md); nothing else in the product names a protocol. The makers import
their module when called: every node process builds the whole command line, and
only the CAN commands need a protocol's libraries.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from bridges.driver import DriverSettings, WheelDriver


def _odrive(settings: DriverSettings) -> WheelDriver:
    from bridges.odrive import OdriveDriver

    return OdriveDriver(settings)


def _odrive_emulator() -> Any:
    from bridges.odrive_emulator import OdriveEmulator

    return OdriveEmulator


def _cia402(settings: DriverSettings) -> WheelDriver:
    from bridges.cia402_driver import Cia402Driver

    return Cia402Driver(settings)


def _cia402_emulator() -> Any:
    from bridges.cia402_emulator import Cia402Emulator

    return Cia402Emulator


@dataclass(frozen=True)
class DriverEntry:
    about: str
    node_id_range: tuple[int, int]  # the node ids the protocol can address, inclusive
    default_node_ids: tuple[int, int, int, int]  # in the wheel order of eq. (1)
    make: Callable[[DriverSettings], WheelDriver]  # the host side
    emulator: Callable[[], Any]  # the class that emulates one robot's four drives


DRIVERS: dict[str, DriverEntry] = {
    "odrive-cansimple": DriverEntry(
        "ODrive CANSimple (firmware 0.5/0.6): one node per axis, id = node << 5 | cmd",
        (0, 63), (0, 1, 2, 3), _odrive, _odrive_emulator),
    "cia402": DriverEntry(
        "CiA 402 servo drives over CANopen (NMT, SDO configuration from an EDS, PDOs, "
        "SYNC; cyclic synchronous torque; node 127 is the bridge's own heartbeat)", (1, 126),
        (1, 2, 3, 4), _cia402, _cia402_emulator),
}
DEFAULT_DRIVER = "odrive-cansimple"
ENTRY_POINT_GROUP = "omnifleet.drivers"


def register_driver(name: str, driver: DriverEntry) -> None:
    """Add a protocol under ``name`` (``--driver`` takes it from then on, in this
    process); a name already taken is refused."""
    if name in DRIVERS:
        raise ValueError(f"a driver named {name!r} is registered already")
    DRIVERS[name] = driver


def entry(name: str) -> DriverEntry:
    """The protocol registered as ``name`` (the installed entry points read the first
    time a name is not found); ValueError listing them if none is."""
    if name not in DRIVERS:
        from bridges.plugins import broken, load_entry_points

        load_entry_points(ENTRY_POINT_GROUP, DRIVERS, DriverEntry, "driver")
        why = broken(ENTRY_POINT_GROUP, name)
        if why is not None:
            raise ValueError(why)
    try:
        return DRIVERS[name]
    except KeyError:
        raise ValueError(f"unknown driver {name!r}; choose one of {', '.join(sorted(DRIVERS))}") from None


def node_ids_for(name: str, node_ids: Sequence[int] | None) -> tuple[int, ...]:
    """The drives' node ids for protocol ``name`` (its default when None); ValueError
    naming them when the protocol cannot address them."""
    e = entry(name)
    ids = tuple(e.default_node_ids if node_ids is None else (int(n) for n in node_ids))
    lo, hi = e.node_id_range
    if len(ids) != 4 or len(set(ids)) != 4 or not all(lo <= n <= hi for n in ids):
        raise ValueError(f"--node-ids {','.join(map(str, ids))}: {name} needs 4 distinct node "
                         f"ids in {lo}..{hi} (the wheel order of eq. 1)")
    return ids


def make_driver(name: str, settings: DriverSettings) -> WheelDriver:
    """The host side of protocol ``name`` (ValueError naming a bad node id or file)."""
    node_ids_for(name, settings.node_ids)
    return entry(name).make(settings)
