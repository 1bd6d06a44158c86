"""Scenario schema: the bundled paper scenario, and bad files refused with file and key named.

Each bad variant is the bundled paper.toml with one edit, written to tmp_path.
"""

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from deploy.contract.scenario import SCENARIO_DIR, ScenarioError, load_scenario

REPO = Path(__file__).resolve().parents[2]
PAPER_TEXT = (SCENARIO_DIR / "paper.toml").read_text()


def variant(tmp_path, old, new, name="bad.toml"):
    """paper.toml with ``old`` replaced (exactly once) by ``new``, written under tmp_path."""
    assert PAPER_TEXT.count(old) == 1, f"paper.toml no longer contains {old!r} exactly once"
    path = tmp_path / name
    path.write_text(PAPER_TEXT.replace(old, new))
    return path


BAD = {
    "mistyped key": ("fdb_gains = [12.0, 0.25]", "fdb_gian = [12.0, 0.25]", "fdb_gian"),
    "adjacency 2x3": (
        "adjacency = [[1, 0, 0], [1, 0, 0], [1, 1, 0]]",
        "adjacency = [[1, 0, 0], [1, 0, 0]]",
        "graph.adjacency",
    ),
    "no spanning tree": ("leader = [1, 0, 0]", "leader = [0, 0, 0]", "graph"),
    "non-finite robot position": ("position = [4.4, -17.5]", "position = [nan, -17.5]", "robots[0]"),
    "infinite robot position": ("position = [16.4, -5.5]", "position = [16.4, inf]", "robots[2]"),
    "unknown behavior": (
        'enabled = ["FDB", "FOCB", "FRCB"]', 'enabled = ["FDB", "FOCB", "FRCX"]', "behaviors.enabled"
    ),
    "unknown priority name": (
        'priority = ["FOCB", "FRCB", "FDB"]', 'priority = ["FOCB", "FRCB", "FBD"]', "behaviors.priority"
    ),
    "duplicated robot id": ("id = 3", "id = 2", "robots.id"),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_scenario_is_refused_naming_file_and_key(tmp_path, case):
    """A ScenarioError whose message names the file and the offending key."""
    old, new, key = BAD[case]
    path = variant(tmp_path, old, new, name=f"bad-{case.replace(' ', '-')}.toml")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    assert path.name in message
    assert key in message


def test_non_finite_robot_position_names_the_position_key(tmp_path):
    """The message for position = [nan, ...] names robots[0].position, the offending key."""
    path = variant(tmp_path, "position = [4.4, -17.5]", "position = [nan, -17.5]")
    with pytest.raises(ScenarioError, match=r"robots\[0\]\.position"):
        load_scenario(path)


NON_FINITE_ELSEWHERE = {
    "obstacle position": ("position = [8.0, -2.0]", "position = [nan, -2.0]", "obstacles[4].position"),
    "duration": ("duration_s = 24.0", "duration_s = nan", "duration_s"),
    "FDB gain": ("fdb_gains = [12.0, 0.25]", "fdb_gains = [nan, 0.25]", "behaviors.fdb_gains"),
    "safety distance": (
        "obstacle_safe_distance_m = 2.0",
        "obstacle_safe_distance_m = nan",
        "behaviors.obstacle_safe_distance_m",
    ),
}


@pytest.mark.parametrize("case", list(NON_FINITE_ELSEWHERE), ids=list(NON_FINITE_ELSEWHERE))
def test_non_finite_values_elsewhere_are_refused(tmp_path, case):
    """nan in an obstacle position, the duration, a gain or a safety distance is a ScenarioError
    naming the file and the key (docs/scenarios.md: validated on load with clear errors)."""
    old, new, key = NON_FINITE_ELSEWHERE[case]
    path = variant(tmp_path, old, new)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert path.name in str(info.value) and key in str(info.value)


def _cli():
    exe = shutil.which("omnifleet") or str(Path(sys.executable).parent / "omnifleet")
    if Path(exe).exists():
        return [exe]
    return [sys.executable, "-m", "deploy.cli"]


@pytest.mark.parametrize("case", ["mistyped key", "no spanning tree"])
def test_cli_refuses_bad_scenario_with_exit_code_2(tmp_path, case):
    """`omnifleet run <bad file> --in-process` exits with 2 and stderr names file and key."""
    old, new, key = BAD[case]
    path = variant(tmp_path, old, new)
    r = subprocess.run(
        [*_cli(), "run", str(path), "--in-process", "--no-figures", "--out", str(tmp_path / "out")],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 2, r.stderr
    assert key in r.stderr and path.name in r.stderr
    assert not (tmp_path / "out").exists()


def test_self_loop_is_zeroed_and_reported(tmp_path):
    """The printed A has a_11 = 1 (eq. 49): the loader zeroes the diagonal and says so in
    scenario.notes (erratum 7); off-diagonal weights are kept."""
    assert "adjacency = [[1, 0, 0]" in PAPER_TEXT
    sc = load_scenario(SCENARIO_DIR / "paper.toml")
    np.testing.assert_array_equal(np.diag(sc.adjacency), 0.0)
    np.testing.assert_array_equal(sc.adjacency, [[0, 0, 0], [1, 0, 0], [1, 1, 0]])
    assert any("erratum 7" in note and "adjacency" in note for note in sc.notes)
    # no self loop, no note
    clean = variant(tmp_path, "adjacency = [[1, 0, 0]", "adjacency = [[0, 0, 0]", "clean.toml")
    assert load_scenario(clean).notes == ()


def test_paper_scenario_loads_with_section4_values():
    """Bundled `paper`: 3 robots at the Section 4 initial positions, dt = 1 / control_rate_hz,
    b = [1, 0, 0], the authors' offsets (erratum 1), Table 2 gains."""
    sc = load_scenario("paper")
    assert sc.n == 3 and sc.robot_ids == [1, 2, 3]
    assert sc.dt == pytest.approx(1.0 / sc.spec.control_rate_hz)
    assert sc.steps == round(sc.spec.duration_s * sc.spec.control_rate_hz)
    assert sc.spec.duration_s == 24.0
    q, q_dot = sc.initial_state()
    np.testing.assert_array_equal(q[:, :2], [[4.4, -17.5], [16.4, -23.5], [16.4, -5.5]])
    np.testing.assert_array_equal(q_dot[:, :2], [[0.0, 0.0], [-1.6, 0.2], [0.0, 0.0]])
    np.testing.assert_array_equal(sc.leader_weights, [1, 0, 0])
    assert [tuple(r.offset) for r in sc.spec.robots] == [(0, 0), (-4, -4), (-4, 4)]
    b = sc.spec.behaviors
    radii = (b.obstacle_safe_distance_m, b.robot_safe_distance_m, sc.spec.robot.body_radius_m)
    assert radii == (2.0, 1.6, 0.5)
    c = sc.spec.controller
    assert (c.alpha, c.mu, c.T_p, c.upsilon) == (0.5, 30.0, 4.0, 1.5)
    assert math.isclose(sc.spec.eso.r1, 0.7) and sc.spec.estimator.iota == [0.1, 0.1, 25.0, 6.0]
