"""Any msgspec Struct as a JSON message Foxglove decodes: a JSON Schema whose
root is ``"type": "object"``, and the encoder that matches it.

Foxglove's (and Lichtblick's) JSON-schema reader (``parseJsonSchema`` of
``@foxglove/mcap-support``) walks the schema itself and accepts only: an object
root; fields typed by one ``type`` string (boolean, string, number, integer,
object with ``properties``, array whose ``items`` has a ``type`` of one of
those but not array); no ``$ref``, no ``anyOf``, no type lists, no
``prefixItems``. msgspec's own ``json.schema`` gives a ``$ref`` root, tuples as
``prefixItems`` and nullable fields as ``anyOf``: every channel failed. So the
schema is derived here from ``msgspec.inspect``, type by type:

- ``int``/``float``/``bool``/``str`` -> integer/number/boolean/string;
- a fixed-length tuple of numbers (``Vec3``) -> an array of numbers with
  ``minItems == maxItems``; any list or variable tuple -> an array;
- ``X | None`` -> the schema of X; the field is left out of the message when
  it is None (and is not ``required``);
- a nested struct -> an object; an array of arrays (``list[Vec4]``) -> an
  array of ``{"values": [...]}`` objects (Foxglove cannot nest arrays);
- ``dict[K, V]`` -> an array of ``{"key": str, "value": V}`` objects
  (Foxglove needs named properties);
- anything else (other unions, ``Any``) -> a string holding the value's JSON.

Non-finite floats have no JSON form: a scalar one is left out (float fields
are therefore never ``required``); inside an array it is written as null.
Every message of the wire is finite by contract, so that stays theoretical.

The encoder walks each message in Python, field by field (~20-40 µs a message):
a recording run hears every sample and reply. Where a type allows it, the same
JSON comes from msgspec in C instead (~2 µs): a mirror type with the same fields
as an object (``msgspec.convert(..., from_attributes=True)``), used for a message
whose nested arrays (wrapped in ``{"values": ...}`` above) are empty, for types
whose every float is bounded (a decoded wire message: finite by its schema) and
that hold no dict and no other union (tests/integration/test_foxglove.py checks that
both give the same JSON).
"""

from __future__ import annotations

import base64
import math
from collections.abc import Callable
from typing import Any

import msgspec
import msgspec.inspect as mi

JsonSchema = dict[str, Any]
Convert = Callable[[Any], Any] | None  # None: the value is its own JSON form

_SCALARS: dict[type, str] = {mi.IntType: "integer", mi.FloatType: "number",
                             mi.BoolType: "boolean", mi.StrType: "string"}
_ARRAYS = (mi.ListType, mi.VarTupleType, mi.SetType, mi.FrozenSetType)


class StructJson:
    """Schema and encoder of one Struct type, built once."""

    def __init__(self, kind: type[msgspec.Struct]) -> None:
        self.kind = kind
        info = mi.type_info(kind)
        self.schema, convert = _struct(info)
        self.schema = {"title": f"omnifleet.{kind.__name__}", **self.schema}
        self._convert = convert
        self._encoder = msgspec.json.Encoder()
        mirror = _mirror(info)
        self._mirror, self._empty = (None, ()) if mirror is None else mirror

    def as_object(self, msg: msgspec.Struct) -> dict[str, Any]:
        return self._convert(msg)

    def encode(self, msg: msgspec.Struct) -> bytes:
        if self._mirror is not None and not any(getattr(msg, f) for f in self._empty):
            return self._encoder.encode(msgspec.convert(msg, self._mirror, from_attributes=True))
        return self._encoder.encode(self._convert(msg))


class _Unmirrored(Exception):
    """A type whose JSON the mirror cannot give (a dict, a union, an unbounded float)."""


def _mirror(info: mi.StructType) -> tuple[type, tuple[str, ...]] | None:
    """A Struct with ``info``'s fields written as a JSON object, and the top-level
    fields that must be empty for it to give the same JSON as the walk (lists of
    arrays, which the walk wraps); None when no mirror gives the same JSON."""
    try:
        return _mirror_struct(info, top=True)
    except _Unmirrored:
        return None


def _mirror_struct(info: mi.StructType, top: bool = False) -> tuple[type, tuple[str, ...]]:
    fields: list[tuple[str, Any, Any]] = []
    empty: list[str] = []
    for f in info.fields:
        typ, optional = _strip_none(f.type)
        if isinstance(typ, _ARRAYS) and _is_array(typ.item_type):
            if not top:
                raise _Unmirrored  # only a top-level one can be checked cheaply
            empty.append(f.name)
            py: Any = list
        else:
            py = _mirror_type(typ)
        if optional:
            fields.append((f.name, py | None, None))
        else:
            fields.append((f.name, py, msgspec.NODEFAULT))
    cls = msgspec.defstruct(f"{info.cls.__name__}Json", [
        (n, t) if d is msgspec.NODEFAULT else (n, t, d) for n, t, d in fields],
        kw_only=True, omit_defaults=True)
    return cls, tuple(empty)


def _is_array(t: mi.Type) -> bool:
    return isinstance(_strip_none(t)[0], (mi.TupleType, *_ARRAYS))


