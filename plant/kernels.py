"""A compiled kernel is used only if it was built from the source beside it.

``pip install`` builds plant/fleet_kernel.pyx and agents/law_kernel.pyx (setup.py) and
copies the modules next to their sources. A clone whose .pyx was edited afterwards would
otherwise run the old arithmetic without a word: each kernel carries the sha256 of the
source it was built from (``BUILT_FROM``: the .pyx and the section files it includes), and
:func:`checked` compares it with the source that sits beside it, when there is one.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from types import ModuleType

# how every kernel is compiled: setup.py for the product's, and the tests' build of the law
# kernel with its sections callable one by one (tests/law_probe), so both run one arithmetic
DIRECTIVES = {"language_level": 3, "boundscheck": False, "wraparound": False,
              "cdivision": True, "initializedcheck": False}


class StaleKernel(ImportError):
    """A compiled kernel built from another version of its source."""


def source_digest(pyx: Path) -> str:
    """The sha256 of a kernel's source as setup.py takes it: the .pyx, then the sections
    it includes (``<name>_sections/*.pxi``, by name)."""
    h = hashlib.sha256(pyx.read_bytes())
    for section in sorted(pyx.with_name(pyx.stem + "_sections").glob("*.pxi")):
        h.update(section.read_bytes())
    return h.hexdigest()


def checked(module: ModuleType) -> ModuleType:
    """``module`` itself, or StaleKernel when the .pyx beside it (and its sections) is not
    what it was built from."""
    built = Path(module.__file__ or "")
    source = built.with_name(built.name.split(".", 1)[0] + ".pyx")
    if source.exists() and source_digest(source) != module.BUILT_FROM:
        raise StaleKernel(f"{built.name} was built from another version of {source} or its "
                          "sections: rebuild it (pip install -e . , or python setup.py "
                          "build_ext --inplace)")
    return module
