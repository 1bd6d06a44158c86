"""Every numeric option is checked once (deploy/contract/options.py): a value outside its range
is refused on every command with exit code 2 and a message naming the option, never a
traceback; a run shorter than one control period is refused."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from deploy.cli import build_parser, main
from deploy.contract.options import OPTIONS, Bound, OptionError, check_duration
from deploy.runtime.transport import Counters, Node

REPO = Path(__file__).resolve().parents[2]
CAN = ("--can-interface", "virtual", "--can-channel", "test-options")


def run(capsys, *argv: str) -> tuple[int, str]:
    try:
        rc = main(list(argv))
    except SystemExit as exc:  # argparse's usage errors
        rc = exc.code
    return rc, capsys.readouterr().err


# (argv, the option the message must name): the cases first, then one bad value
# for every numeric option of every command
BAD = [
    (("run", "paper", "--duration", "nan"), "--duration"),
    (("run", "paper", "--duration", "inf"), "--duration"),
    (("run", "paper", "--in-process", "--duration", "0.0001"), "--duration"),
    (("run", "paper", "--duration", "0"), "--duration"),
    (("run", "paper", "--duration", "-1"), "--duration"),
    (("run", "paper", "--in-process", "--control-rate", "10", "--duration", "0.05"), "--duration"),
    (("run", "paper", "--control-rate", "nan"), "--control-rate"),
    (("run", "paper", "--control-rate", "1e9"), "--control-rate"),
    (("run", "paper", "--step-deadline", "0"), "--step-deadline"),
    (("run", "paper", "--startup-timeout", "inf"), "--startup-timeout"),
    (("run", "paper", "--priority", "21"), "--priority"),
    (("agent", "--scenario", "paper", "--robot", "1", "--control-rate", "-5"), "--control-rate"),
    (("plant", "--scenario", "paper", "--control-rate", "-5"), "--control-rate"),
    (("leader", "--scenario", "paper", "--control-rate", "0"), "--control-rate"),
    (("leader", "--scenario", "paper", "--duration", "0.0001"), "--duration"),
    (("leader", "--scenario", "paper", "--step-deadline", "1e300"), "--step-deadline"),
    (("agent", "--scenario", "paper", "--robot", "1", "--lost-peer-grace", "-1"),
     "--lost-peer-grace"),
    (("plant", "--scenario", "paper", "--command-timeout", "0"), "--command-timeout"),
    (("bridge", "--scenario", "lab", "--robot", "1", *CAN, "--command-timeout", "nan"),
     "--command-timeout"),
    (("bridge", "--scenario", "lab", "--robot", "1", *CAN, "--heartbeat-timeout", "-1"),
     "--heartbeat-timeout"),
    (("bridge", "--scenario", "lab", "--robot", "1", *CAN, "--bitrate", "0"), "--bitrate"),
    (("emulate", "--scenario", "lab", "--robot", "1", *CAN, "--physics-rate", "0"), "--physics-rate"),
    (("emulate", "--scenario", "lab", "--robot", "1", *CAN, "--encoder-rate", "inf"),
     "--encoder-rate"),
    (("emulate", "--scenario", "lab", "--robot", "1", *CAN, "--drop-rate", "1.5"), "--drop-rate"),
    (("emulate", "--scenario", "lab", "--robot", "1", *CAN, "--duration", "nan"), "--duration"),
    (("emulate", "--scenario", "lab", "--robot", "1", *CAN, "--seed", "-3"), "--seed"),
    (("can-check", *CAN, "--spin-torque", "3"), "--spin-torque"),
    (("can-check", *CAN, "--listen", "nan"), "--listen"),
    (("record", "--scenario", "paper", "--out", "x", "--duration", "inf"), "--duration"),
    (("record", "--scenario", "paper", "--out", "x", "--control-rate", "0"), "--control-rate"),
    (("faults", "sweep", "paper", "--seeds", "0"), "--seeds"),
    (("faults", "sweep", "paper", "--duration", "nan"), "--duration"),
    (("faults", "sweep", "paper", "--duration", "0.0005"), "--duration"),
    (("bench", "--repeats", "0"), "--repeats"),
    (("scenario", "generate", "--robots", "0", "--control-rate", "100", "--out", "x"), "--robots"),
    (("scenario", "generate", "--robots", "3", "--control-rate", "100", "--duration", "0.001",
      "--out", "x"), "--duration"),
    (("deploy", "plan", "deploy/hosts/example.toml", "paper", "--duration", "-1"), "--duration"),
    (("deploy", "plan", "deploy/hosts/example.toml", "paper", "--duration", "0.0001"),
     "--duration"),
    (("deploy", "certs", "h", "paper", "--out", "x", "--days", "0"), "--days"),
    (("view", "x", "--speed", "0"), "--speed"),
]


@pytest.mark.parametrize("argv, flag", BAD, ids=[" ".join(a) for a, _ in BAD])
def test_bad_number_exits_2_naming_the_option(capsys, tmp_path, monkeypatch, argv, flag):
    monkeypatch.chdir(REPO)  # deploy/hosts/example.toml; nothing is written: refused first
    rc, err = run(capsys, *argv)
    assert rc == 2, err
    assert flag in err and "Traceback" not in err


@pytest.mark.parametrize("argv", [
    ("run", "paper", "--duration", "nan"),
    ("run", "paper", "--in-process", "--duration", "0.0001"),
    ("agent", "--scenario", "paper", "--robot", "1", "--control-rate", "-5"),
    ("leader", "--scenario", "paper", "--control-rate", "0"),
])
def test_the_command_line_says_it_without_a_traceback(argv):
    """The issue's cases through the real entry point, as a user meets them."""
    r = subprocess.run([sys.executable, "-m", "deploy.cli", *argv], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert argv[-2] in r.stderr and "Traceback" not in r.stderr, r.stderr


def _actions(parser: argparse.ArgumentParser, path: str = "omnifleet"):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _actions(sub, f"{path} {name}")
        else:
            yield path, action


def test_every_numeric_option_comes_from_the_one_table():
    """No command declares a number with a bare float/int: each is an entry of
    deploy/contract/options.py, with its range (one place per fact)."""
    seen = set()
    for path, action in _actions(build_parser()):
        if action.type in (float, int):
            pytest.fail(f"{path} {action.option_strings}: a bare {action.type.__name__}")
        owner = getattr(action.type, "__self__", None)
        if isinstance(owner, Bound):
            flag = action.option_strings[0]
            assert flag in OPTIONS and OPTIONS[flag].bound == owner, (path, flag)
            seen.add(flag)
    assert {"--duration", "--control-rate", "--step-deadline", "--priority"} <= seen


def test_bounds_accept_their_range_and_nothing_else():
    rate = OPTIONS["--control-rate"].bound
    assert rate.parse("1000") == 1000.0 and rate.parse("100000") == 100000.0
    for text in ("0", "-5", "nan", "inf", "-inf", "1e5000", "100000.1", "fast", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            rate.parse(text)
    count = OPTIONS["--repeats"].bound
    assert count.parse("3") == 3
    for text in ("0", "2.5", "-1"):
        with pytest.raises(argparse.ArgumentTypeError):
            count.parse(text)
    assert OPTIONS["--lost-peer-grace"].bound.parse("0") == 0.0


def test_a_run_takes_at_least_one_control_period():
    check_duration(0.001, 1000.0)  # exactly one step
    check_duration(None, 1000.0)  # the scenario's own, checked on load
    for bad in (0.000999, 0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(OptionError, match="--duration"):
            check_duration(bad, 1000.0)


def test_a_node_says_once_that_it_computed_a_non_finite_value(capsys):
    """Node.note_nonfinite: counted every time, said on stderr once."""
    node = SimpleNamespace(role="agent-2", counters=Counters())
    for k in range(3):
        Node.note_nonfinite(node, f"command at step {k}")
    err = capsys.readouterr().err
    assert node.counters.nonfinite == 3
    assert err.count("non-finite") == 1 and "agent-2" in err and "step 0" in err
