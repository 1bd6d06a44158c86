"""The house imports one way (docs/layout.md): plant at the bottom, agents and bridges on it,
deploy on top, and inside deploy its sub-packages from the contract up to the command line.

Every import counts, at module level or inside a function (a lazy import is still a
dependency), read with ``ast`` from the source: nothing is imported to check it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("plant", "agents", "bridges", "deploy")

# What each top-level folder may import of the project (besides itself).
ALLOWED = {
    "plant": set(),
    "agents": {"plant"},
    "bridges": {"plant"},
    "deploy": {"plant", "agents", "bridges"},
}

# deploy's sub-packages, bottom to top; a module imports only its own layer or below. The
# command line (cli/) is the roof; no module sits directly in deploy/.
DEPLOY_LAYERS = ("contract", "runtime", "nodes", "fleet", "report", "ros2", "run", "bench", "cli")


def modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in sorted((REPO / pkg).rglob("*.py")):
            parts = f.relative_to(REPO).with_suffix("").parts
            out[".".join(p for p in parts if p != "__init__")] = f
    return out


def imports_of(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m.split(".")[0] in PACKAGES}


def project_imports() -> dict[str, set[str]]:
    mods = modules()
    # `from deploy.report import metrics` names a module; `from x import Name` does not
    return {m: {i for i in imports_of(f) if i in mods} for m, f in mods.items()}


def layer(module: str) -> int:
    return DEPLOY_LAYERS.index(module.split(".")[1])


def test_top_level_folders_import_one_way():
    wrong = [f"{m} -> {i}" for m, deps in project_imports().items() for i in sorted(deps)
             if i.split(".")[0] != m.split(".")[0] and i.split(".")[0] not in ALLOWED[m.split(".")[0]]]
    assert not wrong, "imports that run back up:\n" + "\n".join(wrong)


def test_deploy_sub_packages_import_downward():
    for m in modules():
        if m.startswith("deploy."):
            assert m.split(".")[1] in DEPLOY_LAYERS, f"{m}: a sub-package of deploy/ not in DEPLOY_LAYERS"
    wrong = [f"{m} (layer {DEPLOY_LAYERS[layer(m)]}) -> {i}"
             for m, deps in project_imports().items() if m.startswith("deploy.")
             for i in sorted(deps) if i.startswith("deploy.") and i != "deploy" and layer(i) > layer(m)]
    assert not wrong, "imports that run back up inside deploy/:\n" + "\n".join(wrong)


def test_no_module_imports_itself_in_a_loop():
    graph = project_imports()
    state: dict[str, int] = {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for i in graph.get(m, ()):
            if state.get(i) == 1:
                pytest.fail("import cycle: " + " -> ".join(path[path.index(i):] + [m, i]))
            if i not in state:
                visit(i, path + [m])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [])


@pytest.mark.parametrize("bad, why", [
    ("from deploy.run.runner import make_plant\n", "plant -> deploy"),
    ("def f():\n    from agents.core import AgentCore\n", "a lazy import counts"),
])
def test_the_check_sees_an_import_that_runs_back_up(tmp_path, bad, why):
    f = tmp_path / "x.py"
    f.write_text(bad)
    assert imports_of(f) & {"deploy.run.runner", "agents.core"}, why
