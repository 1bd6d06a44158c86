"""``python -m deploy.nodes``, the entry `omnifleet run` starts its nodes by: the same
node commands, with the same options and the same exit codes, as ``omnifleet``."""

from __future__ import annotations

import argparse

from deploy.cli import build_parser as full_parser
from deploy.nodes.__main__ import build_parser as node_parser
from deploy.nodes.__main__ import main

NODE_COMMANDS = ("agent", "plant", "leader", "bridge", "emulate")


def _commands(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _options(p: argparse.ArgumentParser) -> list[tuple[tuple[str, ...], object, object]]:
    return sorted((tuple(a.option_strings), a.default, a.choices) for a in p._actions
                  if a.option_strings)


def test_the_node_entry_has_each_node_command_with_the_same_options():
    full, nodes = _commands(full_parser()), _commands(node_parser())
    assert sorted(nodes) == sorted(NODE_COMMANDS)
    for name in NODE_COMMANDS:
        assert _options(nodes[name]) == _options(full[name]), name


def test_a_bad_scenario_is_exit_2_there_too(capsys):
    assert main(["agent", "--scenario", "no-such-scenario", "--robot", "1"]) == 2
    assert "bad scenario" in capsys.readouterr().err
