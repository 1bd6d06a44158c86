"""Plug-ins an installed package declares by entry point: a wheel-drive protocol (group
``omnifleet.drivers``, bridges/drivers.py) or a plant (``omnifleet.plants``,
deploy/contract/plant_registry.py). Read once, and only when a name is not among the
registered ones (``importlib.metadata`` costs ~11 ms a process)."""

from __future__ import annotations

from typing import Any

_read: set[str] = set()
_broken: dict[tuple[str, str], str] = {}  # (group, name) -> why it cannot be used


def load_entry_points(group: str, registry: dict[str, Any], kind: type, what: str) -> None:
    """Add each entry point of ``group`` to ``registry`` under its name, unless the name
    is taken (a built-in is never replaced). One that does not load, or is not a
    ``kind``, is left out and remembered: :func:`broken` says why, for its name only (a
    broken plug-in does not keep the others from being used)."""
    if group in _read:
        return
    _read.add(group)
    from importlib.metadata import entry_points

    for ep in entry_points(group=group):
        if ep.name in registry:
            continue
        try:
            entry = ep.load()
        except Exception as exc:  # a broken plug-in is named when asked for, not a crash
            _broken[group, ep.name] = (f"{what} {ep.name!r} (entry point {ep.value}) does not "
                                       f"load: {type(exc).__name__}: {exc}")
            continue
        if not isinstance(entry, kind):
            _broken[group, ep.name] = (f"{what} {ep.name!r} (entry point {ep.value}) is not a "
                                       f"{kind.__name__}")
            continue
        registry[ep.name] = entry


def broken(group: str, name: str) -> str | None:
    """Why the plug-in ``name`` of ``group`` cannot be used (None: it is not broken)."""
    return _broken.get((group, name))
