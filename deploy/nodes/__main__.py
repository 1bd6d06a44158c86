"""``python -m deploy.nodes COMMAND ...``: the node commands alone (agent, plant, leader,
bridge, emulate), as ``omnifleet run`` starts its processes. The same commands as
``omnifleet COMMAND``, without building the whole command line's parser and importing
what its other commands need: ~0.1 s of CPU less a node, and five to thirty-odd of
them start at once (docs/bench.md)."""

from __future__ import annotations

import argparse
import sys

from deploy.nodes.bridge_cli import add_bridge_commands
from deploy.nodes.cli import add_node_commands
from deploy.nodes.emulator_cli import add_emulate_command
from deploy.nodes.entry import dispatch


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="omnifleet", description="One node of a fleet "
                                "(`omnifleet run` starts them; `omnifleet --help` lists "
                                "every command).")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_node_commands(sub)
    add_bridge_commands(sub)
    add_emulate_command(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
