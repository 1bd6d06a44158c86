# The law kernel as the product builds it (agents/law_kernel.pyx and every section it
# includes, the same text through Cython's include), then its sections callable one by one
# from Python (exports.pxi), for the tests that check each section at its own boundary.
# Built by tests/law_probe/__init__.py at the first test that asks for it, with the
# product's compiler directives (plant/kernels.py DIRECTIVES): one arithmetic in both.

include "../../agents/law_kernel.pyx"
include "exports.pxi"
