"""Figures a reader of the paper understands (docs/outputs.md), checked on what is drawn:
bodies with headings at every scale, desired formation paths, units and labelled
thresholds, legends beside the data; and captions computed from the run (erratum 16's
estimator lag, FRCB chatter at R_c) on series built here with known content."""

from __future__ import annotations

import math

import matplotlib
import numpy as np
import pytest
from matplotlib.patches import Circle, FancyArrow

from agents.leader import LeaderGenerator
from deploy.contract.scenario import load_scenario
from deploy.report.figure_captions import fig5_caption, fig6_caption
from deploy.report.figures import (
    MIN_BODY_FRACTION,
    distances_figure,
    errors_figure,
    trajectories_figure,
    write_figures,
)
from deploy.report.timeseries import BEHAVIOR_BITS, TimeSeries

matplotlib.use("Agg")


def leader_series(name: str, seconds: float, hz: float = 100.0):
    """A series of ``seconds`` with the scenario's true leader, robots parked at their
    formation points (x0 + offset, no rotation), estimates exact."""
    sc = load_scenario(name).with_control_rate(hz)
    steps = int(round(seconds * hz))
    ts = TimeSeries.allocate(steps, sc.n)
    gen = LeaderGenerator(sc.leader_spec(), sc.dt)
    offsets = np.array([r.offset for r in sc.spec.robots], float)
    for k in range(steps):
        q0, v0 = gen.state()
        q = np.column_stack([q0[:2] + offsets, np.full(sc.n, q0[2])])
        ts.record_world(k, k * sc.dt, q0, v0, q, np.zeros((sc.n, 3)), q[:, :2])
        gen.advance()
    ts.q0_hat[:-1] = ts.leader_q[1:, None, :]  # the estimate after step k is for t_{k+1}
    ts.q0_hat[-1] = ts.leader_q[-1]
    return sc, ts


def test_a_lagging_estimate_is_explained_by_erratum_16_with_its_numbers():
    sc, ts = leader_series("paper", 6.0)
    ts.q0_hat[:, :, 0] += 1.0  # 1 m off in x
    text = fig5_caption(sc, ts)
    assert "median after 5 s: 1, 1, 1 m" in text
    assert "iota_4 = 6 m/s^2, below it" in text and "erratum 16" in text
    assert "docs/errata.md" in text and "paper-consistent" in text
    # the leader's largest acceleration per axis, as erratum 16 gives it (40 and 64 m/s^2)
    assert "up to 40 / 64 m/s^2" in text


def test_an_estimate_that_converges_is_said_to():
    sc, ts = leader_series("lab", 6.0)
    text = fig5_caption(sc, ts)
    assert "median after 5 s: 0, 0, 0 m" in text and "converges close to zero" in text
    assert "errata" not in text.split("(b)")[1].split("(c)")[0].replace("erratum 16's", "")


