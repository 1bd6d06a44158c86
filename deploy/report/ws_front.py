"""The live view's door: Foxglove **and** Lichtblick (and older Foxglove) connect.

``foxglove-sdk`` 0.30's WebSocket server accepts only the subprotocol names
``foxglove.sdk.v1`` (and ``foxglove.sdk.v1.1``) in the handshake: read from the installed
extension (``foxglove/_foxglove_py.abi3.so`` holds no other name) and measured here (a
client offering only ``foxglove.websocket.v1`` got HTTP 400 "Missing expected
sec-websocket-protocol header"); its ``start_server`` has no option for another name.
Lichtblick before its 1.22 release (lichtblick-suite/lichtblick#819) and Foxglove builds
from before the SDK offer only ``foxglove.websocket.v1``. The two names are one protocol:
Foxglove's developers say so (foxglove discussion 1131, quoted in #819), and Lichtblick
added the new name beside the old one for that reason.

So the SDK's server listens on a loopback port of its own, and :class:`WsFront` listens
where the user asked. For each connection it reads the HTTP upgrade request only:

- a client that offers ``foxglove.sdk.v1`` is passed on unchanged;
- one that offers only ``foxglove.websocket.v1`` has its offer renamed for the SDK and
  the SDK's answer renamed back, so it is served under the name it asked for;
- one that offers neither is refused with HTTP 400 and a body naming both; said once on
  stderr with the reason (then counted: ``refused``), not once per retry.

After the handshake the bytes go both ways unchanged: one asyncio task per direction on
a thread of its own, off the run's thread.
"""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Callable

SDK_PROTOCOL = "foxglove.sdk.v1"
LEGACY_PROTOCOL = "foxglove.websocket.v1"
SERVED = (SDK_PROTOCOL, LEGACY_PROTOCOL)
MAX_HEAD_BYTES = 64 * 1024  # an HTTP upgrade request is a few hundred bytes
HEAD_END = b"\r\n\r\n"
CHUNK = 64 * 1024


def offered_protocols(head: bytes) -> list[str]:
    """The subprotocols a WebSocket upgrade request offers, in its order."""
    out = []
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"sec-websocket-protocol":
            out += [p.strip() for p in value.decode("latin-1").split(",") if p.strip()]
    return out


