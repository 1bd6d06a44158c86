"""The run's recording: one MCAP file that Foxglove (or Lichtblick) opens as it is.

It holds

- the wire messages (any ``msgspec.Struct``, whatever ``deploy.contract.wire`` defines):
  JSON with a root-object JSON Schema per type (``deploy/report/foxglove_json.py``),
  on the key without its ``omr/<fleet>/`` prefix (``/robot/1/state``), so two
  runs have the same topics;
- the scene, frames and plot signals of ``deploy/report/foxglove_scene.py``
  (:meth:`McapRecorder.write_scene`, at the end of a run, from its time
  series): Foxglove's own protobuf schemas, taken from the ``foxglove-sdk``
  package, encoded by it.

Times: ``publish_time`` is always the wall clock (when the message was heard,
or when the step ran); ``log_time`` — the time Foxglove's timeline shows — is
the simulation time of lockstep runs (``sim_dt`` given; t = 0 is the epoch,
1970-01-01T00:00:00Z) and the wall clock of realtime runs. A metadata record
``omnifleet`` in the file says which.

Why the ``mcap`` writer and not the SDK's ``open_mcap``: the SDK's MCAP sink
writes ``publish_time = log_time`` and numbers messages itself; this file needs
two clocks, the wire's own sequence numbers and the wire's JSON channels beside
the SDK's protobuf ones. The SDK still provides every scene schema and encoding.

Messages are appended by the launcher's thread and written by one writer thread in
batches, so a slow disk never blocks a subscriber; :meth:`close` drains what is
queued and writes the MCAP summary (also after Ctrl-C). A message that cannot
be encoded (a value JSON cannot hold) is counted in ``failed``, never raised; every
integer the MCAP record holds is brought into its range first (a wire seq >= 2^32
killed the writer thread once). Should the writer fail anyway (a full disk, a bug),
the recorder is ``broken``: it says why, stops queueing (memory stays flat),
counts what it could not write in ``lost``, and the run fails loudly (non-zero exit,
verdict not PASS). ``written`` is exactly the number of messages in the file.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from mcap.writer import Writer

from deploy.report.foxglove_json import StructJson

WIRE_PREFIX = re.compile(r"^omr/[^/]+/")  # Keys.root: omr/<fleet>/
UINT32 = 0xFFFF_FFFF
UINT64_MAX = 2**64 - 1
LIBRARY = "omnifleet"
MAX_KEYS_KEPT = 4096  # wire keys whose channel is remembered


def wire_topic(key: str) -> str:
    """``omr/paper-15255/robot/1/state`` -> ``/robot/1/state`` (stable across runs)."""
    return "/" + WIRE_PREFIX.sub("", key, count=1).lstrip("/")


def _clamp_ns(t: int) -> int:
    return min(max(int(t), 0), UINT64_MAX)


class McapRecorder:
    def __init__(self, path: Path, sim_dt: float | None = None, profile: str = "") -> None:
        """``sim_dt``: the step of a lockstep run; log time is then simulation time.
        ``profile``: the MCAP profile ("ros2": a file of ROS 2 channels only, as rosbag2
        readers ask, deploy/ros2/bag.py)."""
        self.path = path
        self.sim_dt = sim_dt
        self._file = open(path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file)
        self._writer.start(profile=profile, library=LIBRARY)
        self._lock = threading.Lock()  # the mcap writer is not thread-safe
        self._json: dict[type, tuple[StructJson, int]] = {}  # type -> (codec, schema id)
        self._schemas: dict[str, int] = {}  # protobuf schema name -> id
        self._channels: dict[str, int] = {}
        # called with (this recorder, sc, series, t0_unix_ns) as the scene is written, under
        # the writer's lock: more channels from the run's series (deploy/ros2/bag.py)
        self.with_scene: list[Any] = []
        self._by_key: dict[tuple[str, type], tuple[StructJson, int]] = {}  # the wire's keys
        self._sequence: dict[int, int] = {}  # channel -> next sequence (messages without seq)
        self._queue: deque[tuple[str, int, Any]] = deque()
        self._sources: list[Any] = []  # more wire messages, read by the writer (add_source)
        self._wake = threading.Event()
        self._closing = False
        self._closed = False
        self._sim_ns = 0  # newest simulation time seen on the wire (messages without one)
        self.written = 0
        self.failed = 0  # messages that could not be encoded (counted, never raised)
        self.first_error: str | None = None
        self.broken: str | None = None  # why the writer failed (the run then fails)
        self.incomplete: str | None = None  # why messages never reached it (the run then fails)
        self.lost = 0  # messages not written because it had failed
        self._thread = threading.Thread(target=self._drain_forever, name="mcap", daemon=True)
        self._thread.start()

    # -- wire messages --------------------------------------------------------------
    def add(self, key: str, arrival_unix_ns: int, msg: msgspec.Struct) -> None:
        """Thread-safe (deque.append is atomic). ``arrival_unix_ns``: the wall clock."""
        if self.broken is not None:
            self.lost += 1  # nothing queued for a writer that cannot write (flat memory)
            return
        self._queue.append((key, arrival_unix_ns, msg))

    def add_source(self, source: Any) -> None:
        """Wire messages this recorder reads itself, on its writer's thread:
        ``source.read()`` returns the (key, wall clock ns, message) that came since the
        last read (message None: one that did not decode, counted as failed);
        ``source.close()`` is called when the recording closes."""
        self._sources.append(source)

    def missed(self, why: str, n: int) -> None:
        """``n`` messages that never reached this recorder (a source of them failed): the
        recording goes on, but is incomplete, said and counted as a failure (the run fails)."""
        import sys

        self.incomplete = self.incomplete or why
        self.lost += n
        print(f"recorder: INCOMPLETE ({why}); the run will fail", file=sys.stderr, flush=True)

    def _json_channel(self, topic: str, kind: type) -> tuple[StructJson, int]:
        entry = self._json.get(kind)
        if entry is None:
            codec = StructJson(kind)
            sid = self._writer.register_schema(
                name=codec.schema["title"], encoding="jsonschema",
                data=json.dumps(codec.schema).encode())
            entry = self._json[kind] = (codec, sid)
        ch = self._channels.get(topic)
        if ch is None:
            ch = self._channels[topic] = self._writer.register_channel(topic, "json", entry[1])
        return entry[0], ch

    def _log_time(self, msg: Any, arrival_ns: int) -> int:
        """Lockstep: the step k's time (k * dt), else the message's time t, else
        the newest simulation time heard (reports, control without a step)."""
        if self.sim_dt is None:
            return arrival_ns
        k, t = getattr(msg, "k", None), getattr(msg, "t", None)
        if isinstance(k, int) and 0 <= k < 2**40:
            ns = int(round(k * self.sim_dt * 1e9))
        elif isinstance(t, float) and 0.0 <= t < 1e9:
            ns = int(round(t * 1e9))
        else:
            return self._sim_ns
        self._sim_ns = max(self._sim_ns, ns)
        return ns

    def _write_wire(self, key: str, arrival_ns: int, msg: Any) -> None:
        if self.broken is not None:
            self.lost += 1
            return
        try:  # the value: what cannot be encoded is refused and counted
            found = self._by_key.get((key, type(msg)))
            if found is None:
                found = self._json_channel(wire_topic(key), type(msg))
                if len(self._by_key) < MAX_KEYS_KEPT:  # a forger's made-up keys stay bounded
                    self._by_key[(key, type(msg))] = found
            codec, ch = found
            data = codec.encode(msg)
            seq = getattr(msg, "seq", None)
            if not isinstance(seq, int) or isinstance(seq, bool):
                seq = self._next_sequence(ch)
            log_time = _clamp_ns(self._log_time(msg, arrival_ns))
        except Exception as exc:  # noqa: BLE001 - a recorder never dies on a value
            self.failed += 1
            self.first_error = self.first_error or f"{key}: {type(exc).__name__}: {exc}"
            return
        # the writer: every field within the record's range, so what fails here is the
        # writer itself (a full disk), never the value
        self._add(ch, log_time, data, _clamp_ns(arrival_ns), seq & UINT32,  # uint32
                  what=key)

    def _add(self, ch: int, log_time: int, data: bytes, publish_time: int, sequence: int,
             what: str) -> None:
        try:
            self._writer.add_message(ch, log_time=log_time, data=data,
                                     publish_time=publish_time, sequence=sequence)
        except Exception as exc:  # noqa: BLE001 - said loudly by the run, not raised here
            self._break(f"writing {what}: {type(exc).__name__}: {exc}")
            self.lost += 1
            return
        self.written += 1

    def _break(self, why: str) -> None:
        if self.broken is None:
            self.broken = why
            import sys

            print(f"recorder: FAILED ({why}); the rest of the run is not recorded and "
                  "the run will fail", file=sys.stderr, flush=True)
        self.lost += len(self._queue)
        self._queue.clear()

    def _next_sequence(self, ch: int) -> int:
        n = self._sequence.get(ch, 0)
        self._sequence[ch] = n + 1
        return n

    def _drain(self) -> None:
        q = self._queue
        with self._lock:
            for source in self._sources:
                for key, arrival_ns, msg in source.read():
                    if msg is None:
                        self.failed += 1
                        self.first_error = self.first_error or f"{key}: does not decode"
                        continue
                    self._write_wire(key, arrival_ns, msg)
            while q:
                self._write_wire(*q.popleft())

    def _drain_forever(self) -> None:
        try:
            while not self._closing:
                self._wake.wait(0.25)
                self._drain()
        except BaseException as exc:  # noqa: BLE001 - never a silent death of the thread
            self._break(f"writer thread: {type(exc).__name__}: {exc}")

    # -- scene and plots ------------------------------------------------------------
    def write_message(self, topic: str, msg: Any, log_time_ns: int, publish_time_ns: int) -> None:
        """One scene message (a ``foxglove.messages`` type) or plot message (a Struct)."""
        try:
            if isinstance(msg, msgspec.Struct):
                codec, ch = self._json_channel(topic, type(msg))
                data = codec.encode(msg)
            else:
                ch = self._protobuf_channel(topic, msg)
                data = msg.encode()
        except Exception as exc:  # noqa: BLE001
            self.failed += 1
            self.first_error = self.first_error or f"{topic}: {type(exc).__name__}: {exc}"
            return
        if self.broken is not None:
            self.lost += 1
            return
        self._add(ch, _clamp_ns(log_time_ns), data, _clamp_ns(publish_time_ns),
                  self._next_sequence(ch) & UINT32, what=topic)

    def _protobuf_channel(self, topic: str, msg: Any) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            schema = type(msg).get_schema()
            sid = self._schemas.get(schema.name)
            if sid is None:
                sid = self._schemas[schema.name] = self._writer.register_schema(
                    name=schema.name, encoding=schema.encoding, data=bytes(schema.data))
            ch = self._channels[topic] = self._writer.register_channel(topic, "protobuf", sid)
        return ch

    def write_scene(self, sc, series, t0_unix_ns: int | None = None,
                    step_unix_ns: np.ndarray | None = None) -> None:
        """The scene, frames and plot signals of a whole run, from its time series,
        on the file's clock (simulation time with ``sim_dt``, else the wall clock).

        ``t0_unix_ns``: wall clock at t = 0 (default: now); ``step_unix_ns``: wall
        clock at each step when known (the publish time; else t0 + t)."""
        from deploy.report.foxglove_plots import FleetPlots
        from deploy.report.foxglove_scene import FleetScene
        from deploy.report.foxglove_topics import PLOT_RATE_HZ, SCENE_RATE_HZ, stride

        self._drain()
        t0 = int(t0_unix_ns) if t0_unix_ns is not None else time.time_ns()
        fs = FleetScene(sc, stamp_offset_ns=0 if self.sim_dt is not None else t0)
        fp = FleetPlots(sc)
        steps = series.steps
        scene_rows = set(range(0, steps, stride(sc, SCENE_RATE_HZ))) | ({steps - 1} if steps else set())
        plot_rows = set(range(0, steps, stride(sc, PLOT_RATE_HZ))) | scene_rows
        with self._lock:
            for k, plots in fp.rows(series, sorted(plot_rows)):
                t_ns = int(round(k * sc.dt * 1e9))
                wall = int(step_unix_ns[k]) if step_unix_ns is not None else t0 + t_ns
                log = t_ns if self.sim_dt is not None else t0 + t_ns
                for topic, msg in plots.items():
                    self.write_message(topic, msg, log, wall)
                if k in scene_rows:
                    for topic, msg in fs.scene_messages(series, k).items():
                        self.write_message(topic, msg, log, wall)
            for more in self.with_scene:
                more(self, sc, series, t0)

    def write_cdr(self, topic: str, ros_type: str, definition: str, data: bytes,
                  log_time_ns: int, publish_time_ns: int) -> None:
        """One ROS 2 message, CDR-encoded, on a channel with its ``ros2msg`` schema (what
        rosbag2's MCAP storage and Foxglove read as a ROS 2 topic)."""
        ch = self._channels.get(topic)
        if ch is None:
            sid = self._schemas.get(ros_type)
            if sid is None:
                sid = self._schemas[ros_type] = self._writer.register_schema(
                    name=ros_type, encoding="ros2msg", data=definition.encode())
            ch = self._channels[topic] = self._writer.register_channel(topic, "cdr", sid)
        if self.broken is not None:
            self.lost += 1
            return
        self._add(ch, _clamp_ns(log_time_ns), data, _clamp_ns(publish_time_ns),
                  self._next_sequence(ch) & UINT32, what=topic)

    # -- the end --------------------------------------------------------------------
    def close(self, metadata: dict[str, str] | None = None) -> None:
        """Drain, write the summary, close the file. Idempotent."""
        if self._closed:
            return
        self._closing = True
        self._wake.set()
        self._thread.join()
        try:
            self._drain()
        except BaseException as exc:  # noqa: BLE001
            self._break(f"closing: {type(exc).__name__}: {exc}")
        with self._lock:
            try:
                self._writer.add_metadata(LIBRARY, {
                    "log_time": "simulation time (t = 0 is 1970-01-01T00:00:00Z)"
                    if self.sim_dt is not None else "wall clock",
                    "publish_time": "wall clock",
                    "messages_failed": str(self.failed),
                    **({"broken": self.broken} if self.broken else {}),
                    **(metadata or {})})
                self._writer.finish()
            except Exception as exc:  # noqa: BLE001
                self._break(f"finishing the file: {type(exc).__name__}: {exc}")
            finally:
                try:  # its buffer's last flush: a full disk says so here too
                    self._file.close()
                except OSError as exc:
                    self._break(f"closing the file: {type(exc).__name__}: {exc}")
        self._closed = True
        for source in self._sources:
            source.close()
        if self.broken is not None:  # the count is what the file holds, read back
            self.written = messages_in(self.path)

    def summary(self) -> dict[str, Any]:
        """For metrics.json."""
        out: dict[str, Any] = {"file": self.path.name, "messages": self.written,
                               "failed": self.failed}
        if self.first_error:
            out["first_error"] = self.first_error
        if self.broken is not None or self.incomplete is not None:
            out["error"] = self.broken or self.incomplete
            out["lost"] = self.lost
        return out


def messages_in(path: Path) -> int:
    """How many messages the MCAP file at ``path`` really holds (0 when unreadable)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            return sum(1 for _ in make_reader(f).iter_messages())
    except Exception:  # noqa: BLE001 - a truncated file: count what a reader gets
        return 0
