"""Scenario text edited by hand, for the loader's refusals (shared by the tests of
walls and polygons and of leader paths)."""

from __future__ import annotations

import pytest

from deploy.contract.scenario import SCENARIO_DIR, ScenarioError, parse_scenario

WALL_GAP = (SCENARIO_DIR / "wall-gap.toml").read_text()


def refused(old: str, new: str, text: str = WALL_GAP) -> str:
    """The loader's message for ``text`` with ``old`` replaced by ``new`` (it must refuse)."""
    assert old in text, old
    with pytest.raises(ScenarioError) as info:
        parse_scenario(text.replace(old, new, 1), "mine.toml")
    return str(info.value)
