"""A minimal ``foxglove.websocket.v1`` client for the tests (what Foxglove does
when it opens a WebSocket connection): read ``serverInfo`` and ``advertise``,
subscribe to topics, decode binary ``messageData`` frames with the advertised
schemas (``foxglove_decode``).

The protocol's name: foxglove-sdk's server accepts only ``foxglove.sdk.v1`` in
the handshake (``rust/foxglove/src/websocket/handshake.rs``) — the same
protocol as ``foxglove.websocket.v1`` under a new name; the live view's door
(deploy/report/ws_front.py) serves both. Foxglove and Lichtblick (since
lichtblick-suite/lichtblick#819) offer both names; older clients only the old one.
This client offers what it is told (both by default) and checks that the server
picked one of them."""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import time
from dataclasses import dataclass, field
from typing import Any

import websockets
from foxglove_decode import decode

SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
MESSAGE_DATA = 0x01


@dataclass
class Session:
    subprotocol: str | None = None
    server_info: dict[str, Any] | None = None
    channels: dict[int, dict[str, Any]] = field(default_factory=dict)  # id -> advertisement
    received: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)  # topic -> (log time, msg)

    def topics(self) -> set[str]:
        return {c["topic"] for c in self.channels.values()}


def _schema_bytes(ch: dict[str, Any]) -> bytes:
    if ch.get("schemaEncoding") == "protobuf":  # binary schemas travel base64-encoded
        return base64.b64decode(ch["schema"])
    return ch["schema"].encode()


async def _watch(url: str, topics: set[str], done, timeout_s: float,
                 subprotocols: list[str]) -> Session:
    s = Session()
    subs: dict[int, int] = {}  # subscription id -> channel id
    deadline = time.monotonic() + timeout_s
    async with websockets.connect(url, subprotocols=subprotocols, max_size=None) as ws:
        assert ws.subprotocol in subprotocols
        s.subprotocol = ws.subprotocol
        while time.monotonic() < deadline and not done(s):
            try:
                frame = await asyncio.wait_for(ws.recv(), max(0.01, deadline - time.monotonic()))
            except TimeoutError:
                break
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    s.server_info = msg
                elif msg["op"] == "advertise":
                    new = []
                    for ch in msg["channels"]:
                        s.channels[ch["id"]] = ch
                        if ch["topic"] in topics:
                            sid = len(subs) + 1
                            subs[sid] = ch["id"]
                            new.append({"id": sid, "channelId": ch["id"]})
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
            elif frame and frame[0] == MESSAGE_DATA:
                sid, log_time = struct.unpack_from("<IQ", frame, 1)
                ch = s.channels[subs[sid]]
                value = decode(ch["schemaName"], ch.get("schemaEncoding", ""), _schema_bytes(ch),
                               ch["encoding"], frame[13:])
                s.received.setdefault(ch["topic"], []).append((log_time, value))
    return s


def watch(url: str, topics: set[str], done, timeout_s: float = 30.0,
          subprotocols: list[str] = SUBPROTOCOLS) -> Session:
    """Connect offering ``subprotocols`` (default: both names, as Foxglove and Lichtblick
    do today), subscribe to ``topics``, collect until ``done(session)`` or timeout."""
    return asyncio.run(_watch(url, topics, done, timeout_s, subprotocols))
