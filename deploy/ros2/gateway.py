"""``--ros2``: the run's state as ROS 2 topics over rmw_zenoh, from the listener's side.

The gateway lives in the process that already hears the whole run (the launcher, or
``omnifleet record`` across hosts): at most ``rate_hz`` times a (wall-clock) second it reads
the newest row of the run's time series and puts it on its own Zenoh session, connected to
the ROS 2 router at ``endpoint``, as rmw_zenoh would (deploy/ros2/graph.py). In a fleet the
launcher's loop drives it (:meth:`Ros2Gateway.poll`); in process a thread of its own does.
No control process imports this package or spends a cycle on ROS 2: a step's CPU budget is
untouched (docs/ros2.md says why this is not one publisher per node). Rows between two
ticks are not published, and counted.

What a ROS 2 graph sees: one node per omnifleet node (``/omnifleet/plant``,
``/omnifleet/agent_N``, ``/omnifleet/leader``, ``/omnifleet/launcher``; ``bridge_N`` for
a CAN robot), each with its publishers' liveliness tokens, all under one session.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import deploy.ros2.fleet_messages as fm
from deploy.ros2.graph import TRANSIENT_LOCAL, Qos, Ros2Node, attachment, data_key, gid
from deploy.ros2.options import Ros2Options
from deploy.ros2.steering import STEER_TOPIC, Steering
from deploy.ros2.types import encode, type_hash

NODE_NAMESPACE = "omnifleet"
STATUS_PERIOD_S = 1.0  # /fleet/status once a second (of the wall): diagnostics' usual rate
DEFAULT_QOS = Qos()  # reliable, volatile, keep last 10 (a ROS 2 publisher's default)


@dataclass
class _Topic:
    """One publisher of the gateway: its zenoh publisher, liveliness token and GID."""

    publisher: Any
    token: Any
    gid: bytes
    seq: int = 0
    matching: bool = True  # some subscriber listens (zenoh's matching status)
    listener: Any = None  # zenoh's matching listener that keeps ``matching``


@dataclass
class GatewayCounts:
    published: int = 0
    rows_skipped: int = 0  # rows newer than the last published, never published
    late_ticks: int = 0  # ticks that took longer than the period (the gateway fell behind)
    errors: int = 0
    unmatched: int = 0  # messages not built: no subscriber listened
    cpu_s: float = 0.0


def _node_names(sc: Any, bridged: set[int]) -> dict[str, str]:
    """omnifleet node -> ROS 2 node name (role -> name)."""
    names = {"launcher": "launcher", "leader": "leader"}
    if len(bridged) < sc.n:
        names["plant"] = "plant"
    for rid in sc.robot_ids:
        names[f"agent-{rid}"] = f"agent_{rid}"
        if rid in bridged:
            names[f"bridge-{rid}"] = f"bridge_{rid}"
    return names


class Ros2Gateway:
    """Publishes the run to ROS 2 (``follow`` a series, ``close`` at the end)."""

    def __init__(self, sc: Any, opts: Ros2Options, realtime: bool,
                 bridged: set[int] | None = None,
                 start_unix_ns: Callable[[], int | None] = lambda: None,
                 refused: Callable[[], int] = lambda: 0,
                 session_factory: Callable[[Ros2Options], Any] | None = None) -> None:
        self.sc, self.opts, self.realtime = sc, opts, realtime
        self.bridged = bridged or set()
        self.start_unix_ns, self.refused = start_unix_ns, refused
        # role -> "running", "exited N", "killed by the fault plan" (the launcher's children)
        self.processes: Callable[[], dict[str, str]] = lambda: {}
        # each agent's deadline misses so far (the listener's telemetry; None in process)
        self.agent_misses: Callable[[], Any] = lambda: None
        self.counts = GatewayCounts()
        self.session = (session_factory or open_session)(opts)
        self.zid = str(self.session.info.zid())
        self._ids = itertools.count()
        ns_nodes = f"{opts.namespace}/{NODE_NAMESPACE}"
        self.nodes = {role: Ros2Node(opts.domain, self.zid, next(self._ids), ns_nodes, name)
                      for role, name in _node_names(sc, self.bridged).items()}
        self._node_tokens = [self.session.liveliness().declare_token(n.token())
                             for n in self.nodes.values()]
        self.topics: dict[str, _Topic] = {}
        self._declare_all()
        self.steer: Steering | None = None  # a leader steered from ROS 2: its input
        if sc.leader_spec().steered is not None:
            self.steer = Steering(self.session, self.nodes["leader"], next(self._ids),
                                  self.topic_name(STEER_TOPIC), DEFAULT_QOS)
        self.frames = fm.frames_for(sc)
        self._status_due = 0.0
        self._due = 0.0  # driven: when the next tick may run
        self._series: Any = None
        self._ready: Callable[[], int] | None = None
        self._newest = -1
        self._sent = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        # static: latched (transient local) from the moment the topic appears
        ns = time.time_ns() if realtime else 0
        self.put(self.topic_name("obstacles"),
                 fm.obstacle_markers(ns, fm.obstacle_shapes_of(sc)), ns)
        # rosbags writes a type's serializer at its first message (~ms): the status's
        # now, before the run, rather than in the run's loop a second into it
        encode(fm.status(ns, []))

    # -- the graph ---------------------------------------------------------------------

    def topic_name(self, relative: str) -> str:
        return f"{self.opts.namespace}/{relative}"

    def _declare(self, role: str, relative: str, ros_type: str, qos: Qos = DEFAULT_QOS,
                 absolute: str | None = None) -> None:
        import zenoh

        node = self.nodes[role]
        name = absolute or self.topic_name(relative)
        entity = next(self._ids)
        h = type_hash(ros_type)
        key = data_key(self.opts.domain, name, ros_type, h)
        if qos.durability == TRANSIENT_LOCAL:  # late joiners get the last sample (rmw_zenoh)
            import zenoh.ext as zext

            pub = zext.declare_advanced_publisher(
                self.session, key, cache=zext.CacheConfig(max_samples=qos.depth),
                publisher_detection=True)
        else:
            pub = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.DROP)
        token = self.session.liveliness().declare_token(
            node.endpoint_token(entity, "MP", name, ros_type, h, qos))
        topic = self.topics[name] = _Topic(pub, token, gid(self.zid, node.node_id, entity))
        if qos.durability != TRANSIENT_LOCAL:
            # whether someone subscribes, kept by zenoh's callback: no call into zenoh a
            # tick per topic to ask it
            topic.matching = pub.matching_status.matching

            def on_matching(status: Any, topic: _Topic = topic) -> None:
                topic.matching = status.matching

            topic.listener = pub.declare_matching_listener(on_matching)

    def _declare_all(self) -> None:
        for rid in self.sc.robot_ids:
            holder = f"bridge-{rid}" if rid in self.bridged else "plant"
            self._declare(holder, f"robot_{rid}/odom", fm.ODOM)
            self._declare(holder, f"robot_{rid}/joint_states", fm.JOINTS)
            self._declare(f"agent-{rid}", f"robot_{rid}/cmd_vel", fm.CMD_VEL)
        self._declare("leader", "leader/pose", fm.POSE)
        self._declare("launcher", "tf", fm.TF)
        self._declare("launcher", "obstacles", fm.MARKERS, Qos(durability=TRANSIENT_LOCAL,
                                                               depth=1))
        self._declare("launcher", "fleet/status", fm.STATUS)
        if not self.realtime:  # simulated time for use_sim_time nodes
            self._declare("launcher", "clock", fm.CLOCK, Qos(depth=1), absolute="/clock")

    def steering(self) -> tuple[int, tuple[float, float, float]] | None:
        """A steered leader's newest command from ROS 2 (None: none, or not steered)."""
        return None if self.steer is None else self.steer.newest()

    def put(self, name: str, msg: Any, stamp_ns: int) -> None:
        """A message (a rosbags object, or its CDR bytes) on topic ``name``."""
        topic = self.topics[name]
        data = msg if isinstance(msg, bytes) else encode(msg)
        topic.publisher.put(data, attachment=attachment(topic.seq, stamp_ns, topic.gid))
        topic.seq += 1
        self.counts.published += 1

    # -- the run's rows -----------------------------------------------------------------

    def follow(self, series: Any, ready: Callable[[], int] | None = None,
               driven: bool = False) -> Ros2Gateway:
        """Publish rows of ``series``; ``ready()`` gives the newest filled row (else
        :meth:`publish` says it). ``driven``: no thread of its own; the caller's loop
        calls :meth:`poll` (the launcher's, which wakes every 50 ms anyway)."""
        self._series, self._ready = series, ready
        if not driven:
            self._thread = threading.Thread(target=self._loop, name="ros2-gateway",
                                            daemon=True)
            self._thread.start()
        return self

    def poll(self) -> None:
        """Driven: publish the newest row when a period of ``rate_hz`` has passed since the
        last tick. On the launcher's thread, right after it filed the rows: no wake of its
        own (a Python thread woken from a sleep ran its first ~1 ms with cold caches: a
        tick of 4 messages took ~950 µs of CPU after a 50 ms sleep, ~350 µs warm)."""
        now = time.monotonic()
        if now >= self._due:
            self._due = now + 1.0 / self.opts.rate_hz
            self.tick()

    def publish(self, k: int) -> None:
        """Rows 0..k are filled (cheap: called from the run's own thread)."""
        self._newest = k

    def _loop(self) -> None:
        period = 1.0 / self.opts.rate_hz
        next_at = time.monotonic()
        while True:
            next_at += period
            if self._stop.wait(max(0.0, next_at - time.monotonic())):
                return
            self.tick()
            now = time.monotonic()
            if now > next_at + period:  # fell behind: start again from now
                self.counts.late_ticks += 1
                next_at = now

    def stamp_ns(self, k: int) -> int:
        t_ns = int(round(k * self.sc.dt * 1e9))  # the listener's series fills t at its end
        if not self.realtime:
            return t_ns  # simulated time, the /clock's
        t0 = self.start_unix_ns()
        return t_ns + t0 if t0 is not None else time.time_ns()

    def tick(self) -> None:
        ts = self._series
        k = self._ready() if self._ready is not None else self._newest
        if ts is None or k < 0:
            return
        k = min(k, ts.steps - 1)
        with self._lock:
            if k <= self._sent:
                return
            cpu = time.thread_time()
            try:
                self._send(ts, k)
                self.counts.rows_skipped += max(0, k - self._sent - 1)
            except Exception:  # noqa: BLE001 - ROS 2 never stops a run; counted
                self.counts.errors += 1
            self._sent = k
            self.counts.cpu_s += time.thread_time() - cpu

    def _wanted(self, relative: str) -> bool:
        """Whether some subscriber listens (zenoh's matching status): a message nobody
        reads is not built (a ROS 2 graph that watches nothing costs the wheel sums)."""
        if self.topics[self.topic_name(relative)].matching:
            return True
        self.counts.unmatched += 1
        return False

    def _send(self, ts: Any, k: int) -> None:
        ns = self.stamp_ns(k)
        if not self.realtime and self.topics["/clock"].matching:
            self.put("/clock", self.frames.clock_bytes(ns), ns)
        for relative, _type, data in self.frames.encoded(ts, k, ns, self._wanted):
            self.put(self.topic_name(relative), data, ns)
        now = time.monotonic()
        if now >= self._status_due and self._wanted("fleet/status"):
            self._status_due = now + STATUS_PERIOD_S
            self.put(self.topic_name("fleet/status"), fm.status(ns, self._status(ts, k)), ns)

    def _status(self, ts: Any, k: int, verdict: dict | None = None) -> list:
        out = fm.robot_status(ts, k, k * self.sc.dt, list(self.sc.robot_ids), NODE_NAMESPACE,
                              self.agent_misses())
        processes = self.processes()
        merged = []
        for name, level, message, values in out:  # an agent's process beside its health
            state = processes.pop("agent-" + name.rsplit("_", 1)[1], None)
            if state is not None:
                values["process"] = state
                if state != "running":  # gone while the run goes: an error until it ends
                    message = f"{message}; its process: {state}"
                    level = "error" if verdict is None else level
            merged.append((name, level, message, values))
        out = merged
        for role, state in sorted(processes.items()):
            out.append((f"{NODE_NAMESPACE}/{role.replace('-', '_')}",
                        "ok" if state == "running" or verdict is not None else "error",
                        state, {"process": state}))
        values = {"refused_messages": str(self.refused()),
                  "ros2_rows_skipped": str(self.counts.rows_skipped),
                  "ros2_late_ticks": str(self.counts.late_ticks)}
        if verdict is None:
            out.append((f"{NODE_NAMESPACE}/launcher", "ok", "running", values))
        else:
            ok = bool(verdict.get("pass"))
            out.append((f"{NODE_NAMESPACE}/launcher", "ok" if ok else "error",
                        "verdict: PASS" if ok else "verdict: FAIL: " + "; ".join(
                            verdict.get("reasons", []))[:400], values))
        return out

    def bind_observer(self, observer: Any) -> None:
        """Stamps on the run's clock (realtime: t = 0 from ``ctl/start``) and the
        listener's refusals in /fleet/status."""
        def start_unix_ns() -> int | None:
            if observer.run_t0 is None:
                return None
            return time.time_ns() - int((time.monotonic() - observer.run_t0) * 1e9)

        self.start_unix_ns = start_unix_ns
        self.refused = lambda: observer.invalid
        self.agent_misses = lambda: observer.collector.agent_misses

    def counts_json(self) -> dict[str, Any]:
        c = self.counts
        out = {"published": c.published, "not_built_unsubscribed": c.unmatched,
               "rows_skipped": c.rows_skipped, "late_ticks": c.late_ticks, "errors": c.errors,
               "cpu_s": round(c.cpu_s, 3), "rate_hz": self.opts.rate_hz}
        if self.steer is not None:
            out["leader_cmd_vel"] = self.steer.counts()
        return out

    def summary(self) -> str:
        c = self.counts
        steer = "" if self.steer is None else "; " + self.steer.summary()
        return (f"ros2: {c.published} messages published, {c.unmatched} not built (no "
                f"subscriber), {c.rows_skipped} rows skipped at {self.opts.rate_hz:g} Hz, "
                f"{c.late_ticks} late ticks, {c.errors} errors, "
                f"{c.cpu_s:.2f} s CPU{steer}; left the ROS 2 graph")

    def close(self, verdict: dict | None = None) -> None:
        """Publish the last row (and the verdict, when given), then leave the graph."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.tick()
        if verdict is not None and self._series is not None and self._sent >= 0:
            ns = self.stamp_ns(self._sent)
            self.put(self.topic_name("fleet/status"),
                     fm.status(ns, self._status(self._series, self._sent, verdict)), ns)
        if self.steer is not None:
            self.steer.close()
        for t in self.topics.values():
            if t.listener is not None:
                t.listener.undeclare()
            t.token.undeclare()
        for tok in self._node_tokens:
            tok.undeclare()
        self.session.close()


def open_session(opts: Ros2Options) -> Any:
    """A peer session connected to the ROS 2 router (rmw_zenoh's default session:
    peer mode, multicast scouting off, timestamps on, the router at its endpoint)."""
    import json

    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps([opts.endpoint]))
    # rmw_zenoh's sessions stamp samples (its transient-local cache orders by them)
    cfg.insert_json5("timestamping/enabled", "true")
    return zenoh.open(cfg)


def polling(progress: Callable[[int, int], None] | None, gateway: Ros2Gateway
            ) -> Callable[[int, int], None]:
    """A progress callback (the launcher and the recorder call theirs each time round
    their loop) that also lets a driven gateway publish."""
    def both(done: int, total: int) -> None:
        gateway.poll()
        if progress is not None:
            progress(done, total)

    return both


def gateway_from_args(args: Any, sc: Any, plant: str, command: str) -> Ros2Gateway | None | bool:
    """The --ros2 gateway of a command (None without --ros2; False: a bad option or an
    endpoint zenoh refused, said on stderr: the command exits 2)."""
    import sys

    from deploy.ros2.options import Ros2OptionError, ros2_options
    from deploy.runtime.plants import CAN_EMULATED

    try:
        opts = ros2_options(args)
    except Ros2OptionError as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return False
    if opts is None:
        return None
    try:
        gateway = Ros2Gateway(sc, opts, realtime=args.clock == "realtime",
                              bridged=set(sc.robot_ids) if plant == CAN_EMULATED else set())
    except Exception as exc:  # noqa: BLE001 - zenoh raises its own errors for a bad endpoint
        print(f"{command}: --ros2 {opts.endpoint}: {exc}", file=sys.stderr)
        return False
    print(f"ros2: the fleet on ROS 2 domain {opts.domain} through {opts.endpoint} "
          f"({len(gateway.topics)} topics, {len(gateway.nodes)} nodes under "
          f"{opts.namespace}/{NODE_NAMESPACE}, at most {opts.rate_hz:g} Hz; docs/ros2.md)",
          file=sys.stderr, flush=True)
    return gateway
