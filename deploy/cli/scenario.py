"""``omnifleet scenario``: start from a scenario rather than from a blank file.

- ``list``: the bundled scenarios, with their description;
- ``show NAME``: a bundled scenario's TOML, to read or to copy (``> mine.toml``);
- ``check FILE``: load and validate a scenario file (exit 2 with the key when bad);
- ``new FILE [--from NAME]``: a commented starting scenario (``deploy/scenario_starter.toml``)
  or a copy of a bundled one, named after FILE, validated before it is written;
- ``generate --robots N --control-rate HZ [--duration S] [--seed K] --out FILE``: the
  scale benchmark's scenario (``deploy/contract/scaled_scenarios.py``: N lab robots in a
  5-wide grid behind a straight leader, a binary-tree graph from robot 1), written
  only after it validates, so anyone can reproduce ``omnifleet bench``'s scale
  figures or start a new fleet from it.
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from pathlib import Path

from deploy.contract.options import EXIT_BAD_INPUT, add_option, check_duration
from deploy.contract.output_paths import check_file
from deploy.contract.scaled_scenarios import scale_scenario
from deploy.contract.scenario import (
    SCENARIO_DIR,
    Scenario,
    ScenarioError,
    bundled_names,
    load_scenario,
    parse_scenario,
)

STARTER = Path(__file__).resolve().parent.parent / "scenario_starter.toml"


def _cmd_list(_args: argparse.Namespace) -> int:
    for name in bundled_names():
        path = SCENARIO_DIR / f"{name}.toml"
        try:
            sc = load_scenario(path)
            print(f"{path.stem:18s} {sc.n} robots, {1.0 / sc.dt:g} Hz, {sc.spec.duration_s:g} s: "
                  f"{sc.spec.description}")
        except ScenarioError as exc:  # a bundled file that does not load is a bug: say so
            print(f"{path.stem:18s} DOES NOT LOAD: {exc}")
    return 0


def _bundled(name: str, command: str) -> Path | None:
    """The bundled scenario ``name``'s file, or None after saying which exist."""
    path = SCENARIO_DIR / f"{name.removesuffix('.toml')}.toml"
    if path.exists():
        return path
    known = ", ".join(bundled_names())
    print(f"omnifleet scenario {command}: no bundled scenario {name!r} (bundled: {known})",
          file=sys.stderr)
    return None


def _cmd_show(args: argparse.Namespace) -> int:
    path = _bundled(args.name, "show")
    if path is None:
        return EXIT_BAD_INPUT
    sys.stdout.write(path.read_text())
    return 0


def _cmd_check(args: argparse.Namespace) -> int:
    sc = load_scenario(args.file)  # ScenarioError: exit 2 with file and key (cli.main)
    for note in sc.notes:
        print(f"note: {note}", file=sys.stderr)
    s = sc.spec
    print(f"{args.file}: valid: {sc.n} robots, {1.0 / sc.dt:g} Hz, {s.duration_s:g} s, "
          f"{len(s.obstacles)} disc obstacles, {len(s.walls)} walls, {len(s.polygons)} polygons, "
          f"leader path {s.leader.path}, plant {s.plant.kind}")
    return 0


def _cmd_generate(args: argparse.Namespace) -> int:
    check_file(args.out, "--out")  # OutputPathError: exit 2 (cli.main), before anything
    check_duration(args.duration, args.control_rate)  # the ranges: checked on parse
    text = scale_scenario(args.robots, args.control_rate, args.duration, args.seed)
    return _write(Path(args.out), text, args.force, "generate")


def scenario_name(path: Path) -> str:
    """A scenario (and fleet) name from a file name: its stem, without the characters a
    key expression cannot hold."""
    return re.sub(r"[/*$?#\s]+", "-", path.stem).strip("-") or "scenario"


def _cmd_new(args: argparse.Namespace) -> int:
    check_file(args.file, "FILE")  # OutputPathError: exit 2 (cli.main), before anything
    src = STARTER if args.source is None else _bundled(args.source, "new")
    if src is None:
        return EXIT_BAD_INPUT
    out = Path(args.file)
    text = re.sub(r'^name = ".*"$', f'name = "{scenario_name(out)}"', src.read_text(),
                  count=1, flags=re.M)
    if args.source is not None:
        text = f"# Copied from the bundled scenario `{args.source}` by `omnifleet scenario new`.\n{text}"
    return _write(out, text, args.force, "new")


