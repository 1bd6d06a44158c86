"""Figures like the paper's Fig. 4 (trajectories), Fig. 5 (errors), Fig. 6
(distances, torques), drawn from a run's time series. Headless (Agg).

For a reader of the paper (docs/outputs.md): robots drawn as bodies with a heading
arrow at every scale (enlarged, and said so, where to scale they would be dots), the
desired formation paths x0 + rho_i dashed beside the travelled ones, a unit on every
axis and every threshold line labelled, legends beside the axes (never over the data),
and under each figure its caption (deploy/report/figure_captions.py: where the run differs from
the paper and why, with the doc that explains it), also written to CAPTIONS.md.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, FancyArrow  # noqa: E402
from matplotlib.patches import Polygon as PolygonPatch  # noqa: E402

from deploy.contract.scenario import Scenario  # noqa: E402
from deploy.report.figure_captions import Captions, body_scale, captions  # noqa: E402
from deploy.report.metrics import leader_estimate_error  # noqa: E402
from deploy.report.palette import COLORS  # noqa: E402
from deploy.report.run_folder import FIGURE_FILES
from deploy.report.timeseries import TimeSeries  # noqa: E402
from plant.shapes import offset_outline  # noqa: E402

SNAPSHOT_TIMES_S = (0.0, 0.96, 8.4, 10.8, 15.0, 24.0)  # the paper's Fig. 4 snapshots
MIN_BODY_FRACTION = 0.015  # a robot is drawn at least this fraction of the plot's extent
MIN_OBSTACLE_FRACTION = 0.004  # ... and a point obstacle this fraction
CAPTION_WIDTH = 150  # characters per caption line under a figure
LEGEND = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "fontsize": 8, "borderaxespad": 0.0}


def _color(i: int) -> str:
    return COLORS[i % len(COLORS)]


def _snapshot_indices(t: np.ndarray) -> list[int]:
    idx = [int(np.searchsorted(t, ts)) for ts in SNAPSHOT_TIMES_S if ts <= t[-1] + 1e-9]
    return sorted({min(k, len(t) - 1) for k in idx} | {len(t) - 1})


def _extent(sc: Scenario, ts: TimeSeries) -> float:
    """The larger side of the box holding the leader's and the robots' paths (m)."""
    pts = np.concatenate([ts.leader_q[:, :2], ts.q[:, :, :2].reshape(-1, 2)])
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        return 1.0
    return float(max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1]), 1e-3))


def _trajectory_size(ts: TimeSeries, caption: str) -> tuple[float, float]:
    """A figure whose axes have the paths' aspect (equal scales): no empty bands."""
    pts = np.concatenate([ts.leader_q[:, :2], ts.q[:, :, :2].reshape(-1, 2)])
    pts = pts[np.isfinite(pts).all(axis=1)]
    ratio = 1.0 if not len(pts) else (np.ptp(pts[:, 1]) + 1e-3) / (np.ptp(pts[:, 0]) + 1e-3)
    width = 12.0
    axes_h = float(np.clip(0.6 * width * ratio, 3.5, 9.0))  # the axes: ~60 % of the width
    lines = len(caption) // CAPTION_WIDTH + 1 if caption else 0
    return width, axes_h + 1.3 + 0.14 * lines


def draw_robot(ax, x: float, y: float, phi: float, radius: float, color: str,
               lw: float = 1.0) -> None:
    """A robot as its body (a circle of ``radius``) and an arrow from its centre along
    its heading, 1.8 radii long (visible at every scale: ``radius`` is the drawn one)."""
    ax.add_patch(Circle((x, y), radius, fill=True, facecolor="white", edgecolor=color, lw=lw,
                        zorder=3))
    ax.add_patch(FancyArrow(x, y, 1.8 * radius * math.cos(phi), 1.8 * radius * math.sin(phi),
                            width=0.18 * radius, head_width=0.8 * radius,
                            head_length=0.6 * radius, length_includes_head=True,
                            color=color, lw=0, zorder=4))


