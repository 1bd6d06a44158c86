"""The leader's one input from ROS 2: geometry_msgs/msg/Twist on /leader/cmd_vel, for a
leader steered from outside (leader.path = "ros2"; agents/steered_leader.py).

Taken on zenoh's thread, judged before anything else sees it: at most ``MAX_STEER_HZ``
samples a second are decoded (a flood costs a counter each, never the CPU of a decode);
a sample that is not one CDR Twist, or not finite, is refused and counted by reason; the
newest accepted one is kept, numbered, for the launcher to pass on (deploy/run/launcher.py,
``leader/steer``). Bounds and the timeout are the leader's own.
"""

from __future__ import annotations

import math
import time
from typing import Any

import deploy.ros2.fleet_messages as fm
from deploy.ros2.graph import Qos, Ros2Node, data_key
from deploy.ros2.types import decode, type_hash

STEER_TOPIC = "leader/cmd_vel"
MAX_STEER_HZ = 100.0  # samples a second looked at; beyond, refused undecoded
TWIST_CDR_BYTES = 4 + 6 * 8  # encapsulation header, then six float64


def twist_of(raw: bytes) -> tuple[float, float, float]:
    """[linear.x, linear.y, angular.z] of a CDR geometry_msgs/msg/Twist; ValueError with
    the reason when it is not one, or not finite (linear.z, angular.x, angular.y: a
    planar leader ignores them)."""
    if len(raw) != TWIST_CDR_BYTES:
        raise ValueError(f"not a Twist ({len(raw)} bytes)")
    try:
        msg = decode(raw, fm.TWIST)
    except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds on bad CDR
        raise ValueError("malformed CDR") from exc
    v = (float(msg.linear.x), float(msg.linear.y), float(msg.angular.z))
    if not all(map(math.isfinite, v)):
        raise ValueError("non-finite")
    return v


class Steering:
    """The leader node's ROS 2 subscription (an ``MS`` token: ``ros2 topic info -v`` shows
    it) and what it took."""

    def __init__(self, session: Any, node: Ros2Node, entity_id: int, topic: str,
                 qos: Qos) -> None:
        h = type_hash(fm.TWIST)
        self.taken = 0
        self.refused: dict[str, int] = {}
        self._newest: tuple[int, tuple[float, float, float]] | None = None
        self._budget, self._refill = MAX_STEER_HZ / 10, time.monotonic()
        self._sub = session.declare_subscriber(data_key(node.domain, topic, fm.TWIST, h),
                                               self._on_sample)
        self._token = session.liveliness().declare_token(
            node.endpoint_token(entity_id, "MS", topic, fm.TWIST, h, qos))

    def _refuse(self, why: str) -> None:
        self.refused[why] = self.refused.get(why, 0) + 1

    def _on_sample(self, sample: Any) -> None:
        now = time.monotonic()
        self._budget = min(MAX_STEER_HZ / 10, self._budget + (now - self._refill) * MAX_STEER_HZ)
        self._refill = now
        if self._budget < 1.0:
            self._refuse(f"over {MAX_STEER_HZ:g} a second")
            return
        self._budget -= 1.0
        try:
            v = twist_of(bytes(sample.payload.to_bytes()))
        except ValueError as exc:
            self._refuse(str(exc))
            return
        self._newest = (0 if self._newest is None else self._newest[0] + 1, v)
        self.taken += 1

    def newest(self) -> tuple[int, tuple[float, float, float]] | None:
        """The newest accepted command: (its number, [vx, vy, wz]); None before any."""
        return self._newest

    def counts(self) -> dict[str, Any]:
        return {"taken": self.taken, "refused": dict(self.refused)}

    def summary(self) -> str:
        refused = sum(self.refused.values())
        return (f"/leader/cmd_vel: {self.taken} taken, {refused} refused" + (
            f" ({', '.join(f'{k}: {n}' for k, n in self.refused.items())})" if refused else ""))

    def close(self) -> None:
        self._sub.undeclare()
        self._token.undeclare()
