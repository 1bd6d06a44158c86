"""Start a Python child that runs this very installation of omnifleet, lightly.

Two things every process the launcher (or the bench, or a fault sweep) starts gets:

- **The same code as its parent.** ``python -m deploy.nodes`` puts the working
  directory first on ``sys.path``: a launcher installed in a virtual environment,
  started from a clone, ran its nodes from the clone's sources, which may differ from
  what it runs itself, and were compiled anew by every node where bytecode is not
  written (``PYTHONDONTWRITEBYTECODE``; pip compiled the installed copy at install).
  The child starts with ``-P`` (no working directory on its path) and, when this
  package is not where the interpreter finds it anyway (a clone run as
  ``python -m deploy.cli``), that folder first on ``PYTHONPATH``. README command 1's
  five nodes: 0.1-0.15 s of CPU each saved (docs/bench-history.md).
- **One BLAS thread.** numpy's OpenBLAS starts a thread per core at import, ~0.05 s
  of CPU a process on 2 cores, for arrays that never reach its threading threshold
  (a node's are of 3 to 12 elements). ``OPENBLAS_NUM_THREADS=1`` unless the user
  set it.
"""

from __future__ import annotations

import os
import site
import sys
from collections.abc import Mapping
from pathlib import Path

# the folder that holds the deploy package (a clone, or site-packages)
PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def python_module(module: str) -> list[str]:
    """The command line that runs ``python -m module`` from this installation."""
    return [sys.executable, "-P", "-m", module]


def _found_anyway(root: Path) -> bool:
    """Whether a child interpreter finds ``root`` on its path without being told
    (site-packages, the user's site-packages)."""
    known = [*site.getsitepackages(), site.getusersitepackages()]
    return any(Path(p).resolve() == root for p in known if Path(p).exists())


def child_env(base: Mapping[str, str] | None = None, one_blas_thread: bool = True
              ) -> dict[str, str]:
    """``base`` (default: this process's environment) for a child that imports this
    installation (:func:`python_module`) and, with ``one_blas_thread``, starts one BLAS
    thread (a node; not a launcher timed as a user starts it)."""
    env = dict(os.environ if base is None else base)
    if not _found_anyway(PACKAGE_ROOT):
        env["PYTHONPATH"] = os.pathsep.join(
            [str(PACKAGE_ROOT), *(p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p)])
    if one_blas_thread:
        env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env
