"""Scenario errors a user can act on: the allowed values of an enum, the nearest known
key for a typo, the robots that cannot hear the leader, and starts that overlap (both
bodies named, with the gap). Each case is a bundled scenario with one edit."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.cli import main
from deploy.contract.scenario import SCENARIO_DIR, ScenarioError, parse_scenario, start_overlaps

PAPER = (SCENARIO_DIR / "paper.toml").read_text()
LAB = (SCENARIO_DIR / "lab.toml").read_text()


def refused(text: str, old: str, new: str) -> str:
    assert old in text, f"the scenario no longer holds {old!r}"
    with pytest.raises(ScenarioError) as info:
        parse_scenario(text.replace(old, new, 1), "mine.toml")  # the first one
    return str(info.value)


@pytest.mark.parametrize("old, new, key, allowed", [
    ('x = { fn = "cos"', 'x = { fn = "lemniscate"', "leader.x.fn", "sin, cos"),
    ('kind = "pybullet"', 'kind = "bullet"', "plant.kind", "pybullet, model, kinematic"),
    ('avoidance_engage = "approaching"', 'avoidance_engage = "near"',
     "behaviors.avoidance_engage", "inside, approaching"),
    ('heading = "tangent"', 'heading = "north"', "leader.heading", "tangent, polar"),
])
def test_an_enum_error_lists_the_allowed_values(old, new, key, allowed):
    msg = refused(LAB, old, new)
    assert "mine.toml" in msg and key in msg and f"expected one of: {allowed}" in msg


@pytest.mark.parametrize("old, new, typo, meant", [
    ("radius_m = 0.15", "raduis_m = 0.15", "raduis_m", "radius_m"),
    ("duration_s = 60.0", "duraton_s = 60.0", "duraton_s", "duration_s"),
    ("[behaviors]", "[behaviours]", "behaviours", "behaviors"),
    ("max_speed_mps = 1.5", "max_sped_mps = 1.5", "max_sped_mps", "max_speed_mps"),
    ("theta_rate = 0.2", "theta_rat = 0.2", "theta_rat", "theta_rate"),
])
def test_an_unknown_key_suggests_the_nearest_known_one(old, new, typo, meant):
    msg = refused(LAB, old, new)
    assert f"unknown field `{typo}`" in msg and f"did you mean `{meant}`?" in msg


def test_an_unknown_key_far_from_any_lists_the_keys_of_its_table():
    msg = refused(LAB, "[formation]\n", "[formation]\nzzzz = 1\n")
    assert "`zzzz`" in msg and "did you mean" not in msg
    assert "kappa1" in msg and "scale_changes" in msg  # the keys [formation] has


def test_the_spanning_tree_error_names_the_robots_that_cannot_hear_the_leader():
    """Rows follow [[robots]], not ids: with ids 7, 5, 9 and only the second row hearing
    the leader, robot 5 hears it and 7 and 9 do not (robot 9 listens to 7 only)."""
    text = PAPER.replace("id = 1", "id = 7").replace("id = 2", "id = 5").replace("id = 3", "id = 9")
    text = text.replace("adjacency = [[1, 0, 0], [1, 0, 0], [1, 1, 0]]",
                        "adjacency = [[0, 0, 0], [0, 0, 0], [1, 0, 0]]")
    msg = refused(text, "leader = [1, 0, 0]", "leader = [0, 1, 0]")
    assert "robots 7, 9 hear the leader through no path" in msg
    assert "order of [[robots]]" in msg


def test_robots_that_overlap_at_the_start_are_refused_with_both_ids_and_the_gap():
    # paper robots have r = 0.5: robot 3 moved 0.6 m from robot 2's centre
    msg = refused(PAPER, "position = [16.4, -5.5]", "position = [16.4, -22.9]")
    assert "robots 2 and 3 overlap at the start" in msg
    assert "0.600 m apart" in msg and "gap -0.400 m" in msg


def test_a_robot_that_starts_on_an_obstacle_is_refused_naming_both():
    # lab: r = 0.2; obstacle 0 (radius 0.15) at (-0.1, 0.75); robot 2 placed 0.3 m from it
    msg = refused(LAB, "position = [-2.6, -2.4]", "position = [-0.1, 0.45]")
    assert "robot 2 starts on obstacles[0] at (-0.1, 0.75)" in msg
    assert "0.300 m apart" in msg and "gap -0.050 m" in msg


def test_touching_counts_as_overlap_and_a_hair_apart_does_not():
    """Gap = centre distance minus both radii: <= 0 is a contact from t = 0."""
    pos = np.array([[0.0, 0.0], [1.0, 0.0]])
    assert start_overlaps(pos, [1, 2], 0.5, []) != []
    assert start_overlaps(pos + [[0.0, 0.0], [1e-9, 0.0]], [1, 2], 0.5, []) == []
    disc = [("obstacles[0]", np.array([0.0, 0.7]), 0.2)]
    assert start_overlaps(pos[:1], [1], 0.5, disc) != []
    assert start_overlaps(pos[:1], [1], 0.49, disc) == []


def test_every_bundled_scenario_starts_apart():
    for path in SCENARIO_DIR.glob("*.toml"):
        parse_scenario(path.read_text(), str(path))  # raises on an overlap


def test_a_scenario_shorter_than_one_control_period_is_refused():
    msg = refused(PAPER, "duration_s = 24.0", "duration_s = 0.0005")
    assert "duration_s" in msg and "one control period" in msg


def test_the_cli_shows_the_hint_with_exit_2(capsys, tmp_path):
    bad = tmp_path / "mine.toml"
    bad.write_text(LAB.replace('x = { fn = "cos"', 'x = { fn = "lemniscate"'))
    rc = main(["scenario", "check", str(bad)])
    err = capsys.readouterr().err
    assert rc == 2 and "expected one of: sin, cos" in err and "Traceback" not in err
