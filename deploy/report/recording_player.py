"""Play a recording (MCAP) to Foxglove over its WebSocket protocol, with
playback control: ``omnifleet view`` (``deploy/cli/view.py``).

Every channel of ``RUN_DIR/recording.mcap`` is advertised with its own schema;
messages are played in log-time order at the recording's pace (``--speed``),
from when the first client subscribes (or at once with ``--play``). The server
offers Foxglove's playback control (play, pause, seek, speed from its timeline)
and broadcasts the playback time. Loopback unless ``--listen HOST:PORT`` says
otherwise. Ctrl-C stops it.
"""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import foxglove
import mcap.reader
from foxglove.websocket import (
    Capability,
    PlaybackCommand,
    PlaybackControlRequest,
    PlaybackState,
    PlaybackStatus,
    ServerListener,
)

from deploy.report.ws_front import ViewServer

MIN_SPEED, MAX_SPEED = 0.01, 100.0
TIME_BROADCAST_NS = 1_000_000_000 // 30


def _speed(x: float) -> float:
    return MAX_SPEED if x == math.inf else MIN_SPEED if not x >= MIN_SPEED else min(x, MAX_SPEED)


class RecordingPlayer:
    """Plays an MCAP file's messages into channels of a foxglove Context."""

    def __init__(self, path: Path, context: foxglove.Context, speed: float = 1.0) -> None:
        self.path, self.context = path, context
        with open(path, "rb") as f:
            summary = mcap.reader.make_reader(f).get_summary()
        if summary is None or summary.statistics is None or not summary.statistics.message_count:
            raise ValueError(f"{path}: no messages (or no summary: was the run cut short?)")
        st = summary.statistics
        self.time_range = (st.message_start_time, st.message_end_time)
        self.channels = {}
        for ch in summary.channels.values():
            s = summary.schemas.get(ch.schema_id)
            schema = None if s is None else foxglove.Schema(name=s.name, encoding=s.encoding,
                                                            data=s.data)
            self.channels[ch.id] = foxglove.Channel(ch.topic, schema=schema, context=context,
                                                    message_encoding=ch.message_encoding)
        self.speed = _speed(speed)
        self.status = PlaybackStatus.Paused
        self.lock = threading.Lock()
        self._file = None
        self._seek(self.time_range[0])

    def _seek(self, t_ns: int) -> None:
        if self._file is not None:
            self._file.close()
        self._file = open(self.path, "rb")  # noqa: SIM115 - closed in close()/_seek
        self._iter = mcap.reader.make_reader(self._file).iter_messages(starting_at=t_ns)
        self.current = t_ns
        self._pending = None
        self._anchor: tuple[int, int] | None = None  # (log time, monotonic ns) of playback
        self._last_broadcast = 0

    def seek(self, t_ns: int) -> None:
        self._seek(min(max(t_ns, self.time_range[0]), self.time_range[1]))
        if self.status == PlaybackStatus.Ended:
            self.status = PlaybackStatus.Paused

    def play(self) -> None:
        if self.status != PlaybackStatus.Ended:
            self.status = PlaybackStatus.Playing
            self._anchor = None

    def pause(self) -> None:
        if self.status == PlaybackStatus.Playing:
            self.status = PlaybackStatus.Paused

    def set_speed(self, speed: float) -> None:
        self.speed, self._anchor = _speed(speed), None

    def state(self, did_seek: bool = False, request_id: str | None = None) -> PlaybackState:
        return PlaybackState(current_time=self.current, playback_speed=self.speed,
                             status=self.status, did_seek=did_seek, request_id=request_id)

    def step(self, server) -> float:
        """Send what is due; the seconds until the next message is (at most 0.1)."""
        if self.status != PlaybackStatus.Playing:
            return 0.02
        now = time.monotonic_ns()
        while True:
            rec = self._pending or next(self._iter, None)
            self._pending = None
            if rec is None:
                self.status, self.current = PlaybackStatus.Ended, self.time_range[1]
                server.broadcast_playback_state(self.state())
                return 0.02
            _schema, ch, msg = rec
            if self._anchor is None:
                self._anchor = (msg.log_time, now)
            due = self._anchor[1] + (msg.log_time - self._anchor[0]) / self.speed
            if due > now:
                self._pending = rec
                return min((due - now) * 1e-9, 0.1)
            self.current = msg.log_time
            channel = self.channels[ch.id]
            if channel.has_sinks():
                channel.log(msg.data, log_time=msg.log_time)
            if msg.log_time - self._last_broadcast >= TIME_BROADCAST_NS:
                self._last_broadcast = msg.log_time
                server.broadcast_time(msg.log_time)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class _Listener(ServerListener):
    def __init__(self, player: RecordingPlayer, autoplay: bool) -> None:
        self.player, self.autoplay = player, autoplay

    def on_subscribe(self, client, channel) -> None:
        if self.autoplay:
            with self.player.lock:
                self.autoplay = False
                self.player.play()

    def on_playback_control_request(self, req: PlaybackControlRequest) -> PlaybackState:
        p = self.player
        with p.lock:
            did_seek = req.seek_time is not None
            if did_seek:
                p.seek(req.seek_time)
            p.set_speed(req.playback_speed)
            if req.playback_command == PlaybackCommand.Play:
                p.play()
            elif req.playback_command == PlaybackCommand.Pause:
                p.pause()
            return p.state(did_seek, req.request_id)


def serve_recording(path: Path, host: str, port: int, speed: float = 1.0, play: bool = False,
                    loop: bool = False, stop: threading.Event | None = None,
                    on_ready=None) -> None:
    """Serve until ``stop`` is set (or Ctrl-C); ``on_ready(port)`` once listening."""
    context = foxglove.Context()
    player = RecordingPlayer(path, context, speed)
    server = ViewServer(  # the SDK's server, Lichtblick let in too (ws_front.py)
        host, port, name=f"omnifleet {path.parent.name}", context=context,
        capabilities=[Capability.PlaybackControl, Capability.Time],
        playback_time_range=player.time_range, server_listener=_Listener(player, True))
    stop = stop or threading.Event()
    try:
        if on_ready is not None:
            on_ready(server.port)
        if play:
            player.play()
        while not stop.is_set():
            with player.lock:
                wait = player.step(server)
                if loop and player.status == PlaybackStatus.Ended:
                    player.seek(player.time_range[0])
                    player.play()
            time.sleep(wait)
    finally:
        server.stop()
        player.close()


