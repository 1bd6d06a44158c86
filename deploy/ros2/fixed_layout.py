"""CDR bytes of a message whose strings and sequence lengths never change between two
samples of one topic (a robot's odometry: the same frame ids, the same four wheels), with
only its numbers new: the bytes ``rosbags`` writes for a template, and the numbers packed
into them at the offsets ``rosbags`` itself put them (found by changing one field at a
time and reading where the bytes moved). Not an encoder of our own: every byte not a
number is rosbags', and every number sits where rosbags put it (tests/unit/
test_ros2_graph.py holds both against rosbags' encoding of random messages).

Why: building a message's dataclasses and encoding them costs ~40 µs a message in Python
(rosbags), ~2-3 µs this way; the gateway's share of a realtime step is mostly that
(docs/ros2.md, "Cost").
"""

from __future__ import annotations

import copy
import re
import struct
from typing import Any

from deploy.ros2.types import encode

_INDEX = re.compile(r"^(\w+)\[(\d+)\]$")
# a value each of whose bytes differs from zero's: the field's bytes are exactly those
# that move when it is set
_PROBE = {"d": -1.2345678901234567e-300, "i": -1, "I": 0xFFFF_FFFF}


def _parent_and_key(msg: Any, path: str) -> tuple[Any, str | int]:
    obj = msg
    parts = path.split(".")
    for part in parts[:-1]:
        m = _INDEX.match(part)
        obj = getattr(obj, m.group(1))[int(m.group(2))] if m else getattr(obj, part)
    last = parts[-1]
    m = _INDEX.match(last)
    if m:
        return getattr(obj, m.group(1)), int(m.group(2))
    return obj, last


def _set(msg: Any, path: str, value: Any) -> None:
    parent, key = _parent_and_key(msg, path)
    if isinstance(key, int):
        parent[key] = value
    else:
        setattr(parent, key, value)


class FixedLayout:
    """``pack(*values)``: the template's bytes with ``fields`` (dotted paths, ``name[i]`` for
    an element) set to ``values``, in the order given. ``kinds``: "d" (float64), "i"
    (int32), "I" (uint32) per field."""

    def __init__(self, template: Any, fields: list[str], kinds: str) -> None:
        if len(kinds) != len(fields):
            raise ValueError("one kind per field")
        template = copy.deepcopy(template)
        for path in fields:  # every field ours is zero in the template
            _set(template, path, 0)
        self.base = encode(template)
        places = []
        for path, kind in zip(fields, kinds, strict=True):
            probe = copy.deepcopy(template)
            _set(probe, path, _PROBE[kind])
            moved = [i for i, (a, b) in enumerate(zip(self.base, encode(probe), strict=True))
                     if a != b]
            size = struct.calcsize(kind)
            if len(moved) != size or moved[-1] - moved[0] != size - 1:
                raise ValueError(f"{path}: not one number of {size} bytes in the CDR "
                                 "(or not zero in the template)")
            places.append((moved[0], kind))
        # contiguous fields packed together; never a pad byte (struct writes pads as zeros,
        # over the template's strings)
        order = sorted(range(len(fields)), key=lambda i: places[i][0])
        self.runs: list[tuple[int, struct.Struct, list[int]]] = []
        fmt, start, at, members = "", -1, -1, []
        for i in order:
            offset, kind = places[i]
            if offset < at:
                raise ValueError("two fields share bytes")
            if offset != at and members:
                self.runs.append((start, struct.Struct("<" + fmt), members))
                fmt, members = "", []
            if not members:
                start = offset
            fmt += kind
            members.append(i)
            at = offset + struct.calcsize(kind)
        self.runs.append((start, struct.Struct("<" + fmt), members))

    def pack(self, *values: Any) -> bytes:
        buf = bytearray(self.base)
        for start, packer, members in self.runs:
            packer.pack_into(buf, start, *[values[i] for i in members])
        return bytes(buf)
