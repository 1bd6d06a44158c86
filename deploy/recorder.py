"""Record a run's traffic and telemetry to MCAP (JSON messages with a JSON
schema per message type: Foxglove opens it as it is).

Messages are appended from zenoh threads and written by one writer thread in
batches, so a slow disk never blocks a subscriber; :meth:`close` drains what
is queued and writes the MCAP summary (also after Ctrl-C).
"""

from __future__ import annotations

import json
import threading
from collections import deque
from pathlib import Path
from typing import Any

import msgspec
from mcap.writer import Writer

from deploy.wire import MESSAGE_TYPES, Message, Sample, SensedBody


def _json_schema(kind: type[Message]) -> dict[str, Any]:
    """An object schema (field names, not positions) for one message type."""
    fields = []
    for f in msgspec.structs.fields(kind):
        typ = f.type
        if kind is Sample and f.name in ("robots", "obstacles"):
            typ = list[_SENSED_JSON]
        fields.append((f.name, typ) if f.default is msgspec.NODEFAULT
                      else (f.name, typ, f.default))
    mirror = msgspec.defstruct(kind.__name__, fields, kw_only=True)
    return msgspec.json.schema(mirror)


_SENSED_JSON = msgspec.defstruct(
    "SensedBody", [(f.name, f.type) for f in msgspec.structs.fields(SensedBody)])


def as_json_object(msg: msgspec.Struct) -> dict[str, Any]:
    out = {}
    for name in msg.__struct_fields__:
        v = getattr(msg, name)
        if isinstance(v, list) and v and isinstance(v[0], msgspec.Struct):
            v = [as_json_object(x) for x in v]
        out[name] = v
    return out


class McapRecorder:
    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = open(path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file)
        self._writer.start(profile="", library="omnifleet")
        self._schemas = {
            kind: self._writer.register_schema(
                name=f"omnifleet.{kind.__name__}", encoding="jsonschema",
                data=json.dumps(_json_schema(kind)).encode())
            for kind in MESSAGE_TYPES
        }
        self._channels: dict[str, int] = {}
        self._queue: deque[tuple[str, int, Message]] = deque()
        self._wake = threading.Event()
        self._closing = False
        self.written = 0
        self._encoder = msgspec.json.Encoder()
        self._thread = threading.Thread(target=self._drain_forever, name="mcap", daemon=True)
        self._thread.start()

    def add(self, key: str, arrival_unix_ns: int, msg: Message) -> None:
        """Thread-safe (deque.append is atomic)."""
        self._queue.append((key, arrival_unix_ns, msg))

    def _channel(self, key: str, kind: type[Message]) -> int:
        ch = self._channels.get(key)
        if ch is None:
            ch = self._writer.register_channel(key, "json", self._schemas[kind])
            self._channels[key] = ch
        return ch

    def _drain(self) -> None:
        q = self._queue
        while q:
            key, t_ns, msg = q.popleft()
            data = self._encoder.encode(as_json_object(msg))
            # stamp_ns is the sender's monotonic clock, not a date: log and publish
            # times are the arrival on the wall clock, which Foxglove shows
            self._writer.add_message(self._channel(key, type(msg)), log_time=t_ns,
                                     data=data, publish_time=t_ns, sequence=msg.seq)
            self.written += 1

    def _drain_forever(self) -> None:
        while not self._closing:
            self._wake.wait(0.25)
            self._drain()

    def close(self) -> None:
        self._closing = True
        self._wake.set()
        self._thread.join()
        self._drain()
        self._writer.finish()
        self._file.close()