def _write(out: Path, text: str, force: bool, command: str) -> int:
    """Write scenario ``text`` to ``out`` once it validates (ScenarioError: exit 2,
    nothing written); never over an existing file unless ``force``."""
    if out.exists() and not force:
        print(f"omnifleet scenario {command}: {out} exists (--force to replace it)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    sc: Scenario = parse_scenario(text, str(out))  # validated before anything is written
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"wrote {out}: {sc.n} robots at {1.0 / sc.dt:g} Hz for {sc.spec.duration_s:g} s "
          f"(check it: omnifleet scenario check {shlex.quote(str(out))}; run it: omnifleet run "
          f"{shlex.quote(str(out))})")
    return 0


def _cmd_perturb(args: argparse.Namespace) -> int:
    from deploy.contract.scenario_variants import perturbed, scenario_toml

    out = check_file(args.out, "--out")  # OutputPathError: exit 2 (cli.main)
    if out.exists() and not args.force:
        print(f"omnifleet scenario perturb: {out} exists (--force to replace it)", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        sc = perturbed(load_scenario(args.name), args.seed, args.obstacle_jitter, args.start_jitter)
    except ValueError as exc:  # a bad jitter, or no clear start (ScenarioError: cli.main)
        if isinstance(exc, ScenarioError):
            raise
        print(f"omnifleet scenario perturb: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    text = f"# omnifleet scenario perturb {args.name} --seed {args.seed}\n" + scenario_toml(sc)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    moved = len(sc.spec.obstacles) + len(sc.spec.walls) + len(sc.spec.polygons)
    print(f"wrote {out}: {sc.name}, {moved} obstacles and {sc.n} starts jittered "
          f"(run it: omnifleet run {out})")
    return 0


def add_scenario_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenario", help="list, show, check, start or generate scenarios",
                       description="Start from a scenario: list and show the bundled ones, "
                       "check a file, write a new one from the commented starter or a bundled "
                       "one, or generate an N-robot fleet (the scale benchmark's).")
    cmds = p.add_subparsers(dest="scenario_command", required=True, metavar="ACTION")
    cmds.add_parser("list", help="the bundled scenarios").set_defaults(func=_cmd_list)
    show = cmds.add_parser("show", help="print a bundled scenario's TOML (to copy it)")
    show.add_argument("name", help="bundled scenario name (see `omnifleet scenario list`)")
    show.set_defaults(func=_cmd_show)
    check = cmds.add_parser("check", help="validate a scenario file")
    check.add_argument("file", help="scenario file (or bundled name)")
    check.set_defaults(func=_cmd_check)
    new = cmds.add_parser(
        "new", help="write a commented starting scenario (or a copy of a bundled one)",
        description="Write FILE: a commented three-robot starting scenario, or with --from a "
        "copy of a bundled scenario; its name is FILE's. Validated before it is written.")
    new.add_argument("file", metavar="FILE", help="where to write the TOML")
    new.add_argument("--from", dest="source", metavar="NAME",
                     help="copy this bundled scenario (see `omnifleet scenario list`) instead "
                     "of the starter")
    new.add_argument("--force", action="store_true", help="replace FILE if it exists")
    new.set_defaults(func=_cmd_new)
    gen = cmds.add_parser(
        "generate", help="write an N-robot scenario (the scale benchmark's)",
        description="N lab robots in a 5-wide grid formation behind a leader driving "
        "straight at 0.5 m/s, a binary-tree graph from robot 1 (which hears the leader), "
        "obstacles beside the lanes. Validated before it is written.")
    add_option(gen, "--robots", required=True)
    add_option(gen, "--control-rate", required=True,
               help="control rate of every node (the bench uses 100)")
    add_option(gen, "--duration", default=20.0, help="simulated duration")
    add_option(gen, "--seed", help="jitter every start by up to 5 cm per axis, reproducibly "
               "(default: the bench's fixed layout)")
    gen.add_argument("--out", required=True, metavar="FILE", help="where to write the TOML")
    gen.add_argument("--force", action="store_true", help="replace --out if it exists")
    gen.set_defaults(func=_cmd_generate)
    per = cmds.add_parser(
        "perturb", help="write a seeded perturbation of a scenario (obstacles and starts jittered)",
        description="Every obstacle moved uniformly within --obstacle-jitter of where it is, "
        "every start within --start-jitter, drawn again where it would overlap an obstacle or "
        "another robot; the same seed gives the same file. `omnifleet safety sweep` runs many.")
    per.add_argument("name", help="bundled scenario name or TOML file")
    add_option(per, "--seed", required=True, help="the perturbation's seed")
    add_option(per, "--obstacle-jitter")
    add_option(per, "--start-jitter")
    per.add_argument("--out", required=True, metavar="FILE", help="where to write the TOML")
    per.add_argument("--force", action="store_true", help="replace --out if it exists")
    per.set_defaults(func=_cmd_perturb)
