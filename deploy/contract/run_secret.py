"""Who may say ``ctl/*`` on one host (docs/hardening.md): the processes of the run, and
nobody else.

``omnifleet run`` draws a secret for the run and hands it to every node it starts
in the environment (``OMNIFLEET_RUN_SECRET``; never on a command line, which ``ps``
shows, and never on the wire). A node that holds the secret signs each control
message it sends with an HMAC of its content and accepts only control messages
whose HMAC checks: a process that reached a node's socket and read its traffic can
replay a tick it saw, but cannot make a ``stop``, an ``estop`` or an ``end`` nobody
sent. Nodes started by hand (no secret) accept control as before; across hosts the
ACL says who may publish ``ctl/*`` (the plant and the launcher).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets

RUN_SECRET_ENV = "OMNIFLEET_RUN_SECRET"
MAC_CHARS = 32  # hex digits of the HMAC-SHA256 kept in a message


def new_secret() -> str:
    return secrets.token_hex(32)


def run_secret() -> str | None:
    """This process's run secret, if its launcher gave it one."""
    return os.environ.get(RUN_SECRET_ENV) or None


def control_mac(secret: str, command: str, k: int, t: float, start_unix_ns: int, seq: int,
                stamp_ns: int) -> str:
    """The HMAC of a control message's content (every field but the MAC itself)."""
    text = f"{command}|{k}|{t!r}|{start_unix_ns}|{seq}|{stamp_ns}".encode()
    return hmac.new(secret.encode(), text, hashlib.sha256).hexdigest()[:MAC_CHARS]


def sign_report(secret: str | None, report):
    """``report`` (a wire ``NodeReport``) with the HMAC of its encoding (MAC left empty),
    so the launcher files only its own nodes' reports; unchanged without a secret."""
    if secret is None:
        return report
    import msgspec

    # the wire's own encoding (wire.encode is a default msgpack Encoder), written out here so
    # the secret does not import the wire that imports it (an import cycle)
    text = msgspec.msgpack.encode(msgspec.structs.replace(report, mac=""))
    return msgspec.structs.replace(report, mac=hmac.new(
        secret.encode(), text, hashlib.sha256).hexdigest()[:MAC_CHARS])


def report_is_genuine(secret: str | None, msg) -> bool:
    """Whether a decoded ``NodeReport`` was signed with ``secret`` (msgpack encodes a
    decoded message to the same bytes again, so its MAC can be checked)."""
    if secret is None:
        return True
    return hmac.compare_digest(sign_report(secret, msg).mac, msg.mac)


def control_is_genuine(secret: str | None, msg) -> bool:
    """Whether ``msg`` (a wire ``Control``) may be acted on here."""
    if secret is None:
        return True
    want = control_mac(secret, msg.command, msg.k, msg.t, msg.start_unix_ns, msg.seq,
                       msg.stamp_ns)
    return hmac.compare_digest(want, msg.mac)
