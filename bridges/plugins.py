"""Plug-ins an installed package declares by entry point: a wheel-drive protocol (group
``omnifleet.drivers``, bridges/drivers.py) or a plant (``omnifleet.plants``,
deploy/contract/plant_registry.py). Read once, and only when a name is not among the
registered ones (``importlib.metadata`` costs ~11 ms a process)."""

from __future__ import annotations

from typing import Any

_read: set[str] = set()


def load_entry_points(group: str, registry: dict[str, Any], kind: type, what: str) -> None:
    """Add each entry point of ``group`` to ``registry`` under its name, unless the name
    is taken (a built-in is never replaced); an entry point that does not load, or is not
    a ``kind``, is a ValueError naming it."""
    if group in _read:
        return
    _read.add(group)
    from importlib.metadata import entry_points

    for ep in entry_points(group=group):
        if ep.name in registry:
            continue
        try:
            entry = ep.load()
        except Exception as exc:  # a broken plug-in is named, not a crash of every command
            raise ValueError(f"{what} {ep.name!r} (entry point {ep.value}) does not load: "
                             f"{type(exc).__name__}: {exc}") from exc
        if not isinstance(entry, kind):
            raise ValueError(f"{what} {ep.name!r} (entry point {ep.value}) is not a "
                             f"{kind.__name__}")
        registry[ep.name] = entry