def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.15)
    plt.close(fig)


def _layout(fig, caption: str) -> None:
    """Room on the right for the legends and at the bottom for the caption, wrapped."""
    import textwrap

    wrapped = textwrap.fill(caption, CAPTION_WIDTH) if caption else ""
    lines = wrapped.count("\n") + 1 if wrapped else 0
    bottom = (0.14 * lines + 0.1) / fig.get_size_inches()[1] if lines else 0.0
    fig.tight_layout(rect=(0.0, bottom, 0.84, 1.0))
    if wrapped:
        fig.text(0.01, 0.01, wrapped, fontsize=7, va="bottom", ha="left")


def fig_trajectories(sc: Scenario, ts: TimeSeries, path: Path, caption: str = "") -> None:
    _save(trajectories_figure(sc, ts, caption), path)


def trajectories_figure(sc: Scenario, ts: TimeSeries, caption: str = ""):
    """Fig. 4: leader path, robot paths and their desired formation paths, obstacles with
    their R_a band, the robots' bodies and headings at the snapshot times."""
    s = sc.spec
    extent = _extent(sc, ts)
    drawn = s.robot.body_radius_m * body_scale(sc, extent, MIN_BODY_FRACTION)
    point = MIN_OBSTACLE_FRACTION * extent
    r_a = s.behaviors.obstacle_safe_distance_m
    fig, ax = plt.subplots(figsize=_trajectory_size(ts, caption))
    ax.plot(ts.leader_q[:, 0], ts.leader_q[:, 1], "b--", lw=2, label="virtual leader")
    for i, rid in enumerate(sc.robot_ids):
        ax.plot(ts.q[:, i, 0], ts.q[:, i, 1], "-", color=_color(i), lw=1.5, label=f"robot {rid}")
        ax.plot(ts.target[:, i, 0], ts.target[:, i, 1], "--", color=_color(i), lw=0.9, alpha=0.7,
                label=f"robot {rid} desired x0 + rho_{rid}")
    for o in s.obstacles:
        ax.add_patch(Circle(o.position, max(o.radius_m, point), color="0.3"))
        ax.add_patch(Circle(o.position, o.radius_m + r_a, fill=False, ls=":", color="0.3"))
    for poly in sc.obstacle_shapes():  # walls and polygons, with their R_a band
        ax.add_patch(PolygonPatch(poly.array, closed=True, color="0.3"))
        ax.add_patch(PolygonPatch(offset_outline(poly, r_a), closed=True, fill=False, ls=":",
                                  color="0.3"))
    if s.obstacles or s.walls or s.polygons:
        ax.plot([], [], ls=":", color="0.3", label=f"R_a = {r_a:g} m from obstacle surface")
    for k in _snapshot_indices(ts.t):
        for i in range(sc.n):
            x, y, phi = ts.q[k, i]
            if np.isfinite(ts.q[k, i]).all():
                draw_robot(ax, x, y, phi, drawn, _color(i), lw=1.2)
        ax.annotate(f"t = {ts.t[k]:.2f} s", ts.q[k, 0, :2], fontsize=7, xytext=(6, 6),
                    textcoords="offset points")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="box")
    ax.grid(True, alpha=0.3)
    ax.legend(**LEGEND)
    scale = drawn / s.robot.body_radius_m
    note = "" if scale <= 1.0 else f", robots drawn {scale:.2g}x their size"
    ax.set_title(f"{s.name}: trajectories and desired formation paths{note}", fontsize=10)
    _layout(fig, caption)
    return fig


def fig_errors(sc: Scenario, ts: TimeSeries, path: Path, caption: str = "") -> None:
    _save(errors_figure(sc, ts, caption), path)


