"""ROS 2 message types, their RIHS01 hashes and their CDR bytes, from ``rosbags``' type
store of ROS 2 Jazzy (Kilted carries the same definitions and hashes for every type used
here). ``rosbags`` rather than a hand-written encoder: its store is generated from the
distribution's own .msg files, and its codec is the one rosbag2 tools read.
"""

from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np

DISTRIBUTION = "jazzy"
_DTYPES = {"float64": np.float64, "float32": np.float32, "uint8": np.uint8, "int8": np.int8,
           "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
           "int64": np.int64, "uint64": np.uint64}
_ZERO = {"string": "", "bool": False, "float32": 0.0, "float64": 0.0}


@cache
def store() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@cache
def type_hash(ros_type: str) -> str:
    """``RIHS01_<sha256>`` of a type, as rmw_zenoh puts it in keys and tokens."""
    return store().hash_rihs01(ros_type)


@cache
def definition(ros_type: str) -> str:
    """The ``ros2msg`` text of a type with its dependencies (an MCAP schema)."""
    return store().generate_msgdef(ros_type, ros_version=2)[0]


def _zero(node: tuple) -> Any:
    kind, detail = node
    if kind == 1:  # BASE
        return _ZERO.get(detail[0], 0)
    if kind == 2:  # NAME
        return make(detail)
    inner, size = detail
    numbers = inner[0] == 1 and inner[1][0] in _DTYPES
    if kind == 3:  # a fixed array
        return np.zeros(size, _DTYPES[inner[1][0]]) if numbers else [
            _zero(inner) for _ in range(size)]
    return np.zeros(0, _DTYPES[inner[1][0]]) if numbers else []  # an empty sequence


@cache
def _shape(ros_type: str) -> tuple[Any, frozenset[str], dict[str, Any]]:
    """A type's class, field names and zero values, built once. The zeros are shared
    between messages: a message here is built, encoded and dropped, never changed."""
    st = store()
    _, defs = st.fielddefs[ros_type]
    return st.types[ros_type], frozenset(n for n, _ in defs), {n: _zero(d) for n, d in defs}


def make(ros_type: str, **fields: Any) -> Any:
    """A message of ``ros_type``: the fields given, every other one zero (as a ROS 2
    constructor leaves them)."""
    cls, names, zeros = _shape(ros_type)
    if not names.issuperset(fields):
        raise TypeError(f"{ros_type} has no field {sorted(set(fields) - names)[0]!r}")
    return cls(**(zeros | fields))


def encode(msg: Any) -> bytes:
    """CDR, little-endian, with its 4-byte encapsulation header."""
    return bytes(store().serialize_cdr(msg, msg.__msgtype__, little_endian=True))


def decode(raw: bytes, ros_type: str) -> Any:
    return store().deserialize_cdr(raw, ros_type)
