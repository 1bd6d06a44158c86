"""Fuzzing the scenario decoder (``parse_scenario``, what ``load_scenario`` runs on a
file's bytes) with mutations of the bundled scenarios.

Properties: a text either loads or raises :class:`ScenarioError`, nothing else;
a scenario that loads has only finite numbers (``limits.*`` may be inf: no limit)
and everything the runtime derives from it (dt, steps, initial state, the robot
model, every agent's configuration) can be built and is finite.
Inputs: the parsed TOML with one to three edits (a key deleted, a value replaced
by another type, NaN/inf, a negative, zero, huge number, huge array or random
unicode), written back as TOML; and the raw text with mutated bytes.
"""

from __future__ import annotations

import json
import math
import tomllib
from typing import Any

import msgspec
import numpy as np
import pytest
from fuzzing import any_float, fuzz_decoder, fuzz_settings, mutated_bytes, non_finite_floats
from hypothesis import given
from hypothesis import strategies as st

from deploy.contract.scenario import SCENARIO_DIR, Scenario, ScenarioError, parse_scenario

BUNDLED = {p.stem: p.read_bytes() for p in sorted(SCENARIO_DIR.glob("*.toml"))}
PARSED = {name: tomllib.loads(raw.decode()) for name, raw in BUNDLED.items()}

Path_ = tuple[str | int, ...]


# --- TOML out: every table inline, so any nesting is one line ------------------------------
def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string is a JSON string (\uXXXX escapes included)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(doc: dict[str, Any]) -> str:
    return "".join(f"{json.dumps(k)} = {toml_value(v)}\n" for k, v in doc.items())


# --- edits of the parsed document ---------------------------------------------------------
def paths(node: Any, at: Path_ = ()) -> list[Path_]:
    """Every key and list index inside ``node``."""
    out: list[Path_] = []
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        out.append((*at, k))
        out.extend(paths(v, (*at, k)))
    return out


toml_scalars = st.one_of(st.booleans(), st.integers(-(2**63), 2**63 - 1), any_float,
                         st.text(max_size=30))
toml_values = st.recursive(toml_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=10), inner, max_size=3)),
    max_leaves=12)


@st.composite
def replacement(draw: st.DrawFn, old: Any) -> Any:
    kind = draw(st.sampled_from(["any", "number", "number", "negate", "huge array", "same type"]))
    if kind == "number":
        return draw(st.one_of(any_float, st.sampled_from([0, -1, 10**30, -(10**30), 2**63 - 1])))
    if kind == "negate" and isinstance(old, int | float) and not isinstance(old, bool):
        return -old
    if kind == "huge array":
        item = old[0] if isinstance(old, list) and old else draw(toml_scalars)
        return [item] * draw(st.integers(100, 3000))
    if kind == "same type" and isinstance(old, list):
        return draw(st.lists(st.one_of(any_float, st.just(old[0] if old else 0.0)), max_size=6))
    return draw(toml_values)


@st.composite
def edited_document(draw: st.DrawFn, text: str) -> bytes:
    """A TOML document with 1-3 keys deleted, replaced or added (any TOML file)."""
    return _edited(draw, tomllib.loads(text))


@st.composite
def edited_scenario(draw: st.DrawFn) -> bytes:
    doc = json.loads(json.dumps(PARSED[draw(st.sampled_from(sorted(PARSED)))],
                                allow_nan=True))  # a deep copy
    return _edited(draw, doc)


def _edited(draw: st.DrawFn, doc: dict[str, Any]) -> bytes:
    for _ in range(draw(st.integers(1, 3))):
        where = draw(st.sampled_from(paths(doc)))
        parent = doc
        for k in where[:-1]:
            parent = parent[k]
        key = where[-1]
        op = draw(st.sampled_from(["delete", "replace", "replace", "replace", "add key"]))
        if op == "delete":
            del parent[key]
        elif op == "replace":
            parent[key] = draw(replacement(parent[key]))
        elif isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=12))] = draw(toml_values)
    return to_toml(doc).encode()


# --- properties ----------------------------------------------------------------------------
def check_scenario(sc: Scenario) -> None:
    bad = [p for p in non_finite_floats(msgspec.to_builtins(sc.spec)) if not p.startswith("['limits']")]
    assert not bad, bad
    assert math.isfinite(sc.dt) and sc.dt > 0
    assert sc.steps >= 1  # the loader refuses a run shorter than one control period
    q, qd = sc.initial_state()
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(qd))
    model = sc.model()
    for name in ("P", "A0", "body_input"):
        assert np.all(np.isfinite(getattr(model, name))), name
    for i in range(sc.n):
        q0, v0 = sc.initial_estimates(i)
        assert np.all(np.isfinite(q0)) and np.all(np.isfinite(v0))
        sc.agent_config(i, model)


def decode(raw: bytes) -> Scenario:
    return fuzz_decoder("scenario", parse_scenario, raw, rejects=(ScenarioError,),
                        check=check_scenario)


@fuzz_settings(300)
@given(raw=edited_scenario())
def test_edited_scenarios(raw: bytes) -> None:
    decode(raw)


@fuzz_settings(200)
@given(st.data())
def test_mutated_scenario_bytes(data: st.DataObject) -> None:
    raw = BUNDLED[data.draw(st.sampled_from(sorted(BUNDLED)))]
    decode(data.draw(mutated_bytes(raw)))


@fuzz_settings(100)
@given(raw=st.one_of(st.binary(max_size=400), st.text(max_size=400).map(str.encode)))
def test_random_text(raw: bytes) -> None:
    decode(raw)


def test_bundled_scenarios_pass_the_checks() -> None:
    for raw in BUNDLED.values():
        assert decode(raw) is not None


# --- cases the fuzzing found, pinned -------------------------------------------------------
PAPER = BUNDLED["paper"].decode()


def test_ragged_adjacency_is_a_scenario_error() -> None:
    """Found: numpy's ValueError (inhomogeneous shape) came out of the loader."""
    old = "adjacency = [[1, 0, 0], [1, 0, 0], [1, 1, 0]]"
    assert PAPER.count(old) == 1
    with pytest.raises(ScenarioError, match="graph.adjacency.*3x3"):
        parse_scenario(PAPER.replace(old, "adjacency = [[0, 0], [1, 0, 0], [1, 1, 0]]"), "bad.toml")


def test_bytes_that_are_not_utf8_are_a_scenario_error() -> None:
    """Found: UnicodeDecodeError came out of the loader for a file starting with b'\\x80'."""
    with pytest.raises(ScenarioError, match="not UTF-8"):
        parse_scenario(b"\x80" + BUNDLED["paper"], "bad.toml")
