"""``--live``: the run's scene and plots over Foxglove's WebSocket protocol
(served by ``foxglove-sdk`` as ``foxglove.sdk.v1``, and as ``foxglove.websocket.v1``
through deploy/report/ws_front.py: Foxglove and Lichtblick connect) while the run goes.

Off the control path: the run only tells the view how far its time series is
filled (:meth:`LiveView.publish` stores an int, or the view polls a ``ready``
callable); a thread of the view wakes at a display rate, reads the newest rows
and publishes them — building messages only for channels a client subscribed
to, so nobody watching costs (almost) nothing. The SDK's server runs on its own
(Rust) threads, drops the oldest messages for a slow client and never blocks
the publisher.

Log time: simulation time in lockstep (as in the recording; the server
advertises the ``time`` capability and broadcasts it), the wall clock in
realtime. Binds loopback unless told otherwise (``--live 0.0.0.0:8765``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import foxglove
from foxglove import channels as fc
from foxglove.websocket import Capability

from deploy.contract.scenario import Scenario
from deploy.report.foxglove_json import StructJson
from deploy.report.foxglove_plots import FleetPlots, FleetSignals, RobotSignals
from deploy.report.foxglove_scene import FleetScene
from deploy.report.foxglove_topics import (
    LEADER_POSE_TOPIC,
    PLOT_FLEET,
    POSES_TOPIC,
    SCENE_RATE_HZ,
    SCENE_TOPICS,
    TF_TOPIC,
    plot_topic,
    stride,
)
from deploy.report.timeseries import TimeSeries
from deploy.report.ws_address import DEFAULT_HOST, DEFAULT_PORT
from deploy.report.ws_front import ViewServer

LIVE_PLOT_RATE_HZ = 50.0  # plot rows per simulated second, live (the recording has more)
LIVE_TRACE_HISTORY_S = 0.25  # live: trace points older than 2 s this far apart (scenes stay small)
MAX_ROWS_PER_TICK = 64  # a view that fell behind skips rows rather than lag



class LiveView:
    def __init__(self, sc: Scenario, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 realtime: bool = False) -> None:
        self.sc, self.realtime = sc, realtime
        self.scene = FleetScene(sc, LIVE_TRACE_HISTORY_S)
        self.plots = FleetPlots(sc)
        self.context = foxglove.Context()
        # the SDK's server behind a door that lets Lichtblick in too (ws_front.py)
        self.server = ViewServer(host, port, name=f"omnifleet {sc.name}", context=self.context,
                                 capabilities=[] if realtime else [Capability.Time])
        ctx = self.context
        self.channels: dict[str, object] = {
            **{t: fc.SceneUpdateChannel(t, context=ctx) for t in SCENE_TOPICS},
            TF_TOPIC: fc.FrameTransformsChannel(TF_TOPIC, context=ctx),
            POSES_TOPIC: fc.PosesInFrameChannel(POSES_TOPIC, context=ctx),
            LEADER_POSE_TOPIC: fc.PoseInFrameChannel(LEADER_POSE_TOPIC, context=ctx),
        }
        self._json = {RobotSignals: StructJson(RobotSignals), FleetSignals: StructJson(FleetSignals)}
        plots = {plot_topic(r): RobotSignals for r in sc.robot_ids} | {PLOT_FLEET: FleetSignals}
        for topic, kind in plots.items():
            self.channels[topic] = foxglove.Channel(topic, schema=self._json[kind].schema,
                                                    message_encoding="json", context=ctx)
        self.plot_stride = stride(sc, LIVE_PLOT_RATE_HZ)
        self.scene_stride = stride(sc, SCENE_RATE_HZ)
        self._series: TimeSeries | None = None
        self._ready: Callable[[], int] | None = None
        self._newest = -1
        self._sent = -1  # newest row published
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.published = 0  # messages handed to the server
        self.errors = 0
        self.cpu_s = 0.0  # CPU time the view's thread spent building and handing over messages

    @property
    def port(self) -> int:
        return self.server.port

    def follow(self, series: TimeSeries, ready: Callable[[], int] | None = None) -> LiveView:
        """Serve rows of ``series``; ``ready()`` gives the newest filled row (else
        :meth:`publish` says it)."""
        self._series, self._ready = series, ready
        self._thread = threading.Thread(target=self._loop, name="live-view", daemon=True)
        self._thread.start()
        return self

    def publish(self, k: int) -> None:
        """Rows 0..k of the series are filled (cheap: called on the control thread)."""
        self._newest = k

    def _newest_row(self) -> int:
        return self._ready() if self._ready is not None else self._newest

    def _loop(self) -> None:
        period = 1.0 / SCENE_RATE_HZ
        while not self._stop.wait(period):
            self._tick()

    def _tick(self) -> None:
        ts, k = self._series, self._newest_row()
        if ts is None or k <= self._sent or k < 0:
            return
        cpu = time.thread_time()
        try:
            self._send(ts, self._sent, min(k, ts.steps - 1))
        except Exception:  # noqa: BLE001 - a viewer never stops a run
            self.errors += 1
        self._sent = k
        self.cpu_s += time.thread_time() - cpu

    def _send(self, ts: TimeSeries, after: int, k: int) -> None:
        log = (lambda _k: time.time_ns()) if self.realtime else (
            lambda kk: int(round(kk * self.sc.dt * 1e9)))
        if not self.realtime:
            self.server.broadcast_time(log(k))
        if any(self.channels[plot_topic(r)].has_sinks() for r in self.sc.robot_ids) or \
                self.channels[PLOT_FLEET].has_sinks():
            first = (after // self.plot_stride + 1) * self.plot_stride
            rows = list(range(first, k + 1, self.plot_stride))[-MAX_ROWS_PER_TICK:]
            for row, msgs in self.plots.rows(ts, rows, series_target=False):
                for topic, msg in msgs.items():
                    ch = self.channels[topic]
                    if ch.has_sinks():
                        ch.log(self._json[type(msg)].encode(msg), log_time=log(row))
                        self.published += 1
        if any(self.channels[t].has_sinks() for t in (*SCENE_TOPICS, TF_TOPIC, POSES_TOPIC,
                                                        LEADER_POSE_TOPIC)):
            for topic, msg in self.scene.scene_messages(ts, k).items():
                ch = self.channels[topic]
                if ch.has_sinks():
                    ch.log(msg, log_time=log(k))
                    self.published += 1

    def close(self) -> None:
        """Publish the last row, stop the thread and the server (the port is free after)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._tick()
        self.server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def collector_rows(collector, realtime: bool = False) -> Callable[[], int]:
    """``ready`` for a distributed run: the newest row of the launcher's collector
    whose states, telemetry and leader have all arrived (lockstep fills rows in
    order); realtime, where cells may never come, the newest state's row."""
    newest = -1

    def ready() -> int:
        nonlocal newest
        collector.flush()  # the state logs it holds (Collector.defer_rows)
        if realtime:
            return collector.newest_k
        k = newest
        while (k + 1 < collector.steps and collector.have_state[k + 1].all()
               and collector.have_telemetry[k + 1].all() and collector.have_leader[k + 1]):
            k += 1
        newest = k
        return k

    return ready
