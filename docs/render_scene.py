"""Draw the scene of a recording with matplotlib, from the decoded messages —
what Foxglove's 3D panel shows, seen from above — beside the run's own Fig. 4
(``fig4_trajectories.png``, drawn from the time series like the paper's).

    python docs/render_scene.py RUN_DIR docs/foxglove-scene.png

Needs the test extra (``google.protobuf``: the scene is decoded from the
recording's own protobuf schemas, as Foxglove decodes it).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.image as mpimg  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
from mcap.reader import make_reader  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from foxglove_decode import decode  # noqa: E402

from deploy.report.figures import SNAPSHOT_TIMES_S  # noqa: E402
from deploy.report.foxglove_topics import SCENE_BEHAVIORS, SCENE_OBSTACLES, SCENE_ROBOTS, SCENE_TRACES  # noqa: E402

TOPICS = (SCENE_OBSTACLES, SCENE_TRACES, SCENE_BEHAVIORS, SCENE_ROBOTS)


def _rgba(c) -> tuple[float, float, float, float]:
    return (c.r, c.g, c.b, c.a)


def scenes_at(path: Path, times_s) -> tuple[dict, dict]:
    """{topic: last SceneUpdate} at the end, and {t: {topic: SceneUpdate}} at each
    snapshot time (the last scene at or before it)."""
    marks = sorted(int(round(t * 1e9)) for t in times_s)
    snaps: dict[int, dict] = {m: {} for m in marks}
    last: dict[str, object] = {}
    with open(path, "rb") as f:
        for schema, ch, msg in make_reader(f).iter_messages(topics=list(TOPICS)):
            value = decode(schema.name, schema.encoding, schema.data, ch.message_encoding, msg.data)
            last[ch.topic] = value
            for m in marks:
                if msg.log_time <= m:
                    snaps[m][ch.topic] = value
    return last, snaps


def _draw_lines(ax, line, **kw) -> None:
    pts = [(p.x, p.y) for p in line.points]
    if not pts:
        return
    color = _rgba(line.color)
    if line.type == 2:  # LINE_LIST: pairs
        for a, b in zip(pts[0::2], pts[1::2]):
            ax.plot([a[0], b[0]], [a[1], b[1]], color=color, lw=0.8, **kw)
        return
    if line.type == 1:  # LINE_LOOP
        pts = [*pts, pts[0]]
    ax.plot([p[0] for p in pts], [p[1] for p in pts], color=color, lw=1.0, **kw)


def _draw_bodies(ax, update, label_time: float | None = None) -> None:
    for e in update.entities:
        for c in e.cylinders:
            p = c.pose.position
            ax.add_patch(plt.Circle((p.x, p.y), c.size.x / 2, color=_rgba(c.color), fill=False
                                    if e.id.startswith("robot") else True, lw=1.2))
        for a in e.arrows:
            p, q = a.pose.position, a.pose.orientation
            yaw = 2 * math.atan2(q.z, q.w)
            ax.plot([p.x, p.x + a.shaft_length * math.cos(yaw)],
                    [p.y, p.y + a.shaft_length * math.sin(yaw)], color=_rgba(a.color), lw=1.0)
        for line in e.lines:
            _draw_lines(ax, line)
    if label_time is not None:
        robot = next((e for e in update.entities if e.id.startswith("robot-")), None)
        if robot is not None:
            p = robot.cylinders[0].pose.position
            ax.annotate(f"t={label_time:.2f}s", (p.x, p.y), fontsize=7, xytext=(4, 4),
                        textcoords="offset points")


def render(run_dir: Path, out: Path) -> None:
    last, snaps = scenes_at(run_dir / "recording.mcap", SNAPSHOT_TIMES_S)
    fig4 = run_dir / "fig4_trajectories.png"
    fig, axes = plt.subplots(1, 2 if fig4.exists() else 1, figsize=(16 if fig4.exists() else 9, 7))
    ax = axes[0] if fig4.exists() else axes
    for line in (ln for e in last[SCENE_TRACES].entities for ln in e.lines):
        _draw_lines(ax, line)
    for e in last[SCENE_OBSTACLES].entities:
        for c in e.cylinders:
            p = c.pose.position
            ax.add_patch(plt.Circle((p.x, p.y), c.size.x / 2, color=_rgba(c.color)))
        for line in e.lines:
            _draw_lines(ax, line)
    for m, topics in snaps.items():
        if SCENE_ROBOTS in topics:
            _draw_bodies(ax, topics[SCENE_ROBOTS], m * 1e-9)
        if SCENE_BEHAVIORS in topics:
            _draw_bodies(ax, topics[SCENE_BEHAVIORS])
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("the recording's scene topics, decoded (robots at the paper's snapshot times;\n"
                 "rings: R_a around obstacles, R_a/R_c around robots with FOCB/FRCB active)",
                 fontsize=9)
    if fig4.exists():
        axes[1].imshow(mpimg.imread(fig4))
        axes[1].set_axis_off()
        axes[1].set_title("the same run's fig4_trajectories.png (drawn like the paper's Fig. 4)",
                          fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    render(Path(sys.argv[1]), Path(sys.argv[2]))
