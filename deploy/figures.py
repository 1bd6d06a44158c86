"""Figures like the paper's Fig. 4 (trajectories), Fig. 5 (errors), Fig. 6
(distances, torques), drawn from a run's time series. Headless (Agg)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402
from matplotlib.patches import Polygon as PolygonPatch  # noqa: E402

from deploy.palette import COLORS  # noqa: E402
from deploy.scenario import Scenario  # noqa: E402
from deploy.timeseries import TimeSeries  # noqa: E402
from plant.shapes import offset_outline  # noqa: E402

SNAPSHOT_TIMES_S = (0.0, 0.96, 8.4, 10.8, 15.0, 24.0)  # the paper's Fig. 4 snapshots


def _color(i: int) -> str:
    return COLORS[i % len(COLORS)]


def _snapshot_indices(t: np.ndarray) -> list[int]:
    idx = [int(np.searchsorted(t, ts)) for ts in SNAPSHOT_TIMES_S if ts <= t[-1] + 1e-9]
    return sorted({min(k, len(t) - 1) for k in idx} | {len(t) - 1})


def fig_trajectories(sc: Scenario, ts: TimeSeries, path: Path) -> None:
    """Fig. 4: leader path, robot paths, obstacles with R_a circles, snapshots."""
    s = sc.spec
    r = s.robot.body_radius_m
    fig, ax = plt.subplots(figsize=(9, 7))
    ax.plot(ts.leader_q[:, 0], ts.leader_q[:, 1], "b--", lw=2, label="virtual leader")
    for i, rid in enumerate(sc.robot_ids):
        ax.plot(ts.q[:, i, 0], ts.q[:, i, 1], "-", color=_color(i), lw=1.5, label=f"robot {rid}")
    for o in s.obstacles:
        ax.add_patch(Circle(o.position, max(o.radius_m, 0.15), color="0.3"))
        ax.add_patch(
            Circle(o.position, o.radius_m + s.behaviors.obstacle_safe_distance_m,
                   fill=False, ls=":", color="0.3")
        )
    for poly in sc.obstacle_shapes():  # walls and polygons, with their R_a band
        ax.add_patch(PolygonPatch(poly.array, closed=True, color="0.3"))
        ax.add_patch(PolygonPatch(offset_outline(poly, s.behaviors.obstacle_safe_distance_m),
                                  closed=True, fill=False, ls=":", color="0.3"))
    for k in _snapshot_indices(ts.t):
        for i in range(sc.n):
            x, y, phi = ts.q[k, i]
            ax.add_patch(Circle((x, y), r, fill=False, color=_color(i), lw=1))
            ax.plot([x, x + r * math.cos(phi)], [y, y + r * math.sin(phi)], color=_color(i), lw=1)
        ax.annotate(f"t={ts.t[k]:.2f}s", ts.q[k, 0, :2], fontsize=7, xytext=(4, 4),
                    textcoords="offset points")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{s.name}: trajectories (dotted: obstacle safety radius R_a)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_errors(sc: Scenario, ts: TimeSeries, path: Path) -> None:
    """Fig. 5: (a) FDB task error, (b) estimator error, (c) tracking error."""
    bound = math.sqrt(2.0) * sc.spec.controller.T_p
    est_err = np.linalg.norm(ts.q0_hat[:, :, :2] - ts.leader_q[:, None, :2], axis=2)
    panels = (
        ("(a) |task error| of FDB (m)", ts.fdb_error),
        ("(b) |leader estimate - leader| (m)", est_err),
        ("(c) |behavioral tracking error q - q_d|", np.linalg.norm(ts.e, axis=2)),
    )
    fig, axes = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
    for ax, (title, data) in zip(axes, panels, strict=False):
        for i, rid in enumerate(sc.robot_ids):
            ax.plot(ts.t, data[:, i], color=_color(i), lw=1.2, label=f"robot {rid}")
        ax.set_yscale("symlog", linthresh=1e-2)
        ax.set_title(title, fontsize=10, loc="left")
        ax.grid(True, alpha=0.3)
    axes[2].axvline(bound, color="k", ls="--", lw=1)
    axes[2].axhline(sc.spec.metrics.settle_threshold, color="0.5", ls=":", lw=1)
    axes[2].text(bound, axes[2].get_ylim()[1] * 0.5, f" sqrt(2) T_p = {bound:.3f} s", fontsize=8)
    axes[0].legend(fontsize=8)
    axes[2].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_distances(sc: Scenario, ts: TimeSeries, path: Path) -> None:
    """Fig. 6: (a) nearest obstacle, (b) nearest robot (centre distances), (c) |u|."""
    s = sc.spec
    r = s.robot.body_radius_m
    pos = ts.q[:, :, :2]
    fig, axes = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
    det = s.behaviors.detection_range_m
    gaps = sc.obstacle_gaps(pos)  # (k, n, m) surface to surface, discs, walls, polygons
    if gaps.shape[2]:
        d = gaps.min(axis=2) + r  # robot centre to the nearest obstacle surface
        for i, rid in enumerate(sc.robot_ids):
            axes[0].plot(ts.t, np.where(d[:, i] <= det, d[:, i], np.nan), color=_color(i),
                         label=f"robot {rid}")
        axes[0].axhline(s.behaviors.obstacle_safe_distance_m, color="k", ls="--", lw=1,
                        label="R_a")
        axes[0].axhline(r, color="r", ls=":", lw=1, label="contact (point obstacle)")
    axes[0].set_title("(a) distance to the nearest obstacle within r_det (m)", fontsize=10,
                      loc="left")
    if sc.n > 1:
        dd = np.linalg.norm(pos[:, :, None, :] - pos[:, None, :, :], axis=3)
        dd[:, np.arange(sc.n), np.arange(sc.n)] = np.inf
        nearest = dd.min(axis=2)
        for i, rid in enumerate(sc.robot_ids):
            axes[1].plot(ts.t, np.where(nearest[:, i] <= det, nearest[:, i], np.nan),
                         color=_color(i), label=f"robot {rid}")
        axes[1].axhline(s.behaviors.robot_safe_distance_m, color="k", ls="--", lw=1, label="R_c")
        axes[1].axhline(2 * r, color="r", ls=":", lw=1, label="contact 2r")
    axes[1].set_title("(b) distance to the nearest robot within r_det (m)", fontsize=10,
                      loc="left")
    for i, rid in enumerate(sc.robot_ids):
        axes[2].plot(ts.t, np.linalg.norm(ts.torque[:, i], axis=1), color=_color(i),
                     label=f"robot {rid}")
    axes[2].set_yscale("symlog", linthresh=1.0)
    axes[2].set_title("(c) |u| wheel torque norm (N m)", fontsize=10, loc="left")
    axes[2].set_xlabel("t (s)")
    for ax in axes:
        mark_safety_filter(ax, ts)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def mark_safety_filter(ax, ts: TimeSeries) -> None:
    """Shade the spans where the safety filter changed some robot's command (issue 17);
    nothing where it never acted, so a run it left alone looks like the paper's."""
    acting = ts.safety_active.any(axis=1)
    if not acting.any():
        return
    edges = np.flatnonzero(np.diff(np.concatenate([[0], acting.astype(int), [0]])))
    for n, (a, b) in enumerate(zip(edges[::2], edges[1::2], strict=True)):
        t1 = ts.t[b] if b < len(ts.t) else ts.t[-1]
        ax.axvspan(ts.t[a], t1, color="orange", alpha=0.25, lw=0,
                   label="safety filter acted" if n == 0 else None)


def write_figures(sc: Scenario, ts: TimeSeries, out_dir: Path) -> list[Path]:
    paths = [out_dir / "fig4_trajectories.png", out_dir / "fig5_errors.png",
             out_dir / "fig6_distances_torques.png"]
    for fn, p in zip((fig_trajectories, fig_errors, fig_distances), paths, strict=False):
        fn(sc, ts, p)
    return paths