def errors_figure(sc: Scenario, ts: TimeSeries, caption: str = ""):
    """Fig. 5: (a) FDB task error, (b) leader estimate error at the same instant
    (metrics.leader_estimate_error), (c) tracking error with the settling band and bound."""
    bound = math.sqrt(2.0) * sc.spec.controller.T_p
    band = sc.spec.metrics.settle_threshold
    panels = (
        ("(a) FDB task error |x - x_fd|", "m", ts.t, ts.fdb_error),
        ("(b) leader estimate error |p0_hat_i - p0|", "m", ts.t[1:], leader_estimate_error(ts)),
        ("(c) behavioral tracking error |q - q_d|", "m, rad", ts.t, np.linalg.norm(ts.e, axis=2)),
    )
    fig, axes = plt.subplots(3, 1, figsize=(11, 9.5), sharex=True)
    for ax, (title, unit, t, data) in zip(axes, panels, strict=True):
        for i, rid in enumerate(sc.robot_ids):
            ax.plot(t, data[:, i], color=_color(i), lw=1.2, label=f"robot {rid}")
        ax.set_yscale("symlog", linthresh=1e-2)
        ax.set_title(title, fontsize=10, loc="left")
        ax.set_ylabel(f"({unit}), symlog")
        ax.grid(True, alpha=0.3)
    axes[2].axvline(bound, color="k", ls="--", lw=1, label=f"sqrt(2) T_p = {bound:.3f} s")
    axes[2].axhline(band, color="0.4", ls=":", lw=1.2,
                    label=f"settling band {band:g} ({band * 100:g} cm)")
    for ax in axes:
        ax.legend(**LEGEND)
    axes[2].set_xlabel("t (s)")
    _layout(fig, caption)
    return fig


def fig_distances(sc: Scenario, ts: TimeSeries, path: Path, caption: str = "") -> None:
    _save(distances_figure(sc, ts, caption), path)


def distances_figure(sc: Scenario, ts: TimeSeries, caption: str = ""):
    """Fig. 6: (a) centre to the nearest obstacle surface, (b) centre distance to the
    nearest robot (as the paper plots them; the metrics' gaps are these minus r, 2r),
    (c) the largest wheel torque."""
    s = sc.spec
    r = s.robot.body_radius_m
    pos = ts.q[:, :, :2]
    fig, axes = plt.subplots(3, 1, figsize=(11, 9.5), sharex=True)
    det = s.behaviors.detection_range_m
    gaps = sc.obstacle_gaps(pos)  # (k, n, m) surface to surface, discs, walls, polygons
    if gaps.shape[2]:
        d = gaps.min(axis=2) + r  # robot centre to the nearest obstacle surface
        for i, rid in enumerate(sc.robot_ids):
            axes[0].plot(ts.t, np.where(d[:, i] <= det, d[:, i], np.nan), color=_color(i),
                         label=f"robot {rid}")
        axes[0].axhline(s.behaviors.obstacle_safe_distance_m, color="k", ls="--", lw=1,
                        label=f"R_a = {s.behaviors.obstacle_safe_distance_m:g} m (FOCB)")
        axes[0].axhline(r, color="r", ls=":", lw=1, label=f"contact: r = {r:g} m")
    axes[0].set_title("(a) robot centre to the nearest obstacle surface, within r_det",
                      fontsize=10, loc="left")
    axes[0].set_ylabel("(m)")
    if sc.n > 1:
        dd = np.linalg.norm(pos[:, :, None, :] - pos[:, None, :, :], axis=3)
        dd[:, np.arange(sc.n), np.arange(sc.n)] = np.inf
        nearest = dd.min(axis=2)
        for i, rid in enumerate(sc.robot_ids):
            axes[1].plot(ts.t, np.where(nearest[:, i] <= det, nearest[:, i], np.nan),
                         color=_color(i), label=f"robot {rid}")
        axes[1].axhline(s.behaviors.robot_safe_distance_m, color="k", ls="--", lw=1,
                        label=f"R_c = {s.behaviors.robot_safe_distance_m:g} m (FRCB)")
        axes[1].axhline(2 * r, color="r", ls=":", lw=1, label=f"contact: 2r = {2 * r:g} m")
    axes[1].set_title("(b) centre distance to the nearest robot, within r_det", fontsize=10,
                      loc="left")
    axes[1].set_ylabel("(m)")
    for i, rid in enumerate(sc.robot_ids):
        axes[2].plot(ts.t, np.abs(ts.torque[:, i]).max(axis=1), color=_color(i), lw=0.8,
                     label=f"robot {rid}")
    if math.isfinite(s.limits.max_wheel_torque_nm):
        axes[2].axhline(s.limits.max_wheel_torque_nm, color="k", ls="--", lw=1,
                        label=f"limit {s.limits.max_wheel_torque_nm:g} N m")
    axes[2].set_yscale("symlog", linthresh=1.0)
    axes[2].set_title("(c) largest wheel torque |u|_inf", fontsize=10, loc="left")
    axes[2].set_ylabel("(N m), symlog")
    axes[2].set_xlabel("t (s)")
    for ax in axes:
        mark_safety_filter(ax, ts)
        ax.grid(True, alpha=0.3)
        ax.legend(**LEGEND)
    _layout(fig, caption)
    return fig


