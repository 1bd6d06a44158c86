"""``python -m deploy.nodes COMMAND ...``: the node commands alone (agent, plant, leader,
bridge, emulate), as ``omnifleet run`` starts its processes. The same commands as
``omnifleet COMMAND``, without building the whole command line's parser and importing
what its other commands need: ~0.1 s of CPU less a node, and five to thirty-odd of
them start at once (docs/bench-history.md)."""

from __future__ import annotations

import argparse
import sys

from deploy.nodes.entry import add_every_node_command, dispatch


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="omnifleet", description="One node of a fleet "
                                "(`omnifleet run` starts them; `omnifleet --help` lists "
                                "every command).")
    add_every_node_command(p.add_subparsers(dest="command", required=True, metavar="COMMAND"))
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
