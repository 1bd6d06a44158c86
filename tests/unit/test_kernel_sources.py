"""A compiled kernel is refused when its source changed since it was built: the .pyx, or a
section file it includes (plant/kernels.py, setup.py)."""

from pathlib import Path
from types import ModuleType

import agents.law_kernel
import pytest

from plant.kernels import StaleKernel, checked, source_digest


def _kernel(tmp_path: Path) -> tuple[Path, ModuleType]:
    """A kernel's source in ``tmp_path`` (a .pyx and two sections) and a module built from it."""
    pyx = tmp_path / "k.pyx"
    pyx.write_text('include "k_sections/a.pxi"\ninclude "k_sections/b.pxi"\n')
    (tmp_path / "k_sections").mkdir()
    (tmp_path / "k_sections" / "a.pxi").write_text("cdef double a = 1.0\n")
    (tmp_path / "k_sections" / "b.pxi").write_text("cdef double b = 2.0\n")
    module = ModuleType("k")
    module.__file__ = str(tmp_path / "k.cpython-311-x86_64-linux-gnu.so")
    module.BUILT_FROM = source_digest(pyx)
    return pyx, module


def test_a_kernel_built_from_its_source_is_used(tmp_path):
    _, module = _kernel(tmp_path)
    assert checked(module) is module


@pytest.mark.parametrize("edited", ["k.pyx", "k_sections/a.pxi", "k_sections/b.pxi"])
def test_an_edit_of_the_pyx_or_of_any_section_refuses_the_built_kernel(tmp_path, edited):
    _, module = _kernel(tmp_path)
    with (tmp_path / edited).open("a") as f:
        f.write("# edited\n")
    with pytest.raises(StaleKernel, match="rebuild"):
        checked(module)


def test_a_new_section_refuses_the_built_kernel(tmp_path):
    _, module = _kernel(tmp_path)
    (tmp_path / "k_sections" / "c.pxi").write_text("cdef double c = 3.0\n")
    with pytest.raises(StaleKernel):
        checked(module)


def test_the_law_kernel_in_use_was_built_from_its_pyx_and_every_section():
    pyx = Path(agents.law_kernel.__file__).with_name("law_kernel.pyx")
    sections = sorted(pyx.with_name("law_kernel_sections").glob("*.pxi"))
    assert len(sections) >= 10  # the kernel is split by section
    included = [line.split('"')[1] for line in pyx.read_text().splitlines()
                if line.startswith("include ")]
    assert sorted(included) == sorted(f"law_kernel_sections/{s.name}" for s in sections)
    assert agents.law_kernel.BUILT_FROM == source_digest(pyx)


def test_the_product_kernel_exports_only_what_the_product_calls():
    """The sections one by one are the tests' (tests/law_probe), not the product's."""
    exported = {n for n in dir(agents.law_kernel) if n.endswith(("_of", "_of_"))}
    # a lab's law schedules its scale with it; the leader node batches its path with it
    assert exported == {"smooth_step_of", "leader_batch_of"}


def test_the_tests_build_of_the_kernel_is_the_products_sections():
    from law_probe import load

    probe = load()
    assert probe.BUILT_FROM == agents.law_kernel.BUILT_FROM
    assert hasattr(probe, "Law") and hasattr(probe, "safety_filter_of")
