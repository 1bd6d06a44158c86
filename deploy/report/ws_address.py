"""Where a Foxglove WebSocket server listens (``--live``, ``omnifleet view``):
``[HOST:]PORT``, loopback unless a host is given."""

from __future__ import annotations

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765  # Foxglove's default for a WebSocket connection


class LiveAddressError(ValueError):
    """A ``[HOST:]PORT`` that is not one."""


def parse_address(text: str) -> tuple[str, int]:
    """``8765`` -> (127.0.0.1, 8765); ``0.0.0.0:8765``; ``[::1]:8765``; port 0: any free one."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host = DEFAULT_HOST
    host = host.strip("[]") or DEFAULT_HOST
    try:
        p = int(port)
    except ValueError:
        raise LiveAddressError(f"{text!r} is not [HOST:]PORT") from None
    if not 0 <= p <= 65535:
        raise LiveAddressError(f"port {p} is out of range 0-65535")
    return host, p


def url(host: str, port: int) -> str:
    return f"ws://[{host}]:{port}" if ":" in host else f"ws://{host}:{port}"
