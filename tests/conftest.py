"""Shared fixtures (bundled scenarios and short in-process runs, cached per session) and
the fuzz tests' tally.

The markers (``pyproject.toml`` declares them; each test module declares its own with
``pytestmark`` or decorators; tests/unit/test_markers.py checks that they say what the
tests do):

- ``e2e``: tests/e2e/, whole fleets of processes (``pytest -m "not e2e"``: the rest);
  a test there that starts no process belongs in tests/unit or tests/integration;
- ``realtime``: a test that (or whose fixture) judges a run against the wall clock
  with tests/realtime_clock.py (skipped only when other programs measurably took the
  CPU);
- ``root``: network namespaces (tests/netns.py; skipped without root);
- ``slow``: runs that take tens of seconds here; every ``e2e`` and ``realtime`` test is
  one;
- ``load_safe``: an e2e test whose assertions hold however busy the machine is: its
  fleets run on the lockstep clock (a step waits up to 2 s for a late input), or it
  claims nothing of their timing (the bench's smoke run), its waits are generous bounds,
  it holds no port, name or host setting another test could take meanwhile, and no
  probe of it must act while a run of fixed length goes; tests/suite.py runs it beside
  the others. A realtime test in such a module stays ``realtime``: the suite runs
  those one at a time.
"""

from __future__ import annotations

import functools

import pytest

from deploy.contract.scenario import load_scenario
from deploy.run.runner import run_in_process


@functools.cache
def cached_run(name: str, duration_s: float | None, plant: str | None = None):
    """One in-process run per (scenario, duration, plant) for the whole session."""
    return run_in_process(load_scenario(name), plant, duration_s)


@pytest.fixture(scope="session")
def paper():
    return load_scenario("paper")


def pytest_sessionfinish(session: pytest.Session) -> None:
    """A pytest-xdist worker (tests/suite.py) hands its fuzz tally to the controller."""
    out = getattr(session.config, "workeroutput", None)
    if out is not None:
        from fuzzing import TALLY

        out["fuzz_tally"] = {name: vars(t) for name, t in TALLY.by_decoder.items()}


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:
    """pytest-xdist's controller: add a finished worker's fuzz tally to its own."""
    from fuzzing import TALLY

    for name, counts in getattr(node, "workeroutput", {}).get("fuzz_tally", {}).items():
        TALLY.add(name, **counts)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """Inputs tried per decoder by the fuzz tests (tests/fuzzing.py), when any ran."""
    from fuzzing import TALLY

    if TALLY.by_decoder:
        terminalreporter.section("fuzz: inputs per decoder")
        for line in TALLY.lines():
            terminalreporter.write_line(line)
