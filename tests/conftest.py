"""Shared fixtures (bundled scenarios and short in-process runs, cached per session) and
the markers, applied here by where a test lives and what it needs (one place):

- ``e2e``: tests/e2e/, whole fleets of processes (``pytest -m "not e2e"``: the rest);
  a test there that starts no process belongs in tests/unit or tests/integration;
- ``realtime``: a test that (or whose fixture) judges a run against the wall clock
  with tests/realtime_clock.py (skipped only when other programs measurably took the
  CPU), or marked so explicitly;
- ``root``: network namespaces (tests/netns.py; skipped without root);
- ``slow``: integration modules whose runs take tens of seconds here;
- ``load_safe``: an e2e test whose assertions hold however busy the machine is
  (``LOAD_SAFE``): its fleets run on the lockstep clock (a step waits up to 2 s for a
  late input), or it claims nothing of their timing (the bench's smoke run), its waits
  are generous bounds, and no probe of it must act while a run of fixed length goes;
  tests/suite.py runs it beside the others. A realtime test
  (above) in such a module stays ``realtime``: the suite runs those one at a time.
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


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own: it reads -n then
def pytest_cmdline_main(config: pytest.Config) -> None:
    """A selection with no test that must run alone (``-m "not e2e and not slow"``, the
    quick lane) runs over the cores, as tests/suite.py runs its first phase, unless the
    caller said ``-n`` (tests/lanes.py)."""
    from lanes import spreads
    from suite import workers

    o = config.option
    if (config.pluginmanager.hasplugin("xdist") and not hasattr(config, "workerinput")
            and getattr(o, "numprocesses", 0) is None and o.dist == "no" and not o.tx
            and not o.usepdb and not getattr(o, "trace", False)
            and not getattr(o, "stepwise", False) and not o.collectonly
            and spreads(o.markexpr or "") and workers() > 1):  # one core: nothing to spread
        o.numprocesses, o.dist = workers(), "worksteal"
        config.stash[SPREAD] = o.numprocesses


SPREAD = pytest.StashKey[int]()


def pytest_report_header(config: pytest.Config) -> str | None:
    n = config.stash.get(SPREAD, None)
    if n is None:
        return None
    return (f"spread over {n} workers: the selection holds no test that must run alone "
            "(tests/lanes.py); -n 0 runs it one test at a time")


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


# e2e modules, or single tests (module::test), that start lockstep fleets only (or no fleet,
# or claim nothing of a fleet's timing: the bench's smoke run checks that every figure is
# written), whose waits are bounds, not races, and that hold no port, name or host setting
# another test could take meanwhile: fleet names and run directories are their own, TCP
# ports the kernel's free ones, namespaces random. Not here: CAN bridges and emulators
# judged on the wall clock, a cut link (a liveliness lease measured in wall time),
# realtime runs, and the probes that must act while a run of fixed length goes (forgeries,
# floods, garbage, a stop: on a busy machine a probe that came up late found the run over,
# and a stop of the plant's was not heard within its 5 s of tries).
LOAD_SAFE = {"test_bench", "test_cli", "test_fault_runs", "test_pybullet_runs", "test_run_outputs",
             "test_security", "test_wall_gap",
             *(f"test_distributed::{t}" for t in (
                 "test_lockstep_run_equals_the_in_process_reference",
                 "test_run_reports_processes_messages_and_a_recording",
                 "test_the_plants_record_of_samples_and_replies_is_what_the_launcher_heard",
                 "test_each_agent_hears_only_its_graph_neighbours",
                 "test_sigint_stops_every_process_of_the_run",
                 "test_a_launcher_killed_outright_leaves_no_process_behind",
                 "test_an_agent_for_an_unknown_robot_fails_fast",
                 "test_a_bad_zenoh_config_is_a_clear_error",
                 "test_a_node_that_dies_fails_the_run_and_is_named",
                 "test_a_bad_fleet_name_is_refused_before_anything_starts",
                 "test_each_node_links_only_to_the_nodes_it_talks_to")),
             "test_laws_fleet::test_a_python_law_in_lockstep_equals_the_in_process_reference",
             "test_netns::test_lockstep_across_namespaces_equals_the_single_host_run"}
SLOW_MODULES = {"test_safety_scenarios", "test_paper_consistent", "test_closed_loop",
                "test_pybullet_plant", "test_look_ahead", "test_faults", "test_anti_windup"}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        path = item.path
        module = getattr(item, "module", None)
        if path.parent.name == "e2e":
            item.add_marker(pytest.mark.e2e)
            item.add_marker(pytest.mark.slow)
            if {path.stem, f"{path.stem}::{item.originalname}"} & LOAD_SAFE:
                item.add_marker(pytest.mark.load_safe)
        if path.stem in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
        if path.parent.name != "unit" and _judges_the_clock(item):
            item.add_marker(pytest.mark.realtime)
            item.add_marker(pytest.mark.slow)  # it lasts its run's wall time (tests/lanes.py)
        if path.stem == "test_netns" or (module is not None and hasattr(module, "netns_problem")):
            item.add_marker(pytest.mark.root)


# the judge, and the helpers that call it for a test (tests/can_fleet_runs.py)
CLOCK_JUDGES = {"judged", "judge_clock", "once_more", "clean_fleet_run", "killed_fleet_run"}


def _judges_the_clock(item: pytest.Item) -> bool:
    """Whether the test, or a fixture it uses, calls the realtime judge: the marker
    follows what a test does, not its name or its folder."""
    funcs = [getattr(item, "function", None)]
    info = getattr(item, "_fixtureinfo", None)
    if info is not None:
        funcs += [d.func for defs in info.name2fixturedefs.values() for d in defs]
    return any(f is not None and CLOCK_JUDGES & set(f.__code__.co_names) for f in funcs)
