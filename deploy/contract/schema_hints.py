"""What a refused key or value should have been, for every TOML file a user writes
(scenario, fault plan, hosts file): msgspec says `Object contains unknown field `drop` -
at `$.link[0]``; this adds the nearest known key at that place ("did you mean"), or
every key known there, and for a value outside a choice the allowed values."""

from __future__ import annotations

import difflib
import re
from types import UnionType
from typing import Literal, Union, get_args, get_origin

import msgspec

_UNKNOWN_FIELD = re.compile(r"unknown field `([^`]*)`(?: - at `\$([^`]*)`)?")
_BAD_ENUM = re.compile(r"Invalid enum value .* - at `\$([^`]*)`")


def readable(msg: str, root: type) -> str:
    """msgspec's message with ``$.`` dropped from its paths and :func:`hint` added."""
    return msg.replace("`$.", "`").replace("`$`", "top level") + hint(msg, root)


def hint(msg: str, root: type, at: str = "") -> str:
    """For an unknown key, the nearest known one at that place; for a value outside an
    enum, the allowed values; empty when there is nothing to add. ``root``: the struct
    the file decodes into; ``at``: where in it ``msg``'s paths start (``.machines.a``)."""
    if m := _UNKNOWN_FIELD.search(msg):
        known = keys_at(root, at + (m.group(2) or ""))
        near = difflib.get_close_matches(m.group(1), known, n=1, cutoff=0.6)
        if near:
            return f"; did you mean `{near[0]}`?"
        elsewhere = tables_with(root, m.group(1))
        if elsewhere:  # a key of a table, written outside it
            return (f"; `{m.group(1)}` is a key of {', '.join(elsewhere)}"
                    + (f" (known keys here: {', '.join(known)})" if known else ""))
        return f"; known keys here: {', '.join(known)}" if known else ""
    if m := _BAD_ENUM.search(msg):
        allowed = enum_at(root, at + m.group(1))
        return f"; expected one of: {', '.join(allowed)}" if allowed else ""
    return ""


def _types_at(root: type, path: str) -> list:
    """The schema types at a msgspec path such as ``.leader.x`` or ``.obstacles[0]``
    (several where the schema has a union there; a dict's values by any key)."""
    types: list = [root]
    for name, index in re.findall(r"\.([\w-]+)|\[(\d+)\]", path):
        nxt: list = []
        for t in types:
            for u in _members(t):
                if index and get_origin(u) is list:
                    nxt += list(get_args(u)[:1])
                elif name and get_origin(u) is dict:
                    nxt += list(get_args(u)[1:2])
                elif name and isinstance(u, type) and issubclass(u, msgspec.Struct):
                    nxt += [f.type for f in msgspec.structs.fields(u) if f.encode_name == name]
        types = nxt
    return types


def _members(t) -> tuple:
    """A union's members (``X | None`` included), or the type itself."""
    return get_args(t) if get_origin(t) in (Union, UnionType) else (t,)


def keys_at(root: type, path: str) -> list[str]:
    keys = {f.encode_name for t in _types_at(root, path) for u in _members(t)
            if isinstance(u, type) and issubclass(u, msgspec.Struct)
            for f in msgspec.structs.fields(u)}
    return sorted(keys)


def enum_at(root: type, path: str) -> list[str]:
    return [str(v) for t in _types_at(root, path) for u in _members(t)
            if get_origin(u) is Literal for v in get_args(u)]


def tables_with(root: type, key: str, depth: int = 3) -> list[str]:
    """The TOML tables under ``root`` that have ``key`` (``[defaults]``, ``[[link]]``)."""
    found: list[str] = []

    def walk(t: type, name: str, level: int) -> None:
        for u in _members(t):
            many = get_origin(u) is list
            inner = get_args(u)[0] if many and get_args(u) else u
            if not (isinstance(inner, type) and issubclass(inner, msgspec.Struct)):
                continue
            here = f"[[{name}]]" if many else f"[{name}]"
            fields = msgspec.structs.fields(inner)
            if name and any(f.encode_name == key for f in fields):
                found.append(here)
            if level < depth:
                for f in fields:
                    walk(f.type, f"{name}.{f.encode_name}" if name else f.encode_name, level + 1)

    walk(root, "", 0)
    return found
