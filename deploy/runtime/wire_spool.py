"""A node's own record of what it sent and heard on some keys, for a recording made on
its host: records appended to a file of its own, read by the launcher as they come.

Why: in ``paper`` 144,000 of a recording's 157,000 wire messages are the plant's
samples and the agents' replies. The plant builds every sample and checks every
reply anyway; a launcher that heard them too woke, read, authenticated and decoded
each one more time, and each sender sent it once more. The plant writes them here
instead (one system call per ``FLUSH_BYTES``) and the launcher reads them in bulk: in
``paper``, 3 pairs side by side, the launcher's CPU fell from 7.8 s to 6.6 s, every
process's from 26.5 s to 24.7 s, the run from 13.5 s to 12.0 s (docs/bench-history.md).
On emulated CAN each bridge does the same for its robot's samples and commands (lab at
200 Hz, 3 pairs: the recording launcher's CPU 474-556 -> 378-438 µs a step).

A record: ``key length (u16) | wall clock at the send or arrival, unix ns (u64) |
payload length (u32) | key | payload``, the payload being the message's bytes
before their seal (the file is the run's own, in its private directory). A process
killed mid-write leaves at most one incomplete record at its file's end: a reader
keeps it until it is whole, and never sees it otherwise. Each process writes a file
of its own (``<role>-<pid>.spool``): a restarted node never appends to the dead
one's half record.
"""

from __future__ import annotations

import os
import struct
import sys
import threading
import time
from pathlib import Path

SPOOL_SUFFIX = ".spool"
FLUSH_BYTES = 1 << 16  # ~200 of paper's messages: a few milliseconds of a run
READ_BYTES = 1 << 20  # at most this much of a file at one read
_HEAD = struct.Struct("<HQI")


def spool_path(directory: str | Path, role: str) -> Path:
    """This process's spool file in ``directory``."""
    return Path(directory) / f"{role}-{os.getpid()}{SPOOL_SUFFIX}"


class SpoolWriter:
    """Appends the messages of ``keys`` (exact keys) to ``path``; ``flush`` writes out
    what is held. A write that fails (a full disk) stops the spool: said once on
    stderr, every message not kept counted in ``lost`` (the node's report carries it,
    and the run's recording is then broken), never raised into the node's loop."""

    def __init__(self, path: str | Path, keys: set[str], flush_bytes: int = FLUSH_BYTES) -> None:
        self.path = Path(path)
        self.keys = frozenset(keys)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND
                                       | os.O_CLOEXEC, 0o600)
        self._buf = bytearray()
        self._held = 0  # records in _buf
        self._flush_bytes = flush_bytes
        self._raw_keys: dict[str, bytes] = {}
        self.written = 0  # records written to the file
        self.lost = 0  # records that never got there (a failed write, and every one after it)

    def write(self, key: str, payload: bytes) -> None:
        """One message on ``key`` (one of ``keys``), stamped with the wall clock now."""
        if self._fd is None:
            self.lost += 1
            return
        raw = self._raw_keys.get(key)
        if raw is None:
            raw = self._raw_keys[key] = key.encode()
        buf = self._buf
        buf += _HEAD.pack(len(raw), time.time_ns(), len(payload))
        buf += raw
        buf += payload
        self._held += 1
        if len(buf) >= self._flush_bytes:
            self.flush()

    def flush(self) -> None:
        """Write out everything held."""
        if not self._buf or self._fd is None:
            return
        view = memoryview(self._buf)
        try:
            while view:
                view = view[os.write(self._fd, view):]
            self.written += self._held
        except OSError as exc:
            # what the file got of these records is a half one at most: a reader never
            # takes it (and none follows)
            self.lost += self._held
            print(f"spool {self.path}: cannot write ({exc.strerror or exc}); the samples and "
                  "replies from here on are not recorded", file=sys.stderr, flush=True)
            os.close(self._fd)
            self._fd = None
        finally:
            view.release()
            self._buf.clear()
            self._held = 0

    def close(self) -> None:
        self.flush()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class SpoolReader:
    """Reads the complete records of every spool file of ``directory`` as they come.
    Thread-safe. A file is opened when first seen (:meth:`open_all`), so it stays
    readable after the directory is removed."""

    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory)
        self._files: dict[str, tuple[int, bytearray]] = {}  # name -> (fd, bytes not yet whole)
        self._lock = threading.Lock()
        self.records = 0

    def open_all(self) -> None:
        """Open the spool files that appeared since the last look."""
        with self._lock:
            self._open_new()

    def _open_new(self) -> None:
        try:
            names = [n for n in os.listdir(self.dir) if n.endswith(SPOOL_SUFFIX)]
        except OSError:
            return  # the run's directory is gone: what is open stays readable
        for name in names:
            if name not in self._files:
                try:
                    fd = os.open(self.dir / name, os.O_RDONLY | os.O_CLOEXEC)
                except OSError:
                    continue
                self._files[name] = (fd, bytearray())

    def read(self) -> list[tuple[str, int, bytes]]:
        """Every record completed since the last read: (key, wall clock ns, payload)."""
        out: list[tuple[str, int, bytes]] = []
        with self._lock:
            self._open_new()
            for fd, held in self._files.values():
                while True:
                    chunk = os.read(fd, READ_BYTES)
                    if not chunk:
                        break
                    held += chunk
                    _records(held, out)
        self.records += len(out)
        return out

    def close(self) -> None:
        with self._lock:
            for fd, _held in self._files.values():
                os.close(fd)
            self._files.clear()


def _records(held: bytearray, out: list[tuple[str, int, bytes]]) -> None:
    """Move the whole records at the start of ``held`` to ``out``."""
    at, size, head = 0, len(held), _HEAD.size
    unpack = _HEAD.unpack_from
    while size - at >= head:
        key_len, unix_ns, n = unpack(held, at)
        end = at + head + key_len + n
        if end > size:
            break
        k0 = at + head
        out.append((held[k0:k0 + key_len].decode(errors="replace"), unix_ns,
                    bytes(held[k0 + key_len:end])))
        at = end
    del held[:at]