def mark_safety_filter(ax, ts: TimeSeries) -> None:
    """Shade the spans where the safety filter changed some robot's command (docs/safety.md);
    nothing where it never acted, so a run it left alone looks like the paper's."""
    acting = ts.safety_active.any(axis=1)
    if not acting.any():
        return
    edges = np.flatnonzero(np.diff(np.concatenate([[0], acting.astype(int), [0]])))
    for n, (a, b) in enumerate(zip(edges[::2], edges[1::2], strict=True)):
        t1 = ts.t[b] if b < len(ts.t) else ts.t[-1]
        ax.axvspan(ts.t[a], t1, color="orange", alpha=0.25, lw=0,
                   label="safety filter acted" if n == 0 else None)


def warm_up() -> None:
    """What a first figure costs besides its drawing, paid ahead (a figure process that
    waits for its run): the fonts loaded, the mathtext parser built (a log axis labels its
    ticks 10^k in mathtext), the PNG encoder loaded. Draws a small log-scale plot with a
    legend and a text into memory."""
    import io

    fig, ax = plt.subplots(figsize=(2.0, 1.5))
    ax.semilogy([0.0, 1.0], [1e-3, 1e2], label="warm")
    ax.set_xlabel("t (s)")
    ax.legend(**LEGEND)
    fig.text(0.01, 0.01, "caption", fontsize=7)
    _layout(fig, "")
    fig.savefig(io.BytesIO(), format="png", dpi=110, bbox_inches="tight", pad_inches=0.15)
    plt.close(fig)


def write_figures(sc: Scenario, ts: TimeSeries, out_dir: Path,
                  only: tuple[int, ...] = (0, 1, 2), notes: bool = True) -> list[Path]:
    """The three figures, each with its caption under it, and CAPTIONS.md beside them.
    ``only``: which of the figures (0: Fig. 4, 1: Fig. 5, 2: Fig. 6); ``notes``: whether
    CAPTIONS.md too (two processes drawing a run's figures share them out)."""
    paths = [out_dir / name for name in FIGURE_FILES[:3]]
    caps: Captions = captions(sc, ts, body_scale(sc, _extent(sc, ts), MIN_BODY_FRACTION))
    drawn = []
    for n, (fn, p, text) in enumerate(zip((fig_trajectories, fig_errors, fig_distances), paths,
                                          (caps.fig4, caps.fig5, caps.fig6), strict=True)):
        if n in only:
            fn(sc, ts, p, text)
            drawn.append(p)
    if notes:
        drawn.append(out_dir / FIGURE_FILES[3])
        drawn[-1].write_text(caps.markdown(sc.name))
    return drawn
