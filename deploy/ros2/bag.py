"""``--ros2`` runs also record their ROS 2 topics: the same messages the gateway publishes,
CDR-encoded on ``ros2msg`` channels, written from the run's final series as the scene is
(every row at ``--ros2-rate`` per simulated second, whoever subscribed), into
``ros2.mcap`` (MCAP profile ``ros2``) beside ``recording.mcap``, with the rosbag2
``metadata.yaml`` that names it: the run folder opens as a ROS 2 bag (``ros2 bag info
RUN_DIR``, ``ros2 bag play RUN_DIR``, rosbags' reader), and Foxglove opens either file.

Why a file of its own and not channels of ``recording.mcap``: a rosbag2 reader reads every
schema of the file as message-definition text, and the recording's Foxglove schemas are
binary protobuf descriptors (rosbags' reader failed on the first one: "invalid
continuation byte"); a bag must hold ROS 2 channels only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import deploy.ros2.fleet_messages as fm
from deploy.ros2.gateway import NODE_NAMESPACE, STATUS_PERIOD_S
from deploy.ros2.options import Ros2Options
from deploy.ros2.types import DISTRIBUTION, definition, encode, type_hash

ROSBAG2_VERSION = 9  # metadata.yaml's format (Jazzy writes 9)


BAG_FILE = "ros2.mcap"


class BagTopics:
    """Writes the ROS 2 channels into ``ros2.mcap`` beside a recording (:meth:`__call__`,
    the recording's ``with_scene`` hook) and then the bag's ``metadata.yaml``
    (:meth:`write_metadata`)."""

    def __init__(self, opts: Ros2Options, realtime: bool) -> None:
        self.opts, self.realtime = opts, realtime
        self.counts: dict[str, tuple[str, int]] = {}  # topic -> (type, messages)
        self.first_ns: int | None = None
        self.last_ns = 0
        self.broken: str | None = None  # why ros2.mcap could not be written

    def _name(self, relative: str) -> str:
        return f"{self.opts.namespace}/{relative}"

    def _write(self, recorder: Any, topic: str, msg: Any, log_ns: int,
               ros_type: str | None = None) -> None:
        """``msg``: a rosbags message, or its CDR bytes with their ``ros_type``."""
        ros_type = ros_type or msg.__msgtype__
        data = msg if isinstance(msg, bytes) else encode(msg)
        recorder.write_cdr(topic, ros_type, definition(ros_type), data, log_ns, log_ns)
        n = self.counts.get(topic, (ros_type, 0))[1]
        self.counts[topic] = (ros_type, n + 1)
        self.first_ns = log_ns if self.first_ns is None else min(self.first_ns, log_ns)
        self.last_ns = max(self.last_ns, log_ns)

    def __call__(self, recording: Any, sc: Any, series: Any, t0_unix_ns: int) -> None:
        from deploy.report.recorder import McapRecorder

        bag = McapRecorder(Path(recording.path).parent / BAG_FILE,
                           sim_dt=None if self.realtime else sc.dt, profile="ros2")
        try:
            self._write_all(bag, sc, series, t0_unix_ns)
        finally:
            bag.close({"scenario": sc.name, "ros_distro": DISTRIBUTION})
        self.broken = bag.broken

    def _write_all(self, recorder: Any, sc: Any, series: Any, t0_unix_ns: int) -> None:
        frames = fm.frames_for(sc)
        steps = series.steps
        stride = max(1, round(1.0 / (self.opts.rate_hz * sc.dt)))
        status_stride = max(1, round(STATUS_PERIOD_S / sc.dt))
        rows = sorted(set(range(0, steps, stride)) | ({steps - 1} if steps else set()))
        offset = t0_unix_ns if self.realtime else 0  # the recording's own clock
        if rows:
            self._write(recorder, self._name("obstacles"),
                        fm.obstacle_markers(offset, fm.obstacle_shapes_of(sc)), offset)
        for k in rows:
            ns = offset + int(round(k * sc.dt * 1e9))
            if not self.realtime:
                self._write(recorder, "/clock", frames.clock_bytes(ns), ns, fm.CLOCK)
            for relative, ros_type, data in frames.encoded(series, k, ns):
                self._write(recorder, self._name(relative), data, ns, ros_type)
            if k % status_stride == 0:
                self._write(recorder, self._name("fleet/status"), fm.status(ns, fm.robot_status(
                    series, k, k * sc.dt, list(sc.robot_ids), NODE_NAMESPACE)), ns)

    def write_metadata(self, folder: Path, recording: str = BAG_FILE) -> Path:
        """rosbag2's ``metadata.yaml`` for ``folder`` (a bag of one MCAP file), written in
        YAML's JSON form (flow style: every YAML 1.2 reader takes it; no YAML writer needed)."""
        import json

        total = sum(n for _, n in self.counts.values())
        start = self.first_ns or 0
        duration = max(0, self.last_ns - start)
        info = {"rosbag2_bagfile_information": {
            "version": ROSBAG2_VERSION, "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": total,
            "topics_with_message_count": [{
                "topic_metadata": {"name": topic, "type": ros_type,
                                   "serialization_format": "cdr", "offered_qos_profiles": [],
                                   "type_description_hash": type_hash(ros_type)},
                "message_count": n} for topic, (ros_type, n) in sorted(self.counts.items())],
            "compression_format": "", "compression_mode": "",
            "relative_file_paths": [recording],
            "files": [{"path": recording, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": total}],
            "custom_data": {}, "ros_distro": DISTRIBUTION}}
        path = folder / "metadata.yaml"
        path.write_text(json.dumps(info, indent=1) + "\n")
        return path