@pytest.mark.parametrize("every, chatters", [(1, True), (50, False)])
def test_frcb_chatter_at_r_c_is_named_with_its_switches(every, chatters):
    sc, ts = leader_series("lab", 2.0)
    r_c = sc.spec.behaviors.robot_safe_distance_m
    ts.q[:, 1, :2] = ts.q[:, 0, :2] + [0.0, r_c]  # robot 2 sits at R_c from robot 1
    ts.q[:, 2, :2] = ts.q[:, 0, :2] + [0.0, -3.0]
    on = (np.arange(ts.steps) // every) % 2 == 1
    ts.active[:, 1] = BEHAVIOR_BITS["FDB"] | np.where(on, BEHAVIOR_BITS["FRCB"], 0)
    ts.torque[:, 1, 0] = np.where(on, 1.5, 0.1)
    text = fig6_caption(sc, ts)
    switches = int(np.count_nonzero(on[1:] != on[:-1]))
    named = f"robot 2: {switches} switches in 2 s near R_c, |u| up to 1.5 N m"
    assert (named in text) == chatters and ("docs/control-rate.md" in text) == chatters
    assert "robot 1:" not in text  # at R_c too, but its FRCB never switched: no chatter


def test_robots_are_bodies_with_heading_arrows_at_every_scale():
    for name, enlarged in (("paper", True), ("wall-gap", False)):
        sc, ts = leader_series(name, 1.0)
        r = sc.spec.robot.body_radius_m
        fig = trajectories_figure(sc, ts, "caption")
        ax = fig.axes[0]
        bodies = [p for p in ax.patches if isinstance(p, Circle) and p.get_zorder() == 3]
        arrows = [p for p in ax.patches if isinstance(p, FancyArrow)]
        snapshots = 3  # in 1 s: the paper's t = 0 and 0.96 s, and the last row
        assert len(bodies) == len(arrows) == snapshots * sc.n
        drawn = bodies[0].get_radius()
        extent = max(np.ptp(ts.q[:, :, 0]), np.ptp(ts.q[:, :, 1]), np.ptp(ts.leader_q[:, 0]),
                     np.ptp(ts.leader_q[:, 1]))
        if enlarged:  # to scale, a 0.5 m robot on an 80 m figure-of-eight is a dot
            assert drawn == pytest.approx(MIN_BODY_FRACTION * extent, rel=1e-6) and drawn > r
            assert f"robots drawn {drawn / r:.2g}x their size" in ax.get_title()
        else:
            assert drawn == r and "drawn" not in ax.get_title()
        # each arrow starts at its body's centre and points along the robot's heading
        for body, arrow in zip(bodies, arrows, strict=True):
            xy = arrow.get_xy()
            tip = xy[np.argmax(np.linalg.norm(xy - body.center, axis=1))]
            heading = math.atan2(tip[1] - body.center[1], tip[0] - body.center[0])
            k = np.flatnonzero(np.isclose(ts.q[:, :, 0], body.center[0]).any(axis=1))[0]
            i = int(np.flatnonzero(np.isclose(ts.q[k, :, 0], body.center[0]))[0])
            assert math.remainder(heading - ts.q[k, i, 2], 2 * math.pi) == pytest.approx(0, abs=1e-6)
        labels = [ln.get_label() for ln in ax.get_lines()]
        assert all(f"robot {rid} desired x0 + rho_{rid}" in labels for rid in sc.robot_ids)
        matplotlib.pyplot.close(fig)


def test_every_axis_has_a_unit_thresholds_are_labelled_and_legends_sit_beside_the_data():
    sc, ts = leader_series("lab", 1.0)
    for build in (trajectories_figure, errors_figure, distances_figure):
        fig = build(sc, ts, "caption")
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        for ax in fig.axes:
            assert "(" in ax.get_ylabel() and ")" in ax.get_ylabel(), (build, ax.get_title())
            legend = ax.get_legend()
            assert legend is not None
            # beside, never over, the plotting area
            assert legend.get_window_extent(renderer).x0 >= ax.get_window_extent(renderer).x1
            for line in ax.get_lines():
                xs = np.asarray(line.get_xdata(), float)
                if len(xs) == 2 and line.get_linestyle() in ("--", ":"):  # threshold lines
                    assert not line.get_label().startswith("_"), (build, ax.get_title())
        matplotlib.pyplot.close(fig)
    fig = errors_figure(sc, ts)
    labels = [ln.get_label() for ln in fig.axes[2].get_lines()]
    assert "settling band 0.05 (5 cm)" in labels and "sqrt(2) T_p = 5.657 s" in labels
    matplotlib.pyplot.close(fig)


def test_write_figures_writes_the_captions_beside_them(tmp_path):
    sc, ts = leader_series("wall-gap", 1.0)
    paths = write_figures(sc, ts, tmp_path)
    assert [p.name for p in paths] == ["fig4_trajectories.png", "fig5_errors.png",
                                       "fig6_distances_torques.png", "CAPTIONS.md"]
    from deploy.report.run_folder import RUN_OUTPUTS

    assert {p.name for p in paths} <= set(RUN_OUTPUTS)  # --overwrite removes them, no mixing
    text = (tmp_path / "CAPTIONS.md").read_text()
    for p in paths[:3]:
        assert p.stat().st_size > 10_000 and f"## {p.name}" in text
