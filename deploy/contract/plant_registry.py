"""The plants by name: the one place a plant's name, what it is, and what it allows live.

The scenario's ``[plant] kind``, every ``--plant`` option, the launcher's choice of
clock and the report read this table; ``deploy/runtime/plants.py`` builds a plant from
its entry. It lives in the contract (the bottom of ``deploy/``) so the scenario's schema
can check a name without importing what builds it, and it imports nothing heavy: the
command line reads it before the nodes' fork server starts.

A plant of one's own (docs/extending.md) is a :class:`PlantEntry` whose builder takes
``(scenario, q, q_dot, disturbance, gui)`` (the robots' initial states, the scenario's
disturbance) and returns a :class:`plant.interface.Plant`. It is found two ways: by a
:func:`register_plant` call (this process only: ``run --in-process``, the sweeps,
``compare``), or by an entry point of group ``omnifleet.plants`` in an installed package
(every process of a fleet too: a plant node looks it up by name). Entry points are read
only when a name is not one of these (``importlib.metadata`` costs ~11 ms).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

ENTRY_POINT_GROUP = "omnifleet.plants"

__all__ = ["CAN_EMULATED", "PLANTS", "PlantEntry", "add_plant_option", "find_plant", "in_process_plants",
           "is_dynamic", "register_plant"]

CAN_EMULATED = "can-emulated"  # every robot through a CAN bridge and a drive emulator


@dataclass(frozen=True)
class PlantEntry:
    """A plant by name.

    ``build``: how one process builds it, a callable ``(scenario, q, q_dot, disturbance,
    gui) -> Plant`` or the same as ``"module:function"`` (imported when a plant is built);
    None: the plant is processes of its own, started by the launcher (``can-emulated``).
    """

    about: str  # for --plant's help
    build: Callable[..., Any] | str | None
    realtime_only: bool = False  # hardware, or its emulation: the wall clock only
    dynamic: bool = True  # torques move its robots (eq. 4); False: velocities are set directly
    gui: bool = False  # --gui opens its window


PLANTS: dict[str, PlantEntry] = {
    "pybullet": PlantEntry("rigid bodies, real contacts", "deploy.runtime.plants:pybullet_plant",
                           gui=True),
    "model": PlantEntry("eq. 4, RK4", "deploy.runtime.plants:model_plant"),
    "kinematic": PlantEntry("q_dot = the commanded velocity", "deploy.runtime.plants:kinematic_plant",
                            dynamic=False),
    CAN_EMULATED: PlantEntry("every robot through a CAN bridge and a drive emulator, one "
                             "process each (--driver picks the drives' protocol)", None,
                             realtime_only=True),
}


def register_plant(name: str, entry: PlantEntry) -> None:
    """Add a plant under ``name``: a scenario's ``[plant] kind`` and ``--plant`` take it
    from then on, in this process (a fleet's other processes: an entry point); a name
    already taken is refused."""
    if name in PLANTS:
        raise ValueError(f"a plant named {name!r} is registered already")
    if not name or any(c.isspace() for c in name):
        raise ValueError(f"a plant's name is one word, got {name!r}")
    PLANTS[name] = entry


def find_plant(name: str) -> PlantEntry | None:
    """The plant registered as ``name``, or None; the installed entry points are read
    the first time a name is not found. A plug-in of that name that cannot be used:
    ValueError saying why."""
    if name not in PLANTS:
        from bridges.plugins import broken, load_entry_points

        load_entry_points(ENTRY_POINT_GROUP, PLANTS, PlantEntry, "plant")
        why = broken(ENTRY_POINT_GROUP, name)
        if why is not None:
            raise ValueError(why)
    return PLANTS.get(name)


def in_process_plants() -> tuple[str, ...]:
    """The plants one process holds, as registered so far: a scenario's ``[plant] kind``
    is one of them (or an installed plugin's, :func:`find_plant`)."""
    return tuple(name for name, e in PLANTS.items() if e.build is not None)


def is_dynamic(name: str) -> bool:
    """Whether torques move the robots of plant ``name`` (a name not registered here, from
    another installation's metrics.json: taken as dynamic)."""
    entry = PLANTS.get(name)
    return entry is None or entry.dynamic


def add_plant_option(p: argparse.ArgumentParser, *, in_process: bool = True,
                     help_tail: str = "default: the scenario's plant.kind") -> None:
    """``--plant NAME`` on a command: a registered plant (``in_process``: one that one
    process holds), an installed plugin's included; another name exits 2 listing them."""
    names = in_process_plants() if in_process else tuple(PLANTS)

    def plant_name(value: str) -> str:
        try:
            entry = find_plant(value)
        except ValueError as exc:  # a plug-in of that name that cannot be used
            raise argparse.ArgumentTypeError(str(exc)) from None
        if entry is None or (in_process and entry.build is None):
            allowed = in_process_plants() if in_process else tuple(PLANTS)
            raise argparse.ArgumentTypeError(
                f"{value!r} is not a plant{' one process holds' if in_process else ''}; "
                f"choose one of {', '.join(allowed)}")
        return value

    p.add_argument("--plant", type=plant_name, default=None, metavar="PLANT",
                   help="; ".join(f"{name}: {PLANTS[name].about}" for name in names)
                   + f" (or a plant a package registers, docs/extending.md; {help_tail})")
