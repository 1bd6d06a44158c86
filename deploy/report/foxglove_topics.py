"""Every topic, frame and rate of what omnifleet shows in Foxglove, in one place:
the scene (``deploy/report/foxglove_scene.py``), the plot signals
(``deploy/report/foxglove_plots.py``), the recording, the live view and the layout
(``deploy/report/foxglove_layout.py``) all take them from here."""

from __future__ import annotations

from deploy.contract.scenario import Scenario

WORLD_FRAME = "world"
LEADER_FRAME = "leader"
SCENE_OBSTACLES = "/scene/obstacles"
SCENE_ROBOTS = "/scene/robots"
SCENE_FORMATION = "/scene/formation"
SCENE_BEHAVIORS = "/scene/behaviors"
SCENE_TRACES = "/scene/traces"
SCENE_TOPICS = (SCENE_OBSTACLES, SCENE_ROBOTS, SCENE_FORMATION, SCENE_BEHAVIORS, SCENE_TRACES)
TF_TOPIC = "/tf"
POSES_TOPIC = "/robots/poses"
LEADER_POSE_TOPIC = "/leader/pose"
FRAME_TOPICS = (TF_TOPIC, POSES_TOPIC, LEADER_POSE_TOPIC)
PLOT_FLEET = "/plot/fleet"

SCENE_RATE_HZ = 30.0  # scenes per simulated second in a recording (a display's rate)
PLOT_RATE_HZ = 250.0  # plot rows per simulated second at most (Fig. 5's transients last ~0.4 s)


def robot_frame(rid: int) -> str:
    return f"robot-{rid}"


def plot_topic(rid: int) -> str:
    return f"/plot/robot/{rid}"


def plot_topics(sc: Scenario) -> list[str]:
    return [*(plot_topic(r) for r in sc.robot_ids), PLOT_FLEET]


def stride(sc: Scenario, rate_hz: float) -> int:
    """Steps between two messages at (at most) ``rate_hz``."""
    return max(1, int(round(1.0 / (rate_hz * sc.dt))))
