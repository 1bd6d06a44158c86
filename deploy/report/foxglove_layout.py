"""The Foxglove layout for a run (``docs/foxglove-layout.json``), arranged like
the paper's figures: the scene from above (Fig. 4) on the left; on the right the
tracking and formation errors (Fig. 5), the distances and wheel torques
(Fig. 6) and the active behaviors over time.

Written in the layout-file format Foxglove's and Lichtblick's "Import from
file..." read (``configById`` + ``layout``), from the topic names of
``deploy/report/foxglove_scene.py``, so the file cannot name a topic that does not
exist (a test regenerates it and compares). Regenerate with
``python -m deploy.report.foxglove_layout [SCENARIO] > docs/foxglove-layout.json``.
"""

from __future__ import annotations

import json
import sys
from typing import Any

from deploy.contract.scenario import Scenario, load_scenario
from deploy.report.foxglove_topics import (
    LEADER_POSE_TOPIC,
    PLOT_FLEET,
    POSES_TOPIC,
    SCENE_BEHAVIORS,
    SCENE_FORMATION,
    SCENE_OBSTACLES,
    SCENE_ROBOTS,
    SCENE_TRACES,
    WORLD_FRAME,
    plot_topic,
)
from deploy.report.palette import COLORS

SCENE_PANEL = "3D!fleet"
PANELS = {
    "tracking": "Plot!fig5-tracking",
    "formation": "Plot!fig5-formation",
    "distances": "Plot!fig6-distances",
    "torques": "Plot!fig6-torques",
    "behaviors": "StateTransitions!behaviors",
}


def _series(value: str, label: str, color: str | None = None) -> dict[str, Any]:
    s = {"value": value, "enabled": True, "timestampMethod": "receiveTime", "label": label}
    return s | ({"color": color} if color else {})


def _plot(title: str, paths: list[dict[str, Any]], y_label: str) -> dict[str, Any]:
    return {"foxglovePanelTitle": title, "paths": paths, "showXAxisLabels": True,
            "showYAxisLabels": True, "showLegend": True, "legendDisplay": "floating",
            "showPlotValuesInLegend": False, "isSynced": True, "xAxisVal": "timestamp",
            "sidebarDimension": 240, "yAxisLabel": y_label}


def _per_robot(sc: Scenario, field: str, what: str = "") -> list[dict[str, Any]]:
    return [_series(f"{plot_topic(r)}.{field}", f"robot {r}{what}", COLORS[i % len(COLORS)])
            for i, r in enumerate(sc.robot_ids)]


def _scene() -> dict[str, Any]:
    visible = {t: {"visible": True} for t in (SCENE_OBSTACLES, SCENE_TRACES, SCENE_FORMATION,
                                              SCENE_BEHAVIORS, SCENE_ROBOTS)}
    hidden = {t: {"visible": False} for t in (POSES_TOPIC, LEADER_POSE_TOPIC)}
    return {
        "foxglovePanelTitle": "Fig. 4: the fleet (scene)",
        "cameraState": {"perspective": False, "distance": 110.0, "phi": 0.0, "thetaOffset": 90.0,
                        "target": [0.0, 0.0, 0.0], "targetOffset": [0.0, -3.0, 0.0],
                        "targetOrientation": [0.0, 0.0, 0.0, 1.0], "fovy": 45.0, "near": 0.5,
                        "far": 5000.0},
        "followMode": "follow-none", "followTf": WORLD_FRAME,
        "scene": {"enableStats": False, "transforms": {"showLabel": False, "visible": False}},
        "transforms": {}, "topics": visible | hidden,
        "layers": {"grid": {"visible": True, "frameLocked": True, "label": "Grid (10 m)",
                            "instanceId": "grid", "layerId": "foxglove.Grid", "size": 120,
                            "divisions": 12, "lineWidth": 1, "color": "#24248e40",
                            "position": [0, 0, 0], "rotation": [0, 0, 0]}},
        "publish": {"type": "point", "poseTopic": "/move_base_simple/goal",
                    "pointTopic": "/clicked_point", "poseEstimateTopic": "/initialpose",
                    "poseEstimateXDeviation": 0.5, "poseEstimateYDeviation": 0.5,
                    "poseEstimateThetaDeviation": 0.26179939},
        "imageMode": {},
    }


def layout(sc: Scenario) -> dict[str, Any]:
    p = PANELS
    config = {
        SCENE_PANEL: _scene(),
        p["tracking"]: _plot("Fig. 5: behavioral tracking error |e| (settles below the band)", [
            *_per_robot(sc, "tracking_error"),
            _series(f"{PLOT_FLEET}.settle_threshold", "settling band", "#7f7f7f")], "|e|"),
        p["formation"]: _plot("Fig. 5: formation error and leader estimate error (m)", [
            *_per_robot(sc, "formation_error", " formation"),
            *[_series(f"{plot_topic(r)}.estimator_error", f"robot {r} estimator")
              for r in sc.robot_ids]], "m"),
        p["distances"]: _plot("Fig. 6: smallest gaps between surfaces (m; contact at 0)", [
            _series(f"{PLOT_FLEET}.min_obstacle_gap", "robot-obstacle gap", "#4d4d4d"),
            _series(f"{PLOT_FLEET}.min_robot_gap", "robot-robot gap", "#d62728"),
            *[_series(f"{plot_topic(r)}.safety_dv", f"robot {r} safety filter: |dv| (m/s)")
              for r in sc.robot_ids]], "m"),
        p["torques"]: _plot("Fig. 6: wheel torques (N m)", [
            _series(f"{plot_topic(r)}.torque[{j}]", f"robot {r} wheel {j + 1}",
                    COLORS[i % len(COLORS)] if j == 0 else None)
            for i, r in enumerate(sc.robot_ids) for j in range(4)], "N m"),
        p["behaviors"]: {"foxglovePanelTitle": "active behaviors (highest priority first)",
                         "paths": [{"value": f"{plot_topic(r)}.order", "timestampMethod": "receiveTime",
                                    "label": f"robot {r}"} for r in sc.robot_ids],
                         "isSynced": True},
    }
    right = {
        "first": {"first": p["tracking"], "second": p["formation"], "direction": "column"},
        "second": {"first": {"first": p["distances"], "second": p["torques"], "direction": "column"},
                   "second": p["behaviors"], "direction": "column", "splitPercentage": 78},
        "direction": "column", "splitPercentage": 48,
    }
    return {"configById": config, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1.0},
            "layout": {"first": SCENE_PANEL, "second": right, "direction": "row",
                       "splitPercentage": 50}}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    print(json.dumps(layout(load_scenario(argv[0] if argv else "paper")), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
