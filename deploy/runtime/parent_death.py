"""A child process that ends when the process that started it does."""

from __future__ import annotations

import ctypes
import signal


def die_with_parent() -> None:
    """Linux: get SIGTERM when the launching process dies (no orphans, even
    after a SIGKILL of the launcher). Called by the child itself at start-up
    (a preexec_fn is unsafe in the launcher, which runs zenoh threads)."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass
