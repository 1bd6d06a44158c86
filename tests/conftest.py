"""Shared fixtures: bundled scenarios and short in-process runs, cached per session."""

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


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """Inputs tried per decoder by the fuzz tests (tests/fuzzing.py), when any ran."""
    from fuzzing import TALLY

    if TALLY.by_decoder:
        terminalreporter.section("fuzz: inputs per decoder")
        for line in TALLY.lines():
            terminalreporter.write_line(line)
