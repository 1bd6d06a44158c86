"""The ``omnifleet`` command line.

Exit codes: 0 success, 1 the run failed (a node died) or did not meet the
scenario's criteria (with ``--check``), 2 bad input (scenario, arguments,
zenoh configuration, an output path that cannot be written), 3 a node lost a peer it cannot run without, 130
interrupted (SIGINT), 143 terminated (SIGTERM).
"""

from __future__ import annotations

import argparse
import sys

from deploy.run.node_forks import close_early, start_early

# What the parser needs is imported when it is built, not with this module: a run that
# starts a fleet starts the nodes' fork server first, and its imports then run beside
# these (~0.2 s of CPU each; deploy/nodes/forks.py).


def package_version() -> str:
    """The installed package's version (its metadata, from pyproject.toml)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("omnifleet")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


class _Version(argparse.Action):
    """``--version``: the package's metadata read only when asked (importlib.metadata
    costs ~11 ms, on every command otherwise)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(f"omnifleet {package_version()}")  # on stdout, as argparse's own
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    from deploy.cli.run import add_run_command
    from deploy.nodes.entry import add_every_node_command

    p = argparse.ArgumentParser(
        prog="omnifleet",
        description="Collision-free formation control for mecanum-wheel robot fleets. "
        "Start with `omnifleet scenario list` and `omnifleet run lab --in-process` (a report "
        "folder in runs/lab/, ending with a verdict); COMMAND --help says more, README.md "
        "and docs/ the rest.",
    )
    p.add_argument("--version", action=_Version, nargs=0,
                   help="show the installed version and exit")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_run_command(sub)
    add_every_node_command(sub)
    from deploy.cli.bench import add_bench_command
    from deploy.cli.can_check import add_can_check_command
    from deploy.cli.faults import add_faults_command

    add_can_check_command(sub)
    add_bench_command(sub)
    add_faults_command(sub)
    from deploy.cli.compare import add_compare_command
    from deploy.cli.safety import add_safety_command

    add_safety_command(sub)
    add_compare_command(sub)
    from deploy.cli.fleet import add_deploy_commands
    from deploy.cli.scenario import add_scenario_commands

    add_scenario_commands(sub)
    from deploy.cli.record import add_record_command
    from deploy.cli.router import add_router_command
    from deploy.cli.view import add_view_command

    add_record_command(sub)
    add_view_command(sub)
    add_router_command(sub)
    add_deploy_commands(sub)
    return p


def starts_a_fleet(argv: list[str]) -> bool:
    """Whether ``omnifleet ...`` will start a fleet of node processes: ``run``, but not
    ``--in-process`` nor help (whose nodes the fork server then forks, on either clock)."""
    return argv[:1] == ["run"] and "--in-process" not in argv and not {"-h", "--help"} & set(argv)


def main(argv: list[str] | None = None) -> int:
    if starts_a_fleet(sys.argv[1:] if argv is None else argv):
        start_early()  # its nodes' fork server
    try:
        from deploy.nodes.entry import dispatch

        return dispatch(build_parser().parse_args(argv))
    finally:
        close_early()  # started, and no run took it (bad input, an early error)