def rename_protocol(head: bytes, old: str, new: str) -> bytes:
    """``head`` with every Sec-WebSocket-Protocol header offering ``old`` offering ``new``
    instead (a request's offer, or a response's choice)."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == b"sec-websocket-protocol":
            names = [p.strip() for p in value.decode("latin-1").split(",")]
            lines[i] = name + b": " + ", ".join(new if p == old else p for p in names).encode()
    return b"\r\n".join(lines)


def refusal(offered: list[str]) -> bytes:
    body = (f"omnifleet live view: offer the WebSocket subprotocol {SDK_PROTOCOL} (Foxglove) "
            f"or {LEGACY_PROTOCOL} (Lichtblick, older Foxglove); this client offered "
            f"{', '.join(offered) or 'none'}\n").encode()
    return (b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain\r\nConnection: close\r\n"
            b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body)


class WsFront:
    """Listens on ``host:port`` (0: any free port) in front of the SDK's server on
    ``127.0.0.1:sdk_port``; :attr:`port` is where clients connect."""

    def __init__(self, host: str, port: int, sdk_port: int,
                 say: Callable[[str], None] | None = None) -> None:
        self.sdk_port = sdk_port
        self.say = say or (lambda line: print(line, file=sys.stderr, flush=True))
        self.served = {SDK_PROTOCOL: 0, LEGACY_PROTOCOL: 0}  # clients, by the name they got
        self.refused = 0
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task] = set()
        started = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._server = self._loop.run_until_complete(
                    asyncio.start_server(self._client, host, port))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                failure.append(exc)
                started.set()
                return
            started.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=run, name="live-view-front", daemon=True)
        self._thread.start()
        started.wait()
        if failure:
            self._thread.join()
            self._loop.close()
            raise failure[0]
        self.port: int = self._server.sockets[0].getsockname()[1]

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._tasks.add(asyncio.current_task())
        try:
            await self._serve(reader, writer)
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass  # a client that went away, or sent no request worth the name
        finally:
            writer.close()
            self._tasks.discard(asyncio.current_task())

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head, early = await _read_head(reader)
        offered = offered_protocols(head)
        legacy = SDK_PROTOCOL not in offered and LEGACY_PROTOCOL in offered
        if not any(p in offered for p in SERVED):
            self._refuse(writer, offered)
            writer.write(refusal(offered))
            await writer.drain()
            return
        if legacy:
            head = rename_protocol(head, LEGACY_PROTOCOL, SDK_PROTOCOL)
        sdk_reader, sdk_writer = await asyncio.open_connection("127.0.0.1", self.sdk_port)
        try:
            sdk_writer.write(head + early)
            answer, after = await _read_head(sdk_reader)
            if legacy:
                answer = rename_protocol(answer, SDK_PROTOCOL, LEGACY_PROTOCOL)
            writer.write(answer + after)
            self.served[LEGACY_PROTOCOL if legacy else SDK_PROTOCOL] += 1
            await asyncio.gather(_pipe(reader, sdk_writer), _pipe(sdk_reader, writer))
        finally:
            sdk_writer.close()

    def _refuse(self, writer: asyncio.StreamWriter, offered: list[str]) -> None:
        self.refused += 1
        if self.refused == 1:
            peer = writer.get_extra_info("peername")
            self.say(f"live view: refused a client from {peer[0] if peer else '?'}: it offered "
                     f"the subprotocols {', '.join(offered) or '(none)'}; this view serves "
                     f"{SDK_PROTOCOL} (Foxglove) and {LEGACY_PROTOCOL} (Lichtblick, older "
                     "Foxglove); further refusals are counted, not said")

    def close(self) -> None:
        """Stop listening and end every connection; the port is free after."""
        if self._loop.is_closed():
            return

        async def shut() -> None:
            self._server.close()
            for t in list(self._tasks):
                t.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)
            await self._server.wait_closed()

        asyncio.run_coroutine_threadsafe(shut(), self._loop).result(10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        self._loop.close()


async def _read_head(reader: asyncio.StreamReader) -> tuple[bytes, bytes]:
    """An HTTP message's head, up to and with its blank line (at most MAX_HEAD_BYTES),
    and what came after it in the same reads (the SDK sends its first frames at once)."""
    buf = b""
    while HEAD_END not in buf:
        chunk = await reader.read(1024)
        if not chunk:
            raise asyncio.IncompleteReadError(buf, None)
        buf += chunk
        if len(buf) > MAX_HEAD_BYTES:
            raise asyncio.LimitOverrunError("request head too long", len(buf))
    end = buf.index(HEAD_END) + len(HEAD_END)
    return buf[:end], buf[end:]


async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    try:
        while chunk := await src.read(CHUNK):
            dst.write(chunk)
            await dst.drain()
    finally:
        if dst.can_write_eof():
            try:
                dst.write_eof()
            except OSError:
                pass


class ViewServer:
    """``foxglove.start_server`` (loopback, a free port) behind a :class:`WsFront` on
    ``host:port``: what the live view and ``omnifleet view`` serve. Everything else
    (``broadcast_time``, ...) is the SDK server's."""

    def __init__(self, host: str, port: int, **sdk_options: object) -> None:
        import foxglove

        self.sdk = foxglove.start_server(host="127.0.0.1", port=0, **sdk_options)
        try:
            self.front = WsFront(host, port, self.sdk.port)
        except BaseException:
            self.sdk.stop()
            raise

    @property
    def port(self) -> int:
        return self.front.port

    def __getattr__(self, name: str) -> object:
        return getattr(self.sdk, name)

    def stop(self) -> None:
        self.front.close()
        self.sdk.stop()
