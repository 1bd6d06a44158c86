"""The processes omnifleet starts run its own code (deploy/runtime/own_python.py): not a
``deploy`` package that happens to sit in the working directory, and with one BLAS
thread unless the user chose otherwise."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from deploy.runtime.own_python import PACKAGE_ROOT, child_env, python_module

WHERE = "import deploy, os; print(deploy.__file__); print(os.environ['OPENBLAS_NUM_THREADS'])"


def test_a_child_started_elsewhere_imports_this_installation_not_the_working_directory(
        tmp_path: Path) -> None:
    decoy = tmp_path / "deploy"
    decoy.mkdir()
    (decoy / "__init__.py").write_text("raise SystemExit('the decoy was imported')\n")
    (decoy / "nodes").mkdir()
    (decoy / "nodes" / "__init__.py").write_text("")
    (decoy / "nodes" / "__main__.py").write_text("raise SystemExit('the decoy ran')\n")
    env = child_env({k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"})
    where = subprocess.run([*python_module("deploy.nodes")[:-2], "-c", WHERE], cwd=tmp_path,
                           env=env, capture_output=True, text=True, timeout=60)
    assert where.returncode == 0, where.stderr
    path, threads = where.stdout.split()
    assert Path(path).resolve() == PACKAGE_ROOT / "deploy" / "__init__.py"
    assert threads == "1"
    node = subprocess.run([*python_module("deploy.nodes"), "--help"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=60)
    assert node.returncode == 0, node.stderr
    assert "agent" in node.stdout and "decoy" not in node.stdout + node.stderr


def test_the_users_blas_threads_and_python_path_are_kept() -> None:
    env = child_env({"OPENBLAS_NUM_THREADS": "4", "PYTHONPATH": "/somewhere"})
    assert env["OPENBLAS_NUM_THREADS"] == "4"
    assert "/somewhere" in env["PYTHONPATH"].split(os.pathsep)
    assert "OPENBLAS_NUM_THREADS" not in child_env({}, one_blas_thread=False)