def _mirror_type(t: mi.Type) -> Any:
    if isinstance(t, mi.FloatType):
        if t.ge is None or t.le is None:
            raise _Unmirrored  # a NaN would be written as null, where the walk leaves it out
        return float
    if type(t) in _SCALARS:
        return {mi.IntType: int, mi.BoolType: bool, mi.StrType: str}[type(t)]
    if isinstance(t, mi.StructType):
        return _mirror_struct(t)[0]
    if isinstance(t, mi.TupleType):
        return tuple[tuple(_mirror_type(x) for x in t.item_types)]  # type: ignore[misc]
    if isinstance(t, mi.ListType | mi.VarTupleType):
        return list[_mirror_type(t.item_type)]  # type: ignore[misc]
    raise _Unmirrored


def _struct(info: mi.StructType) -> tuple[JsonSchema, Callable[[Any], dict[str, Any]]]:
    props: dict[str, JsonSchema] = {}
    required: list[str] = []
    plan: list[tuple[str, str, Convert, bool, bool]] = []  # name, key, convert, optional, float
    for f in info.fields:
        typ, optional = _strip_none(f.type)
        schema, conv = _field(typ)
        props[f.encode_name] = schema
        is_float = isinstance(typ, mi.FloatType)
        if not optional and not is_float:
            required.append(f.encode_name)
        plan.append((f.name, f.encode_name, conv, optional, is_float))

    def convert(obj: Any) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, key, conv, optional, is_float in plan:
            v = getattr(obj, name)
            if v is None and optional:
                continue
            if is_float and not math.isfinite(v):
                continue
            out[key] = v if conv is None else conv(v)
        return out

    return {"type": "object", "properties": props, "required": required}, convert


def _strip_none(t: mi.Type) -> tuple[mi.Type, bool]:
    """``X | None`` -> (X, True); anything else -> (t, False)."""
    if isinstance(t, mi.UnionType):
        rest = tuple(x for x in t.types if not isinstance(x, mi.NoneType))
        if len(rest) == 1 and len(rest) < len(t.types):
            return rest[0], True
    return t, False


def _field(t: mi.Type) -> tuple[JsonSchema, Convert]:
    if type(t) in _SCALARS:
        return {"type": _SCALARS[type(t)]}, None
    if isinstance(t, mi.BytesType | mi.ByteArrayType):
        return {"type": "string", "contentEncoding": "base64"}, _b64
    if isinstance(t, mi.StructType):
        return _struct(t)
    if isinstance(t, mi.TupleType):
        kinds = {_SCALARS.get(type(x)) for x in t.item_types}
        if kinds <= {"integer", "number"} and None not in kinds:
            item = "integer" if kinds == {"integer"} else "number"
            n = len(t.item_types)
            return {"type": "array", "items": {"type": item}, "minItems": n, "maxItems": n}, None
        if len(kinds) == 1 and None not in kinds:
            n = len(t.item_types)
            return {"type": "array", "items": {"type": kinds.pop()},
                    "minItems": n, "maxItems": n}, None
        return _as_json_text()
    if isinstance(t, _ARRAYS):
        item, conv = _array_item(t.item_type)
        if conv is None:  # msgspec writes lists, tuples and sets as JSON arrays
            return {"type": "array", "items": item}, None
        return {"type": "array", "items": item}, lambda xs, c=conv: [c(x) for x in xs]
    if isinstance(t, mi.DictType):
        value, vconv = _array_item(t.value_type)
        schema = {"type": "array", "items": {
            "type": "object", "properties": {"key": {"type": "string"}, "value": value},
            "required": ["key", "value"]}}
        if vconv is None:
            return schema, lambda d: [{"key": str(k), "value": v} for k, v in d.items()]
        return schema, lambda d, c=vconv: [{"key": str(k), "value": c(v)} for k, v in d.items()]
    if isinstance(t, mi.LiteralType):
        kinds = {type(v) for v in t.values}
        if kinds == {str}:
            return {"type": "string"}, None
        if kinds <= {int}:
            return {"type": "integer"}, None
    if isinstance(t, mi.EnumType):
        return {"type": "string"}, lambda e: str(e.value)
    return _as_json_text()


def _array_item(t: mi.Type) -> tuple[JsonSchema, Convert]:
    """An array's item; Foxglove cannot read an array of arrays, so an inner
    array becomes an object ``{"values": [...]}``; a nullable item its JSON text."""
    t, optional = _strip_none(t)
    if optional:
        return _as_json_text()
    schema, conv = _field(t)
    if schema["type"] != "array":
        return schema, conv
    wrapped = {"type": "object", "properties": {"values": schema}, "required": ["values"]}
    if conv is None:
        return wrapped, lambda xs: {"values": xs}
    return wrapped, lambda xs, c=conv: {"values": c(xs)}


_text_encoder = msgspec.json.Encoder()


def _as_json_text() -> tuple[JsonSchema, Convert]:
    return {"type": "string", "contentMediaType": "application/json"}, (
        lambda v: _text_encoder.encode(v).decode())


def _b64(v: bytes) -> str:
    return base64.b64encode(bytes(v)).decode()
