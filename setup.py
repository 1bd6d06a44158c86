"""Builds the compiled kernels (Cython, at ``pip install``); everything else is in pyproject.toml.

The kernels hold the per-step arithmetic of the plant (eq. 4 integrated for the fleet, the
disturbance, perception) and of the agent's law (eqs. 14-42, the safety filter): plain loops
on C doubles, a few microseconds a step where the same equations as Python floats cost
tens (docs/bench.md, "The compiled kernels"). The built modules are also copied next to
their sources, so that ``python -m ...`` and ``python -m pytest`` run from a clone (which
put the clone ahead of site-packages on sys.path) find them there.
"""

from pathlib import Path

from Cython.Build import cythonize
from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

KERNELS = [
    Extension("plant.fleet_kernel", ["plant/fleet_kernel.pyx"]),
    Extension("agents.law_kernel", ["agents/law_kernel.pyx"]),
]


def _kernels_module():
    """plant/kernels.py (``source_digest``, ``DIRECTIVES``), loaded by path: importing the
    plant package would import the kernels this build makes."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_kernels", Path("plant/kernels.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# each kernel knows the source it was built from (BUILT_FROM), so that a module built from
# an older .pyx or section is refused at import instead of running stale arithmetic
# (plant/kernels.py)
kernels = _kernels_module()
SOURCE_HASHES = {ext.name.replace(".", "_").upper() + "_SHA256":
                 kernels.source_digest(Path(ext.sources[0])) for ext in KERNELS}


class BuildNextToSources(build_ext):
    """build_ext that also leaves each module beside its .pyx (what --inplace does)."""

    def run(self) -> None:
        super().run()
        if not self.inplace:
            self.copy_extensions_to_source()


setup(
    ext_modules=cythonize(
        KERNELS,
        compiler_directives=kernels.DIRECTIVES,
        compile_time_env=SOURCE_HASHES,
    ),
    cmdclass={"build_ext": BuildNextToSources},
)
