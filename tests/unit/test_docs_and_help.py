"""What a newcomer reads first says what is: `run --help` names every bundled scenario
(derived from the folder, never typed), no help text prints raw Sphinx markup, every
package docstring names files that exist, the README's tables keep one row a line and
it names every command, every link of README and docs/ leads somewhere, and no
code comment cites an issue number or a design section outside the repository."""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
from pathlib import Path

import pytest

from deploy.cli import build_parser
from deploy.contract.scenario import bundled_names

REPO = Path(__file__).resolve().parents[2]


def _subparsers(p: argparse.ArgumentParser, prefix: str = ""):
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield f"{prefix}{name}", sub
                yield from _subparsers(sub, f"{prefix}{name} ")


def test_run_help_names_every_bundled_scenario():
    assert len(bundled_names()) == len(list((REPO / "deploy" / "scenarios").glob("*.toml")))
    helps = dict(_subparsers(build_parser()))
    text = helps["run"].description  # what --help prints (wrapped there, at hyphens too)
    assert all(name in text for name in bundled_names()), text


def test_no_help_text_prints_sphinx_markup():
    for name, p in _subparsers(build_parser()):
        text = p.format_help()
        assert not re.search(r"``|:func:|:class:|:mod:|:meth:", text), name


@pytest.mark.parametrize("package", ["plant", "agents", "bridges", "deploy", "deploy/contract",
                                     "deploy/runtime", "deploy/nodes", "deploy/fleet",
                                     "deploy/report", "deploy/run", "deploy/bench"])
def test_a_package_docstring_names_only_files_that_exist(package):
    folder = REPO / package
    doc = ast.get_docstring(ast.parse((folder / "__init__.py").read_text())) or ""
    named = set(re.findall(r"\b([a-z_0-9]+\.(?:py|dbc))\b", doc))
    assert not [n for n in named if not (folder / n).exists()], named


def _tracked(*patterns: str) -> list[Path]:
    out = subprocess.run(["git", "ls-files", *patterns], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout.split()
    return [REPO / f for f in out if not f.startswith("paper/")]


def test_markdown_tables_keep_one_row_a_line_and_links_lead_somewhere():
    for f in _tracked("*.md"):
        lines = f.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.startswith("|"):
                assert line.rstrip().endswith("|"), f"{f.name}:{i + 1}: a table row broken"
                if i + 1 < len(lines) and lines[i + 1].strip():
                    assert lines[i + 1].startswith("|"), f"{f.name}:{i + 2}: a row's tail"
        for link in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", f.read_text()):
            if not link.startswith(("http:", "https:", "mailto:")):
                assert (f.parent / link).exists(), f"{f.name}: {link}"


def test_the_readme_names_every_command():
    readme = (REPO / "README.md").read_text()
    top = {name for name, _ in _subparsers(build_parser()) if " " not in name}
    assert not [c for c in top if f"`{c}`" not in readme and f"`{c} " not in readme]


def test_no_code_or_doc_cites_an_issue_number_or_an_outside_design_section():
    pattern = re.compile(r"\b[Ii]ssues? [0-9]+|\bissue-[0-9]+|DESIGN \N{SECTION SIGN}")
    cited = [f"{f.relative_to(REPO)}:{n}" for f in _tracked("*.py", "*.md", "*.toml")
             for n, line in enumerate(f.read_text().splitlines(), 1) if pattern.search(line)
             and f.name != "test_docs_and_help.py"]
    assert cited == []
