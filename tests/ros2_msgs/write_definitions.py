"""Write the .msg files of every ROS 2 type the fleet publishes (and their dependencies)
into this folder, as ``<package>/msg/<Type>.msg``, for tests that need ROS 2's definitions
without fetching anything (zenoh-ros2-sdk computes its own RIHS01 hashes from them).

The text is ``rosbags``' Jazzy store's (generated from the distribution's .msg files; it
keeps fields and constants, not comments or default values, which RIHS01 does not hash).
Run once when a type is added: ``python tests/ros2_msgs/write_definitions.py``."""

from __future__ import annotations

from pathlib import Path

from deploy.ros2 import fleet_messages as fm
from deploy.ros2.types import definition

HERE = Path(__file__).parent
SEPARATOR = "=" * 80 + "\n"


def write(ros_type: str) -> list[Path]:
    parts = definition(ros_type).split(SEPARATOR)
    sections = [(ros_type, parts[0])] + [
        (head.removeprefix("MSG: ").replace("/", "/msg/", 1), body)
        for head, _, body in (p.partition("\n") for p in parts[1:])]
    written = []
    for name, text in sections:
        package, _, type_name = name.split("/")
        path = HERE / package / "msg" / f"{type_name}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text.rstrip("\n") + "\n")
        written.append(path)
    return written


if __name__ == "__main__":
    for t in (fm.ODOM, fm.CMD_VEL, fm.JOINTS, fm.POSE, fm.TF, fm.MARKERS, fm.STATUS, fm.CLOCK,
              fm.TWIST):
        write(t)
    print(sorted(str(p.relative_to(HERE)) for p in HERE.glob("*/msg/*.msg")))
