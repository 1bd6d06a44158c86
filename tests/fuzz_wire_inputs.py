"""Hypothesis strategies for wire messages (deploy/contract/wire.py), by message type.

A message is a msgpack array of its fields (``array_like`` structs), so inputs
are built as field lists from the type hints: ``sane`` lists are valid messages
(the decoder must accept them), otherwise any field may be out of range, of the
wrong type or non-finite, and the array may be cut short or run long.
"""

from __future__ import annotations

import functools
import types
import typing
from typing import Any

import msgspec
from fuzzing import any_float, any_int, any_msgpack, nasty_ints
from hypothesis import strategies as st

from deploy.contract.wire import (
    CONTROL_COMMANDS,
    MAX_ORDER_CHARS,
    MAX_ROLE_CHARS,
    WIRE_VERSION,
    LeaderState,
    Message,
    StateLog,
    Telemetry,
    TelemetryRow,
)

ROBOT_IDS = (1, 2, 3)  # the bundled scenarios' robots

sane_float = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
sane_int = st.integers(0, 2**62)


def _robot_id(sane: bool) -> st.SearchStrategy[int]:
    ids = st.sampled_from(ROBOT_IDS)
    return ids if sane else st.one_of(ids, any_int, st.sampled_from([0, -1, 4, 64, 2**31]))


def _of_type(tp: Any, name: str, sane: bool) -> st.SearchStrategy[Any]:
    """Field values of annotation ``tp`` (the field ``name`` picks the ranges)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (types.UnionType, typing.Union):
        return st.one_of(*(st.none() if a is type(None) else _of_type(a, name, sane) for a in args))
    if tp is bool:
        return st.booleans()
    if tp is int:
        if name == "v":
            return st.just(WIRE_VERSION) if sane else st.one_of(st.just(WIRE_VERSION), any_int)
        if name in ("robot",):
            return _robot_id(sane)
        if name == "ident":
            return st.one_of(st.sampled_from(ROBOT_IDS), st.integers(-50, -1)) if sane \
                else st.one_of(_robot_id(False), st.integers(-2**63, -1))
        return sane_int if sane else st.one_of(sane_int, any_int, nasty_ints)
    if tp is float:
        return sane_float if sane else st.one_of(sane_float, any_float)
    if tp is str:
        if name == "command":
            cmds = st.sampled_from(CONTROL_COMMANDS)
            return cmds if sane else st.one_of(cmds, st.text(max_size=12))
        limit = MAX_ORDER_CHARS if name == "order" else MAX_ROLE_CHARS
        return st.text(max_size=limit) if sane else st.text(max_size=2 * limit)
    if origin is tuple:
        items = [_of_type(a, name, sane) for a in args]
        if sane:
            return st.tuples(*items).map(list)
        return st.one_of(st.tuples(*items).map(list),
                         st.lists(_of_type(args[0], name, sane), max_size=len(args) + 2))
    if origin is list:
        return st.lists(_of_type(args[0], name, sane), max_size=4 if sane else 6)
    if origin is dict:
        return st.dictionaries(st.text(max_size=20), _of_type(args[1], name, sane), max_size=4)
    if isinstance(tp, type) and issubclass(tp, msgspec.Struct):
        return struct_fields(tp, sane)
    raise TypeError(f"no strategy for {tp!r}")


@functools.cache
def _field_strategies(kind: type[msgspec.Struct], sane: bool) -> tuple[st.SearchStrategy[Any], ...]:
    """One strategy per field of ``kind``, built once: a strategy built anew at every draw
    had hypothesis work out its properties again each time, most of a fuzz test's time."""
    hints = typing.get_type_hints(kind)
    return tuple(_of_type(hints[name], name, sane) for name in kind.__struct_fields__)


ONE_IN_12 = st.integers(0, 11)
SHAPES = st.sampled_from(["keep"] * 6 + ["cut", "extend"])
EXTRA_FIELDS = st.lists(any_msgpack, min_size=1, max_size=3)


@st.composite
def struct_fields(draw: st.DrawFn, kind: type[msgspec.Struct], sane: bool) -> list[Any]:
    """The field list of one ``kind`` value (what its msgpack array holds)."""
    values = []
    for field_values in _field_strategies(kind, sane):
        if not sane and draw(ONE_IN_12) == 0:
            values.append(draw(any_msgpack))  # any type at all
        else:
            values.append(draw(field_values))
    if not sane:
        shape = draw(SHAPES)
        if shape == "cut":
            values = values[:draw(st.integers(0, len(values)))]
        elif shape == "extend":
            values += draw(EXTRA_FIELDS)
    return values


@st.composite
def _batch_fields(draw: st.DrawFn, kind: type[Message]) -> list[Any]:
    """A valid batched message: its lists as long as each other, never empty."""
    values = draw(struct_fields(kind, True))
    names = list(kind.__struct_fields__)
    vec3 = st.tuples(sane_float, sane_float, sane_float).map(list)
    if kind is LeaderState:
        n = draw(st.integers(1, 4))
        values[names.index("q")] = draw(st.lists(vec3, min_size=n, max_size=n))
        values[names.index("q_dot")] = draw(st.lists(vec3, min_size=n, max_size=n))
    elif kind is Telemetry:
        rows = names.index("rows")
        values[rows] = values[rows] or [draw(struct_fields(TelemetryRow, True))]
    elif kind is StateLog:
        robots = draw(st.lists(st.sampled_from(ROBOT_IDS), min_size=1, max_size=3))
        values[names.index("robots")] = robots
        n = len(robots)
        values[names.index("rows")] = [
            [draw(sane_int), draw(sane_float), draw(st.lists(vec3, min_size=n, max_size=n)),
             draw(st.lists(vec3, min_size=n, max_size=n)),
             draw(st.lists(st.booleans(), min_size=n, max_size=n))]
            for _ in range(draw(st.integers(1, 3)))]
    return values


BATCHED = (LeaderState, Telemetry, StateLog)


def message_bytes(kind: type[Message], sane: bool) -> st.SearchStrategy[bytes]:
    """Encoded field lists of ``kind`` (valid when ``sane``)."""
    if sane and kind in BATCHED:
        return _batch_fields(kind).map(msgspec.msgpack.encode)
    return struct_fields(kind, sane).map(msgspec.msgpack.encode)
