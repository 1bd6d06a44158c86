"""Decode messages the way Foxglove (and Lichtblick) does, for the tests.

- protobuf: the channel's schema is a ``FileDescriptorSet``; build the message
  class from it with ``google.protobuf`` and parse (Foxglove uses protobufjs
  on the same descriptor set);
- JSON: Foxglove's ``parseJsonSchema`` (``@foxglove/mcap-support``) walks the
  schema to learn the message's fields; :func:`check_foxglove_json_schema`
  applies its rules (object root, one ``type`` string per field, arrays of
  non-arrays, objects with ``properties``) and raises where it would; then the
  message is validated against the schema with ``jsonschema``.
"""

from __future__ import annotations

import json
from functools import cache
from typing import Any

import jsonschema
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

_SCALAR = {"boolean", "number", "integer"}


def check_foxglove_json_schema(schema: dict[str, Any], where: str = "root") -> None:
    """Raise ValueError where Foxglove's JSON-schema reader would throw."""
    if schema.get("type") != "object":
        raise ValueError(f'{where}: expected "type": "object", got {schema.get("type")!r}')
    props = schema.get("properties")
    if not isinstance(props, dict):
        raise ValueError(f"{where}: an object needs properties")
    for name, field in props.items():
        t = field.get("type")
        at = f"{where}.{name}"
        if t in _SCALAR:
            continue
        if t == "string":
            if field.get("contentEncoding") not in (None, "base64"):
                raise ValueError(f"{at}: unsupported contentEncoding")
        elif t == "object":
            check_foxglove_json_schema(field, at)
        elif t == "array":
            items = field.get("items")
            it = items.get("type") if isinstance(items, dict) else None
            if it in _SCALAR:
                continue
            if it == "string":
                if items.get("contentEncoding") is not None:
                    raise ValueError(f"{at}: contentEncoding in an array item")
            elif it == "object":
                check_foxglove_json_schema(items, at)
            else:
                raise ValueError(f"{at}: unsupported array item type {it!r}")
        else:
            raise ValueError(f"{at}: unsupported field type {t!r}")


@cache
def _protobuf_class(name: str, data: bytes):
    fds = descriptor_pb2.FileDescriptorSet.FromString(data)
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    while pending:  # a file after the files it imports
        progressed = False
        for f in list(pending):
            if all(dep in {p.name for p in fds.file if p not in pending} for dep in f.dependency):
                pool.Add(f)
                pending.remove(f)
                progressed = True
        if not progressed:
            raise ValueError(f"{name}: unresolvable imports in the descriptor set")
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


@cache
def _json_validator(data: bytes) -> jsonschema.Draft202012Validator:
    """The channel's schema, checked once (``jsonschema.validate`` checks the schema
    again on every call: 38 s for one 0.3 s recording of paper)."""
    schema = json.loads(data)
    check_foxglove_json_schema(schema)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def decode(schema_name: str, schema_encoding: str, schema_data: bytes, message_encoding: str,
           payload: bytes) -> Any:
    """The decoded message (a protobuf message or a dict); raises if Foxglove could not."""
    if message_encoding == "protobuf":
        assert schema_encoding == "protobuf", schema_encoding
        msg = _protobuf_class(schema_name, bytes(schema_data))()
        msg.ParseFromString(payload)
        return msg
    if message_encoding == "json":
        assert schema_encoding == "jsonschema", schema_encoding
        value = json.loads(payload)
        _json_validator(bytes(schema_data)).validate(value)
        return value
    raise AssertionError(f"unexpected message encoding {message_encoding!r}")
