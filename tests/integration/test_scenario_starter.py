"""The scenario starter (deploy/scenario_starter.toml) leads where it says: its commented
alternatives, done as it says, load; it names the allowed values of every choice it sets;
and what it says is refused is refused, with what to do.

Seen: uncommenting the starter's waypoint and wall blocks failed `scenario check` with
``leader.x: only with path = "harmonic"`` while the starter said ``kind = "analytic"`` and
never "harmonic"; ``theta_rate`` (meaningless on a waypoint path) was taken silently."""

from __future__ import annotations

import re

import msgspec
import pytest

from deploy.cli.scenario import STARTER
from deploy.contract.plant_registry import in_process_plants
from deploy.contract.scenario import ScenarioError, ScenarioFile, parse_scenario
from deploy.contract.schema_hints import enum_at

TEXT = STARTER.read_text()
HARMONIC = re.compile(r'^path = "harmonic"\n(?:.*\n)*?theta_rate = .*\n', re.M)


def _uncomment(block_start: str, text: str = TEXT) -> str:
    """The commented block that begins with ``#   block_start``, uncommented."""
    lines, out, inside = text.splitlines(), [], False
    for line in lines:
        if line.startswith(f"#   {block_start}"):
            inside = True
        if inside and line.startswith("#   "):
            out.append(line[4:])
            continue
        inside = False
        out.append(line)
    return "\n".join(out) + "\n"


def _waypoints_as_told() -> str:
    """The four harmonic lines replaced by the uncommented waypoint lines."""
    block = "\n".join(ln[4:] for ln in TEXT.splitlines() if ln.startswith("#   ") and (
        "path = " in ln or "waypoints =" in ln or "speed_mps" in ln or "accel_mps2" in ln))
    return HARMONIC.sub(block + "\n", TEXT)


def test_the_starter_loads_as_it_is_and_with_each_alternative_done_as_it_says():
    parse_scenario(TEXT, "starter.toml")
    sc = parse_scenario(_waypoints_as_told(), "starter.toml")
    assert sc.spec.leader.path == "waypoints" and sc.spec.leader.theta_rate is None
    walls = _uncomment("[[polygons]]", _uncomment("[[walls]]", _waypoints_as_told()))
    sc = parse_scenario(walls, "starter.toml")
    assert len(sc.spec.walls) == 1 and len(sc.spec.polygons) == 1


def test_waypoints_beside_the_harmonic_lines_are_refused_saying_what_to_remove():
    both = _uncomment("path = ", TEXT).replace('path = "harmonic"\n', "", 1)
    with pytest.raises(ScenarioError, match=r"leader\.x.*remove x, y, theta0 and theta_rate"):
        parse_scenario(both, "starter.toml")
    only_rate = re.sub(r"^[xy] = .*\n", "", both, flags=re.M)
    with pytest.raises(ScenarioError, match=r"`leader\.theta_rate`: only with path = \"harmonic\""):
        parse_scenario(only_rate, "starter.toml")


def _choices(node: object, where: str = "") -> list[tuple[str, str]]:
    """(path, value) of every key the starter sets whose value is a choice."""
    out = []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _choices(v, f"{where}.{k}")
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _choices(v, f"{where}[{i}]")
    elif isinstance(node, str) and enum_at(ScenarioFile, where):
        out.append((where, node))
    return out


def test_the_starter_names_every_allowed_value_of_each_choice_it_sets():
    choices = _choices(msgspec.toml.decode(TEXT.encode()))
    assert {w for w, _ in choices} >= {".leader.kind", ".leader.path", ".leader.heading"}
    for where, _ in choices:
        for allowed in enum_at(ScenarioFile, where):
            assert f'"{allowed}"' in TEXT, f"{where}: the starter never names {allowed!r}"
    # the plant's kind is a name of the plant registry, not of the schema
    for allowed in in_process_plants():
        assert f'"{allowed}"' in TEXT, f"plant.kind: the starter never names {allowed!r}"


def test_a_value_outside_a_choice_names_the_choices_and_a_mistyped_key_the_nearest():
    with pytest.raises(ScenarioError, match=r'expected one of: harmonic, waypoints'):
        parse_scenario(TEXT.replace('path = "harmonic"', 'path = "analytic"'), "s.toml")
    with pytest.raises(ScenarioError, match=r"did you mean `theta_rate`"):
        parse_scenario(TEXT.replace("theta_rate = 0.2", "theta_rat = 0.2"), "s.toml")
