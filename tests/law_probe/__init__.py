"""The law kernel with its sections callable one by one, built for the tests.

The product's kernel (agents/law_kernel.pyx) exports only what the agents run: the whole
step (``Law``). The tests check each section at its own boundary as well (the estimator,
the ESO, the behaviors, the fusion, the controller, the safety filter, the degradation),
so they build a module of their own from the same text: ``law_kernel_probe.pyx`` includes
the product's .pyx and every section it includes, then ``exports.pxi`` (a ``def *_of``
per section). Same sources, same compiler directives (plant/kernels.py ``DIRECTIVES``):
the sections the probe runs are the product's, and :func:`load` checks that the probe
was built from the sources the product's kernel was built from.

Built once per source version into ``build/law_probe/<digest>/`` (~20 s on the 2-core
machine), under a file lock so that parallel test workers build it once.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from plant.kernels import DIRECTIVES, source_digest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
KERNEL = ROOT / "agents" / "law_kernel.pyx"
PROBE = HERE / "law_kernel_probe.pyx"
NAME = "law_kernel_probe"

_loaded: ModuleType | None = None


def _digest() -> str:
    """The probe's sources: the product's kernel (its digest) and the probe's own files."""
    h = hashlib.sha256(source_digest(KERNEL).encode())
    for f in (PROBE, HERE / "exports.pxi"):
        h.update(f.read_bytes())
    return h.hexdigest()


def _build(out: Path) -> None:
    """Cython and the C compiler, as setup.py runs them, into ``out``."""
    from Cython.Build import cythonize
    from setuptools import Distribution, Extension

    ext = Extension(NAME, [str(PROBE)])
    modules = cythonize(
        [ext], compiler_directives=DIRECTIVES, include_path=[str(ROOT)], quiet=True,
        build_dir=str(out / "c"),
        compile_time_env={"AGENTS_LAW_KERNEL_SHA256": source_digest(KERNEL)})
    dist = Distribution({"name": NAME, "ext_modules": modules})
    cmd = dist.get_command_obj("build_ext")
    cmd.build_lib, cmd.build_temp = str(out), str(out / "tmp")
    cmd.ensure_finalized()
    cmd.run()


def load() -> ModuleType:
    """The probe module, built first if this version of the sources has none yet."""
    global _loaded
    if _loaded is not None:
        return _loaded
    out = ROOT / "build" / "law_probe" / _digest()[:16]
    out.mkdir(parents=True, exist_ok=True)
    with open(out.parent / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another test worker may be building it
        built = sorted(out.glob(NAME + ".*.so"))
        if not built:
            _build(out)
            built = sorted(out.glob(NAME + ".*.so"))
    spec = importlib.util.spec_from_file_location(NAME, built[0])
    module = importlib.util.module_from_spec(spec)
    sys.modules[NAME] = module
    spec.loader.exec_module(module)
    if module.BUILT_FROM != source_digest(KERNEL):
        raise ImportError(f"{built[0]} was not built from the kernel's sources")
    _loaded = module
    return module
