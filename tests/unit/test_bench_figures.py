"""The pure parts of `omnifleet bench` (deploy/bench/): the generated scale scenarios, the
sizes it accepts, a figure judged against its target on its median, the memory figure
only where agents ran."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from deploy.bench.suite import SCALE_SIZES, Bench, Figure, Settings
from deploy.cli.bench import scale_sizes
from deploy.contract.scaled_scenarios import scale_scenario, tree_adjacency
from deploy.contract.scenario import has_spanning_tree, load_scenario


@pytest.mark.parametrize("n", [1, 3, 10, 30])
def test_scale_scenarios_load_with_a_spanning_tree_and_clear_start(n, tmp_path):
    path = tmp_path / f"scale-{n}.toml"
    path.write_text(scale_scenario(n))
    sc = load_scenario(path)
    assert sc.n == n and sc.dt == pytest.approx(0.01)
    assert has_spanning_tree(np.array(tree_adjacency(n), float), np.eye(1, n).ravel())
    q, _ = sc.initial_state()
    d = np.linalg.norm(q[:, None, :2] - q[None, :, :2], axis=2) + np.eye(n) * 1e9
    assert d.min() > 2 * sc.spec.robot.body_radius_m  # nobody starts touching


def test_scale_sizes_are_whole_numbers_from_1_to_100():
    assert scale_sizes("30,3,3") == (3, 30)
    for bad in ("", "3,x", "0", "101", "2.5"):
        with pytest.raises(argparse.ArgumentTypeError):
            scale_sizes(bad)
    assert SCALE_SIZES[-1] == 30  # the full run reaches the 30 robots


def test_figure_judges_its_target_on_the_median():
    f = Figure("x", "ms", "", [0.5, 2.0, 0.9], ("<=", 1.0))
    assert f.median == 0.9 and f.met is True
    assert Figure("y", "x", "", [9.0, 11.0, 8.0], (">=", 10.0)).met is False
    assert Figure("z", "x", "", []).met is None


def test_the_memory_figure_is_of_agents_that_ran(tmp_path):
    """`--only in-process` (or costs) starts no agent: no memory figure, so no "no figure
    for memory" and no exit 1 for a bench that measured all it was asked. A fleet that ran
    and reported no agent's memory is still a missing figure."""
    bench = Bench(tmp_path, Settings.of(True, 1), lambda msg: None)
    bench.run_all([])
    assert "memory.agent_peak_rss_mb" not in bench.figures
    bench.fleet_runs = 1
    bench.run_all([])
    assert bench.figures["memory.agent_peak_rss_mb"].error
    bench.agent_rss_mb = [58.0, 61.5]
    bench.figures.clear()
    bench.run_all([])
    assert bench.figures["memory.agent_peak_rss_mb"].median == 61.5
