"""The markers each test declares (``pytestmark``, decorators) say what it does, read from
the sources with ``ast`` (nothing is imported or collected):

- every module in tests/e2e/ is ``e2e`` and ``slow``; every ``realtime`` test is ``slow``;
- a test that judges a run against the wall clock (it, or a fixture of its module it
  takes, calls one of ``CLOCK_JUDGES``) is ``realtime``: the suite must run it alone
  (tests/unit/, whose tests of the judge judge made-up runs, aside);
- a module that builds network namespaces (``netns_problem``) is ``root``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]
# the wall-clock judge (tests/realtime_clock.py) and the helpers that call it for a test
# (tests/can_fleet_runs.py)
CLOCK_JUDGES = {"judged", "judge_clock", "once_more", "clean_fleet_run", "killed_fleet_run"}


def _marks(decorators: list[ast.expr]) -> set[str]:
    """``pytest.mark.NAME`` (called or not) among decorators or a pytestmark's items."""
    out = set()
    for d in decorators:
        target = d.func if isinstance(d, ast.Call) else d
        if (isinstance(target, ast.Attribute) and isinstance(target.value, ast.Attribute)
                and target.value.attr == "mark"):
            out.add(target.attr)
    return out


def _module_marks(tree: ast.Module) -> set[str]:
    for node in tree.body:
        if (isinstance(node, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets)):
            v = node.value
            return _marks(list(v.elts) if isinstance(v, ast.List | ast.Tuple) else [v])
    return set()


def _called(node: ast.AST) -> set[str]:
    """The names ``node`` calls (``f(...)``, ``m.f(...)``)."""
    calls = [n.func for n in ast.walk(node) if isinstance(n, ast.Call)]
    return {c.id for c in calls if isinstance(c, ast.Name)} | {
        c.attr for c in calls if isinstance(c, ast.Attribute)}


def _is_fixture(fn: ast.FunctionDef) -> bool:
    return any("fixture" in ast.unparse(d) for d in fn.decorator_list)


def _modules() -> list[tuple[Path, ast.Module]]:
    return [(p, ast.parse(p.read_text(), str(p))) for p in sorted(TESTS.rglob("test_*.py"))]


@pytest.mark.parametrize("path, tree", _modules(), ids=lambda v: getattr(v, "stem", ""))
def test_each_test_declares_the_markers_of_what_it_does(path: Path, tree: ast.Module) -> None:
    module = _module_marks(tree)
    funcs = [n for n in tree.body if isinstance(n, ast.FunctionDef)]
    judging_fixtures = {f.name for f in funcs if _is_fixture(f) and CLOCK_JUDGES & _called(f)}
    wrong = []
    if path.parent.name == "e2e" and not {"e2e", "slow"} <= module:
        wrong.append("an e2e module: pytestmark = [pytest.mark.e2e, pytest.mark.slow, ...]")
    if "netns_problem" in _called(tree) and "root" not in module:
        wrong.append("builds network namespaces: mark it root")
    for f in funcs:
        if not f.name.startswith("test_") or _is_fixture(f) or path.parent.name == "unit":
            continue  # (unit tests of the judge itself judge made-up runs)
        marks = module | _marks(f.decorator_list)
        takes = {a.arg for a in f.args.args}
        if (CLOCK_JUDGES & _called(f) or takes & judging_fixtures) and "realtime" not in marks:
            wrong.append(f"{f.name} judges the wall clock: mark it realtime")
        if "realtime" in marks and "slow" not in marks:
            wrong.append(f"{f.name} is realtime: mark it slow too")
    assert not wrong, f"{path.relative_to(TESTS)}:\n" + "\n".join(wrong)
