"""Per-node keys: where they come from, how a node gets them, and what it does with
them (docs/hardening.md).

Every pair of roles of a fleet shares one key, and nobody else holds it: the key of
(A, B) is keyed BLAKE2b of the pair's names under the fleet's master secret. A node
holds the keys it shares with every other role (and one with itself, for what it
hears of its own), never the master. So a message of A carries, per receiver B, a
tag under key (A, B) (deploy/contract/mac.py): B can check it, and no third node
can make it — not an outside process, not another node of the run (agent 3 holds
no key of agent 2 with the plant, so it cannot command robot 2).

Who gets a tag, and whom a receiver believes, is the table of
:mod:`deploy.contract.audience`: a message on key K is tagged for every role that
receives K, and a receiver accepts it only from a role that publishes K.

Where keys come from:

- ``omnifleet run``: the launcher draws a master secret per run and hands each node
  its keyring through a pipe (``--keys-fd``): never in the environment (which
  ``/proc/PID/environ`` shows to the same user), on a command line or on disk.
- across hosts: ``omnifleet deploy certs`` writes each role's keyring beside its
  certificate (``<role>.keys``, mode 0600; the master stays with the CA's key), and
  the node reads it with ``--keys FILE``; a file others may read is refused.

A node with no keyring (started by hand without ``--keys``) sends and accepts
messages without envelopes, as before.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import deploy.contract.mac as mac
from deploy.contract.audience import ROUTER_ROLE, publishes, receives
from deploy.contract.scenario import Scenario
from deploy.contract.wire import Keys

FORMAT = "omnifleet-keys-1"
KEY_BYTES = 32
MAX_KEYRING_BYTES = 4 * 1024 * 1024
MAX_CACHED = 4096  # prepared key expressions kept per node (a wildcard hears made-up keys)

UNSIGNED, WRONG_SENDER, BAD_MAC = mac.UNSIGNED, mac.WRONG_SENDER, mac.BAD_MAC
# what a connection of the local data path says first (deploy/runtime/datagrams.py): the
# key expression its tag is over (no key of a fleet is one: theirs start with omr/)
HELLO = "hello"


class KeysError(ValueError):
    """A keyring that cannot be used (exit 2 at the CLI, naming the file)."""


def new_master() -> bytes:
    return secrets.token_bytes(KEY_BYTES)


def pair_key(master: bytes, fleet: str, a: str, b: str) -> bytes:
    """The key roles ``a`` and ``b`` of ``fleet`` share (the same either way round)."""
    lo, hi = sorted((a, b))
    return hashlib.blake2b(f"{fleet}\n{lo}\n{hi}".encode(), key=master, digest_size=KEY_BYTES,
                           person=b"omnifleet-pair").digest()


def keyring_text(master: bytes, fleet: str, role: str, roles: Iterable[str]) -> str:
    """The keyring of ``role``: its key with each of ``roles`` (itself included)."""
    peers = {r: pair_key(master, fleet, role, r).hex() for r in dict.fromkeys([*roles, role])}
    return json.dumps({"format": FORMAT, "fleet": fleet, "role": role, "peers": peers})


def parse_keyring(text: str | bytes, where: str) -> tuple[str, str, dict[str, bytes]]:
    """(fleet, role, {peer: key}) of a keyring; KeysError naming ``where``."""
    try:
        raw = json.loads(text)
        if raw.get("format") != FORMAT:
            raise KeysError(f"{where}: not an omnifleet keyring ({FORMAT})")
        peers = {str(r): bytes.fromhex(k) for r, k in raw["peers"].items()}
        fleet, role = str(raw["fleet"]), str(raw["role"])
    except KeysError:
        raise
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise KeysError(f"{where}: not a valid keyring ({exc})") from exc
    if any(len(k) != KEY_BYTES for k in peers.values()):
        raise KeysError(f"{where}: a key is not {KEY_BYTES} bytes")
    return fleet, role, peers


def read_fd(fd: int) -> bytes:
    """Everything the launcher wrote on the pipe ``fd`` (then closed)."""
    try:
        with os.fdopen(fd, "rb") as f:
            data = f.read(MAX_KEYRING_BYTES + 1)
    except OSError as exc:
        raise KeysError(f"--keys-fd {fd}: {exc.strerror}") from exc
    if len(data) > MAX_KEYRING_BYTES:
        raise KeysError(f"--keys-fd {fd}: more than {MAX_KEYRING_BYTES} bytes")
    return data


def read_file(path: str | Path) -> bytes:
    """A keyring file, which only its owner may read (mode 0600 or stricter)."""
    path = Path(path)
    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode):
            raise KeysError(f"{path}: not a regular file")
        if st.st_mode & 0o077:
            raise KeysError(f"{path}: mode {stat.S_IMODE(st.st_mode):04o}: others may read "
                            f"its keys (chmod 600 {path})")
        if st.st_size > MAX_KEYRING_BYTES:
            raise KeysError(f"{path}: more than {MAX_KEYRING_BYTES} bytes")
        return path.read_bytes()
    except OSError as exc:
        raise KeysError(f"{path}: cannot read: {exc.strerror} (`omnifleet deploy certs` "
                        "writes one per role)") from exc


def write_file(path: str | Path, text: str) -> Path:
    """A keyring file, mode 0600 from its creation."""
    path = Path(path)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    return path


class Keyring:
    """One node's keys and what it does with them: :meth:`seal` what it sends,
    :meth:`open` what it hears, both on raw bytes."""

    def __init__(self, role: str, peers: dict[str, bytes], sc: Scenario, keys: Keys) -> None:
        """``peers``: the key shared with each role of the fleet (``role`` itself
        included); roles the scenario does not have are refused (KeysError)."""
        self.role, self.keys = role, keys
        self._pair = dict(peers)
        self._me = mac.hint(role)
        roles = list(dict.fromkeys([role, *peers]))
        self._hints = {r: mac.hint(r) for r in roles}
        self._by_hint: dict[bytes, list[str]] = {}  # the roles of each hint we hold a key with
        for r in roles:
            if r in self._pair:
                self._by_hint.setdefault(self._hints[r], []).append(r)
        self.senders: dict[str, list[str]] = {}  # key -> the roles that may put it
        self.receivers: dict[str, list[str]] = {}  # key -> the roles that get a tag
        if ROUTER_ROLE in roles:  # it would be a sender of every key
            raise KeysError(f"keyring of {role}: a router forwards, it holds no keys")
        try:
            for r in roles:
                if r not in self._pair:
                    continue
                for k in publishes(r, sc, keys, roles):
                    self.senders.setdefault(k, []).append(r)
                for k in receives(r, sc, keys, roles):
                    self.receivers.setdefault(k, []).append(r)
        except (ValueError, KeyError) as exc:
            raise KeysError(f"keyring of {role}: a peer that is not a role of scenario "
                            f"{sc.name} ({exc})") from exc
        self._seal: dict[str, tuple[list[tuple[bytes, Any]], bytes]] = {}
        self._open: dict[str, dict[bytes, list[Any]]] = {}

    @classmethod
    def from_text(cls, text: str | bytes, where: str, role: str, sc: Scenario,
                  keys: Keys) -> Keyring:
        """The keyring in ``text`` (from ``where``), checked to be ``role``'s in this fleet."""
        fleet, owner, peers = parse_keyring(text, where)
        if fleet != keys.fleet:
            raise KeysError(f"{where}: keys of fleet {fleet!r}, not of {keys.fleet!r}")
        if owner != role:
            raise KeysError(f"{where}: keys of {owner}, not of {role}")
        return cls(role, peers, sc, keys)

    def seal(self, payload: bytes, key_expr: str) -> bytes:
        """``payload`` with a tag for every receiver of ``key_expr`` this node has a key with."""
        plan = self._seal.get(key_expr)
        if plan is None:
            tags = [(self._hints[r], mac.prefixed(self._pair[r], key_expr, self.role, r))
                    for r in self.receivers.get(key_expr, ())]
            plan = (tags, mac.trailer(self._me, len(tags)))
            if len(self._seal) < MAX_CACHED:
                self._seal[key_expr] = plan
        return mac.seal(payload, *plan)

    def hello(self, receiver: str) -> bytes | None:
        """What a connection to ``receiver`` says first: a fresh nonce in an envelope
        tagged, over :data:`HELLO`, under the key we share with it (None: we have none).
        The receiver binds the connection to us (:meth:`hello_from`) and takes what follows
        on it as ours, with no tag of its own: a connected socket is the kernel's, nobody
        else writes into it (docs/hardening.md, "One host: authenticated connections")."""
        key = self._pair.get(receiver)
        if key is None:
            return None
        tag = [(self._hints[receiver], mac.prefixed(key, HELLO, self.role, receiver))]
        return mac.seal(secrets.token_bytes(16), tag, mac.trailer(self._me, 1))

    def hello_from(self, data: bytes) -> str | None:
        """The role whose :meth:`hello` ``data`` is (its tag checks under the key we share
        with that role), or None."""
        head = mac.parse_head(data)
        if head is None:
            return None
        for r in self._by_hint.get(head[1], ()):
            start = mac.prefixed(self._pair[r], HELLO, r, self.role)
            payload, _ = mac.open_envelope(data, self._me, {head[1]: [start]})
            if payload is not None:
                return r
        return None

    def may_send(self, role: str, key_expr: str) -> bool:
        """Whether ``role`` is a sender of ``key_expr`` (what its tag would have to say)."""
        return role in self.senders.get(key_expr, ())

    def open(self, data: bytes, key_expr: str) -> tuple[memoryview | None, str]:
        """(the payload, "") when ``data`` came from a sender of ``key_expr`` with a tag
        for this node that checks; else (None, why)."""
        senders = self._open.get(key_expr)
        if senders is None:
            senders = {}
            for r in self.senders.get(key_expr, ()):
                senders.setdefault(self._hints[r], []).append(
                    mac.prefixed(self._pair[r], key_expr, r, self.role))
            if len(self._open) < MAX_CACHED:
                self._open[key_expr] = senders
        return mac.open_envelope(data, self._me, senders)
