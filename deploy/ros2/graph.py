"""rmw_zenoh's names on the Zenoh wire: data keys, liveliness tokens, QoS strings,
the attachment of every sample (rmw_zenoh_cpp, Jazzy and Kilted: rmw_zenoh's design
document and its ``liveliness_utils.cpp``). Pure: strings and bytes, no session.

- data: ``<domain>/<topic without its leading />/<DDS type name>/<type hash>``;
- a node's token: ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<ns>/<name>``;
- an endpoint's: ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<MP|MS>/<enclave>/<ns>/
  <name>/<topic>/<DDS type name>/<type hash>/<qos>``, names mangled ('/' -> '%', an empty
  namespace or enclave is '%');
- QoS: ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
  <liveliness kind>,<s>,<ns>``, each field empty where it equals rmw_zenoh's default
  (reliable, volatile, keep last 42, infinite durations, automatic);
- attachment: sequence number (int64), source timestamp (int64, ns), then the 16-byte
  source GID with its length as a LEB128 varint (zenoh's serializer; one byte 0x10).
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
DEFAULT_DEPTH = 42  # rmw_zenoh's depth where a profile gives 0 (and its token default)
GID_BYTES = 16
RELIABLE, BEST_EFFORT = 1, 2  # rmw_qos_reliability_policy_e
TRANSIENT_LOCAL, VOLATILE = 1, 2  # rmw_qos_durability_policy_e
KEEP_LAST = 1  # rmw_qos_history_policy_e
# a ROS 2 name's token: letters, digits, underscores, not starting with a digit
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class Ros2NameError(ValueError):
    """A namespace or topic that ROS 2 would refuse."""


def check_namespace(ns: str) -> str:
    """``ns`` as an absolute ROS 2 namespace ('' for none): '/'-separated tokens."""
    ns = ns.strip()
    if ns in ("", "/"):
        return ""
    parts = ns.strip("/").split("/")
    bad = [p for p in parts if not _TOKEN.fullmatch(p)]
    if bad:
        raise Ros2NameError(f"ROS 2 namespace {ns!r}: {bad[0]!r} is not a name (letters, "
                            "digits and '_', not starting with a digit)")
    return "/" + "/".join(parts)


def dds_type_name(ros_type: str) -> str:
    """``nav_msgs/msg/Odometry`` -> ``nav_msgs::msg::dds_::Odometry_`` (rmw_zenoh's)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    return "%" if name in ("", "/") else name.replace("/", "%")


def data_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    return f"{domain}/{topic.lstrip('/')}/{dds_type_name(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class Qos:
    reliability: int = RELIABLE
    durability: int = VOLATILE
    depth: int = 10

    def token(self) -> str:
        """The profile as rmw_zenoh writes it in a token (defaults left empty)."""
        rel = "" if self.reliability == RELIABLE else str(self.reliability)
        dur = "" if self.durability == VOLATILE else str(self.durability)
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        return f"{rel}:{dur}:,{depth}:,:,:,,"


@dataclass(frozen=True)
class Ros2Node:
    """One ROS 2 node of the fleet's graph, as one Zenoh session declares it."""

    domain: int
    zid: str  # the session's Zenoh id (hex)
    node_id: int
    namespace: str  # absolute ('' for none)
    name: str
    enclave: str = ""

    def _prefix(self, entity_id: int, kind: str) -> str:
        return (f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}")

    def token(self) -> str:
        return self._prefix(self.node_id, "NN")

    def endpoint_token(self, entity_id: int, kind: str, topic: str, ros_type: str,
                       type_hash: str, qos: Qos) -> str:
        """``kind``: "MP" (publisher) or "MS" (subscription)."""
        return (f"{self._prefix(entity_id, kind)}/{mangle(topic)}/{dds_type_name(ros_type)}/"
                f"{type_hash}/{qos.token()}")


def gid(zid: str, node_id: int, entity_id: int) -> bytes:
    """A publisher's 16-byte GID: unique per session and entity (rmw_zenoh hashes the
    same three)."""
    return hashlib.sha256(f"{zid}/{node_id}/{entity_id}".encode()).digest()[:GID_BYTES]


_HEAD = struct.Struct("<qqB")


def attachment(seq: int, stamp_ns: int, source_gid: bytes) -> bytes:
    if len(source_gid) != GID_BYTES:
        raise ValueError("a GID is 16 bytes")
    return _HEAD.pack(seq, stamp_ns, GID_BYTES) + source_gid


def parse_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID); ValueError when it is not one."""
    if len(raw) != _HEAD.size + GID_BYTES or raw[_HEAD.size - 1] != GID_BYTES:
        raise ValueError(f"not an rmw_zenoh attachment ({len(raw)} bytes)")
    seq, stamp, _ = _HEAD.unpack_from(raw)
    return seq, stamp, bytes(raw[_HEAD.size:])
