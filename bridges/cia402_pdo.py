"""One PDO's payload packed with ``struct`` from canopen's own mapping of it.

canopen reads a PDO's mapping (from an EDS, or from the drive by SDO) into a
:class:`canopen.pdo.PdoMap`: which object sits at which bit offset, with which data
type. The cyclic path packs and unpacks its payloads many times a second (a bridge
~1600 frames/s per robot); canopen's per-variable ``raw`` costs a few microseconds
and a log record each. :class:`PdoLayout` is the same layout compiled once into
``struct`` fields: canopen stays the one reader of the mapping, only the per-frame
work is cheaper (tests/unit/test_cia402.py checks it equal to canopen's packing for
every mapped object). Supported: whole objects of the fixed-size numeric types,
byte-aligned, as every CiA 402 drive maps them; another mapping is refused by name.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from canopen.objectdictionary import ODVariable

PDO_NOT_VALID = 1 << 31  # COB-ID bit 31: the PDO does not exist / is not valid


@dataclass(frozen=True)
class PdoLayout:
    """A PDO as the cyclic path uses it: its COB-ID, transmission type and fields."""

    name: str  # canopen's name of it, e.g. TxPDO1_node1
    cob_id: int
    trans_type: int  # 0-240: on (every n-th) SYNC; 254/255: on event
    fields: tuple[tuple[int, int, struct.Struct], ...]  # (index, byte offset, packing)
    length: int  # bytes mapped
    # the fields end to end from byte 0 as one struct (None: a gap, or another order):
    # one call packs a payload (a bridge packs its RPDO four times a period)
    whole: struct.Struct | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        at, codes = 0, []
        for _, offset, packing in self.fields:
            code = packing.format.lstrip("<")
            if offset != at or not packing.format.startswith("<") or len(code) != 1:
                object.__setattr__(self, "whole", None)
                return
            codes.append(code)
            at += packing.size
        object.__setattr__(self, "whole", struct.Struct("<" + "".join(codes))
                           if at == self.length else None)

    @classmethod
    def of(cls, pdo_map: Any) -> PdoLayout:
        """The layout of a canopen PdoMap (read from an object dictionary or a drive);
        ValueError naming what cannot be packed this way."""
        fields = []
        seen = set()
        for var in pdo_map.map:
            od = var.od
            packing = ODVariable.STRUCT_TYPES.get(od.data_type)
            where = f"{pdo_map.name}: 0x{var.index:04X}:{var.subindex:02X} ({var.name})"
            if not isinstance(packing, struct.Struct) or var.length != 8 * packing.size:
                raise ValueError(f"{where} is not mapped as a whole number object")
            if var.offset % 8:
                raise ValueError(f"{where} is not byte aligned (bit offset {var.offset})")
            if var.index in seen:
                raise ValueError(f"{where} is mapped twice")
            seen.add(var.index)
            fields.append((var.index, var.offset // 8, packing))
        length = (pdo_map.length + 7) // 8
        if length > 8:
            raise ValueError(f"{pdo_map.name}: {length} bytes mapped, a CAN frame holds 8")
        return cls(pdo_map.name, int(pdo_map.cob_id), int(pdo_map.trans_type or 0),
                   tuple(fields), length)

    def maps(self, index: int) -> bool:
        return any(i == index for i, _, _ in self.fields)

    @property
    def synchronous(self) -> bool:
        """Sent (TPDO) or applied (RPDO) on SYNC, rather than on an event."""
        return self.trans_type <= 240

    def pack(self, values: Mapping[int, int | float]) -> bytes:
        """The payload of these objects' values (every mapped index given); ValueError
        for a value its type cannot hold."""
        if self.whole is not None:
            try:
                return self.whole.pack(*[values[index] for index, _, _ in self.fields])
            except struct.error:
                pass  # the loop below names the object that does not fit
        buf = bytearray(self.length)
        for index, offset, packing in self.fields:
            try:
                packing.pack_into(buf, offset, values[index])
            except struct.error as exc:
                raise ValueError(f"{self.name}: 0x{index:04X} = {values[index]!r}: {exc}") from None
        return bytes(buf)

    def unpack(self, data: bytes) -> dict[int, int | float]:
        """The mapped objects' values in a payload of at least ``length`` bytes."""
        return {index: packing.unpack_from(data, offset)[0] for index, offset, packing in self.fields}
