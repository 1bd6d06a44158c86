"""What the whole command line (``deploy/cli/``) and the nodes' own entry (``python -m
deploy.nodes``, what ``omnifleet run`` starts) share: the node commands, and running a
parsed command, with the errors any command can end with said in one line with exit 2
(130/143 when interrupted) instead of a traceback."""

from __future__ import annotations

import argparse
import os
import signal
import sys

from deploy.contract.fault_plan import FaultPlanError
from deploy.contract.options import EXIT_BAD_INPUT, OptionError
from deploy.contract.output_paths import OutputPathError
from deploy.contract.scenario import ScenarioError
from deploy.contract.wire import FleetNameError
from deploy.nodes.bridge_cli import add_bridge_commands
from deploy.nodes.cli import add_node_commands
from deploy.nodes.emulator_cli import add_emulate_command
from deploy.runtime.transport import TransportError


def add_every_node_command(sub: argparse._SubParsersAction) -> None:
    """agent, plant, leader, bridge and emulate."""
    add_node_commands(sub)
    add_bridge_commands(sub)
    add_emulate_command(sub)


def _prog(args: argparse.Namespace) -> str:
    """``omnifleet COMMAND [SUBCOMMAND]`` as the user typed it."""
    words = [args.command] + [v for k, v in vars(args).items()
                              if k.endswith("_command") and isinstance(v, str)]
    return " ".join(["omnifleet", *words])


def dispatch(args: argparse.Namespace) -> int:
    """``args.func(args)``, its exit code; a known error said plainly (exit 2)."""
    try:
        return args.func(args)
    except ScenarioError as exc:
        print(f"omnifleet: bad scenario: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except FaultPlanError as exc:
        print(f"omnifleet: bad fault plan: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (TransportError, FleetNameError) as exc:
        print(f"omnifleet: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (OptionError, OutputPathError) as exc:
        print(f"{_prog(args)}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as exc:
        print("omnifleet: interrupted; every process of the run was stopped", file=sys.stderr)
        return 143 if getattr(exc, "signal_name", "") == "SIGTERM" else 130
    except BrokenPipeError:
        # the reader of our output went away (`omnifleet scenario list | head`): stop
        # writing, quietly, as a tool killed by SIGPIPE would (Python's own recipe: the
        # rest of stdout goes to /dev/null so that its flush at exit cannot raise again)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
